#!/usr/bin/env bash
# Installs every Debian 12 package breast_sim needs to build, test and run: one list, idempotent.
# Run as root (or with sudo available). Safe to call again: apt-get skips what is already there.
set -euo pipefail

PACKAGES=(
  # toolchain
  build-essential cmake git pkg-config ca-certificates
  # core numerics and science libraries
  libeigen3-dev libsuitesparse-dev libopenblas0-pthread libopenblas-pthread-dev
  libcgal-dev libgmp-dev libmpfr-dev libboost-dev libboost-program-options-dev
  libvtk9-dev libpcl-dev libopencv-dev libyaml-cpp-dev zlib1g-dev nlohmann-json3-dev
  libgtest-dev googletest
  # reference solver (speed-accuracy study, test_reference): CalculiX
  calculix-ccx
  # MRI volumes (NIfTI, NRRD, MetaImage, DICOM series through GDCM), their filters and resampling
  libinsighttoolkit5-dev
  # fuzz targets (libFuzzer) and the sanitizer build of the core tests (ASan, UBSan)
  clang-14 libclang-rt-14-dev
  # ROS 1 (Debian ships it into /usr)
  ros-core-dev catkin python3-catkin-pkg python3-rostest librostest-dev
  ros-message-generation ros-message-runtime libroscpp-dev
  libstd-msgs-dev libsensor-msgs-dev libgeometry-msgs-dev libvisualization-msgs-dev
  libtf2-ros-dev libpcl-conversions-dev
  libstd-srvs-dev libdiagnostic-msgs-dev libtf2-msgs-dev libtf2-geometry-msgs-dev
  libactionlib-dev libactionlib-msgs-dev librosbag-dev librosbag-storage-dev python3-rosbag
  # rviz demo and its headless screenshot (scripts/rviz_screenshot.sh)
  rviz xvfb
  # scripts (charts, checks) use Debian's python
  python3-numpy python3-yaml python3-matplotlib
)

if [ "$(id -u)" -eq 0 ]; then SUDO=""; else SUDO="sudo"; fi

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "[install_deps] all ${#PACKAGES[@]} packages present"
  exit 0
fi
echo "[install_deps] installing ${#missing[@]} packages: ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
# CHOLMOD is ~20x faster with OpenBLAS than with the reference BLAS; make sure it is the one selected.
for alt in libblas.so.3-x86_64-linux-gnu liblapack.so.3-x86_64-linux-gnu; do
  cand=$(update-alternatives --list "$alt" 2>/dev/null | grep openblas-pthread | head -1 || true)
  [ -n "$cand" ] && $SUDO update-alternatives --set "$alt" "$cand" >/dev/null || true
done
echo "[install_deps] done"
