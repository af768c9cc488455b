"""Our runtime's messages start as rclpy's do: every type both know, default-constructed and
serialized, gives the same bytes (declared defaults such as Quaternion's w = 1 included)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from rcbf_ros.messages.cdr import serialize_message
from rcbf_ros.messages.classes import get_message
from rcbf_ros.messages.typestore import jazzy_typestore as typestore

pytestmark = pytest.mark.ros2
HERE = Path(__file__).resolve().parent


def test_default_messages_serialize_as_rclpys(jazzy, tmp_path, ros_domain_id):
    names = sorted(name for name in typestore().fielddefs if '/msg/' in name)
    listing = tmp_path / 'types.txt'
    listing.write_text('\n'.join(names))
    done = jazzy.run(f'PY=$(head -1 "$(command -v ros2)" | cut -c3-); '
                     f'"$PY" {HERE / "rclpy_defaults.py"} {listing}',
                     domain_id=ros_domain_id, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:]
    theirs = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(theirs) > 100, sorted(theirs)  # std, geometry, nav, sensor, diagnostic, ...
    different = [name for name, data in theirs.items()
                 if serialize_message(get_message(name)()).hex() != data]
    assert not different, different
