//! The `guardian` Python package: guardian's planner client for Python, built from the Rust
//! client library (`guardian-client`) with PyO3, so Python planners speak the same wire
//! protocol through the same code as Rust ones.
//!
//! ```python
//! import guardian
//! g = guardian.Client()                        # the default service, as guardianctl
//! v = g.check(plan, claimed="pick-and-place")   # plan: numpy array [N, joints + 1]
//! if not v.go: print(v.reason, v.nearest, v.distance, v.threshold)
//! ```
//!
//! Trajectories are numpy arrays of float32 or float64, `[waypoints, joints + 1]`, copied
//! into the request without a Python-level loop. Every request releases the GIL while it
//! waits for the daemon. Every failure status of the wire protocol is an exception class of
//! its own under `guardian.GuardianError`; stubs are in `guardian.pyi`.

use std::path::PathBuf;
use std::time::Duration;

use guardian_client as gc;
use numpy::{PyArray1, PyArray2, PyArray3, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::IntoPyObjectExt;
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyTypeError, PyValueError};
use pyo3::prelude::*;
use send_wrapper::SendWrapper;

create_exception!(
    guardian,
    GuardianError,
    PyException,
    "Base class of every guardian error."
);
create_exception!(
    guardian,
    ConnectError,
    GuardianError,
    "The daemon's services could not be opened (bad settings or iceoryx2 failure)."
);
create_exception!(
    guardian,
    DaemonNotRunning,
    ConnectError,
    "No guardiand serves this service name (under these iceoryx2 settings)."
);
create_exception!(
    guardian,
    Timeout,
    GuardianError,
    "No answer within the client's timeout (the daemon may be gone)."
);
create_exception!(
    guardian,
    NotServing,
    GuardianError,
    "The daemon is gone: no server, or the request was dropped unanswered."
);
create_exception!(
    guardian,
    InvalidClassName,
    GuardianError,
    "The class name was rejected (empty, too long, or not printable)."
);
create_exception!(
    guardian,
    InvalidTrajectory,
    GuardianError,
    "A trajectory failed the daemon's validation (identify, enroll): `kind`, `index`, `example`."
);
create_exception!(
    guardian,
    UnknownClass,
    GuardianError,
    "The class is not enrolled: `class_name`."
);
create_exception!(
    guardian,
    EmptyBank,
    GuardianError,
    "No classes are enrolled."
);
create_exception!(
    guardian,
    BadRequest,
    GuardianError,
    "The daemon rejected the request as malformed."
);
create_exception!(
    guardian,
    InternalError,
    GuardianError,
    "The daemon failed internally (never answered as go)."
);
create_exception!(
    guardian,
    TransportError,
    GuardianError,
    "An iceoryx2 operation failed."
);
create_exception!(
    guardian,
    ProtocolError,
    GuardianError,
    "The answer violates the wire protocol."
);
create_exception!(
    guardian,
    LimitExceeded,
    GuardianError,
    "The enroll would take the bank past a configured limit; nothing changed: `limit`, `max`, `requested`."
);
create_exception!(
    guardian,
    NotPermitted,
    GuardianError,
    "The daemon does not permit this operation here (admin separation, or not an admin)."
);
create_exception!(
    guardian,
    StorageError,
    GuardianError,
    "The daemon could not persist the change (state directory full or read-only); nothing changed."
);
create_exception!(
    guardian,
    Unreplicated,
    GuardianError,
    "A fleet member made the change (in effect and durable there), but fewer peers than its `replicas` acknowledged it in time."
);
create_exception!(
    guardian,
    AdminSocketError,
    GuardianError,
    "The admin socket could not be reached or broke off: `path`."
);
create_exception!(
    guardian,
    AdminSocketNotFound,
    AdminSocketError,
    "No admin socket was found: `looked` lists (place, what was there)."
);

/// An exception of type `T` with `message` and attributes.
fn raise<T: pyo3::PyTypeInfo>(
    py: Python<'_>,
    message: String,
    attrs: &[(&str, Py<PyAny>)],
) -> PyErr {
    let err = PyErr::new::<T, _>(message);
    let value = err.value(py);
    for (k, v) in attrs {
        if let Err(e) = value.setattr(*k, v) {
            return e;
        }
    }
    err
}

