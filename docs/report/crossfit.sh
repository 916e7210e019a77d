#!/usr/bin/env bash
# Cross-fitted calibration, checked per fold: for each alphabet A of a loao-full.sh run, a
# bank calibrated on the other five fold models' genuine scores (each on its own test
# alphabet, which it never saw), then A's fold model scored on A with that bank's
# calibration (`outliers --calibration-from`): the false-reject rate on tasks that neither
# the model nor the calibration saw.
# Usage: docs/report/crossfit.sh DATASET LOAODIR   (writes LOAODIR/<A>/crossfit-{bank.gcb,outliers.json})
set -euo pipefail
dataset=$1; dir=$2
lab=${GUARDIAN_LAB:-target/release/guardian-lab}
strokes=${STROKES:-../shared/omniglot/strokes}
alphabets=(Balinese Early_Aramaic Greek "Japanese_(katakana)" Korean Latin)
n=${#alphabets[@]}
for i in "${!alphabets[@]}"; do
  test_a=${alphabets[$i]}
  val_a=${alphabets[$(( (i + 1) % n ))]}
  fold="$dir/${test_a//[()]/}"
  pairs=()
  for a in "${alphabets[@]}"; do
    [[ $a == "$test_a" ]] || pairs+=(--cross-fit "$dir/${a//[()]/}/model.safetensors=$a")
  done
  "$lab" bank --model "$fold/model.safetensors" --dataset "$dataset" --alphabets "$val_a" \
    --shots 5 --target-frr 0.01 --geometry-share 0.25 --reps 20 --seed 0 \
    --out "$fold/crossfit-bank.gcb" "${pairs[@]}" > "$fold/crossfit-bank.json"
  "$lab" outliers --model "$fold/model.safetensors" --dataset "$dataset" --strokes "$strokes" \
    --alphabets "$test_a" --calib-alphabets "$val_a" --calibration-from "$fold/crossfit-bank.gcb" \
    --shots 5 --target-frr 0.01 --geometry-share 0.25 --calib-reps 20 --reps 5 --sources 200 \
    --seed 0 --json > "$fold/crossfit-outliers.json"
done
