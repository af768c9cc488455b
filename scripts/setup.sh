#!/usr/bin/env bash
# Create .venv (if missing) and install rcbf_ros with every dependency, pinned by constraints.txt.
# torch MUST come from the pin (torch==2.13.0, a CPU wheel): an unpinned torch pulls a CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -c constraints.txt torch==2.13.0
.venv/bin/python -m pip install --quiet -c constraints.txt -e '.[standalone,test]'
echo "rcbf_ros installed in $(pwd)/.venv"