fn obj<'py, T: IntoPyObject<'py>>(py: Python<'py>, v: T) -> Py<PyAny> {
    v.into_py_any(py).unwrap_or_else(|_| py.None())
}

fn check_err(py: Python<'_>, e: gc::CheckError) -> PyErr {
    use gc::CheckError as E;
    let msg = e.to_string();
    match e {
        E::Timeout { after } => {
            raise::<Timeout>(py, msg, &[("after", obj(py, after.as_secs_f64()))])
        }
        E::NotServing { .. } => raise::<NotServing>(py, msg, &[]),
        E::InvalidClassName(_) => raise::<InvalidClassName>(py, msg, &[]),
        E::InvalidTrajectory {
            kind,
            index,
            example,
        } => raise::<InvalidTrajectory>(
            py,
            msg,
            &[
                ("kind", obj(py, invalid_kind_name(kind))),
                ("index", obj(py, index)),
                ("example", obj(py, example)),
            ],
        ),
        E::UnknownClass { class } => {
            raise::<UnknownClass>(py, msg, &[("class_name", obj(py, class))])
        }
        E::EmptyBank => raise::<EmptyBank>(py, msg, &[]),
        E::BadRequest { .. } => raise::<BadRequest>(py, msg, &[]),
        E::Internal { .. } => raise::<InternalError>(py, msg, &[]),
        E::Transport(_) => raise::<TransportError>(py, msg, &[]),
        E::Protocol { .. } => raise::<ProtocolError>(py, msg, &[]),
        E::LimitExceeded { limit, .. } => raise::<LimitExceeded>(
            py,
            msg,
            &[
                ("limit", obj(py, limit.kind.key())),
                ("max", obj(py, limit.max)),
                ("requested", obj(py, limit.requested)),
            ],
        ),
        E::NotPermitted { .. } => raise::<NotPermitted>(py, msg, &[]),
        E::Storage { .. } => raise::<StorageError>(py, msg, &[]),
        E::Unreplicated { .. } => raise::<Unreplicated>(py, msg, &[]),
        E::AdminSocket { path, .. } => {
            raise::<AdminSocketError>(py, msg, &[("path", obj(py, path.display().to_string()))])
        }
        _ => raise::<GuardianError>(py, msg, &[]),
    }
}

fn enroll_err(py: Python<'_>, e: gc::EnrollError) -> PyErr {
    match e {
        gc::EnrollError::Request(e) => check_err(py, e),
        other => PyValueError::new_err(other.to_string()),
    }
}

fn connect_err(py: Python<'_>, e: gc::ConnectError) -> PyErr {
    let msg = e.to_string();
    match e {
        gc::ConnectError::DaemonNotRunning { service } => {
            raise::<DaemonNotRunning>(py, msg, &[("service", obj(py, service))])
        }
        gc::ConnectError::InvalidConfig { .. } | gc::ConnectError::Iceoryx2Config(_) => {
            PyValueError::new_err(msg)
        }
        _ => raise::<ConnectError>(py, msg, &[]),
    }
}

/// `NonFinite`, `JointOutOfLimits`, ... as the Rust client names them.
fn invalid_kind_name(k: gc::InvalidKind) -> String {
    format!("{k:?}")
}

