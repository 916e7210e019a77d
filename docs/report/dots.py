#!/usr/bin/env python3
"""How much of an alphabet's error is between characters that differ by dots its drawings lack?

Reads the JSON of `guardian-lab eval --per-class --json` (one alphabet) and the recovered
strokes' `labels.tsv` (column `missing_dots`: the ink blobs of a drawing's image that no
stroke explains). A character's dot count is the median over its drawings. A wrong answer
is *by dots* when the query's character and the answer have different dot counts: the
dots the data lacks would tell them apart. Prints the alphabet's accuracy, the share of the
wrong answers that are by dots, and the accuracy if every wrong answer by dots were right
(a ceiling on what the missing dots can cost).

    guardian-lab eval --model M --dataset DATA --alphabets A --way 20 --shot 1 \
        --episodes 2000 --per-class --json > a.json
    docs/report/dots.py a.json ../shared/omniglot/recovered/labels.tsv
"""
import collections
import csv
import json
import statistics
import sys


def main(eval_json, labels_tsv):
    report = json.load(open(eval_json))
    (alphabet,) = report["alphabets"]
    dots = collections.defaultdict(list)
    for row in csv.DictReader(open(labels_tsv), delimiter="\t"):
        if row["alphabet"] == alphabet:
            dots[f"{alphabet}/character{int(row['character']):02d}"].append(
                int(row["missing_dots"])
            )
    if not dots:
        sys.exit(f"{alphabet}: no rows in {labels_tsv}")
    count = {c: statistics.median(v) for c, v in dots.items()}
    queries = wrong = by_dots = 0
    for c in report["per_class"]:
        queries += c["queries"]
        for other, n in c["confused_with"]:
            if c["class"] not in count or other not in count:
                sys.exit(f"{c['class']} or {other}: not in {labels_tsv}")
            wrong += n
            by_dots += n * (count[c["class"]] != count[other])
    print(
        json.dumps(
            {
                "alphabet": alphabet,
                "model_version": report["model_version"],
                "way": report["way"],
                "shot": report["shot"],
                "episodes": queries,
                "accuracy": round(report["accuracy"], 4),
                "characters": len(dots),
                "characters_missing_dots": sum(v > 0 for v in count.values()),
                "drawings_missing_dots": round(
                    sum(d > 0 for v in dots.values() for d in v) / sum(map(len, dots.values())), 3
                ),
                "wrong_answers": wrong,
                "wrong_answers_by_dots": round(by_dots / max(wrong, 1), 3),
                "accuracy_if_dots_were_drawn": round(report["accuracy"] + by_dots / queries, 4),
            }
        )
    )


if __name__ == "__main__":
    main(*sys.argv[1:])
