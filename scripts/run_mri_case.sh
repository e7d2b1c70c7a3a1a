#!/usr/bin/env bash
# The MRI path end to end on data no one here designed: renders the VICTRE phantom as a synthetic prone
# T1 MRI (a DICOM series, the same volume as NIfTI, and its truth) into output_mri/victre_t1/, then runs
# config/victre_mri_case.yaml on it: the automatic segmentation (Dice and chest-wall boundary distance
# against the truth printed), the model, the prone-to-supine pipeline and the simulated supine MRI,
# written to output_mri/ (or the folder given as first argument). Installs what it needs (Debian 12,
# as root) and builds the catkin workspace outside the source tree, as scripts/run_main.sh does.
# Usage: scripts/run_mri_case.sh [OUTPUT_DIR] [extra breast_sim_run options]
set -euo pipefail
source "$(dirname "$0")/common.sh"
out="${1:-${BREAST_SIM_SRC}/output_mri}"; shift || true
mkdir -p "${BREAST_SIM_WORK}"
install_deps
build_catkin_ws
bin="${BREAST_SIM_WS}/devel/lib/breast_sim"
mri="${BREAST_SIM_SRC}/output_mri/victre_t1"   # where config/victre_mri_case.yaml reads it
log "rendering the VICTRE phantom as a prone T1 MRI → ${mri}"
rm -rf "${mri}"
mkdir -p "${mri}"
"${bin}/breast_sim_make_mri" "${BREAST_SIM_SRC}/test/data/victre_labels_1mm.nrrd" --out "${mri}/prone_t1.nii.gz" \
  --truth "${mri}/truth.nrrd" --dicom "${mri}/dicom"
log "MRI case: segmentation, model, supine gravity and sliding, simulated supine MRI → ${out}"
run_case "${BREAST_SIM_SRC}/config/victre_mri_case.yaml" "${out}" "$@"