/// One trajectory from a numpy array `[waypoints, channels]` of float32 or float64. The
/// counts of waypoints and channels are the daemon's to judge, as for a Rust or C planner:
/// it answers with the invalid kind and the offending count.
fn trajectory(a: &Bound<'_, PyAny>, what: &str) -> PyResult<gc::Trajectory> {
    let Ok(u) = a.cast::<PyUntypedArray>() else {
        return Err(PyTypeError::new_err(format!(
            "{what} must be a numpy.ndarray of float32 or float64 [waypoints, joints + 1], got {}",
            a.get_type().name()?
        )));
    };
    if u.ndim() != 2 {
        return Err(PyValueError::new_err(format!(
            "{what} must have 2 dimensions [waypoints, joints + 1], got shape {:?}",
            u.shape()
        )));
    }
    let c = u.shape()[1];
    // Row-major order whatever the layout: a slice copy only when the memory is C order
    // (`as_slice` also accepts Fortran order), else ndarray's logical-order iterator.
    let c_order = u.is_c_contiguous();
    let data: Vec<f32> = if let Ok(a) = a.cast::<PyArray2<f32>>() {
        let r = a.readonly();
        match r.as_slice() {
            Ok(s) if c_order => s.to_vec(),
            _ => r.as_array().iter().copied().collect(),
        }
    } else if let Ok(a) = a.cast::<PyArray2<f64>>() {
        let r = a.readonly();
        match r.as_slice() {
            Ok(s) if c_order => s.iter().map(|&v| v as f32).collect(),
            _ => r.as_array().iter().map(|&v| v as f32).collect(),
        }
    } else {
        return Err(PyTypeError::new_err(format!(
            "{what} must be float32 or float64, got dtype {}",
            u.dtype()
        )));
    };
    Ok(gc::Trajectory::from_flat(data, c))
}

/// Enrollment examples: a 3-D array `[examples, waypoints, channels]` or a sequence of 2-D
/// arrays (of possibly different lengths).
fn examples(a: &Bound<'_, PyAny>) -> PyResult<Vec<gc::Trajectory>> {
    if let Ok(u) = a.cast::<PyUntypedArray>() {
        if u.ndim() != 3 {
            return Err(PyValueError::new_err(format!(
                "examples must be a 3-D array [examples, waypoints, joints + 1] or a list of 2-D arrays, got shape {:?}",
                u.shape()
            )));
        }
        let mut out = Vec::with_capacity(u.shape()[0]);
        for i in 0..u.shape()[0] {
            out.push(trajectory(&a.get_item(i)?, &format!("example {i}"))?);
        }
        return Ok(out);
    }
    let mut out = Vec::new();
    for (i, item) in a.try_iter()?.enumerate() {
        out.push(trajectory(&item?, &format!("example {i}"))?);
    }
    Ok(out)
}

fn opt_f32(v: Option<f32>) -> String {
    v.map_or("None".into(), |v| format!("{v:.4}"))
}

fn timeout(seconds: f64) -> PyResult<Duration> {
    Duration::try_from_secs_f64(seconds)
        .ok()
        .filter(|d| !d.is_zero())
        .ok_or_else(|| PyValueError::new_err(format!("timeout must be > 0 s, got {seconds}")))
}

fn client_config(
    service: Option<String>,
    timeout_s: f64,
    iceoryx2_root_path: Option<PathBuf>,
    iceoryx2_prefix: Option<String>,
) -> PyResult<gc::ClientConfig> {
    Ok(gc::ClientConfig {
        service_name: service.unwrap_or_else(|| gc::ClientConfig::default().service_name),
        timeout: timeout(timeout_s)?,
        iceoryx2_root_path,
        iceoryx2_prefix,
    })
}

/// A class and its embedding distance.
#[pyclass(frozen, get_all, module = "guardian")]
#[derive(Clone)]
struct Neighbour {
    /// Class name.
    name: String,
    /// Distance to the class prototype.
    distance: f32,
    /// The class's threshold.
    threshold: f32,
}

#[pymethods]
impl Neighbour {
    fn __repr__(&self) -> String {
        format!(
            "Neighbour({:?}, distance={:.4}, threshold={:.4})",
            self.name, self.distance, self.threshold
        )
    }
}

fn neighbours(v: &[gc::Neighbour]) -> Vec<Neighbour> {
    v.iter()
        .map(|n| Neighbour {
            name: n.class.clone(),
            distance: n.distance,
            threshold: n.threshold,
        })
        .collect()
}

