"""``python -m rcbf_ros.bag recover|check BAG`` (as ``rcbf_ros bag``)."""
import sys

from rcbf_ros.bag.recover import main

sys.exit(main())
