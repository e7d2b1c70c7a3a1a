#!/usr/bin/env bash
# Quick-start command 1: the main job on the built-in phantom.
# Installs what it needs (Debian 12, as root), builds the catkin workspace outside the source tree,
# builds the simulation model of the phantom and writes the results to an output folder.
# Usage: scripts/run_main.sh [OUTPUT_DIR] [extra breast_sim_run options]
set -euo pipefail
source "$(dirname "$0")/common.sh"
out="${1:-${BREAST_SIM_SRC}/output}"; shift || true
mkdir -p "${BREAST_SIM_WORK}"
install_deps
build_catkin_ws
log "main job: phantom model, supine gravity and morphing to the supine target → ${out}"
run_case "${BREAST_SIM_SRC}/config/phantom_default.yaml" "${out}" "$@"