/// The answer to `Client.check`.
#[pyclass(frozen, get_all, module = "guardian")]
struct Verdict {
    /// The plan is the task it claims to be.
    go: bool,
    /// None for go, else `wrong-task`, `outlier`, `unknown-class`, `invalid-trajectory`,
    /// `workcell` or `geometry-mismatch`.
    reason: Option<&'static str>,
    /// `GO`, or `NO-GO` and the reason with its detail, as guardianctl prints it.
    summary: String,
    /// The claimed class.
    claimed: String,
    /// Distance to the claimed class's prototype.
    distance: Option<f32>,
    /// The claimed class's threshold.
    threshold: Option<f32>,
    /// threshold - distance (positive: inside the class).
    margin: Option<f32>,
    /// Nearest other class's distance - distance (positive: the claimed class is nearest).
    gap: Option<f32>,
    /// The nearest classes, nearest first.
    nearest: Vec<Neighbour>,
    /// The nearest other class for a wrong-task no-go.
    nearest_class: Option<String>,
    /// The invalid or workcell kind (`NonFinite`, `ToolOrientation`, ...).
    kind: Option<String>,
    /// The waypoint index (or offending count) of an invalid or workcell no-go.
    index: Option<u32>,
    /// The geometry feature of a geometry-mismatch no-go.
    feature: Option<String>,
    /// Geometry score against the claimed class.
    geometry_score: Option<f32>,
    /// The claimed class's geometry threshold.
    geometry_threshold: Option<f32>,
    /// Model version that answered.
    model_version: String,
    /// Class bank version that answered.
    bank_version: u64,
}

#[pymethods]
impl Verdict {
    fn __repr__(&self) -> String {
        format!(
            "Verdict({}, claimed={:?}, distance={}, threshold={}, margin={}, nearest={:?})",
            self.summary,
            self.claimed,
            opt_f32(self.distance),
            opt_f32(self.threshold),
            opt_f32(self.margin),
            self.nearest.first().map(|n| n.name.as_str()),
        )
    }
}

impl From<gc::Verdict> for Verdict {
    fn from(v: gc::Verdict) -> Self {
        use gc::NoGoReason as R;
        let summary = v.decision.to_string();
        let (mut reason, mut nearest_class, mut kind, mut index, mut feature) =
            (None, None, None, None, None);
        if let gc::Decision::NoGo { reason: r } = &v.decision {
            reason = Some(r.name());
            match r {
                R::WrongTask { nearest } => nearest_class = Some(nearest.clone()),
                R::InvalidTrajectory { kind: k, index: i } => {
                    kind = Some(invalid_kind_name(*k));
                    index = Some(*i);
                }
                R::Workcell { kind: k, index: i } => {
                    kind = Some(format!("{k:?}"));
                    index = Some(*i);
                }
                R::GeometryMismatch { feature: f, .. } => feature = Some(f.name().to_owned()),
                _ => {}
            }
        }
        Verdict {
            go: v.is_go(),
            reason,
            summary,
            claimed: v.claimed_class,
            distance: v.claimed_distance,
            threshold: v.threshold,
            margin: v.margin,
            gap: v.gap,
            nearest: neighbours(&v.nearest),
            nearest_class,
            kind,
            index,
            feature,
            geometry_score: v.geometry_score,
            geometry_threshold: v.geometry_threshold,
            model_version: v.model_version,
            bank_version: v.bank_version,
        }
    }
}

/// The answer to `Client.identify`.
#[pyclass(frozen, get_all, module = "guardian")]
struct Ranking {
    /// The nearest classes, nearest first.
    nearest: Vec<Neighbour>,
    /// Model version that answered.
    model_version: String,
    /// Class bank version that answered.
    bank_version: u64,
}

#[pymethods]
impl Ranking {
    fn __repr__(&self) -> String {
        let n: Vec<String> = self.nearest.iter().map(Neighbour::__repr__).collect();
        format!(
            "Ranking([{}], model_version={:?}, bank_version={})",
            n.join(", "),
            self.model_version,
            self.bank_version
        )
    }
}

/// An enrolled class.
#[pyclass(frozen, get_all, module = "guardian")]
struct ClassInfo {
    /// Class name.
    name: String,
    /// Enrolled examples.
    examples: u32,
    /// Decision threshold.
    threshold: f32,
    /// The threshold is calibrated for this class (else the global default).
    calibrated: bool,
}

#[pymethods]
impl ClassInfo {
    fn __repr__(&self) -> String {
        format!(
            "ClassInfo({:?}, examples={}, threshold={:.4}, calibrated={})",
            self.name,
            self.examples,
            self.threshold,
            if self.calibrated { "True" } else { "False" }
        )
    }
}

