#!/usr/bin/env bash
# Regenerates the recorded tracker bag of the tests and the demo from the phantom (deterministic):
# test/data/tracking_phantom.bag — 10 s, clouds of 2500 points at 10 Hz in the `tracker` frame,
# patient poses at 20 Hz, /tf_static world -> tracker (see src/nodes/make_test_bags_main.cpp and
# include/breast_sim/ros_interface/tracker_simulation.h). Needs the catkin workspace built.
set -euo pipefail
source "$(dirname "$0")/common.sh"
tool="${BREAST_SIM_WS}/devel/lib/breast_sim/make_test_bags"
[ -x "${tool}" ] || { log "build the workspace first (scripts/run_main.sh): ${tool} is missing"; exit 1; }
(set +u; source "${BREAST_SIM_WS}/devel/setup.bash"; \
  "${tool}" --case "${BREAST_SIM_SRC}/config/phantom_default.yaml" --out "${BREAST_SIM_SRC}/test/data/tracking_phantom.bag" \
    --seconds 10 --cloud-rate 10 --pose-rate 20 --points 2500 --noise-mm 0.5 --seed 1 --start 100 "$@")
