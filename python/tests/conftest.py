"""Fixtures: a real guardiand per test, isolated by its own service name, iceoryx2 root path
and prefix and state directory, on the shipped model and default bank; a dataset of Latin drawings made by
`guardian-lab dataset`.

Environment (python/ci.sh sets them): GUARDIAND_BIN (default target/debug/guardiand),
GUARDIAN_MODEL (default models/embedder.safetensors), GUARDIAN_DATASET (a dataset file that
holds the Latin alphabet; required).
"""

import os
import shutil
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

import pytest

import guardian

REPO = Path(__file__).resolve().parents[2]
# Functional bound for start-up (not a performance claim).
PATIENCE_S = 60.0


def _env_path(name, default):
    return Path(os.environ.get(name) or default)


@pytest.fixture(scope="session")
def dataset():
    path = os.environ.get("GUARDIAN_DATASET")
    if not path:
        pytest.fail("GUARDIAN_DATASET must name a dataset file with the Latin alphabet (python/ci.sh makes one)")
    return guardian.read_dataset(path)


class Drawings:
    """Plans of a dataset by (class name, drawer)."""

    def __init__(self, ds):
        self.ds = ds
        self.index = {
            (ds.classes[int(l)], int(d)): i for i, (l, d) in enumerate(zip(ds.labels, ds.drawer_ids))
        }

    def plan(self, cls, drawer):
        return self.ds.trajectories[self.index[(cls, drawer)]]

    def plans(self, cls, drawers):
        return self.ds.trajectories[[self.index[(cls, d)] for d in drawers]]


@pytest.fixture(scope="session")
def drawings(dataset):
    return Drawings(dataset)


class Daemon:
    def __init__(self, tmp: Path, extra: str = "", default_bank: bool = True):
        tmp.mkdir(parents=True, exist_ok=True)
        tag = uuid.uuid4().hex[:12]
        self.service = f"guardian-pytest/{tag}/rpc"
        # Short: iceoryx2 puts Unix sockets under the root path (108-byte address limit).
        self.root = Path(tempfile.mkdtemp(prefix="gp", dir="/tmp"))
        self.prefix = f"gp{tag}_"
        self.state = tmp / "state"
        self.config = tmp / "guardiand.toml"
        model = _env_path("GUARDIAN_MODEL", REPO / "models" / "embedder.safetensors")
        # The shipped default bank, as the quick-start daemon: its calibrated default
        # threshold applies to the classes enrolled here.
        bank = REPO / "models" / "default-bank.gcb" if default_bank else ""
        self.config.write_text(
            f'model = "{model}"\ndefault-bank = "{bank}"\nstate-dir = "{self.state}"\n'
            f'service-name = "{self.service}"\ntick-ms = 50\n{extra}\n'
            f'[iceoryx2]\nroot-path = "{self.root}/"\nprefix = "{self.prefix}"\n'
        )
        self.log = open(tmp / "guardiand.log", "wb")
        binary = _env_path("GUARDIAND_BIN", REPO / "target" / "debug" / "guardiand")
        env = dict(os.environ, RUST_LOG="info")
        env.pop("NOTIFY_SOCKET", None)
        env.pop("GUARDIAN_ADMIN_SOCKET", None)
        self.proc = subprocess.Popen(
            [str(binary), "--config", str(self.config)], stdout=self.log, stderr=self.log, env=env
        )
        deadline = time.monotonic() + PATIENCE_S
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"guardiand exited with {self.proc.returncode}: {self.log_text()}")
            try:
                self.client()
                self.admin()
                break
            except (guardian.DaemonNotRunning, guardian.AdminSocketNotFound):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def options(self):
        return dict(iceoryx2_root_path=str(self.root), iceoryx2_prefix=self.prefix)

    def client(self, timeout=10.0):
        return guardian.Client(self.service, timeout=timeout, **self.options())

    def admin(self):
        """The admin client, found without a socket path (the daemon's locator file)."""
        return guardian.AdminClient(service=self.service, **self.options())

    def log_text(self):
        self.log.flush()
        return Path(self.log.name).read_text(errors="replace")

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=PATIENCE_S)

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=PATIENCE_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()
        shutil.rmtree(self.root, ignore_errors=True)
        # iceoryx2 keeps one small global_mgmt file per prefix in /dev/shm; each daemon here
        # has its own prefix.
        for leftover in Path("/dev/shm").glob(f"{self.prefix}*"):
            leftover.unlink(missing_ok=True)


@pytest.fixture
def start_daemon(tmp_path):
    """Start a daemon (config lines `extra` added); every one started is stopped after the test."""
    started = []

    def start(extra="", default_bank=True):
        d = Daemon(tmp_path / f"d{len(started)}", extra, default_bank)
        started.append(d)
        return d

    yield start
    for d in started:
        d.stop()


@pytest.fixture
def daemon(start_daemon):
    return start_daemon()