impl From<gc::ClassInfo> for ClassInfo {
    fn from(c: gc::ClassInfo) -> Self {
        ClassInfo {
            name: c.name,
            examples: c.examples,
            threshold: c.threshold,
            calibrated: c.calibrated,
        }
    }
}

/// The robot a daemon serves.
#[pyclass(frozen, get_all, module = "guardian")]
#[derive(Clone)]
struct Robot {
    /// `panda`, `ur5e`, or the name in a description file.
    name: String,
    /// Joints.
    joints: u32,
    /// Floats per waypoint: joints + the tool.
    channels: usize,
    /// SHA-256 of its URDF (hex).
    urdf_sha256: String,
}

#[pymethods]
impl Robot {
    fn __repr__(&self) -> String {
        format!(
            "Robot({:?}, joints={}, channels={})",
            self.name, self.joints, self.channels
        )
    }
}

/// The answer to `Client.status`.
#[pyclass(frozen, get_all, module = "guardian")]
struct Status {
    /// Model version.
    model_version: String,
    /// Class bank version.
    bank_version: u64,
    /// Enrolled classes.
    classes: u32,
    /// Seconds since the daemon started.
    uptime: f64,
    /// Requests answered.
    requests: u64,
    /// Requests answered with an error.
    errors: u64,
    /// Checks answered go.
    go: u64,
    /// Checks answered no-go.
    no_go: u64,
    /// Service-time percentiles (p50, p90, p99, max) in microseconds, None before the
    /// first request.
    latency_us: Option<(f32, f32, f32, f32)>,
    /// The robot served.
    robot: Robot,
}

#[pymethods]
impl Status {
    fn __repr__(&self) -> String {
        format!(
            "Status(robot={}, model_version={:?}, bank_version={}, classes={}, requests={}, go={}, no_go={})",
            self.robot.__repr__(),
            self.model_version,
            self.bank_version,
            self.classes,
            self.requests,
            self.go,
            self.no_go
        )
    }
}

/// A connection to guardiand over iceoryx2 for one thread: give every planner thread its
/// own `Client` (the ports are single-threaded; using one from another thread raises
/// `RuntimeError`).
#[pyclass(frozen, module = "guardian")]
struct Client {
    /// The Rust client, usable only on the thread that created it (checked on every call).
    /// `None` only while dropping.
    inner: Option<SendWrapper<gc::Client>>,
    service: String,
}

impl Client {
    /// The Rust client, if this is the thread that owns it.
    fn owned(&self) -> PyResult<&gc::Client> {
        match &self.inner {
            Some(c) if c.valid() => Ok(c),
            _ => Err(pyo3::exceptions::PyRuntimeError::new_err(
                "this guardian.Client belongs to the thread that created it: use one Client per thread",
            )),
        }
    }

    /// Run `f` on the client with the GIL released. `detach` runs it on this same thread
    /// (checked by `owned`); the wrapper only carries the reference across the `Send`
    /// bound, and checks the thread again when it is used.
    fn detached<T: Send>(
        &self,
        py: Python<'_>,
        f: impl FnOnce(&gc::Client) -> T + Send,
    ) -> PyResult<T> {
        let inner = SendWrapper::new(self.owned()?);
        Ok(py.detach(move || f(&inner)))
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        if let Some(c) = self.inner.take()
            && !c.valid()
        {
            // Collected on another thread: the ports cannot be closed here; leave them to
            // the process's exit (and the daemon's dead-node cleanup).
            std::mem::forget(c);
        }
    }
}

#[pymethods]
impl Client {
    #[new]
    #[pyo3(signature = (service=None, *, timeout=2.0, iceoryx2_root_path=None, iceoryx2_prefix=None))]
    fn new(
        py: Python<'_>,
        service: Option<String>,
        timeout: f64,
        iceoryx2_root_path: Option<PathBuf>,
        iceoryx2_prefix: Option<String>,
    ) -> PyResult<Self> {
        let config = client_config(service, timeout, iceoryx2_root_path, iceoryx2_prefix)?;
        let service = config.service_name.clone();
        // iceoryx2 set-up touches only Rust state: release the GIL for it too.
        let inner = py
            .detach(move || SendWrapper::new(gc::Client::connect(config)))
            .take()
            .map_err(|e| connect_err(py, e))?;
        Ok(Client {
            inner: Some(SendWrapper::new(inner)),
            service,
        })
    }

