#!/usr/bin/env bash
# Every figure of models/MODEL.md for the shipped model on the held-out test alphabets:
# one JSON line per evaluation (10,000 episodes each, seed 0).
# Usage: docs/report/figures.sh DATASET [MODEL] [SIAMESE]
set -euo pipefail
dataset=$1
model=${2:-models/embedder.safetensors}
siamese=${3:-docs/report/siamese.safetensors}
lab=${GUARDIAN_LAB:-target/release/guardian-lab}
test_alphabets='Greek,Korean'
ev() { "$lab" eval --dataset "$dataset" --alphabets "$test_alphabets" --episodes 10000 --seed 0 --json "$@"; }
for way in 2 5 10 20; do ev --model "$model" --way "$way" --shot 1; done
for way in 5 20; do ev --model "$model" --way "$way" --shot 5; done
for way in 2 10 20; do
  ev --baseline siamese --siamese-model "$siamese" --way "$way" --shot 1
  ev --baseline knn --way "$way" --shot 1
  ev --baseline random --way "$way" --shot 1
done
