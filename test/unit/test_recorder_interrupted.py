"""A recorder interrupted while it is being built still leaves a complete bag."""
from __future__ import annotations

import pytest

from rcbf_ros.bag import bag_info
from rcbf_ros.ros.dds import rclpy_compat


def test_ctrl_c_while_the_recorder_is_built_closes_its_bag(ros_domain_id, tmp_path,
                                                           monkeypatch):
    from rcbf_ros.ros.recorder_node import RecorderNode
    bag = tmp_path / 'bag'
    rclpy_compat.init(args=['recorder', '--ros-args', '-p', f'output:={bag}'],
                      domain_id=ros_domain_id)

    def interrupted(self) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(RecorderNode, 'discover', interrupted)
    try:
        with pytest.raises(KeyboardInterrupt):
            RecorderNode()
    finally:
        rclpy_compat.try_shutdown()
    assert bag_info(bag, allow_cut_short=False).message_count == 0
    assert (bag / 'metadata.yaml').is_file()
