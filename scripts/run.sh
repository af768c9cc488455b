#!/usr/bin/env bash
# The main job: set up, then train SAC-RCBF on the Unicycle with the simulator, the safety
# filter, the learner, the scene markers and the recorder as separate processes over DDS
# (loopback only); the summary at the end draws the run's trajectories.
#   EPISODES=8 MODE=modular SYSTEM=unicycle ./scripts/run.sh
# Ctrl-C stops every process; the learner still writes its checkpoint, policy and plot.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/setup.sh
SYSTEM=${SYSTEM:-unicycle}
EPISODES=${EPISODES:-8}
MODE=${MODE:-modular}
SEED=${SEED:-0}
RUN=${RUN:-bags/${SYSTEM}_${MODE}_$(date -u +%Y%m%d-%H%M%S)}
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( $$ % 150 + 20 ))}
echo "training $MODE on $SYSTEM for $EPISODES episodes -> $RUN (ROS_DOMAIN_ID=$ROS_DOMAIN_ID)"
status=0
.venv/bin/python -m rcbf_ros launch "${SYSTEM}_learner" \
  -p "learner:episodes:=$EPISODES" -p "learner:mode:=$MODE" -p "learner:seed:=$SEED" \
  -p "simulator:seed:=$SEED" -p "learner:out_dir:=$RUN/learner" \
  -p "recorder:output:=$RUN/bag" -p "safety_filter:compile_assembly:=true" || status=$?
echo
# The launch's exit code comes first; the summary's counts when the launch succeeded.
.venv/bin/python -m rcbf_ros summary "$RUN" || { rc=$?; [ "$status" -ne 0 ] || status=$rc; }
exit "$status"
