"""The paper's experiments as one command (``rcbf_ros experiment``, no ROS): definitions, a
sequential or Ray runner, evaluation and the report; docs/RESULTS.md holds the numbers."""
from __future__ import annotations
