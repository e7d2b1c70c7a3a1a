#!/usr/bin/env bash
# Renders the rviz demo (launch/demo.launch: the recorded phantom tracker bag, the node precomputing
# and following it, rviz with rviz/breast_sim.rviz) on a virtual X server (Xvfb, software OpenGL) and
# saves a screenshot. Usage: bash scripts/rviz_screenshot.sh [OUT.png] (default docs/ros/rviz.png).
# Environment: RVIZ_SCREENSHOT_WAIT_S (seconds of demo before the shot, default 60),
# BREAST_SIM_WORK (where builds and logs live, as for the other scripts), RVIZ_SCREENSHOT_WS (a catkin
# workspace to run instead of ${BREAST_SIM_WORK}/catkin_ws), RVIZ_SCREENSHOT_PORT (the demo's ROS
# master port; default 11400 + the display number). Needs the workspace built (scripts/run_main.sh
# or run_tests.sh) and the Debian packages rviz and xvfb (scripts/install_deps.sh).
set -euo pipefail
source "$(dirname "$0")/common.sh"
BREAST_SIM_WS="${RVIZ_SCREENSHOT_WS:-${BREAST_SIM_WS}}"
out="${1:-${BREAST_SIM_SRC}/docs/ros/rviz.png}"
wait_s="${RVIZ_SCREENSHOT_WAIT_S:-60}"
[ -f "${BREAST_SIM_WS}/devel/setup.bash" ] || { log "no catkin workspace at ${BREAST_SIM_WS}; run scripts/run_main.sh first"; exit 1; }
command -v Xvfb >/dev/null || { log "Xvfb is missing: apt-get install xvfb"; exit 1; }
command -v rviz >/dev/null || { log "rviz is missing: apt-get install rviz"; exit 1; }

# A free display number and a master of our own, so a running ROS graph is not disturbed.
display=90
while [ -e "/tmp/.X${display}-lock" ]; do display=$((display + 1)); done
port="${RVIZ_SCREENSHOT_PORT:-$((11400 + display))}"
export ROS_MASTER_URI="http://127.0.0.1:${port}"
mkdir -p "${ROS_LOG_DIR}" "$(dirname "${out}")"

Xvfb ":${display}" -screen 0 1080x720x24 -nolisten tcp >/dev/null 2>&1 &
xvfb_pid=$!
launch_pid=""
cleanup() {
  [ -n "${launch_pid}" ] && kill -INT "${launch_pid}" 2>/dev/null && sleep 3 && kill "${launch_pid}" 2>/dev/null || true
  kill "${xvfb_pid}" 2>/dev/null || true
}
trap cleanup EXIT
sleep 2
export DISPLAY=":${display}" LIBGL_ALWAYS_SOFTWARE=1 QT_X11_NO_MITSHM=1
(set +u; source "${BREAST_SIM_WS}/devel/setup.bash"; \
  exec roslaunch -p "${port}" breast_sim demo.launch bag_delay_s:=20) > "${BREAST_SIM_WORK}/rviz_screenshot.log" 2>&1 &
launch_pid=$!
log "demo running on display :${display} (log: ${BREAST_SIM_WORK}/rviz_screenshot.log); screenshot in ${wait_s} s"
sleep "${wait_s}"
kill -0 "${launch_pid}" 2>/dev/null || { log "the demo ended early:"; tail -20 "${BREAST_SIM_WORK}/rviz_screenshot.log"; exit 1; }
/usr/bin/python3 - "${display}" "${out}" <<'PY'
import sys
from PIL import ImageGrab
im = ImageGrab.grab(xdisplay=":" + sys.argv[1])
if im.getextrema() in (((0, 0), (0, 0), (0, 0)),):
    sys.exit("the screen is black: rviz did not draw (see the log)")
im.save(sys.argv[2])
print("[breast_sim] saved", sys.argv[2], im.size)
PY
