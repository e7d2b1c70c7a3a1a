#!/usr/bin/env bash
# Builds the fuzz targets of every file reader (fuzz/, clang with ASan + UBSan) and runs each for
# SECONDS (default 60) on its seed corpus (written fresh from the test data and the core's writers)
# and its growing corpus; prints the executions per target and any crash with its reproducer.
#
#   scripts/fuzz.sh [SECONDS] [--fresh] [--junit FILE] [TARGET ...]
#
#   --fresh       start from the seeds alone (an empty corpus folder), as the test command's smoke does
#   --junit FILE  also write one JUnit test case per target (scripts/count_test_results.py counts them)
#   TARGET        fuzz_nrrd, fuzz_vtu, ... (default: every target)
#
# Builds (niced, like the fuzzers) in ${BREAST_SIM_WORK}/fuzz_build; corpora, seeds and reproducers in
# ${BREAST_SIM_WORK}/fuzz/ (docs/reliability.md).
# Re-run a reproducer: ${BREAST_SIM_WORK}/fuzz_build/fuzz_<format> <file>. Exit status 1 on any crash.
set -uo pipefail
source "$(dirname "$0")/common.sh"

seconds=60
fresh=0
junit=""
targets=()
while [ $# -gt 0 ]; do
  case "$1" in
    --fresh) fresh=1 ;;
    --junit) junit="$2"; shift ;;
    [0-9]*) seconds="$1" ;;
    *) targets+=("$1") ;;
  esac
  shift
done

build="${BREAST_SIM_WORK}/fuzz_build"
work="${BREAST_SIM_WORK}/fuzz"
mkdir -p "${work}"

build_fuzz() {
  log "building the fuzz targets (clang, ASan + UBSan) in ${build}"
  forget_foreign_build "${build}" "${BREAST_SIM_SRC}/fuzz"
  cmake -S "${BREAST_SIM_SRC}/fuzz" -B "${build}" -DCMAKE_C_COMPILER=clang-14 -DCMAKE_CXX_COMPILER=clang++-14 \
    >"${work}/configure.log" 2>&1 || { cat "${work}/configure.log"; return 1; }
  nice -n 10 cmake --build "${build}" -j"${BREAST_SIM_JOBS}" --target fuzz_targets fuzz_seeds
}

build_fuzz || { echo "the fuzz targets failed to build"; exit 1; }
[ ${#targets[@]} -eq 0 ] && mapfile -t targets < "${build}/fuzz_targets.txt"

rm -rf "${work}/seeds"
"${build}/fuzz_seeds" "${work}/seeds" >"${work}/seeds.log" 2>&1 || { cat "${work}/seeds.log"; exit 1; }
tmp="${work}/tmp"
rm -rf "${tmp}"; mkdir -p "${tmp}"

printf '%-18s %12s %10s %8s  %s\n' target executions "exec/s" corpus result
status=0
cases=""
for t in "${targets[@]}"; do
  corpus="${work}/corpus/${t}"
  [ ${fresh} -eq 1 ] && corpus="${tmp}/corpus_${t}"
  artifacts="${work}/artifacts/${t}"
  mkdir -p "${corpus}" "${artifacts}" "${work}/seeds/${t}"
  # Findings are crash-, leak-, oom- and timeout- files; slow-unit- files (an input slower than 10 s,
  # often only a loaded machine) are reported, not counted.
  findings() { ls "${artifacts}" | grep -v '^slow-unit-' | wc -l; }
  before=$(findings)
  logfile="${work}/${t}.log"
  dict="${BREAST_SIM_SRC}/fuzz/dict/${t}.dict"
  # -malloc_limit_mb: no input of a few kB may allocate 512 MB at once (a size taken from a header);
  # -timeout: a slow input is reported like a crash. The readers' temporary files go to ${tmp}.
  TMPDIR="${tmp}" ASAN_OPTIONS="${ASAN_OPTIONS:-}" nice -n 10 "${build}/${t}" \
      -max_total_time="${seconds}" -print_final_stats=1 -timeout=20 -rss_limit_mb=2048 \
      -malloc_limit_mb=512 -artifact_prefix="${artifacts}/" \
      $( [ -f "${dict}" ] && echo "-dict=${dict}" ) \
      "${corpus}" "${work}/seeds/${t}" >"${logfile}" 2>&1
  code=$?
  execs=$(awk '/stat::number_of_executed_units:/ {print $2}' "${logfile}" | tail -1)
  rate=$(awk '/stat::average_exec_per_sec:/ {print $2}' "${logfile}" | tail -1)
  size=$(ls "${corpus}" | wc -l)
  reproducer=$(grep -o 'Test unit written to [^ ]*' "${logfile}" | grep -v slow-unit | tail -1 | sed 's/Test unit written to //')
  slowest=$(grep -o 'Slowest unit: [0-9]* s' "${logfile}" | tail -1 | sed 's/Slowest unit: //')
  if [ ${code} -eq 0 ] && [ "$(findings)" -eq "${before}" ]; then
    result="clean${slowest:+ (slowest input ${slowest})}"
    cases+="<testcase classname=\"fuzz_smoke\" name=\"${t}\" time=\"${seconds}\"/>"
  else
    status=1
    what=$(grep -m1 -E 'ERROR: (AddressSanitizer|libFuzzer|LeakSanitizer)|runtime error:|unexpected exception|does not name the file' "${logfile}" | cut -c1-200)
    result="CRASH (exit ${code}): ${what:-see ${logfile}}; reproducer: ${reproducer:-none written}"
    cases+="<testcase classname=\"fuzz_smoke\" name=\"${t}\"><failure message=\"$(echo "${result}" | sed 's/&/\&amp;/g; s/</\&lt;/g; s/"/\&quot;/g')\"/></testcase>"
  fi
  printf '%-18s %12s %10s %8s  %s\n' "${t}" "${execs:-0}" "${rate:-0}" "${size}" "${result}"
done
rm -rf "${tmp}"
if [ -n "${junit}" ]; then
  mkdir -p "$(dirname "${junit}")"
  echo "<?xml version=\"1.0\"?><testsuites><testsuite name=\"fuzz_smoke\">${cases}</testsuite></testsuites>" > "${junit}"
fi
exit ${status}
