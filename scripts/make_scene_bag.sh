#!/usr/bin/env bash
# Writes a recorded tracking scene of the phantom (deterministic for a seed): a depth camera and a
# hand-held scanner of their own, a hand over the skin, the torso, the patient's pose on tf only, bad
# inputs at known times and a 20 mm drift along the chest wall at the end; see
# include/breast_sim/ros_interface/scene_recording.h. The scene rostest (test/ros/scene.test) makes
# its own from the node's precomputed skin; this is for replaying the scene by hand (rviz, a node
# under study). Needs the catkin workspace built.
# Usage: scripts/make_scene_bag.sh [OUT_BAG] [make_scene_bag options, e.g. --seed 2 --target-elements 3000]
# Beside the bag, OUT_BAG.yaml describes it.
set -euo pipefail
source "$(dirname "$0")/common.sh"
out="${1:-${BREAST_SIM_WORK}/scene.bag}"; shift || true
tool="${BREAST_SIM_WS}/devel/lib/breast_sim/make_scene_bag"
[ -x "${tool}" ] || { log "build the workspace first (scripts/run_main.sh): ${tool} is missing"; exit 1; }
mkdir -p "$(dirname "${out}")"
(set +u; source "${BREAST_SIM_WS}/devel/setup.bash"; \
  "${tool}" --case "${BREAST_SIM_SRC}/config/phantom_default.yaml" --target-elements 3000 \
    --settings "${BREAST_SIM_SRC}/test/data/navigation_settings.yaml" --seed 1 --out "${out}" "$@")
