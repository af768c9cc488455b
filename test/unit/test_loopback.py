"""Cyclone DDS pinned to loopback: the configuration, and the sockets a participant really has."""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import textwrap

import pytest

from rcbf_ros.ros import loopback

REPO = Path(__file__).resolve().parents[2]


# --- loopback ----------------------------------------------------------------------------------

PROC_NET_UDP = """\
   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode ref pointer drops
  123: 0100007F:B9A1 00000000:0000 07 00000000:00000000 00:00000000 00000000     0        0 1001 2 0000000000000000 0
  456: 00000000:3D2C 00000000:0000 07 00000000:00000000 00:00000000 00000000     0        0 1002 2 0000000000000000 0
"""  # noqa: E501  (the kernel's format)


@pytest.mark.skipif(sys.byteorder != 'little', reason='sample from a little-endian host')
def test_proc_net_udp_rows_are_parsed():
    rows = loopback.parse_proc_net_udp(PROC_NET_UDP)
    assert rows == [loopback.UdpSocket(inode=1001, address='127.0.0.1', port=0xB9A1),
                    loopback.UdpSocket(inode=1002, address='0.0.0.0', port=15660)]


def test_the_loopback_configuration_names_the_loopback_address():
    uri = loopback.LOOPBACK_CYCLONEDDS_URI
    assert '<NetworkInterface address="127.0.0.1"/>' in uri
    assert '<AllowMulticast>false</AllowMulticast>' in uri
    assert '<Peer address="127.0.0.1"/>' in uri


_REPORT_SOCKETS = textwrap.dedent("""
    import json, os
    from rcbf_ros.ros.dds import rclpy_compat as rclpy
    from rcbf_ros.messages.classes import get_message
    from rcbf_ros.ros.dds.node import Node
    from rcbf_ros.ros.loopback import bound_device, own_socket_fds, own_udp_sockets
    rclpy.init(args=[])
    node = Node('socket_probe')
    node.create_publisher(get_message('std_msgs/msg/Float64'), 'probe', 10)
    rows = [{'address': row.address, 'port': row.port, 'device': bound_device(fd)}
            for row, fd in own_udp_sockets()]
    with open('/proc/self/net/udp6') as stream:
        inodes = set(own_socket_fds())
        udp6 = [line for line in stream.read().splitlines()[1:]
                if int(line.split()[9]) in inodes]
    print(json.dumps({'udp': rows, 'udp6': udp6}))
    node.destroy_node()
    rclpy.try_shutdown()
""")


@pytest.mark.skipif(not os.path.isdir('/proc/self/net'), reason='Linux /proc only')
def test_a_participant_receives_only_on_loopback(ros_domain_id):
    # Cyclone binds its unicast receive sockets to 0.0.0.0 whatever the configuration says;
    # every socket must be on 127.0.0.1 or bound to the loopback device.
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), RCBF_ROS_RUNTIME='cyclone',
               CYCLONEDDS_URI=loopback.LOOPBACK_CYCLONEDDS_URI,
               PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get('PYTHONPATH')])))
    result = subprocess.run([sys.executable, '-c', _REPORT_SOCKETS], env=env, cwd=REPO,
                            capture_output=True, text=True, timeout=60)
    assert (result.returncode, result.stderr) == (0, '')
    report = json.loads(result.stdout.splitlines()[-1])
    assert report['udp'] and report['udp6'] == []
    for row in report['udp']:
        assert row['address'] == '127.0.0.1' or (row['address'] == '0.0.0.0'
                                                 and row['device'] == 'lo'), report['udp']
    assert any(row['address'] == '0.0.0.0' for row in report['udp'])  # the documented case
