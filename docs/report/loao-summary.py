#!/usr/bin/env python3
"""Mean and spread (min, max, sample std) of leave-one-alphabet-out accuracies per way.
Usage: docs/report/loao-summary.py < loao.jsonl"""
import json, statistics, sys
rows = [json.loads(l) for l in sys.stdin if l.strip().startswith("{")]
by_way = {}
for r in rows:
    by_way.setdefault(r["way"], []).append(r)
print("| way | " + " | ".join(r["alphabets"][0] for r in by_way[min(by_way)]) + " | mean | std | min | max |")
print("|---" * (len(by_way[min(by_way)]) + 5) + "|")
for way, rs in sorted(by_way.items()):
    acc = [r["accuracy"] for r in rs]
    cells = " | ".join(f"{r['accuracy']:.3f} ± {r['ci95']:.3f}" for r in rs)
    std = statistics.stdev(acc) if len(acc) > 1 else 0.0
    print(f"| {way} | {cells} | {statistics.mean(acc):.3f} | {std:.3f} | {min(acc):.3f} | {max(acc):.3f} |")
