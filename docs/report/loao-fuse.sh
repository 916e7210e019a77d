#!/usr/bin/env bash
# Leave-one-alphabet-out of a fused model: for each fold, the fold's branch models (trained
# by `TRAIN_ONLY=1 docs/report/loao-full.sh`, one run per branch, e.g. the sequence and the
# picture network with --embed-dim 64) fused into OUTDIR/<alphabet>/model.safetensors
# (`guardian-lab fuse`), then measured like any fold model (loao-full.sh with EVAL_ONLY=1)
# and with the cross-fitted calibration (crossfit.sh).
# Usage: docs/report/loao-fuse.sh DATASET OUTDIR BRANCHDIR...
# FUSE_ARGS: extra options for `guardian-lab fuse` (e.g. --no-reverse-average).
set -euo pipefail
dataset=$1; out=$2; shift 2
lab=${GUARDIAN_LAB:-target/release/guardian-lab}
here=$(dirname "$0")
alphabets=(Balinese Early_Aramaic Greek "Japanese_(katakana)" Korean Latin)
for a in "${alphabets[@]}"; do
  fold=${a//[()]/}
  mkdir -p "$out/$fold"
  branches=()
  for b in "$@"; do branches+=("$b/$fold/model.safetensors"); done
  [[ -f $out/$fold/model.safetensors ]] || \
    "$lab" fuse "${branches[@]}" ${FUSE_ARGS:-} --out "$out/$fold/model.safetensors" > "$out/$fold/fuse.log"
done
EVAL_ONLY=1 "$here/loao-full.sh" "$dataset" "$out"
"$here/crossfit.sh" "$dataset" "$out"