    /// Is `plan` the task `claimed`? Invalid plans and unknown classes are no-go verdicts.
    fn check(&self, py: Python<'_>, plan: &Bound<'_, PyAny>, claimed: &str) -> PyResult<Verdict> {
        let t = trajectory(plan, "plan")?;
        self.detached(py, |c| c.check(&t, claimed))?
            .map(Verdict::from)
            .map_err(|e| check_err(py, e))
    }

    /// The nearest enrolled classes to `plan`.
    fn identify(&self, py: Python<'_>, plan: &Bound<'_, PyAny>) -> PyResult<Ranking> {
        let t = trajectory(plan, "plan")?;
        let r = self
            .detached(py, |c| c.identify(&t))?
            .map_err(|e| check_err(py, e))?;
        Ok(Ranking {
            nearest: neighbours(&r.nearest),
            model_version: r.model_version,
            bank_version: r.bank_version,
        })
    }

    /// Every enrolled class.
    fn classes(&self, py: Python<'_>) -> PyResult<Vec<ClassInfo>> {
        let v = self
            .detached(py, |c| c.classes())?
            .map_err(|e| check_err(py, e))?;
        Ok(v.into_iter().map(ClassInfo::from).collect())
    }

    /// Versions, counters, latency percentiles and the robot served.
    fn status(&self, py: Python<'_>) -> PyResult<Status> {
        let s = self
            .detached(py, |c| c.status())?
            .map_err(|e| check_err(py, e))?;
        Ok(Status {
            model_version: s.model_version,
            bank_version: s.bank_version,
            classes: s.classes,
            uptime: s.uptime.as_secs_f64(),
            requests: s.requests,
            errors: s.errors,
            go: s.go,
            no_go: s.no_go,
            latency_us: s.latency_us.map(|l| (l[0], l[1], l[2], l[3])),
            robot: Robot {
                channels: s.robot.channels(),
                name: s.robot.name,
                joints: s.robot.joints,
                urdf_sha256: s.robot.urdf_sha256,
            },
        })
    }

    /// Enroll over the planners' service (only without admin separation; else
    /// `NotPermitted`: use `AdminClient`).
    fn enroll(
        &self,
        py: Python<'_>,
        name: &str,
        examples: &Bound<'_, PyAny>,
    ) -> PyResult<ClassInfo> {
        let ex = self::examples(examples)?;
        self.detached(py, |c| c.enroll(name, &ex))?
            .map(ClassInfo::from)
            .map_err(|e| enroll_err(py, e))
    }

    /// Forget over the planners' service (only without admin separation).
    fn forget(&self, py: Python<'_>, name: &str) -> PyResult<()> {
        self.detached(py, |c| c.forget(name))?
            .map_err(|e| check_err(py, e))
    }

    /// The per-request timeout in seconds.
    #[getter]
    fn timeout(&self) -> PyResult<f64> {
        Ok(self.owned()?.timeout().as_secs_f64())
    }

    /// The service name.
    #[getter]
    fn service(&self) -> &str {
        &self.service
    }

    fn __repr__(&self) -> String {
        format!("Client(service={:?})", self.service)
    }
}

/// Enroll and forget over the daemon's admin socket (the caller must be an admin). Each call
/// opens its own connection: one `AdminClient` may be used from any thread.
#[pyclass(frozen, module = "guardian")]
struct AdminClient {
    inner: gc::AdminClient,
}

