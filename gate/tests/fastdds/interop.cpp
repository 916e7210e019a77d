// guardian-gate against eProsima Fast DDS 2.9 (Debian's libfastrtps), the DDS stack behind
// ROS 2 Jazzy's default RMW (rmw_fastrtps_cpp), with ROS 2's topic and type names and the
// "enhanced" service mapping: the request id is the request sample's identity, a reply
// names it as its related sample identity.
//
// Usage: fastdds-interop DOMAIN GATE_NAMESPACE EXECUTIVE_NODE
// The gate (started by run.sh) runs with DDS on loopback, claim-from = [EXECUTIVE_NODE]
// and no guardiand, so every goal must be refused (fail closed). This participant, with
// UDPv4 on 127.0.0.1 only (no shared memory, 127.0.0.1 as its initial peer):
//  1. says on ros_discovery_info that its task writer belongs to EXECUTIVE_NODE, as every
//     ROS 2 participant does, and claims a task: /diagnostics reports it;
//  2. claims another task from a second writer that no node owns: refused, counted in
//     /diagnostics, the claim unchanged;
//  3. sends a FollowJointTrajectory goal through send_goal and reads its result through
//     get_result, matching each reply by its related sample identity: ABORTED,
//     INVALID_GOAL, "fail closed";
//  4. reads the verdict on rt<gate>/verdicts: error, the goal id, the claimed task.
// Prints one line per check and exits 1 if any failed. Bounded: every wait ends.
#include <array>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <thread>

#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastdds/rtps/common/WriteParams.h>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastrtps/utils/IPLocator.h>

#include "ros2.h"
#include "ros2PubSubTypes.h"

using namespace eprosima::fastdds::dds;
using eprosima::fastrtps::rtps::GUID_t;
using eprosima::fastrtps::rtps::IPLocator;
using eprosima::fastrtps::rtps::Locator_t;
using eprosima::fastrtps::rtps::SampleIdentity;
using eprosima::fastrtps::rtps::WriteParams;
namespace bi = builtin_interfaces::msg::dds_;
namespace act = control_msgs::action::dds_;
namespace tm_ = trajectory_msgs::msg::dds_;
namespace rdc = rmw_dds_common::msg::dds_;

static const auto PATIENCE = std::chrono::seconds(30);
static int passed = 0, failed = 0;

static void check(const std::string& what, bool ok, const std::string& detail = "") {
  std::printf("%s%s%s\n", ok ? "ok     " : "FAILED ", what.c_str(),
              (!ok && !detail.empty()) ? (": " + detail).c_str() : "");
  std::fflush(stdout);
  (ok ? passed : failed)++;
}

