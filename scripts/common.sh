# Shared set-up for the quick-start commands. Source it; it does not run anything by itself.
# Debian's ROS 1 lives in /usr and needs Debian's python3, so /usr/bin goes first in PATH.
export PATH="/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin:${PATH}"
BREAST_SIM_SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# Everything built lives outside the source tree.
BREAST_SIM_WORK="${BREAST_SIM_WORK:-${HOME:-/root}/.cache/breast_sim}"
BREAST_SIM_WS="${BREAST_SIM_WORK}/catkin_ws"
BREAST_SIM_CORE_BUILD="${BREAST_SIM_WORK}/core_build"
BREAST_SIM_JOBS="${BREAST_SIM_JOBS:-$(nproc)}"
export ROS_HOME="${BREAST_SIM_WORK}/ros_home"
export ROS_LOG_DIR="${ROS_HOME}/log"
# ROS nodes of the tests talk over loopback by address, so a machine whose hostname does not
# resolve (a fresh container, a chroot) still runs them. Callers may override both.
export ROS_IP="${ROS_IP:-127.0.0.1}"
export ROS_MASTER_URI="${ROS_MASTER_URI:-http://127.0.0.1:11311}"
unset ROS_HOSTNAME

log() { printf '[breast_sim] %s\n' "$*"; }

install_deps() {
  bash "${BREAST_SIM_SRC}/scripts/install_deps.sh"
}

# roslaunch (and so rostest) resolves the name "localhost"; a minimal root file system (a container,
# a chroot) may have no /etc/hosts at all.
ensure_localhost_resolves() {
  if ! getent hosts localhost >/dev/null 2>&1; then
    if [ -w /etc/hosts ] || [ ! -e /etc/hosts ] && [ "$(id -u)" -eq 0 ]; then
      log "'localhost' does not resolve here: adding '127.0.0.1 localhost' to /etc/hosts"
      printf '127.0.0.1\tlocalhost\n::1\tlocalhost ip6-localhost ip6-loopback\n' >> /etc/hosts
    else
      log "warning: 'localhost' does not resolve and /etc/hosts is not writable; rostest will fail"
    fi
  fi
}

# Builds the catkin workspace (Release, -O3) with this checkout linked in as src/breast_sim.
build_catkin_ws() {
  mkdir -p "${BREAST_SIM_WS}/src" "${ROS_LOG_DIR}"
  ln -sfn "${BREAST_SIM_SRC}" "${BREAST_SIM_WS}/src/breast_sim"
  log "building catkin workspace ${BREAST_SIM_WS} (Release, -O3)"
  (cd "${BREAST_SIM_WS}" && catkin_make -j"${BREAST_SIM_JOBS}" \
      -DCMAKE_BUILD_TYPE=Release -DPYTHON_EXECUTABLE=/usr/bin/python3 "$@")
}

# A CMake build folder made for another source folder cannot be reused: remove it so it starts afresh.
#   forget_foreign_build BUILD_DIR SOURCE_DIR
forget_foreign_build() {
  local cache="$1/CMakeCache.txt"
  if [ -f "${cache}" ] && ! grep -qx "CMAKE_HOME_DIRECTORY:INTERNAL=$2" "${cache}"; then
    log "the build folder $1 belongs to another checkout; rebuilding it"
    rm -rf "$1"
  fi
}

# Builds the ROS-free core with plain CMake (catkin is never looked for).
build_core() {
  log "building the ROS-free core with plain CMake in ${BREAST_SIM_CORE_BUILD}"
  mkdir -p "${BREAST_SIM_WORK}"
  forget_foreign_build "${BREAST_SIM_CORE_BUILD}" "${BREAST_SIM_SRC}"
  cmake -S "${BREAST_SIM_SRC}" -B "${BREAST_SIM_CORE_BUILD}" -DBREAST_SIM_CORE_ONLY=ON \
        -DCMAKE_BUILD_TYPE=Release >"${BREAST_SIM_WORK}/core_configure.log" 2>&1 \
    || { cat "${BREAST_SIM_WORK}/core_configure.log"; return 1; }
  cmake --build "${BREAST_SIM_CORE_BUILD}" -j"${BREAST_SIM_JOBS}" "$@"
}

# Runs breast_sim_run on a case and exits with its status, except exit 3 (a stage stopped at its step
# limit or short of its tolerance; every output is written, see metrics.json): a note, and exit 0.
#   run_case CASE_FILE OUT_DIR [breast_sim_run options]
run_case() {
  local case_file="$1" out="$2" status=0
  shift 2
  "${BREAST_SIM_WS}/devel/lib/breast_sim/breast_sim_run" --case "${case_file}" --out "${out}" "$@" || status=$?
  if [ "${status}" -eq 3 ]; then
    log "NOTE: a stage did not converge or reach its tolerance (exit 3); the results are written, see ${out}/metrics.json"
    exit 0
  fi
  exit "${status}"
}