#[pymethods]
impl AdminClient {
    /// `socket` given: that socket. Else found as guardianctl finds it:
    /// `$GUARDIAN_ADMIN_SOCKET`, the locator file of the daemon that `Client` with the same
    /// service and iceoryx2 settings reaches, `/run/guardian/admin.sock`,
    /// `./guardiand-state/admin.sock`.
    #[new]
    #[pyo3(signature = (socket=None, *, service=None, timeout=10.0, iceoryx2_root_path=None, iceoryx2_prefix=None))]
    fn new(
        py: Python<'_>,
        socket: Option<PathBuf>,
        service: Option<String>,
        timeout: f64,
        iceoryx2_root_path: Option<PathBuf>,
        iceoryx2_prefix: Option<String>,
    ) -> PyResult<Self> {
        let config = client_config(service, timeout, iceoryx2_root_path, iceoryx2_prefix)?;
        let inner = match socket {
            Some(p) => gc::AdminClient::new(p, config.timeout),
            None => gc::AdminClient::locate(&config).map_err(|e| {
                let looked: Vec<(String, String)> = e
                    .looked
                    .iter()
                    .map(|(p, w)| (p.display().to_string(), w.clone()))
                    .collect();
                raise::<AdminSocketNotFound>(
                    py,
                    e.to_string(),
                    &[("looked", obj(py, looked)), ("path", py.None())],
                )
            })?,
        };
        Ok(AdminClient { inner })
    }

    /// Add `examples` (a 3-D array [examples, waypoints, joints + 1] or a list of 2-D
    /// arrays) to class `name`, creating it if new.
    fn enroll(
        &self,
        py: Python<'_>,
        name: &str,
        examples: &Bound<'_, PyAny>,
    ) -> PyResult<ClassInfo> {
        let ex = self::examples(examples)?;
        let admin = self.inner.clone();
        py.detach(move || admin.enroll(name, &ex))
            .map(ClassInfo::from)
            .map_err(|e| enroll_err(py, e))
    }

    /// Remove class `name`.
    fn forget(&self, py: Python<'_>, name: &str) -> PyResult<()> {
        let admin = self.inner.clone();
        py.detach(move || admin.forget(name))
            .map_err(|e| check_err(py, e))
    }

    /// The socket's path.
    #[getter]
    fn socket(&self) -> String {
        self.inner.path().display().to_string()
    }

    fn __repr__(&self) -> String {
        format!(
            "AdminClient(socket={:?})",
            self.inner.path().display().to_string()
        )
    }
}

/// A dataset file of the project (`guardian-lab dataset`, docs/dataset.md).
#[pyclass(frozen, get_all, module = "guardian")]
struct Dataset {
    /// float32 [N, steps, joints + 1].
    trajectories: Py<PyArray3<f32>>,
    /// int64 [N], index into `classes`.
    labels: Py<PyArray1<i64>>,
    /// int64 [N], index into `alphabets`.
    alphabet_ids: Py<PyArray1<i64>>,
    /// int64 [N], the Omniglot drawer.
    drawer_ids: Py<PyArray1<i64>>,
    /// Class names (`Alphabet/characterNN`), in label order.
    classes: Vec<String>,
    /// Alphabet names, in id order.
    alphabets: Vec<String>,
    /// The robot that drew it (`panda` for files without that metadata).
    robot: String,
}

#[pymethods]
impl Dataset {
    fn __len__(&self, py: Python<'_>) -> usize {
        self.labels.bind(py).len()
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        format!(
            "Dataset({} trajectories of shape {:?}, {} classes, robot {:?})",
            self.labels.bind(py).len(),
            &self.trajectories.bind(py).shape()[1..],
            self.classes.len(),
            self.robot
        )
    }
}

fn read_err(path: &std::path::Path, what: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(format!("{}: {what}", path.display()))
}

