"""A ROS 2 user's view of `amr sim --ros2-live zenoh`, through an independent rmw_zenoh peer
(eclipse-zenoh for the wire, rosbags for the types and hashes). It joins after the fleet started
(so `/map` and `/tf_static` reach it only as a late joiner), listens for a few seconds and prints
one JSON object: the graph's publishers and what it decoded on each topic.

usage: ros2_live_peer.py PORT DOMAIN LISTEN_S
"""
import json
from pathlib import Path
import sys
import time

import zenoh.ext as ze

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "ros2" / "tests" / "peers"))
from rmw_zenoh_wire import TYPESTORE as ts, open_peer  # noqa: E402
from rmw_zenoh_wire import key as wire_key  # noqa: E402

port, domain, listen_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])


def key(topic, t):
    return wire_key(domain, topic, t)


s = open_peer(port)

SUBS = {
    "/robot_a/scan": "sensor_msgs/msg/LaserScan",
    "/virtual/scan": "sensor_msgs/msg/LaserScan",
    "/robot_a/odom": "nav_msgs/msg/Odometry",
    "/amcl/V": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/clock": "rosgraph_msgs/msg/Clock",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
LATCHED = {"/map": "nav_msgs/msg/OccupancyGrid", "/tf_static": "tf2_msgs/msg/TFMessage"}
got = {t: [] for t in list(SUBS) + list(LATCHED)}


def keep(topic):
    return lambda smp: got[topic].append((bytes(smp.payload.to_bytes()), smp.attachment is not None))


subs = [s.declare_subscriber(key(t, ty), keep(t)) for t, ty in SUBS.items()]
subs += [ze.declare_advanced_subscriber(s, key(t, ty), history=ze.HistoryConfig(detect_late_publishers=True),
                                        subscriber_detection=True, handler=keep(t))
         for t, ty in LATCHED.items()]
time.sleep(listen_s)

publishers, subscriptions = [], []
for r in s.liveliness().get(f"@ros2_lv/{domain}/**", timeout=5.0):
    if r.ok is not None:
        f = str(r.ok.key_expr).split("/")
        if len(f) == 13 and f[5] in ("MP", "MS"):
            entry = {"topic": f[9].replace("%", "/"), "type": f[10], "hash": f[11], "qos": f[12]}
            (publishers if f[5] == "MP" else subscriptions).append(entry)


def decoded(topic, ty, payload):
    m = ts.deserialize_cdr(payload, ty)
    if ty.endswith("LaserScan"):
        return {"frame_id": m.header.frame_id, "ranges": len(m.ranges), "stamp": m.header.stamp.sec + m.header.stamp.nanosec * 1e-9}
    if ty.endswith("Odometry"):
        return {"frame_id": m.header.frame_id, "child": m.child_frame_id}
    if ty.endswith("PoseWithCovarianceStamped"):
        p = m.pose.pose.position
        return {"frame_id": m.header.frame_id, "x": p.x, "y": p.y}
    if ty.endswith("TFMessage"):
        return {"pairs": [[t.header.frame_id, t.child_frame_id] for t in m.transforms]}
    if ty.endswith("DiagnosticArray"):
        return {"status": [[st.name, int(st.level), st.message, {kv.key: kv.value for kv in st.values}] for st in m.status]}
    if ty.endswith("Clock"):
        return {"t": m.clock.sec + m.clock.nanosec * 1e-9}
    if ty.endswith("OccupancyGrid"):
        return {"frame_id": m.header.frame_id, "width": int(m.info.width), "height": int(m.info.height),
                "resolution": float(m.info.resolution), "cells": len(m.data)}
    return {}


out = {"publishers": publishers, "subscriptions": subscriptions, "topics": {}}
types = dict(SUBS, **LATCHED)
for t, samples in got.items():
    out["topics"][t] = {
        "count": len(samples),
        "attachments": sum(1 for _, a in samples if a),
        "first": decoded(t, types[t], samples[0][0]) if samples else None,
        "pairs": sorted({tuple(p) for pl, _ in samples for p in decoded(t, types[t], pl)["pairs"]})
        if types[t].endswith("TFMessage") else None,
        "statuses": [st for pl, _ in samples for st in decoded(t, types[t], pl)["status"]]
        if types[t].endswith("DiagnosticArray") else None,
        "last": decoded(t, types[t], samples[-1][0]) if samples else None,
    }
print(json.dumps(out))
sys.stdout.flush()
s.close()
