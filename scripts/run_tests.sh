#!/usr/bin/env bash
# Quick-start command 2: every test. Installs what it needs (Debian 12, as root), builds the core
# alone with plain CMake and runs its unit tests (proving the core builds without ROS), runs a smoke
# of every file reader's fuzz target and the reader layers' tests under ASan + UBSan (clang), then
# builds the catkin workspace and runs the ROS tests (gtest + rostest). Ends with "N passed, N failed".
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

# 2. The file readers under clang's AddressSanitizer and UndefinedBehaviorSanitizer, one build
#    (${BREAST_SIM_WORK}/fuzz_build, fuzz/CMakeLists.txt) for both: a smoke of every fuzz target (its
#    seed corpus, then 3 s of new inputs; a crash, a sanitizer report or an error that does not name
#    its file fails it), and the core tests of the reader layers. Longer runs: scripts/fuzz.sh SECONDS.
mkdir -p "${results}/fuzz" "${results}/sanitizer"
log "fuzz smoke of every file reader (ASan + UBSan)"
BREAST_SIM_WORK="${BREAST_SIM_WORK}" bash "${BREAST_SIM_SRC}/scripts/fuzz.sh" 3 --fresh --junit "${results}/fuzz/fuzz_smoke.xml" \
  || status=1
[ -f "${results}/fuzz/fuzz_smoke.xml" ] || echo "the fuzz targets failed to build or run" > "${results}/fuzz_smoke.failed"
fuzz_build="${BREAST_SIM_WORK}/fuzz_build"
if [ -f "${fuzz_build}/CMakeCache.txt" ] && cmake --build "${fuzz_build}" -j"${BREAST_SIM_JOBS}" --target sanitizer_tests; then
  log "running the reader layers' core tests under ASan + UBSan"
  # A sanitizer report aborts the test (-fno-sanitize-recover), which then writes no XML; a leak is
  # reported at exit, after the XML: the exit status counts too.
  for name in $(cd "${fuzz_build}" && ctest -N | awk '/Test +#[0-9]+:/ {print $3}'); do
    (cd "${fuzz_build}" && GTEST_OUTPUT="xml:${results}/sanitizer/${name}.xml" UBSAN_OPTIONS="print_stacktrace=1" \
       ctest -R "^${name}\$" --timeout 600 --output-on-failure > "${results}/sanitizer/${name}.log" 2>&1)
    code=$?
    if [ ! -f "${results}/sanitizer/${name}.xml" ] || { [ ${code} -ne 0 ] && ! grep -q "<failure" "${results}/sanitizer/${name}.xml"; }; then
      echo "${name} under the sanitizers exited with status ${code} (a sanitizer report, a crash or a timeout; ${results}/sanitizer/${name}.log)" \
        > "${results}/sanitizer_${name}.failed"
      grep -m3 -E "ERROR: (Address|Leak)Sanitizer|runtime error:" "${results}/sanitizer/${name}.log"
      status=1
    fi
    [ ${code} -ne 0 ] && status=1
  done
else
  log "the sanitizer build failed"; status=1
  echo "the sanitizer build of the reader tests failed" > "${results}/sanitizer_build.failed"
fi

# 3. The catkin workspace: ROS layer, nodes, conversion tests and rostests.
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

# 4. Count every test case (gtest, rostest, fuzz smoke) from the XML results.
/usr/bin/python3 "${BREAST_SIM_SRC}/scripts/count_test_results.py" "${results}"
count_status=$?
[ ${count_status} -ne 0 ] && status=1
exit ${status}
