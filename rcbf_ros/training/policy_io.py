"""Export a trained policy alone, and load it back for deployment behind the safety filter.

``policy.pt`` holds the actor's weights and what is needed to rebuild it (observation size,
action box, hidden sizes, system name); it carries no critic, optimizer or replay data. It holds
tensors and plain data only and is read without running code from it
(:mod:`rcbf_ros.training.run_files`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from rcbf_ros.learning.networks import SquashedGaussianActor
from rcbf_ros.learning.sac import SAC
from rcbf_ros.training.run_files import load_payload, save_payload


def save_policy(path: str | Path, sac: SAC, *, u_low: np.ndarray, u_high: np.ndarray,
                system: str) -> Path:
    """Write the actor of ``sac`` to ``path`` (atomically)."""
    path = Path(path)
    payload = {'actor': sac.actor.state_dict(), 'obs_dim': sac.obs_dim, 'n_u': sac.n_u,
               'u_low': np.asarray(u_low, dtype=float).tolist(),
               'u_high': np.asarray(u_high, dtype=float).tolist(),
               'hidden_sizes': list(sac.config.hidden_sizes), 'system': system}
    return save_payload(path, payload)


class DeterministicPolicy:
    """The exported actor's mean action: ``policy(obs (obs_dim,)) -> u_RL (n_u,)``."""

    def __init__(self, payload: dict[str, Any]) -> None:
        self.obs_dim = int(payload['obs_dim'])
        self.n_u = int(payload['n_u'])
        self.system = str(payload.get('system', ''))
        low = torch.tensor(payload['u_low'], dtype=torch.float32)
        high = torch.tensor(payload['u_high'], dtype=torch.float32)
        self.actor = SquashedGaussianActor(self.obs_dim, low, high,
                                           tuple(payload['hidden_sizes']))
        self.actor.load_state_dict(payload['actor'])
        self.actor.eval()

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32).reshape(-1)
        if obs.size != self.obs_dim:
            raise ValueError(f'observation: expected {self.obs_dim} values, got {obs.size}')
        if not np.all(np.isfinite(obs)):
            raise ValueError('observation: contains NaN or inf')
        with torch.no_grad():
            sample = self.actor(torch.from_numpy(obs).unsqueeze(0))
        return sample.mean_action[0].numpy().astype(np.float64)


def load_policy(path: str | Path) -> DeterministicPolicy:
    """Read ``policy.pt``; FileNotFoundError / ValueError name the problem (a file holding
    more than tensors and plain data is refused unread)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'policy_path: no file {path}')
    try:
        payload = load_payload(path)
    except ValueError as exc:
        raise type(exc)(f'policy_path: {exc}') from None
    missing = {'actor', 'obs_dim', 'n_u', 'u_low', 'u_high', 'hidden_sizes'} - set(payload)
    if missing:
        raise ValueError(f'policy_path: {path} lacks {sorted(missing)} (not a policy export?)')
    return DeterministicPolicy(payload)
