"""Write a rosbag2 MCAP bag with `rosbags` (pure Python, ROS 2 Jazzy types, CDR).

Usage: write_bag.py PLANS.csv OUT_DIR TOPIC
PLANS.csv: one line per waypoint, `plan,joint_name=value,...`; every plan becomes one
trajectory_msgs/msg/JointTrajectory message on TOPIC.
"""
import sys
from collections import OrderedDict

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

plans_csv, out_dir, topic = sys.argv[1:4]
ts = get_typestore(Stores.ROS2_JAZZY)
JointTrajectory = ts.types["trajectory_msgs/msg/JointTrajectory"]
JointTrajectoryPoint = ts.types["trajectory_msgs/msg/JointTrajectoryPoint"]
Header = ts.types["std_msgs/msg/Header"]
Time = ts.types["builtin_interfaces/msg/Time"]
Duration = ts.types["builtin_interfaces/msg/Duration"]

plans = OrderedDict()
for line in open(plans_csv):
    plan, *pairs = line.strip().split(",")
    names = [p.split("=")[0] for p in pairs]
    values = [float(p.split("=")[1]) for p in pairs]
    plans.setdefault(plan, (names, []))[1].append(values)

with Writer(out_dir, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
    conn = writer.add_connection(topic, JointTrajectory.__msgtype__, typestore=ts)
    for i, (names, rows) in enumerate(plans.values()):
        points = [
            JointTrajectoryPoint(
                positions=np.array(r, dtype=np.float64),
                velocities=np.array([], dtype=np.float64),
                accelerations=np.array([], dtype=np.float64),
                effort=np.array([], dtype=np.float64),
                time_from_start=Duration(sec=k // 10, nanosec=(k % 10) * 100_000_000),
            )
            for k, r in enumerate(rows)
        ]
        msg = JointTrajectory(
            header=Header(stamp=Time(sec=i, nanosec=0), frame_id="panda_link0"),
            joint_names=names,
            points=points,
        )
        stamp = 1_700_000_000_000_000_000 + i * 1_000_000
        writer.write(conn, stamp, ts.serialize_cdr(msg, JointTrajectory.__msgtype__))
print(out_dir)
