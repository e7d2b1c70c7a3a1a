#!/usr/bin/env bash
# Quick-start command 2: every test. Installs what it needs (Debian 12, as root), builds the core
# alone with plain CMake and runs its unit tests (proving the core builds without ROS), then builds
# the catkin workspace and runs the ROS tests (gtest + rostest). Ends with "N passed, N failed".
set -uo pipefail
source "$(dirname "$0")/common.sh"
mkdir -p "${BREAST_SIM_WORK}"
install_deps || { echo "0 passed, 1 failed"; exit 1; }
ensure_localhost_resolves

results="${BREAST_SIM_WORK}/test_results"
rm -rf "${results}"; mkdir -p "${results}/core"
status=0

# 1. The ROS-free core and its unit tests (gtest XML per executable).
if build_core; then
  log "running core unit tests"
  (cd "${BREAST_SIM_CORE_BUILD}" && GTEST_OUTPUT="xml:${results}/core/" \
     ctest --output-on-failure -j"${BREAST_SIM_JOBS}" --timeout 900) || status=1
  # A test executable that crashed or timed out wrote no XML: count it as a failure by name.
  for name in $(cd "${BREAST_SIM_CORE_BUILD}" && ctest -N | awk '/Test +#[0-9]+:/ {print $3}'); do
    [ -f "${results}/core/${name}.xml" ] || echo "${name} wrote no result (crashed or timed out)" > "${results}/core_${name}.failed"
  done
else
  log "the core failed to build"; status=1
  echo "the core failed to build" > "${results}/core_build.failed"
fi

# 2. The catkin workspace: ROS layer, nodes, conversion tests and rostests.
if build_catkin_ws && (cd "${BREAST_SIM_WS}" && catkin_make -j"${BREAST_SIM_JOBS}" tests \
      -DCMAKE_BUILD_TYPE=Release -DPYTHON_EXECUTABLE=/usr/bin/python3 >/dev/null); then
  log "running ROS tests"
  rm -rf "${BREAST_SIM_WS}/build/test_results"
  # ROS's setup scripts read unset variables: source them without -u.
  (set +u; cd "${BREAST_SIM_WS}" && source devel/setup.bash && \
     catkin_make run_tests -j1 -DCMAKE_BUILD_TYPE=Release -DPYTHON_EXECUTABLE=/usr/bin/python3) || true
  mkdir -p "${results}/ros"
  cp -r "${BREAST_SIM_WS}/build/test_results/breast_sim/." "${results}/ros/" 2>/dev/null || true
  if ! ls "${results}/ros/"*.xml >/dev/null 2>&1; then
    echo "the ROS tests wrote no result" > "${results}/ros_tests.failed"
  fi
else
  log "the catkin workspace failed to build"; status=1
  echo "the catkin workspace failed to build" > "${results}/catkin_build.failed"
fi

# 3. Count every test case (gtest and rostest) from the XML results.
/usr/bin/python3 "${BREAST_SIM_SRC}/scripts/count_test_results.py" "${results}"
count_status=$?
[ ${count_status} -ne 0 ] && status=1
exit ${status}
