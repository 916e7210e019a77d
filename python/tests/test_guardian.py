"""The guardian Python package against a real guardiand (shipped model, workcell rules on,
empty default bank), with Latin Omniglot drawings converted to Panda plans by
`guardian-lab dataset`: the classes enrolled here are in no bank the model was shipped with.
"""

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import guardian

from conftest import REPO

# Three Latin characters (as the demo (`cargo run --release --example demo`)): enrolled from drawers 1-5, checked with 6/7.
TASKS = {"py-latin-01": "Latin/character01", "py-latin-13": "Latin/character13", "py-latin-18": "Latin/character18"}
ENROLL = [1, 2, 3, 4, 5]


def names(client):
    return {c.name for c in client.classes()}


def enroll_tasks(admin, drawings):
    infos = [admin.enroll(name, drawings.plans(cls, ENROLL)) for name, cls in TASKS.items()]
    for info in infos:
        assert info.examples == len(ENROLL)
    return infos


def test_dataset_reads_as_numpy(dataset):
    t = dataset.trajectories
    assert t.dtype == np.float32 and t.ndim == 3 and t.shape[1:] == (128, 8)
    assert len(dataset) == t.shape[0] == dataset.labels.shape[0] == dataset.drawer_ids.shape[0]
    assert dataset.robot == "panda"
    assert "Latin/character01" in dataset.classes
    assert "Dataset(" in repr(dataset)


def test_every_error_is_a_guardian_error():
    # A daemon that cannot persist an enroll answers Storage: its own exception, still a
    # GuardianError, so `except guardian.GuardianError` never lets it pass as a verdict.
    for name in ["StorageError", "Unreplicated", "NotPermitted", "LimitExceeded", "InternalError"]:
        assert issubclass(getattr(guardian, name), guardian.GuardianError), name


def test_status_names_the_robot(daemon):
    s = daemon.client().status()
    assert (s.robot.name, s.robot.joints, s.robot.channels) == ("panda", 7, 8)
    assert len(s.robot.urdf_sha256) == 64
    assert s.classes == len(daemon.client().classes()) > 0  # the shipped default bank
    assert "Status(robot=Robot(\"panda\"" in repr(s)
    c = daemon.client()
    assert c.service == daemon.service and "Client(service=" in repr(c)


def test_genuine_plans_go_as_float32_and_float64(daemon, drawings):
    admin = daemon.admin()
    enroll_tasks(admin, drawings)
    g = daemon.client()
    for name, cls in TASKS.items():
        plan = drawings.plan(cls, 6)
        for p in (plan, plan.astype(np.float64), np.asfortranarray(plan)):
            v = g.check(p, claimed=name)
            assert v.go, v
            assert v.reason is None and v.summary == "GO"
            assert v.claimed == name
            assert v.distance < v.threshold and v.margin > 0
            assert v.nearest[0].name == name
        assert repr(v).startswith("Verdict(GO, claimed=")
    classes = {c.name: c for c in g.classes() if c.name.startswith("py-")}
    assert set(classes) == set(TASKS)
    assert all(c.examples == 5 and c.threshold > 0 for c in classes.values())
    r = g.identify(drawings.plan("Latin/character13", 6))
    assert r.nearest[0].name == "py-latin-13"
    assert "Ranking([Neighbour(\"py-latin-13\"" in repr(r)


def test_wrong_task_is_no_go_with_the_nearest_class(daemon, drawings):
    enroll_tasks(daemon.admin(), drawings)
    v = daemon.client().check(drawings.plan("Latin/character01", 7), claimed="py-latin-13")
    assert not v.go
    assert v.reason == "wrong-task"
    assert v.nearest_class == "py-latin-01" == v.nearest[0].name
    assert v.summary == "NO-GO wrong task (nearest py-latin-01)"
    assert v.gap < 0


def test_unknown_class_and_empty_bank(start_daemon, drawings):
    daemon = start_daemon(default_bank=False)
    g = daemon.client()
    plan = drawings.plan("Latin/character01", 6)
    with pytest.raises(guardian.EmptyBank):
        g.identify(plan)
    enroll_tasks(daemon.admin(), drawings)
    v = g.check(plan, claimed="never-enrolled")
    assert (v.go, v.reason, v.distance) == (False, "unknown-class", None)
    with pytest.raises(guardian.InvalidClassName):
        g.check(plan, claimed="")


