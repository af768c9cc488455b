"""The learner node's own ``main()`` with the simulator played inside its process.

``python learner_feed.py [--fsize BYTES] [--max-steps N] -- <learner arguments>`` runs
:func:`rcbf_ros.ros.learner_node.main` whose node gets a timer that plays the env's episodes
into its ``sim/step`` callback, one plant step per tick, applying the node's proposal as the
plant's action (as the simulator would with a filter that never corrects). Everything else is
the node's: its parameters, resume, checkpoints, exit work and exit status. ``--fsize`` sets
RLIMIT_FSIZE (SIGXFSZ ignored), so that a write past it fails as on a full disk.
"""
from __future__ import annotations

import argparse
import resource
import signal
import sys
from typing import Any

import numpy as np


class Plant:
    """The simulator's ``sim/step`` messages of ``env``'s episodes, one per :meth:`next`."""

    def __init__(self, env: Any, seed: int) -> None:
        self.env = env
        self.seed: int | None = seed
        self.episode = -1
        self.done = True

    def next(self, proposal: Any) -> Any:
        """The next step's message; ``proposal`` is the node's last ``cmd_proposed``."""
        from rcbf_ros.messages.conversions import msg_to_sections, sections_to_msg
        if self.done or proposal is None:
            self.episode += 1
            obs, info = self.env.reset(seed=self.seed)
            self.seed = None
            u = np.zeros(self.env.nominal_system.n_u)
            reward, terminated, truncated = 0.0, False, False
        else:
            u = np.asarray(msg_to_sections(proposal)['u'], dtype=np.float64)
            obs, reward, terminated, truncated, info = self.env.step(u)
        self.done = bool(terminated or truncated)
        return sections_to_msg({
            'state': info['state'], 'observation': obs, 'reward': [float(reward)],
            'action': u, 'terminated': [float(terminated)], 'truncated': [float(truncated)],
            'violation': [float(info.get('violation', False))],
            'goal_reached': [float(info.get('goal_reached', False))],
            'episode': [float(self.episode)], 'step': [float(self.env.steps)]})


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('--fsize', type=int, default=None)
    parser.add_argument('--max-steps', type=int, default=40)
    parser.add_argument('--system', default='unicycle')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('node_args', nargs='*')
    options = parser.parse_args(argv)
    if options.fsize is not None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (options.fsize, options.fsize))

    from rcbf_ros.envs import make_env
    from rcbf_ros.parameters.rules import find_config, load_params
    from rcbf_ros.ros import learner_node

    config = find_config(options.system)
    params = load_params(config, 'simulator')
    params['max_steps'] = options.max_steps

    class FedLearner(learner_node.LearnerNode):
        def __init__(self) -> None:
            super().__init__()
            self.plant = Plant(make_env(options.system, params), options.seed)
            self.create_timer(0.0005, self.tick)

        def tick(self) -> None:
            self.on_step(self.plant.next(self.pending_msg))

    learner_node.LearnerNode = FedLearner
    return learner_node.main(['learner', '--ros-args', '--params-file', str(config),
                              '-p', f'system:={options.system}', *options.node_args])


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
