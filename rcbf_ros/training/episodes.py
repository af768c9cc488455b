"""One episode of Algorithm 1 in-process (env + filter + learner), and its numbers.

:func:`run_episode` is the inner loop (paper, Algorithm 1 lines 3-7) with the learner's
schedule; :class:`EpisodeStats` the row it yields for ``metrics.jsonl`` and the progress line;
:class:`CriticCheck` the critics' value of the first step against the return that followed,
computed the same way here and in the learner node.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
import math
import time
from typing import Any

import numpy as np

from rcbf_ros.core.filter import SafetyFilter
from rcbf_ros.training.agent import SafeLearner
from rcbf_ros.training.recorder import RunRecorder


@dataclass
class EpisodeStats:
    """Per-episode numbers that go to metrics.jsonl and the progress line."""

    episode: int
    ret: float = 0.0
    steps: int = 0
    violations: int = 0
    min_h_true: float = math.inf
    max_slack: float = 0.0
    filter_active: int = 0
    fail_safe: int = 0
    goal_reached: bool = False
    wall_s: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        out = asdict(self)
        out.update(out.pop('extra'))
        out['steps_per_s'] = self.steps / self.wall_s if self.wall_s > 0 else 0.0
        out['min_h_true'] = None if math.isinf(self.min_h_true) else self.min_h_true
        return out


@dataclass
class CriticCheck:
    """The critics' value of an episode's first step against the discounted return that
    followed (no bootstrap at a time limit): a persistent ``q_start >> disc_return`` is
    over-estimation. The soft value also counts the entropy bonus, at most
    alpha * entropy / (1 - gamma) more. One per episode, fed in step order by the in-process
    loop and by the learner node alike."""

    gamma: float
    """Discount of the learner's SAC."""
    q_start: float = math.nan
    """Q of the first step at (obs, u_RL -> u_safe), read before that step's update."""
    disc_return: float = 0.0
    """sum_t gamma^t r_t over the steps so far."""
    steps: int = 0

    def step(self, learner: SafeLearner, obs: np.ndarray, u_rl: np.ndarray,
             u_safe: np.ndarray, reward: float) -> None:
        """Account one transition; call before the learner observes it."""
        if self.steps == 0:
            self.q_start = learner.critic_value(obs, u_rl, u_safe)
        self.disc_return += self.gamma ** self.steps * reward
        self.steps += 1

    def as_dict(self) -> dict[str, float]:
        return {'q_start': self.q_start, 'disc_return': self.disc_return}


def run_episode(env: Any, filt: SafetyFilter | None, learner: SafeLearner, *, episode: int,
                seed: int | None, recorder: RunRecorder | None = None, train: bool = True,
                deterministic: bool = False, t0_ns: int = 0,
                trace: list[tuple[np.ndarray, bool]] | None = None) -> EpisodeStats:
    """One episode of Algorithm 1's inner loop (lines 3-7), plus the learner's schedule.

    ``seed`` seeds the env's reset (None: continue its generator), as the simulator node does:
    the first episode with the run's seed, later ones from the same stream. ``trace`` gets
    (state, the filter corrected the command: |u_S| > 1e-7) for every state of the episode,
    the last one included.
    """
    stats = EpisodeStats(episode=episode)
    start = time.perf_counter()
    obs, info = env.reset(seed=seed)
    state = info['state']
    done = False
    critic = CriticCheck(learner.sac.config.gamma)
    while not done:
        proposal = learner.propose(obs, state, deterministic=deterministic)
        if filt is None:
            u_safe, slack, result = proposal.u_proposed, 0.0, None
        else:
            result = filt.filter(state, proposal.u_proposed, proposal.disturbance_mean,
                                 proposal.disturbance_std)
            u_safe, slack = result.u_safe, result.slack
            stats.filter_active += int(result.active)
            stats.fail_safe += int(result.fail_safe)
        if trace is not None:
            correction = np.linalg.norm(np.asarray(u_safe) - proposal.u_proposed)
            trace.append((np.array(state, dtype=np.float64), bool(correction > 1e-7)))
        next_obs, reward, terminated, truncated, info = env.step(u_safe)
        next_state = info['state']
        if train:
            critic.step(learner, obs, proposal.u_rl, u_safe, reward)
            learner.observe(obs=obs, state=state, u_rl=proposal.u_rl, u_safe=u_safe,
                            reward=reward, next_obs=next_obs, next_state=next_state,
                            terminated=terminated)
            learner.after_step()
        if recorder is not None:
            recorder.step(t0_ns + int(1e9 * env.t), state=state, proposal=proposal,
                          u_safe=u_safe, reward=reward, result=result)
        stats.ret += reward
        stats.steps += 1
        stats.violations += int(info['violation'])
        if len(info['h_true']):
            stats.min_h_true = min(stats.min_h_true, float(np.min(info['h_true'])))
        if not math.isnan(slack):
            stats.max_slack = max(stats.max_slack, slack)
        stats.goal_reached = stats.goal_reached or bool(info['goal_reached'])
        obs, state = next_obs, next_state
        done = terminated or truncated
    if trace is not None:
        trace.append((np.array(state, dtype=np.float64), False))
    stats.wall_s = time.perf_counter() - start
    stats.extra = {k: float(v) for k, v in learner.last_metrics.items()}
    if train:
        stats.extra.update(critic.as_dict())
    return stats
