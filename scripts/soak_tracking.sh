#!/usr/bin/env bash
# Memory soak of the navigation node (not part of the test command): starts a ROS master and the node
# (config/node.yaml, the phantom at TARGET elements), then bench/ros/tracking_soak.cpp, which
# resets and precomputes the node RESETS times and tracks the phantom tracker's clouds at RATE Hz
# for MINUTES, and prints the node's resident memory (docs/tracking.md, "Memory").
# Usage: scripts/soak_tracking.sh [MINUTES=30] [RATE=30] [TARGET=20000] [RESETS=8] [JSON]
# Needs the catkin workspace built (scripts/run_main.sh or scripts/run_tests.sh).
set -euo pipefail
source "$(dirname "$0")/common.sh"
minutes="${1:-30}"; rate="${2:-30}"; target="${3:-20000}"; resets="${4:-8}"; json="${5:-}"
tools="${BREAST_SIM_WS}/devel/lib/breast_sim"
[ -x "${tools}/tracking_soak" ] || { log "build the workspace first: ${tools}/tracking_soak is missing"; exit 1; }
export ROS_MASTER_URI="http://127.0.0.1:${BREAST_SIM_SOAK_PORT:-11511}"
set +u; source "${BREAST_SIM_WS}/devel/setup.bash"; set -u
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; }
trap cleanup EXIT
rosmaster --core -p "${ROS_MASTER_URI##*:}" >/dev/null 2>&1 & pids+=($!)
sleep 2
rosparam load "${BREAST_SIM_SRC}/config/node.yaml" /breast_sim
rosparam set /breast_sim/case_file "${BREAST_SIM_SRC}/config/phantom_default.yaml"
rosparam set /breast_sim/target_elements "${target}"
"${tools}/breast_sim_node" __name:=breast_sim >"${BREAST_SIM_WORK}/soak_node.log" 2>&1 & node=$!; pids+=($node)
log "node pid ${node} (log ${BREAST_SIM_WORK}/soak_node.log); soak: ${minutes} min at ${rate} Hz, ${target} elements, ${resets} resets"
"${tools}/tracking_soak" --pid "${node}" --minutes "${minutes}" --rate "${rate}" --resets "${resets}" ${json:+--json "${json}"}
