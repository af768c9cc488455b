#!/usr/bin/env bash
# Set up, lint, and run the whole test suite (unit + integration over real DDS on loopback).
# Extra arguments go to pytest (e.g. -m "not slow").
set -uo pipefail
cd "$(dirname "$0")/.."
./scripts/setup.sh || exit 1
# Before any DDS participant exists: loopback only, and a domain id of this run's own.
export CYCLONEDDS_URI="$(.venv/bin/python -c 'from rcbf_ros.ros.loopback import LOOPBACK_CYCLONEDDS_URI as u; print(u)')"
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( $$ % 150 + 20 ))}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
.venv/bin/ruff check . || { echo 'lint failed'; exit 1; }
# The ros2 tier (a real ROS 2 Jazzy, sourced or at /opt/rcbf_jazzy) runs or is skipped; the
# last line says which, and why.
export RCBF_ROS2_TIER_REPORT="$(mktemp)"
.venv/bin/python -m pytest -ra "$@"
rc=$?
cat "$RCBF_ROS2_TIER_REPORT" 2>/dev/null; rm -f "$RCBF_ROS2_TIER_REPORT"
if [ "$rc" -eq 5 ]; then
  echo 'pytest collected no tests: treating as failure'
  exit 1
fi
exit "$rc"
