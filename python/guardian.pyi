"""guardian: Python client of guardiand, the pre-execution safety screen for robot task plans.

    import guardian
    g = guardian.Client()                        # the default service, as guardianctl
    v = g.check(plan, claimed="pick-and-place")   # plan: numpy array [N, joints + 1]
    if not v.go: print(v.reason, v.nearest, v.distance, v.threshold)

Trajectories are numpy arrays of float32 or float64, [waypoints, joints + 1]: the served
robot's joint positions (rad) then the tool (0 or 1). The GIL is released while a call waits
for the daemon.
"""

from os import PathLike
from typing import Literal, Optional, Sequence, Union, final

import numpy as np
import numpy.typing as npt

__version__: str
DEFAULT_SERVICE: str
"""The daemon's default request-response service name."""
DEFAULT_ADMIN_SOCKET: str
"""The installed layout's admin socket."""

Plan = Union[npt.NDArray[np.float32], npt.NDArray[np.float64]]
"""A trajectory: [waypoints, joints + 1], float32 or float64."""
Examples = Union[npt.NDArray[np.float32], npt.NDArray[np.float64], Sequence[Plan]]
"""Enrollment examples: [examples, waypoints, joints + 1], or a list of 2-D plans."""
Reason = Literal[
    "wrong-task", "outlier", "unknown-class", "invalid-trajectory", "workcell", "geometry-mismatch"
]

@final
class Neighbour:
    """A class and its embedding distance."""

    name: str
    distance: float
    threshold: float

@final
class Verdict:
    """The answer to Client.check."""

    go: bool
    """The plan is the task it claims to be."""
    reason: Optional[Reason]
    """None for go, else why not."""
    summary: str
    """`GO`, or `NO-GO` and the reason with its detail, as guardianctl prints it."""
    claimed: str
    distance: Optional[float]
    """Distance to the claimed class's prototype (None: unknown class or invalid plan)."""
    threshold: Optional[float]
    margin: Optional[float]
    """threshold - distance: positive inside the class."""
    gap: Optional[float]
    """Nearest other class's distance - distance: positive when the claimed class is nearest."""
    nearest: list[Neighbour]
    """The nearest classes, nearest first."""
    nearest_class: Optional[str]
    """The nearer class of a wrong-task no-go."""
    kind: Optional[str]
    """The invalid kind (NonFinite, JointOutOfLimits, WrongChannelCount, TooFewWaypoints, ...) or workcell rule."""
    index: Optional[int]
    """The waypoint index (or offending count) of an invalid or workcell no-go."""
    feature: Optional[str]
    """The geometry feature of a geometry-mismatch no-go."""
    geometry_score: Optional[float]
    geometry_threshold: Optional[float]
    model_version: str
    bank_version: int

@final
class Ranking:
    """The answer to Client.identify."""

    nearest: list[Neighbour]
    model_version: str
    bank_version: int

@final
class ClassInfo:
    """An enrolled class."""

    name: str
    examples: int
    threshold: float
    calibrated: bool

@final
class Robot:
    """The robot a daemon serves."""

    name: str
    joints: int
    channels: int
    """Floats per waypoint: joints + the tool."""
    urdf_sha256: str

@final
class Status:
    """The answer to Client.status."""

    model_version: str
    bank_version: int
    classes: int
    uptime: float
    """Seconds since the daemon started."""
    requests: int
    errors: int
    go: int
    no_go: int
    latency_us: Optional[tuple[float, float, float, float]]
    """Service time p50, p90, p99, max in microseconds (None before the first request)."""
    robot: Robot

@final
class Client:
    """A connection to guardiand over iceoryx2, for the thread that made it.

    Give every planner thread its own Client (iceoryx2 ports are single-threaded; using a
    Client from another thread raises RuntimeError). Raises DaemonNotRunning when no daemon
    serves `service`.
    """

    def __init__(
        self,
        service: Optional[str] = None,
        *,
        timeout: float = 2.0,
        iceoryx2_root_path: Optional[Union[str, PathLike[str]]] = None,
        iceoryx2_prefix: Optional[str] = None,
    ) -> None: ...
    @property
    def timeout(self) -> float: ...
    @property
    def service(self) -> str: ...
    def check(self, plan: Plan, claimed: str) -> Verdict:
        """Is `plan` the task `claimed`? Invalid plans and unknown classes are no-go verdicts."""
    def identify(self, plan: Plan) -> Ranking:
        """The nearest enrolled classes. Raises InvalidTrajectory, EmptyBank."""
    def classes(self) -> list[ClassInfo]: ...
    def status(self) -> Status: ...
    def enroll(self, name: str, examples: Examples) -> ClassInfo:
        """Enroll over the planners' service: only without admin separation (else NotPermitted)."""
    def forget(self, name: str) -> None:
        """Forget over the planners' service: only without admin separation (else NotPermitted)."""

@final
class AdminClient:
    """Enroll and forget over the daemon's admin socket; the caller must be an admin.

    Without `socket`, it is found as guardianctl finds it: $GUARDIAN_ADMIN_SOCKET, the
    locator file of the daemon that Client(service, iceoryx2_root_path=..., iceoryx2_prefix=...)
    reaches, /run/guardian/admin.sock, ./guardiand-state/admin.sock; else AdminSocketNotFound.
    Usable from any thread.
    """

    def __init__(
        self,
        socket: Optional[Union[str, PathLike[str]]] = None,
        *,
        service: Optional[str] = None,
        timeout: float = 10.0,
        iceoryx2_root_path: Optional[Union[str, PathLike[str]]] = None,
        iceoryx2_prefix: Optional[str] = None,
    ) -> None: ...
    @property
    def socket(self) -> str: ...
    def enroll(self, name: str, examples: Examples) -> ClassInfo: ...
    def forget(self, name: str) -> None: ...

@final
class Dataset:
    """A dataset file of the project (guardian-lab dataset; docs/dataset.md)."""

    trajectories: npt.NDArray[np.float32]
    """[N, steps, joints + 1]."""
    labels: npt.NDArray[np.int64]
    """[N], index into classes."""
    alphabet_ids: npt.NDArray[np.int64]
    drawer_ids: npt.NDArray[np.int64]
    classes: list[str]
    alphabets: list[str]
    robot: str
    def __len__(self) -> int: ...

def read_dataset(path: Union[str, PathLike[str]]) -> Dataset: ...

class GuardianError(Exception):
    """Base class of every guardian error."""

class ConnectError(GuardianError): ...
class DaemonNotRunning(ConnectError):
    service: str

class Timeout(GuardianError):
    after: float

class NotServing(GuardianError): ...
class InvalidClassName(GuardianError): ...

class InvalidTrajectory(GuardianError):
    kind: str
    index: int
    example: int

class UnknownClass(GuardianError):
    class_name: str

class EmptyBank(GuardianError): ...
class BadRequest(GuardianError): ...
class InternalError(GuardianError): ...
class TransportError(GuardianError): ...
class ProtocolError(GuardianError): ...

class LimitExceeded(GuardianError):
    limit: str
    max: int
    requested: int

class NotPermitted(GuardianError): ...
class StorageError(GuardianError): ...
class Unreplicated(GuardianError): ...

class AdminSocketError(GuardianError):
    path: Optional[str]

class AdminSocketNotFound(AdminSocketError):
    looked: list[tuple[str, str]]
