#!/usr/bin/env python3
"""An example Python planner: reads a dataset of the project (`guardian-lab dataset`,
docs/dataset.md), enrolls a few of its characters as task classes through the admin socket,
checks every other drawing of them — as the task it is and as another task — plus a few
faulty plans, and prints a go/no-go table like the demo (`examples/demo`).

    cargo run --release -p guardian-lab -- dataset --strokes ../shared/omniglot/strokes --out omniglot.safetensors
    python3 examples/python/planner.py omniglot.safetensors

Exit status 1 if any case is not as expected. The enrolled classes are forgotten at the end
(--keep leaves them).
"""

import argparse
import sys
import time

import numpy as np

import guardian


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="a dataset file (guardian-lab dataset)")
    ap.add_argument("--classes", default="Latin/character01,Latin/character13,Latin/character18",
                    help="comma-separated dataset classes to enroll (default: three Latin characters)")
    ap.add_argument("--shots", type=int, default=5, help="drawers enrolled per class (the first ones)")
    ap.add_argument("--checks", type=int, default=3, help="further drawers checked per class")
    ap.add_argument("--service", default=guardian.DEFAULT_SERVICE)
    ap.add_argument("--iceoryx2-root-path")
    ap.add_argument("--iceoryx2-prefix")
    ap.add_argument("--keep", action="store_true", help="leave the example classes enrolled")
    a = ap.parse_args()

    ds = guardian.read_dataset(a.dataset)
    opts = dict(iceoryx2_root_path=a.iceoryx2_root_path, iceoryx2_prefix=a.iceoryx2_prefix)
    g = guardian.Client(a.service, **opts)
    robot = g.status().robot
    if ds.trajectories.shape[2] != robot.channels:
        sys.exit(f"the dataset's robot ({ds.robot}) is not the served one ({robot.name})")
    admin = guardian.AdminClient(service=a.service, **opts)

    # Rows of each class, by drawer.
    rows = {}
    for i, (label, drawer) in enumerate(zip(ds.labels, ds.drawer_ids)):
        rows.setdefault(ds.classes[label], []).append((int(drawer), i))
    names = {}
    for cls in a.classes.split(","):
        if cls not in rows:
            sys.exit(f"class {cls} is not in {a.dataset}")
        drawers = sorted(rows[cls])
        name = "example-" + cls.replace("/", "-").lower()
        names[cls] = name
        admin.enroll(name, ds.trajectories[[i for _, i in drawers[: a.shots]]])

    cases = []  # (case, plan, claimed, expected reason or None for go)
    classes = list(names)
    for k, cls in enumerate(classes):
        later = sorted(rows[cls])[a.shots: a.shots + a.checks]
        for drawer, i in later:
            cases.append((f"{cls} drawer {drawer}", ds.trajectories[i], names[cls], None))
        other = classes[(k + 1) % len(classes)]
        if other != cls:
            drawer, i = later[0]
            cases.append((f"{cls} drawer {drawer} claimed as {other}", ds.trajectories[i], names[other], "wrong-task"))
    drawer, i = sorted(rows[classes[0]])[a.shots]
    plan = ds.trajectories[i]
    cases.append(("never-enrolled class", plan, "example-never", "unknown-class"))
    nan = plan.copy()
    nan[10, 0] = np.nan
    cases.append(("NaN joint value", nan, names[classes[0]], "invalid-trajectory"))
    cases.append(("1 waypoint", plan[:1], names[classes[0]], "invalid-trajectory"))

    fmt = "{:<44} {:<32} {:<18} {:<46} {:>8} {:>9} {:>10}"
    print(fmt.format("case", "claimed", "expected", "verdict", "distance", "threshold", "round trip"))
    ok = 0
    for case, plan, claimed, expected in cases:
        t0 = time.perf_counter()
        v = g.check(plan, claimed)
        us = (time.perf_counter() - t0) * 1e6
        good = v.reason == expected
        ok += good
        num = lambda x: "-" if x is None else f"{x:.3f}"  # noqa: E731
        print(fmt.format(case, claimed, expected or "go", v.summary[:46], num(v.distance), num(v.threshold), f"{us:.0f} us")
              + ("" if good else "  <- not as expected"))
    print(f"{ok}/{len(cases)} as expected")
    if not a.keep:
        for name in names.values():
            admin.forget(name)
    return 0 if ok == len(cases) else 1


if __name__ == "__main__":
    sys.exit(main())
