#!/usr/bin/env python3
"""Round-trip latency of the Python package beside the Rust client, in one run against one
daemon (docs/performance.md, "Python client").

Starts GUARDIAND_BIN (release build) with the shipped model and default bank in event mode,
enrolls three Latin characters (drawers 1-5) through the admin socket, then alternates
Python and Rust (`client/examples/check_latency.rs`, CHECK_LATENCY_BIN) rounds of N checks
of one genuine plan (drawer 6), each after 50 warm-up checks, and prints p50/p99 of each
round and the median of the per-round Python/Rust ratios.

    GUARDIAND_BIN=target/release/guardiand CHECK_LATENCY_BIN=target/release/examples/check_latency \
        python python/bench.py DATASET [--n 1000] [--rounds 2]
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

import guardian

REPO = Path(__file__).resolve().parents[1]


def pct(times, p):
    times = sorted(times)
    i = min(max(int(np.ceil(p * len(times))), 1), len(times)) - 1
    return times[i]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=2)
    a = ap.parse_args()
    ds = guardian.read_dataset(a.dataset)
    idx = {(ds.classes[l], int(d)): i for i, (l, d) in enumerate(zip(ds.labels, ds.drawer_ids))}
    tmp = Path(tempfile.mkdtemp())
    tag = uuid.uuid4().hex[:10]
    service, root, prefix = f"guardian-bench/{tag}/rpc", tmp / "iox", f"gb{tag}_"
    (tmp / "g.toml").write_text(
        f'model = "{REPO / "models" / "embedder.safetensors"}"\ndefault-bank = "{REPO / "models" / "default-bank.gcb"}"\nstate-dir = "{tmp / "state"}"\n'
        f'service-name = "{service}"\n[iceoryx2]\nroot-path = "{root}/"\nprefix = "{prefix}"\n'
    )
    env = dict(os.environ, RAYON_NUM_THREADS="1")
    daemon = subprocess.Popen([os.environ["GUARDIAND_BIN"], "--config", str(tmp / "g.toml")],
                              stderr=open(tmp / "log", "wb"), env=env)
    opts = dict(iceoryx2_root_path=str(root), iceoryx2_prefix=prefix)
    try:
        for _ in range(600):
            try:
                g = guardian.Client(service, **opts)
                admin = guardian.AdminClient(service=service, **opts)
                break
            except (guardian.DaemonNotRunning, guardian.AdminSocketNotFound):
                time.sleep(0.1)
        else:
            sys.exit("guardiand did not start")
        for c in ("01", "13", "18"):
            admin.enroll(f"bench-latin-{c}", ds.trajectories[[idx[(f"Latin/character{c}", d)] for d in range(1, 6)]])
        plan = ds.trajectories[idx[("Latin/character01", 6)]]
        csv = tmp / "plan.csv"
        np.savetxt(csv, plan, delimiter=",", fmt="%.9g")
        print("verdict:", g.check(plan, "bench-latin-01"))
        rows = []
        for r in range(a.rounds):
            for _ in range(50):
                g.check(plan, "bench-latin-01")
            times, go = [], 0
            for _ in range(a.n):
                t0 = time.perf_counter_ns()
                v = g.check(plan, "bench-latin-01")
                times.append((time.perf_counter_ns() - t0) / 1e3)
                go += v.go
            rows.append(("python", r, pct(times, 0.5), pct(times, 0.99), go))
            out = subprocess.run([os.environ["CHECK_LATENCY_BIN"], str(csv), "bench-latin-01", str(a.n), service, str(root), prefix],
                                 capture_output=True, text=True, check=True)
            j = json.loads(out.stdout)
            rows.append(("rust", r, j["p50_us"], j["p99_us"], j["go"]))
        print(f"{'client':<8} {'round':>5} {'p50 us':>8} {'p99 us':>8} {'go':>6}")
        for c, r, p50, p99, go in rows:
            print(f"{c:<8} {r:>5} {p50:>8.1f} {p99:>8.1f} {go:>6}")
        # Each Python round against the Rust round right after it, then the median ratio.
        py = [row for row in rows if row[0] == "python"]
        rs = [row for row in rows if row[0] == "rust"]
        r50 = float(np.median([p[2] / r[2] for p, r in zip(py, rs)]))
        r99 = float(np.median([p[3] / r[3] for p, r in zip(py, rs)]))
        print(f"python/rust, median of the per-round ratios over {a.rounds} rounds of {a.n} checks: p50 {r50:.2f}, p99 {r99:.2f}")
    finally:
        daemon.terminate()
        daemon.wait()
        for leftover in Path("/dev/shm").glob(f"{prefix}*"):
            leftover.unlink(missing_ok=True)


if __name__ == "__main__":
    main()
