#!/usr/bin/env bash
# Leave-one-alphabet-out: for each shared alphabet A, train on four of the others, validate
# (early stopping, LR schedule) on the next one, and evaluate 2-, 10- and 20-way-1-shot on A.
# Usage: docs/report/loao.sh DATASET OUTDIR [extra train args...]
# Prints one JSON line per (alphabet, way); summarise with docs/report/loao-summary.py.
set -euo pipefail
dataset=$1; out=$2; shift 2
lab=${GUARDIAN_LAB:-target/release/guardian-lab}
alphabets=(Balinese Early_Aramaic Greek "Japanese_(katakana)" Korean Latin)
n=${#alphabets[@]}
mkdir -p "$out"
for i in "${!alphabets[@]}"; do
  test_a=${alphabets[$i]}
  val_a=${alphabets[$(( (i + 1) % n ))]}
  train=()
  for a in "${alphabets[@]}"; do
    [[ $a == "$test_a" || $a == "$val_a" ]] || train+=("$a")
  done
  dir="$out/${test_a//[()]/}"
  if [[ ! -f $dir/state.json ]] || ! grep -q '"finished": true' "$dir/state.json"; then
    resume=(); [[ -f $dir/state.json ]] && resume=(--resume)
    "$lab" train --dataset "$dataset" --train-alphabets "$(IFS=,; echo "${train[*]}")" \
      --val-alphabets "$val_a" --out "$dir" --quiet "${resume[@]}" "$@" > "$dir.train.log" 2>&1
  fi
  for way in 2 10 20; do
    "$lab" eval --model "$dir/model.safetensors" --dataset "$dataset" --alphabets "$test_a" \
      --way "$way" --shot 1 --episodes 2000 --seed 0 --json
  done
done
