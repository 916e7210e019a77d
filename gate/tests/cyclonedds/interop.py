"""guardian-gate against a DDS stack that is not Rust: Eclipse Cyclone DDS (the `cyclonedds`
PyPI package, one of ROS 2's middlewares) with ROS 2's topic and type naming.

It starts the guardian-gate binary (argv[1]) with DDS on loopback, a domain of its own and
service-mapping = "cyclone" (rmw_cyclonedds's request/reply layout), and no guardiand, so
every goal must be refused. Cyclone, with multicast off and 127.0.0.1 as its only peer:
publishes the claimed task on rt/<gate>/task (std_msgs String, reliable, transient local)
and sees it in the gate's /diagnostics; sends a FollowJointTrajectory goal through the
action's send_goal service and reads its result through get_result (ABORTED, INVALID_GOAL,
fail closed); reads the verdict on rt/<gate>/verdicts. Run by gate/tests/cyclonedds/run.sh.
"""
import os
import subprocess
import tempfile
import sys, time, uuid
from cyclonedds.domain import DomainParticipant
from cyclonedds.topic import Topic
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.core import Qos, Policy
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ros2types import *  # noqa: F401,F403 (the message types)

PATIENCE = 30
passed, failed = 0, 0
def check(what, ok, detail=""):
    global passed, failed
    print(("ok     " if ok else "FAILED ") + what + (f": {detail}" if detail and not ok else ""))
    if ok: passed += 1
    else: failed += 1

gate_bin = sys.argv[1]
domain = 200 + os.getpid() % 30
gate = f"/cyclone_gate_{os.getpid()}"
tmp = tempfile.mkdtemp()
cfg = os.path.join(tmp, "gate.toml")
with open(cfg, "w") as f:
    f.write(f'gate = "{gate}"\ncontroller = "/cyclone_ctrl_{os.getpid()}"\ndomain-id = {domain}\n'
            'only-networks = ["127.0.0.1"]\nservice-mapping = "cyclone"\n'
            f'[guardiand]\nservice-name = "guardian-cyclone-test/{os.getpid()}/none"\n')
xml = os.path.join(tmp, "cyclone.xml")
with open(xml, "w") as f:
    f.write('<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
            '<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>'
            '<Peers><Peer address="127.0.0.1"/></Peers><MaxAutoParticipantIndex>20</MaxAutoParticipantIndex></Discovery></Domain></CycloneDDS>')
os.environ["CYCLONEDDS_URI"] = "file://" + xml
# The gate's own default log filter (no RUST_LOG), its log in a file (not a terminal).
log_path = os.path.join(tmp, "gate.log")
log = open(log_path, "wb")
gate_env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
proc = subprocess.Popen([gate_bin, "--config", cfg], env=gate_env, stderr=log)
IDLE = 20
try:
    dp = DomainParticipant(domain)
    rel = Qos(Policy.Reliability.Reliable(1_000_000_000), Policy.History.KeepLast(10))
    latched = Qos(Policy.Reliability.Reliable(1_000_000_000), Policy.Durability.TransientLocal, Policy.History.KeepLast(1))
    a = f"{gate}/follow_joint_trajectory/_action"
    task_w = DataWriter(dp, Topic(dp, f"rt{gate}/task", String_), qos=latched)
    diag_r = DataReader(dp, Topic(dp, "rt/diagnostics", DiagnosticArray_), qos=rel)
    req_w = DataWriter(dp, Topic(dp, f"rq{a}/send_goalRequest", SendGoalRequest_), qos=rel)
    rep_r = DataReader(dp, Topic(dp, f"rr{a}/send_goalReply", SendGoalResponse_), qos=rel)
    res_w = DataWriter(dp, Topic(dp, f"rq{a}/get_resultRequest", GetResultRequest_), qos=rel)
    res_r = DataReader(dp, Topic(dp, f"rr{a}/get_resultReply", GetResultResponse_), qos=rel)
    ver_r = DataReader(dp, Topic(dp, f"rt{gate}/verdicts", Verdict_), qos=rel)

    def matched(w):
        deadline = time.time() + PATIENCE
        while time.time() < deadline:
            if w.get_matched_subscriptions():
                return True
            time.sleep(0.1)
        return False
    check("the gate's task, send_goal and get_result readers are discovered",
          matched(task_w) and matched(req_w) and matched(res_w))

    claim = "interop-task"
    task_w.write(String_(data=claim))
    seen = None
    deadline = time.time() + PATIENCE
    while time.time() < deadline and seen != claim:
        for d in diag_r.take(10):
            seen = {kv.key: kv.value for kv in d.status[0].values}.get("claimed task")
        time.sleep(0.1)
    check("the published task reaches the gate (its /diagnostics reports it)", seen == claim, repr(seen))

    names = [f"panda_joint{i}" for i in range(1, 8)]
    ready = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
    pts = [JointTrajectoryPoint_(positions=[q + 0.01 * k for q in ready], velocities=[], accelerations=[],
                                 effort=[], time_from_start=Duration_(k, 0)) for k in range(5)]
    empty = Header_(Time_(0, 0), "")
    goal = Goal_(JointTrajectory_(empty, names, pts), MultiDOFJointTrajectory_(empty, [], []), [], [], [], [], Duration_(0, 0))
    gid_bytes = uuid.uuid4().bytes
    gid = UUID_(list(gid_bytes))
    guid = 0x1234567890ABCDEF

    def take_one(r):
        deadline = time.time() + PATIENCE
        while time.time() < deadline:
            for s in r.take(10):
                if getattr(s, "client_guid", guid) == guid:
                    return s
            time.sleep(0.05)
        return None

    req_w.write(SendGoalRequest_(guid, 1, gid, goal))
    resp = take_one(rep_r)
    check("send_goal is answered", resp is not None and resp.seq == 1, repr(resp))
    res_w.write(GetResultRequest_(guid, 2, gid))
    res = take_one(res_r)
    check("get_result: ABORTED (6), INVALID_GOAL (-1), fail closed",
          res is not None and res.status == 6 and res.result.error_code == -1
          and "fail closed" in res.result.error_string, repr(res))
    v = take_one(ver_r)
    check("the verdict arrives on rt/<gate>/verdicts with the goal id and the claim",
          v is not None and v.verdict == "error" and v.goal_id == gid_bytes.hex() and v.claimed_task == claim, repr(v))

    # An idle gate beside a live Cyclone DDS participant logs (almost) nothing: the target is
    # under one line a minute; RustDDS's "No locators" WARN once came at ~33 lines/s here.
    log.flush()
    before = open(log_path, "rb").read().count(b"\n")
    time.sleep(IDLE)
    text = open(log_path, "rb").read()
    idle_lines = text.count(b"\n") - before
    print(f"idle gate: {idle_lines} log lines in {IDLE} s")
    check(f"an idle gate logs at most one line in {IDLE} s", idle_lines <= 1,
          text.decode(errors="replace").splitlines()[-1:][0][:300] if idle_lines else "")
    check("the gate's log file has no terminal colour codes", b"\x1b[" not in text)
finally:
    proc.terminate()
    proc.wait(timeout=15)
print(f"{passed} passed, {failed} failed")
sys.exit(1 if failed else 0)
