#!/usr/bin/env bash
# Ablation table: each trained variant on the validation alphabet (Latin, used for model
# selection) and on the held-out test alphabets (Greek, Korean); 2,000 episodes, seed 0.
# Usage: docs/report/ablation.sh DATASET NAME=MODEL[:ra] ...   (":ra" / ":nora" = reverse averaging on / off)
set -euo pipefail
dataset=$1; shift
lab=${GUARDIAN_LAB:-target/release/guardian-lab}
for spec in "$@"; do
  name=${spec%%=*}; model=${spec#*=}; ra=()
  if [[ $model == *:ra ]]; then model=${model%:ra}; ra=(--reverse-average); fi
  if [[ $model == *:nora ]]; then model=${model%:nora}; ra=(--no-reverse-average); fi
  for alphabets in Latin Greek,Korean; do
    for way in 2 10 20; do
      "$lab" eval --model "$model" --dataset "$dataset" --alphabets "$alphabets" --way "$way" \
        --episodes 2000 --seed 0 --json "${ra[@]}" | sed "s/^{/{\"variant\":\"$name\",/"
    done
  done
done
