#!/usr/bin/env python3
"""Post-hoc levers on a fused model's embeddings, measured on leave-one-alphabet-out folds.

Reads, per fold, the embeddings `lab/examples/embedding_dump.rs` wrote of the fold's held-out
alphabet (augmentation 0 = the plan as it is, 1.. = the training augmentations' random
rotations, shears and scales of the pen path, seed 7) and scores N-way K-shot episodes
(2,000, seed 0, numpy's generator) four ways:

- plain: the query against the mean of its class's support embeddings (what eval does);
- support augmentations: each support plan's embedding averaged over its augmentations
  (an enrollment-time cost only; the query is embedded once);
- centred: every embedding minus the mean of the episode's support embeddings, each
  branch re-normalised (a transform that depends on every enrolled class);
- both.

Usage: posthoc-levers.py DUMPDIR [--json]   (DUMPDIR/<fold>.txt per fold)
"""
import json
import sys

import numpy as np

FOLDS = ["Balinese", "Early_Aramaic", "Greek", "Japanese_katakana", "Korean", "Latin"]
BRANCH = 64


def load(path):
    d = np.loadtxt(path, skiprows=1)
    k = d[:, 0].astype(int)
    n = int((k == 0).sum())
    return d[:n, 1].astype(int), d[:, 2:].reshape(k.max() + 1, n, -1)


def renormalise(e):
    parts = [e[..., i:i + BRANCH] for i in range(0, e.shape[-1], BRANCH)]
    parts = [p / np.linalg.norm(p, axis=-1, keepdims=True) for p in parts]
    return np.concatenate(parts, -1) / np.sqrt(len(parts))


def accuracy(labels, emb, way, shot, augments, centre, episodes=2000, seed=0):
    rng = np.random.default_rng(seed)
    classes = np.unique(labels)
    members = {c: np.flatnonzero(labels == c) for c in classes}
    right = 0
    for _ in range(episodes):
        chosen = rng.choice(classes, way, replace=False)
        support, queries = [], []
        for c in chosen:
            p = rng.permutation(members[c])
            support.append(p[:shot])
            queries.append(p[shot])
        q = rng.integers(way)
        s = emb[:augments][:, np.concatenate(support)]
        x = emb[0, queries[q]]
        if centre:
            m = s[0].mean(0)
            s, x = renormalise(s - m), renormalise(x - m)
        protos = s.mean(0).reshape(way, shot, -1).mean(1)
        right += int(np.argmin(((protos - x) ** 2).sum(1)) == q)
    return right / episodes


def main():
    folds = {f: load(f"{sys.argv[1]}/{f}.txt") for f in FOLDS}
    out = {}
    for way, shot in [(2, 1), (10, 1), (20, 1), (20, 5)]:
        for name, augments, centre in [
            ("plain", 1, False),
            ("support augmentations", None, False),
            ("centred", 1, True),
            ("both", None, True),
        ]:
            per = {f: accuracy(l, e, way, shot, augments or e.shape[0], centre) for f, (l, e) in folds.items()}
            key = f"{shot}-shot {way}-way, {name}"
            out[key] = {"mean": float(np.mean(list(per.values()))), "worst": min(per.values()), "folds": per}
            if "--json" not in sys.argv:
                print(f"{key}: mean {out[key]['mean']:.4f} worst {out[key]['worst']:.3f} "
                      + " ".join(f"{v:.3f}" for v in per.values()), flush=True)
    if "--json" in sys.argv:
        print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
