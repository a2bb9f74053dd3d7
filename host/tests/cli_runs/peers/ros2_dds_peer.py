"""A ROS 2 user of `amr sim --ros2-live dds --ros2-cmd-vel` on DDS, as Eclipse Cyclone DDS's Python
binding sees it (the PyPI `cyclonedds` wheel bundles the C library): ROS 2's DDS names (`rt/...`,
`pkg::msg::dds_::Type_`) and the message types of cyclone_types.py. It joins
after the fleet started (so `/map` reaches it only as a late joiner), reads scans, /tf and V's
estimate, gives V's pose on /initialpose, then drives V on /cmd_vel for DRIVE_S seconds. Prints one JSON object.

usage: ros2_dds_peer.py DOMAIN DRIVE_S W_RADPS
"""
import json
import math
import sys
import time

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from cyclone_types import (Header, LaserScan, OccupancyGrid, Point, Pose, PoseWithCovariance,
                           PoseWithCovarianceStamped, Quaternion, TFMessage, Twist, Vector3)

domain, drive_s, w_cmd = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])

dp = DomainParticipant(domain)
sensor = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5))
reliable = Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.Durability.Volatile, Policy.History.KeepLast(10))
latched = Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.Durability.TransientLocal, Policy.History.KeepLast(1))
scan_r = DataReader(dp, Topic(dp, "rt/robot_a/scan", LaserScan), qos=sensor)
map_r = DataReader(dp, Topic(dp, "rt/map", OccupancyGrid), qos=latched)
tf_r = DataReader(dp, Topic(dp, "rt/tf", TFMessage), qos=Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.History.KeepLast(100)))
v_r = DataReader(dp, Topic(dp, "rt/amcl/V", PoseWithCovarianceStamped), qos=reliable)
cmd_w = DataWriter(dp, Topic(dp, "rt/cmd_vel", Twist), qos=reliable)
pose_w = DataWriter(dp, Topic(dp, "rt/initialpose", PoseWithCovarianceStamped), qos=reliable)

start = time.time()
out = {"scans": [], "maps": [], "tf_pairs": set(), "estimates": [], "phases": {}}


def poll():
    for s in scan_r.take(20):
        out["scans"].append({"frame_id": s.header.frame_id, "ranges": len(s.ranges)})
    for m in map_r.take(5):
        out["maps"].append({"width": m.info.width, "height": m.info.height, "cells": len(m.data),
                            "resolution": m.info.resolution, "frame_id": m.header.frame_id})
    for t in tf_r.take(50):
        for x in t.transforms:
            out["tf_pairs"].add((x.header.frame_id, x.child_frame_id))
    for e in v_r.take(20):
        q = e.pose.pose.orientation
        th = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        out["estimates"].append([time.time() - start, e.pose.pose.position.x, e.pose.pose.position.y, th,
                                 e.pose.covariance[0], e.header.frame_id])


deadline = time.time() + 20.0
while time.time() < deadline and (not out["estimates"] or len(out["scans"]) < 10 or not out["maps"]):
    poll()
    time.sleep(0.05)
# RViz's "2D Pose Estimate" where V is (with RViz's covariance), then time to verify again.
_, x, y, th = out["estimates"][-1][:4]
cov = [0.0] * 36
cov[0], cov[7], cov[35] = 0.25, 0.25, 0.0685
pose_w.write(PoseWithCovarianceStamped(
    header=Header(frame_id="map"),
    pose=PoseWithCovariance(pose=Pose(position=Point(x=x, y=y), orientation=Quaternion(z=math.sin(th / 2), w=math.cos(th / 2))),
                            covariance=cov)))
out["phases"]["initialpose"] = time.time() - start
t_end = time.time() + 3.0
while time.time() < t_end:
    poll()
    time.sleep(0.05)
out["phases"]["drive"] = time.time() - start
end = time.time() + drive_s
while time.time() < end:
    cmd_w.write(Twist(linear=Vector3(x=0.2), angular=Vector3(z=w_cmd)))
    poll()
    time.sleep(0.1)
out["phases"]["silent"] = time.time() - start
t_end = time.time() + 1.0
while time.time() < t_end:
    poll()
    time.sleep(0.05)
out["tf_pairs"] = sorted(out["tf_pairs"])
print(json.dumps(out))
