#!/usr/bin/env python3
"""Per-fold table and mean / sample std / worst fold of a loao-full.sh run.
Usage: docs/report/loao-full-summary.py OUTDIR [--outliers FILE] [--json]
(--outliers crossfit-outliers.json: the go/no-go figures with the cross-fitted calibration
of docs/report/crossfit.sh)"""
import json, os, statistics, sys

out = sys.argv[1]
ofile = sys.argv[sys.argv.index("--outliers") + 1] if "--outliers" in sys.argv else "outliers.json"
# Folds with accuracy figures; the go/no-go figures where the fold has them (NO_VAL=1 runs
# of loao-full.sh have them only from crossfit.sh).
folds = sorted(d for d in os.listdir(out) if os.path.isfile(os.path.join(out, d, "eval.jsonl")))
rows = {}
for f in folds:
    r = {}
    for line in open(os.path.join(out, f, "eval.jsonl")):
        if line.strip().startswith("{"):
            e = json.loads(line)
            r[f"{e['shot']}-shot {e['way']}-way"] = e["accuracy"]
    opath = os.path.join(out, f, ofile)
    o = json.load(open(opath)) if os.path.isfile(opath) else {"methods": []}
    for m in o["methods"]:
        if m["method"] != "guardian":
            continue
        r["genuine false rejects"] = m["genuine_false_reject"]
        for x in m["faults"]:
            if x["fault"] == "wrong-task" and x["severity"] == 1.0:
                r["wrong task (any) AUROC"] = x["auroc"]
                r["wrong task (any) TPR@1%FPR"] = x["tpr_at_1pct_fpr"]
                r["wrong task (any) detected"] = x["detection"]
            if x["fault"] == "wrong-task" and x["severity"] == 0.5:
                r["wrong task (same alphabet) TPR@1%FPR"] = x["tpr_at_1pct_fpr"]
            if x["fault"] == "unknown-task" and x["severity"] == 1.0:
                r["unknown task (any) TPR@1%FPR"] = x["tpr_at_1pct_fpr"]
            if x["severity"] == 0.5 and x["fault"] in (
                "missing-stroke", "extra-stroke", "mirrored", "rotated", "truncated"):
                r[f"{x['fault']} (0.5) AUROC"] = x["auroc"]
    rows[f] = r
keys = []
for r in rows.values():
    keys += [k for k in r if k not in keys]
summary = {}
print("| figure | " + " | ".join(folds) + " | mean | std | worst |")
print("|---" * (len(folds) + 4) + "|")
for k in keys:
    v = [rows[f].get(k) for f in folds]
    v = [x for x in v if x is not None]
    worst = max(v) if k.startswith("genuine") else min(v)
    std = statistics.stdev(v) if len(v) > 1 else 0.0
    summary[k] = {"mean": statistics.mean(v), "std": std, "worst": worst, "folds": len(v)}
    cells = " | ".join(f"{rows[f][k]:.3f}" if k in rows[f] else "" for f in folds)
    print(f"| {k} | {cells} | **{statistics.mean(v):.3f}** | {std:.3f} | {worst:.3f} |")
if "--json" in sys.argv:
    print(json.dumps({"folds": rows, "summary": summary}))