// Poll `done` every 50 ms until it holds or PATIENCE has passed.
static bool wait_for(const std::function<bool()>& done) {
  auto deadline = std::chrono::steady_clock::now() + PATIENCE;
  while (std::chrono::steady_clock::now() < deadline) {
    if (done()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return false;
}

struct Dds {
  DomainParticipant* participant;
  Publisher* publisher;
  Subscriber* subscriber;
  std::map<std::string, TypeSupport> types;

  template <class PubSub>
  Topic* topic(const std::string& name) {
    TypeSupport ts(new PubSub());
    auto it = types.find(ts.get_type_name());
    if (it == types.end()) {
      ts.register_type(participant);
      it = types.emplace(ts.get_type_name(), ts).first;
    }
    return participant->create_topic(name, it->second.get_type_name(), TOPIC_QOS_DEFAULT);
  }

  DataWriter* writer(Topic* t, bool latched) {
    DataWriterQos q = DATAWRITER_QOS_DEFAULT;
    q.reliability().kind = RELIABLE_RELIABILITY_QOS;
    q.durability().kind = latched ? TRANSIENT_LOCAL_DURABILITY_QOS : VOLATILE_DURABILITY_QOS;
    q.history().kind = KEEP_LAST_HISTORY_QOS;
    q.history().depth = latched ? 1 : 10;
    return publisher->create_datawriter(t, q);
  }

  DataReader* reader(Topic* t) {
    DataReaderQos q = DATAREADER_QOS_DEFAULT;
    q.reliability().kind = RELIABLE_RELIABILITY_QOS;
    q.history().kind = KEEP_LAST_HISTORY_QOS;
    q.history().depth = 100;
    return subscriber->create_datareader(t, q);
  }
};

static bool matched(DataWriter* w) {
  return wait_for([&] {
    PublicationMatchedStatus s;
    w->get_publication_matched_status(s);
    return s.current_count > 0;
  });
}

static rdc::Gid_ gid_of(const GUID_t& g) {
  rdc::Gid_ gid;
  std::array<uint8_t, 16> d{};
  for (int i = 0; i < 12; i++) d[i] = g.guidPrefix.value[i];
  for (int i = 0; i < 4; i++) d[12 + i] = g.entityId.value[i];
  gid.data(d);
  return gid;
}

// The value of `key` in the gate's latest /diagnostics, read until `want` holds for it.
static bool diagnostics_say(DataReader* r, const std::string& key,
                            const std::function<bool(const std::string&)>& want, std::string& seen) {
  return wait_for([&] {
    diagnostic_msgs::msg::dds_::DiagnosticArray_ d;
    SampleInfo info;
    while (r->take_next_sample(&d, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data || d.status().empty()) continue;
      for (const auto& kv : d.status()[0].values()) {
        if (kv.key() == key) seen = kv.value();
      }
    }
    return want(seen);
  });
}

int main(int argc, char** argv) {
  if (argc != 4) {
    std::fprintf(stderr, "usage: %s DOMAIN GATE_NAMESPACE EXECUTIVE_NODE\n", argv[0]);
    return 2;
  }
  const int domain = std::atoi(argv[1]);
  const std::string gate = argv[2];
  const std::string executive = argv[3];  // "/fastdds_executive"

  DomainParticipantQos pq = PARTICIPANT_QOS_DEFAULT;
  pq.name("fastdds_interop");
  pq.transport().use_builtin_transports = false;
  auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
  udp->interfaceWhiteList.emplace_back("127.0.0.1");
  pq.transport().user_transports.push_back(udp);
  Locator_t peer;
  IPLocator::setIPv4(peer, "127.0.0.1");
  pq.wire_protocol().builtin.initialPeersList.push_back(peer);
  Dds dds{};
  dds.participant = DomainParticipantFactory::get_instance()->create_participant(domain, pq);
  if (!dds.participant) {
    std::fprintf(stderr, "cannot create the Fast DDS participant\n");
    return 2;
  }
  dds.publisher = dds.participant->create_publisher(PUBLISHER_QOS_DEFAULT);
  dds.subscriber = dds.participant->create_subscriber(SUBSCRIBER_QOS_DEFAULT);

  const std::string a = gate + "/follow_joint_trajectory/_action";
  Topic* task_t = dds.topic<std_msgs::msg::dds_::String_PubSubType>("rt" + gate + "/task");
  auto* task_w = dds.writer(task_t, true);
  auto* stray_w = dds.writer(task_t, true);
  auto* graph_w = dds.writer(dds.topic<rdc::ParticipantEntitiesInfo_PubSubType>("ros_discovery_info"), true);
  auto* diag_r = dds.reader(dds.topic<diagnostic_msgs::msg::dds_::DiagnosticArray_PubSubType>("rt/diagnostics"));
  auto* req_w = dds.writer(dds.topic<act::FollowJointTrajectory_SendGoal_Request_PubSubType>("rq" + a + "/send_goalRequest"), false);
  auto* rep_r = dds.reader(dds.topic<act::FollowJointTrajectory_SendGoal_Response_PubSubType>("rr" + a + "/send_goalReply"));
  auto* res_w = dds.writer(dds.topic<act::FollowJointTrajectory_GetResult_Request_PubSubType>("rq" + a + "/get_resultRequest"), false);
  auto* res_r = dds.reader(dds.topic<act::FollowJointTrajectory_GetResult_Response_PubSubType>("rr" + a + "/get_resultReply"));
  auto* ver_r = dds.reader(dds.topic<guardian_msgs::msg::dds_::Verdict_PubSubType>("rt" + gate + "/verdicts"));
  if (!task_w || !stray_w || !graph_w || !diag_r || !req_w || !rep_r || !res_w || !res_r || !ver_r) {
    std::fprintf(stderr, "cannot create the Fast DDS entities\n");
    return 2;
  }

  check("the gate's task, send_goal and get_result readers are discovered",
        matched(task_w) && matched(req_w) && matched(res_w));
  // As rmw_fastrtps does: this participant's node and the writers it owns.
  {
    rdc::NodeEntitiesInfo_ node;
    auto slash = executive.rfind('/');
    node.node_namespace(slash == 0 ? "/" : executive.substr(0, slash));
    node.node_name(executive.substr(slash + 1));
    node.writer_gid_seq({gid_of(task_w->guid()), gid_of(graph_w->guid())});
    rdc::ParticipantEntitiesInfo_ info;
    info.gid(gid_of(dds.participant->guid()));
    info.node_entities_info_seq({node});
    graph_w->write(&info);
  }

  // 1. The executive's claim is taken.
  const std::string claim = "interop-task";
  std_msgs::msg::dds_::String_ msg;
  msg.data(claim);
  task_w->write(&msg);
  std::string seen;
  bool ok = diagnostics_say(diag_r, "claimed task", [&](const std::string& v) { return v == claim; }, seen);
  check("the executive node's claim reaches the gate (its /diagnostics reports it)", ok, "'" + seen + "'");

  // 2. A writer no node owns: refused, the claim unchanged.
  msg.data("stray-task");
  stray_w->write(&msg);
  std::string refused;
  ok = diagnostics_say(diag_r, "claims refused", [&](const std::string& v) { return !v.empty() && v != "0"; }, refused);
  std::string still;
  diagnostics_say(diag_r, "claimed task", [&](const std::string& v) { return !v.empty(); }, still);
  check("a claim from a writer of no node of claim-from is refused and changes nothing", ok && still == claim,
        "refused " + refused + ", claimed task '" + still + "'");

  // 3. A goal through send_goal and get_result (enhanced mapping).
  act::FollowJointTrajectory_SendGoal_Request_ req;
  std::array<uint8_t, 16> goal_id{};
  std::mt19937 rng(std::random_device{}());
  for (auto& b : goal_id) b = static_cast<uint8_t>(rng());
  req.goal_id().uuid(goal_id);
  const char* names[] = {"panda_joint1", "panda_joint2", "panda_joint3", "panda_joint4",
                         "panda_joint5", "panda_joint6", "panda_joint7"};
  const double ready[] = {0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785};
  auto& traj = req.goal().trajectory();
  for (auto n : names) traj.joint_names().push_back(n);
  for (int k = 0; k < 5; k++) {
    tm_::JointTrajectoryPoint_ pt;
    for (double q : ready) pt.positions().push_back(q + 0.01 * k);
    pt.time_from_start().sec(k);
    traj.points().push_back(pt);
  }
  auto request = [&](DataWriter* w, void* data) {
    WriteParams wp;
    w->write(data, wp);
    return wp.sample_identity();
  };
  auto reply_to = [&](DataReader* r, const SampleIdentity& id, void* out) {
    return wait_for([&] {
      SampleInfo info;
      while (r->take_next_sample(out, &info) == ReturnCode_t::RETCODE_OK) {
        if (info.valid_data && info.related_sample_identity == id) return true;
      }
      return false;
    });
  };
  act::FollowJointTrajectory_SendGoal_Response_ resp;
  ok = reply_to(rep_r, request(req_w, &req), &resp);
  check("send_goal is answered (the reply names the request's sample identity)", ok);
  act::FollowJointTrajectory_GetResult_Request_ rreq;
  rreq.goal_id().uuid(goal_id);
  act::FollowJointTrajectory_GetResult_Response_ res;
  ok = reply_to(res_r, request(res_w, &rreq), &res);
  check("get_result: ABORTED (6), INVALID_GOAL (-1), fail closed",
        ok && res.status() == 6 && res.result().error_code() == -1 &&
            res.result().error_string().find("fail closed") != std::string::npos,
        "status " + std::to_string(int(res.status())) + ", code " + std::to_string(res.result().error_code()) +
            ", '" + res.result().error_string() + "'");

  // 4. The verdict.
  std::string hex;
  for (auto b : goal_id) {
    char h[3];
    std::snprintf(h, sizeof h, "%02x", b);
    hex += h;
  }
  guardian_msgs::msg::dds_::Verdict_ v;
  ok = wait_for([&] {
    SampleInfo info;
    while (ver_r->take_next_sample(&v, &info) == ReturnCode_t::RETCODE_OK) {
      if (info.valid_data && v.goal_id() == hex) return true;
    }
    return false;
  });
  check("the verdict arrives on rt<gate>/verdicts with the goal id and the claim",
        ok && v.verdict() == "error" && v.claimed_task() == claim,
        "verdict '" + v.verdict() + "', claimed task '" + v.claimed_task() + "'");

  dds.participant->delete_contained_entities();
  DomainParticipantFactory::get_instance()->delete_participant(dds.participant);
  std::printf("%d passed, %d failed\n", passed, failed);
  return failed ? 1 : 0;
}
