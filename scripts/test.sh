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
.venv/bin/python -m pytest -ra "$@"
rc=$?
if [ "$rc" -eq 5 ]; then
  echo 'pytest collected no tests: treating as failure'
  exit 1
fi
exit "$rc"
