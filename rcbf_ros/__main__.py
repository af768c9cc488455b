"""``python -m rcbf_ros``: the ``rcbf_ros`` command."""
import sys

from rcbf_ros.cli.main import main

sys.exit(main())