/// Read a dataset file (safetensors written by `guardian-lab dataset`).
#[pyfunction]
fn read_dataset(py: Python<'_>, path: PathBuf) -> PyResult<Dataset> {
    let bytes = std::fs::read(&path)
        .map_err(|e| pyo3::exceptions::PyOSError::new_err(format!("{}: {e}", path.display())))?;
    let st = safetensors::SafeTensors::deserialize(&bytes)
        .map_err(|e| read_err(&path, format!("not a safetensors file: {e}")))?;
    let (_, meta) =
        safetensors::SafeTensors::read_metadata(&bytes).map_err(|e| read_err(&path, e))?;
    let meta = meta.metadata().clone().unwrap_or_default();
    let list = |key: &str| -> PyResult<Vec<String>> {
        let text = meta
            .get(key)
            .ok_or_else(|| read_err(&path, format!("metadata {key} is missing")))?;
        serde_json::from_str(text).map_err(|e| read_err(&path, format!("metadata {key}: {e}")))
    };
    let classes = list("classes")?;
    let alphabets = list("alphabets")?;
    let robot = meta
        .get("robot")
        .and_then(|r| serde_json::from_str::<serde_json::Value>(r).ok())
        .and_then(|v| v.get("name").and_then(|n| n.as_str()).map(str::to_owned))
        .unwrap_or_else(|| "panda".into());
    let t = st
        .tensor("trajectories")
        .map_err(|e| read_err(&path, format!("trajectories: {e}")))?;
    let shape = t.shape().to_vec();
    if t.dtype() != safetensors::Dtype::F32 || shape.len() != 3 {
        return Err(read_err(
            &path,
            format!(
                "trajectories must be F32 [N, steps, joints + 1], got {:?} {shape:?}",
                t.dtype()
            ),
        ));
    }
    let data: Vec<f32> = t
        .data()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let ints = |name: &str| -> PyResult<Py<PyArray1<i64>>> {
        let v = st
            .tensor(name)
            .map_err(|e| read_err(&path, format!("{name}: {e}")))?;
        if v.dtype() != safetensors::Dtype::I64 || v.shape() != [shape[0]] {
            return Err(read_err(
                &path,
                format!(
                    "{name} must be I64 [{}], got {:?} {:?}",
                    shape[0],
                    v.dtype(),
                    v.shape()
                ),
            ));
        }
        let d: Vec<i64> = v
            .data()
            .chunks_exact(8)
            .map(|c| i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect();
        Ok(PyArray1::from_vec(py, d).unbind())
    };
    let trajectories = PyArray1::from_vec(py, data)
        .reshape([shape[0], shape[1], shape[2]])?
        .unbind();
    Ok(Dataset {
        trajectories,
        labels: ints("labels")?,
        alphabet_ids: ints("alphabet_ids")?,
        drawer_ids: ints("drawer_ids")?,
        classes,
        alphabets,
        robot,
    })
}

/// Python bindings of guardian's planner client.
#[pymodule]
fn guardian(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add(
        "DEFAULT_SERVICE",
        guardian_shared::wire::DEFAULT_SERVICE_NAME,
    )?;
    m.add("DEFAULT_ADMIN_SOCKET", gc::DEFAULT_ADMIN_SOCKET)?;
    m.add_class::<Client>()?;
    m.add_class::<AdminClient>()?;
    m.add_class::<Verdict>()?;
    m.add_class::<Neighbour>()?;
    m.add_class::<Ranking>()?;
    m.add_class::<ClassInfo>()?;
    m.add_class::<Status>()?;
    m.add_class::<Robot>()?;
    m.add_class::<Dataset>()?;
    m.add_function(wrap_pyfunction!(read_dataset, m)?)?;
    m.add("GuardianError", py.get_type::<GuardianError>())?;
    m.add("ConnectError", py.get_type::<ConnectError>())?;
    m.add("DaemonNotRunning", py.get_type::<DaemonNotRunning>())?;
    m.add("Timeout", py.get_type::<Timeout>())?;
    m.add("NotServing", py.get_type::<NotServing>())?;
    m.add("InvalidClassName", py.get_type::<InvalidClassName>())?;
    m.add("InvalidTrajectory", py.get_type::<InvalidTrajectory>())?;
    m.add("UnknownClass", py.get_type::<UnknownClass>())?;
    m.add("EmptyBank", py.get_type::<EmptyBank>())?;
    m.add("BadRequest", py.get_type::<BadRequest>())?;
    m.add("InternalError", py.get_type::<InternalError>())?;
    m.add("TransportError", py.get_type::<TransportError>())?;
    m.add("ProtocolError", py.get_type::<ProtocolError>())?;
    m.add("LimitExceeded", py.get_type::<LimitExceeded>())?;
    m.add("NotPermitted", py.get_type::<NotPermitted>())?;
    m.add("StorageError", py.get_type::<StorageError>())?;
    m.add("Unreplicated", py.get_type::<Unreplicated>())?;
    m.add("AdminSocketError", py.get_type::<AdminSocketError>())?;
    m.add("AdminSocketNotFound", py.get_type::<AdminSocketNotFound>())?;
    Ok(())
}
