"""Files of this checkout that tests go through one by one."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
"""The checkout's root."""
CONFIGS = sorted((REPO / 'config').glob('*.yaml'))
"""Every packaged params file (config/*.yaml)."""
LAUNCH_FILES = sorted((REPO / 'launch').glob('*.launch.py'))
"""Every ROS 2 launch file (launch/*.launch.py)."""