def test_each_invalid_kind_is_reported_with_its_index(daemon, drawings):
    enroll_tasks(daemon.admin(), drawings)
    g = daemon.client()
    good = drawings.plan("Latin/character18", 6).copy()
    nan = good.copy()
    nan[10, 2] = np.nan
    limit = good.copy()
    limit[20, 3] = 0.0  # joint 4 must stay below -0.0698
    tool = good.copy()
    tool[4, 7] = 0.5
    many = np.resize(good, (4097, 8))
    cases = [
        (nan, "NonFinite", 10),
        (limit, "JointOutOfLimits", 20),
        (np.ascontiguousarray(good[:, :7]), "WrongChannelCount", 7),
        (good[:1], "TooFewWaypoints", 1),
        (many, "TooManyWaypoints", 4097),
        (tool, "ToolOutOfRange", 4),
    ]
    for plan, kind, index in cases:
        v = g.check(plan, claimed="py-latin-18")
        assert (v.go, v.reason, v.kind, v.index) == (False, "invalid-trajectory", kind, index), v
        with pytest.raises(guardian.InvalidTrajectory) as e:
            g.identify(plan)
        assert (e.value.kind, e.value.index, e.value.example) == (kind, index, 0)
    # The bad one among good examples is named.
    with pytest.raises(guardian.InvalidTrajectory) as e:
        daemon.admin().enroll("py-bad", [good, tool])
    assert (e.value.kind, e.value.index, e.value.example) == ("ToolOutOfRange", 4, 1)
    # What is not a [waypoints, channels] float array never leaves Python.
    with pytest.raises(TypeError):
        g.check(good.astype(np.int32), claimed="py-latin-18")
    with pytest.raises(TypeError):
        g.check(good.tolist(), claimed="py-latin-18")
    with pytest.raises(ValueError):
        g.check(good.reshape(-1), claimed="py-latin-18")
    with pytest.raises(ValueError):
        daemon.admin().enroll("py-bad", [])


def test_admin_socket_enroll_check_forget(daemon, drawings):
    admin = daemon.admin()
    # Found through the daemon's locator file: its state directory's socket.
    assert Path(admin.socket) == daemon.state / "admin.sock"
    g = daemon.client()
    info = admin.enroll("py-latin-01", drawings.plans("Latin/character01", ENROLL))
    assert info.name == "py-latin-01" and "ClassInfo(\"py-latin-01\", examples=5" in repr(info)
    assert g.check(drawings.plan("Latin/character01", 6), "py-latin-01").go
    admin.forget("py-latin-01")
    assert "py-latin-01" not in names(g)
    assert g.check(drawings.plan("Latin/character01", 6), "py-latin-01").reason == "unknown-class"
    with pytest.raises(guardian.UnknownClass) as e:
        admin.forget("py-latin-01")
    assert e.value.class_name == "py-latin-01"
    # An AdminClient may be used from any thread.
    errors = []
    t = threading.Thread(target=lambda: errors.append(admin.enroll("py-latin-13", drawings.plans("Latin/character13", ENROLL))))
    t.start()
    t.join()
    assert errors[0].name == "py-latin-13"


