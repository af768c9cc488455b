"""The MCAP of an in-process run, on the topics and in the messages the node path uses, so
that the same tools (``ros2 bag``, :mod:`rcbf_ros.reports.run_summary`) read both."""
from __future__ import annotations

import json
from pathlib import Path
import sys
from typing import Any, Callable

import numpy as np

from rcbf_ros.core.filter_info import info_sections


class RunRecorder:
    """MCAP of an in-process run with the topics the node path uses (so tools read both)."""

    TOPICS = {
        '/state': 'std_msgs/msg/Float64MultiArray',
        '/cmd_proposed': 'std_msgs/msg/Float64MultiArray',
        '/cmd_safe': 'std_msgs/msg/Float64MultiArray',
        '/filter_info': 'std_msgs/msg/Float64MultiArray',
        '/reward': 'std_msgs/msg/Float64',
        '/episode': 'std_msgs/msg/String',
        '/learner/metrics': 'std_msgs/msg/String',
    }

    def __init__(self, directory: Path, report: Callable[[str], None] | None = None) -> None:
        from rcbf_ros.bag.writer import BagWriter
        self.writer = BagWriter(directory)
        try:
            for name, type_name in self.TOPICS.items():
                self.writer.add_topic(name, type_name)
        except BaseException:  # Ctrl-C among the topics too: the bag is closed, not left open
            self.writer.close()
            raise
        self.t_ns = 0
        self.report = report or (lambda line: print(line, file=sys.stderr, flush=True))
        """Where the line about a message left out goes (once per topic)."""
        self.oversized: dict[str, int] = {}
        """Per topic, messages too large for any chunk of the bag: left out, counted."""

    def _write(self, topic: str, message: Any, t_ns: int) -> None:
        """Write one message; one too large for the bag is left out and counted, the first
        on each topic reported, and the run goes on."""
        from rcbf_ros.bag.writer import MessageTooLargeError
        try:
            self.writer.write_message(topic, message, t_ns)
        except MessageTooLargeError as exc:
            seen = self.oversized.get(topic, 0)
            self.oversized[topic] = seen + 1
            if not seen:
                self.report(f'{exc} (the first on {topic}; later ones are counted)')

    @staticmethod
    def _array(sections: dict[str, np.ndarray]) -> dict[str, Any]:
        dims = [{'label': k, 'size': int(np.size(v)), 'stride': int(np.size(v))}
                for k, v in sections.items()]
        data = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1)
                               for v in sections.values()])
        return {'layout': {'dim': dims, 'data_offset': 0}, 'data': data}

    def step(self, t_ns: int, *, state: np.ndarray, proposal: Any, u_safe: np.ndarray,
             reward: float, result: Any = None) -> None:
        """One step as the nodes publish it: the command alone on /cmd_safe, the details on
        /filter_info (``result``: the filter's, None when the run is not filtered)."""
        self.t_ns = t_ns
        self._write('/state', self._array({'state': state}), t_ns)
        self._write('/cmd_proposed', self._array({
            'u': proposal.u_proposed, 'disturbance_mean': proposal.disturbance_mean,
            'disturbance_std': proposal.disturbance_std, 'state': state}), t_ns)
        self._write('/cmd_safe', self._array({'u': u_safe}), t_ns)
        fail_safe = bool(result is not None and result.fail_safe)
        self._write('/filter_info', self._array(info_sections(
            u=u_safe, u_rl=proposal.u_proposed, fail_safe=fail_safe, result=result,
            status=result.status if result is not None else 'solved', state=state)), t_ns)
        self._write('/reward', {'data': float(reward)}, t_ns)

    def event(self, topic: str, payload: dict[str, Any]) -> None:
        """``payload`` as JSON on a String topic, stamped with the last step's time."""
        self._write(topic, {'data': json.dumps(payload)}, self.t_ns)

    def close(self) -> None:
        """Finish the MCAP (summary, statistics, metadata)."""
        self.writer.close()
