#!/usr/bin/env bash
# Leave-one-alphabet-out with every figure of the generalisation issue: for each shared
# alphabet A, train on four of the others and validate (early stopping, LR schedule) on the
# next one in the list; then on A (never seen in training, validation or calibration):
# 1-shot 2/10/20-way and 5-shot 20-way accuracy (`eval`, 2,000 episodes, seed 0), and the
# go/no-go figures (`outliers`, 5 shots, calibrated on the fold's validation alphabet).
# Usage: docs/report/loao-full.sh DATASET OUTDIR [extra train args...]
# Writes OUTDIR/<alphabet>/{eval.jsonl,outliers.json}; summarise with
# docs/report/loao-full-summary.py OUTDIR.
# TRAIN_ONLY=1: train the fold models, measure nothing (the branches of a fused model).
# EVAL_ONLY=1: measure the OUTDIR/<alphabet>/model.safetensors already there (a fused model
# made by `guardian-lab fuse`, docs/report/loao-fuse.sh), train nothing.
# NO_VAL=1: train on all five other alphabets without validation (needs --schedule
# one-cycle, which keeps the last model); the go/no-go figures calibrated on the validation
# alphabet are then skipped (it was trained on): use crossfit.sh's.
set -euo pipefail
dataset=$1; out=$2; shift 2
lab=${GUARDIAN_LAB:-target/release/guardian-lab}
strokes=${STROKES:-../shared/omniglot/strokes}
alphabets=(Balinese Early_Aramaic Greek "Japanese_(katakana)" Korean Latin)
if [[ -n ${FOLDS:-} ]]; then IFS=, read -r -a folds <<< "$FOLDS"; else folds=("${alphabets[@]}"); fi
n=${#alphabets[@]}
mkdir -p "$out"
for i in "${!alphabets[@]}"; do
  test_a=${alphabets[$i]}
  [[ " ${folds[*]} " == *" $test_a "* ]] || continue
  val_a=${alphabets[$(( (i + 1) % n ))]}
  held_out=("$test_a"); val=()
  [[ -z ${NO_VAL:-} ]] && { held_out+=("$val_a"); val=(--val-alphabets "$val_a"); }
  train=()
  for a in "${alphabets[@]}"; do
    [[ " ${held_out[*]} " == *" $a "* ]] || train+=("$a")
  done
  dir="$out/${test_a//[()]/}"
  if [[ -z ${EVAL_ONLY:-} ]] && { [[ ! -f $dir/state.json ]] || ! grep -q '"finished": true' "$dir/state.json"; }; then
    resume=(); [[ -f $dir/state.json ]] && resume=(--resume)
    mkdir -p "$dir"
    "$lab" train --dataset "$dataset" --train-alphabets "$(IFS=,; echo "${train[*]}")" \
      "${val[@]}" --out "$dir" --quiet --strokes "$strokes" "${resume[@]}" "$@" \
      > "$dir.train.log" 2>&1
  fi
  [[ -n ${TRAIN_ONLY:-} ]] && continue
  if [[ ! -s $dir/eval.jsonl ]]; then
    for spec in "2 1" "10 1" "20 1" "20 5"; do
      read -r way shot <<< "$spec"
      "$lab" eval --model "$dir/model.safetensors" --dataset "$dataset" --alphabets "$test_a" \
        --way "$way" --shot "$shot" --episodes 2000 --seed 0 --json
    done > "$dir/eval.jsonl.tmp"
    mv "$dir/eval.jsonl.tmp" "$dir/eval.jsonl"
  fi
  if [[ -z ${NO_VAL:-} && ! -s $dir/outliers.json ]]; then
    "$lab" outliers --model "$dir/model.safetensors" --dataset "$dataset" --strokes "$strokes" \
      --alphabets "$test_a" --calib-alphabets "$val_a" --shots 5 --target-frr 0.01 \
      --geometry-share 0.25 --calib-reps 20 --reps 5 --sources 200 --seed 0 --json \
      > "$dir/outliers.json.tmp"
    mv "$dir/outliers.json.tmp" "$dir/outliers.json"
  fi
done