def test_guardianctl_finds_the_admin_socket_without_flags(daemon, drawings, tmp_path):
    ctl = os.environ.get("GUARDIANCTL_BIN") or str(REPO / "target" / "debug" / "guardianctl")
    files = []
    for d in ENROLL:
        f = tmp_path / f"l01-{d}.csv"
        np.savetxt(f, drawings.plan("Latin/character01", d), delimiter=",", fmt="%.7g")
        files.append(str(f))
    base = [ctl, "--service", daemon.service, "--iceoryx2-root-path", str(daemon.root), "--iceoryx2-prefix", daemon.prefix]
    env = {k: v for k, v in os.environ.items() if k != "GUARDIAN_ADMIN_SOCKET"}
    out = subprocess.run(base + ["enroll", "py-ctl", *files], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "enrolled py-ctl: 5 examples" in out.stdout
    assert "py-ctl" in names(daemon.client())
    # With other iceoryx2 settings there is no locator and no socket: the error names where it looked.
    out = subprocess.run([ctl, "--service", "guardian-pytest/none", "--iceoryx2-root-path", str(tmp_path / "none"), "forget", "x"], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode != 0
    assert "no admin socket found" in out.stderr and "/run/guardian/admin.sock (absent)" in out.stderr, out.stderr
    assert str(tmp_path / "guardiand-state" / "admin.sock") in out.stderr


def test_quick_start_socket_in_the_working_directory_is_found(daemon, monkeypatch):
    # No locator for these settings: the quick-start layout's ./guardiand-state/admin.sock.
    monkeypatch.chdir(daemon.state.parent)
    (daemon.state.parent / "guardiand-state").symlink_to(daemon.state)
    admin = guardian.AdminClient(service="guardian-pytest/elsewhere", iceoryx2_root_path=str(daemon.root / "none"))
    assert Path(admin.socket) == daemon.state.parent / "guardiand-state" / "admin.sock"
    with pytest.raises(guardian.UnknownClass):
        admin.forget("nothing")
    monkeypatch.setenv("GUARDIAN_ADMIN_SOCKET", "/nonexistent/admin.sock")
    with pytest.raises(guardian.AdminSocketError) as e:
        guardian.AdminClient(service=daemon.service, **daemon.options()).forget("x")
    assert e.value.path == "/nonexistent/admin.sock"


def test_not_permitted_with_admin_separation(start_daemon, drawings):
    d = start_daemon("[admin]\nseparation = true\n")
    g = d.client()
    examples = drawings.plans("Latin/character01", ENROLL)
    with pytest.raises(guardian.NotPermitted):
        g.enroll("py-latin-01", examples)
    with pytest.raises(guardian.NotPermitted):
        g.forget("py-latin-01")
    assert "py-latin-01" not in names(g)
    # This process is root, an admin: the admin socket serves it.
    assert d.admin().enroll("py-latin-01", examples).examples == 5
    assert "py-latin-01" in names(g)
    # A caller outside the admin uids is refused by the socket as well.
    other = start_daemon("[admin]\nseparation = true\nuids = [12345]\n")
    with pytest.raises(guardian.NotPermitted):
        other.admin().enroll("py-latin-01", examples)


def test_enroll_over_iceoryx2_without_separation(daemon, drawings):
    g = daemon.client()
    assert g.enroll("py-latin-18", list(drawings.plans("Latin/character18", ENROLL))).examples == 5
    assert g.check(drawings.plan("Latin/character18", 6), "py-latin-18").go
    g.forget("py-latin-18")
    assert "py-latin-18" not in names(g)


def test_limit_exceeded(start_daemon, drawings):
    d = start_daemon("max-classes = 1\n", default_bank=False)
    admin = d.admin()
    admin.enroll("py-latin-01", drawings.plans("Latin/character01", ENROLL))
    with pytest.raises(guardian.LimitExceeded) as e:
        admin.enroll("py-latin-13", drawings.plans("Latin/character13", ENROLL))
    assert (e.value.limit, e.value.max, e.value.requested) == ("max-classes", 1, 2)


def test_timeout_when_the_daemon_is_gone(daemon, drawings):
    enroll_tasks(daemon.admin(), drawings)
    g = daemon.client(timeout=0.5)
    plan = drawings.plan("Latin/character01", 6)
    assert g.check(plan, "py-latin-01").go
    daemon.kill()
    with pytest.raises(guardian.Timeout) as e:
        g.check(plan, "py-latin-01")
    assert e.value.after == 0.5


def test_the_gil_is_released_while_waiting(daemon, drawings):
    enroll_tasks(daemon.admin(), drawings)
    g = daemon.client(timeout=1.0)
    plan = drawings.plan("Latin/character01", 6)
    ticks = [0]
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            ticks[0] += 1

    # A stopped daemon never answers: the call waits its whole timeout. Another Python thread
    # makes progress meanwhile only if the wait does not hold the GIL.
    os.kill(daemon.proc.pid, signal.SIGSTOP)
    t = threading.Thread(target=spin)
    try:
        t.start()
        while ticks[0] == 0:
            pass
        with pytest.raises(guardian.Timeout):
            before = ticks[0]
            try:
                g.check(plan, "py-latin-01")
            finally:
                during = ticks[0] - before
    finally:
        stop.set()
        t.join()
        os.kill(daemon.proc.pid, signal.SIGCONT)
    assert during > 1000, during


def test_sixteen_threads_check_concurrently(daemon, drawings):
    enroll_tasks(daemon.admin(), drawings)
    cases = []
    for name, cls in TASKS.items():
        cases.append((drawings.plan(cls, 6), name, True))
    cases.append((drawings.plan("Latin/character01", 7), "py-latin-13", False))
    results = [None] * 16
    barrier = threading.Barrier(16)

    def worker(i):
        try:
            g = daemon.client()  # one Client per thread
            barrier.wait()
            got = []
            for k in range(12):
                plan, claimed, go = cases[(i + k) % len(cases)]
                v = g.check(plan, claimed)
                got.append(v.go == go and v.claimed == claimed)
            results[i] = got
        except Exception as e:  # reported below
            results[i] = e

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i, r in enumerate(results):
        assert isinstance(r, list), f"thread {i}: {r!r}"
        assert all(r) and len(r) == 12, f"thread {i}: {r}"
    s = daemon.client().status()
    assert s.go == 16 * 12 * 3 // 4 and s.no_go == 16 * 12 // 4


def test_a_client_belongs_to_its_thread(daemon):
    g = daemon.client()
    errors = []

    def use():
        try:
            g.status()
        except BaseException as e:  # noqa: BLE001 - the type is what is checked
            errors.append(e)

    t = threading.Thread(target=use)
    t.start()
    t.join()
    assert len(errors) == 1 and isinstance(errors[0], RuntimeError), errors
    assert "one Client per thread" in str(errors[0])
    assert g.status().robot.joints == 7


def test_example_planner_prints_its_table(daemon):
    example = REPO / "examples" / "python" / "planner.py"
    out = subprocess.run(
        [sys.executable, str(example), os.environ["GUARDIAN_DATASET"], "--checks", "1",
         "--service", daemon.service, "--iceoryx2-root-path", str(daemon.root), "--iceoryx2-prefix", daemon.prefix],
        capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].split()[:4] == ["case", "claimed", "expected", "verdict"]
    assert lines[-1] == "9/9 as expected"
    assert any("GO" in l and "Latin/character01 drawer 6" in l for l in lines)
    assert not [n for n in names(daemon.client()) if n.startswith("example-")]  # forgotten again
