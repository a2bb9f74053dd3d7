"""An rmw_zenoh peer written from ros2/rmw_zenoh's design document alone, with eclipse-zenoh (the
Zenoh project's Python binding), rosbags (an independent CDR codec and REP 2011 type hashes) and
xxhash (the GID). It joins the node under test on `tcp/127.0.0.1:<port>` and prints one JSON
object: the graph it sees, what it decoded, and whether each sample's attachment and GID are as
rmw_zenoh writes them. It also publishes /cmd_vel (geometry_msgs/msg/Twist) as rmw_zenoh would.

usage: rmw_zenoh_peer.py PORT DOMAIN
"""
import json
from pathlib import Path
import struct
import sys
import time

import zenoh.ext as ze
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rmw_zenoh_wire import TYPESTORE as ts, attachment, dds, gid, open_peer  # noqa: E402
from rmw_zenoh_wire import key as wire_key  # noqa: E402

port, domain = sys.argv[1], int(sys.argv[2])
TYPES = {
    "scan": "sensor_msgs/msg/LaserScan",
    "map": "nav_msgs/msg/OccupancyGrid",
    "cmd_vel": "geometry_msgs/msg/Twist",
}


def key(topic, t):
    return wire_key(domain, topic, t)


s = open_peer(port)
time.sleep(1.0)

out = {"hashes": {t: ts.hash_rihs01(t) for t in TYPES.values()}}

# The graph: every liveliness token in the domain, split into its fields.
tokens = []
for r in s.liveliness().get(f"@ros2_lv/{domain}/**", timeout=5.0):
    if r.ok is not None:
        tokens.append(str(r.ok.key_expr))
out["tokens"] = sorted(tokens)
gid_of = {}
for t in tokens:
    f = t.split("/")
    if len(f) == 13 and f[5] == "MP":
        gid_of[f[9].replace("%", "/")] = gid(t)

# A late joiner on /map (transient local): the cached sample, through an advanced subscriber.
got_map = []
map_sub = ze.declare_advanced_subscriber(
    s, key("/map", TYPES["map"]),
    history=ze.HistoryConfig(detect_late_publishers=True),
    subscriber_detection=True,
    handler=lambda smp: got_map.append((bytes(smp.payload.to_bytes()),
                                        bytes(smp.attachment.to_bytes()) if smp.attachment else b"")),
)
scans = []
scan_sub = s.declare_subscriber(
    key("/robot_a/scan", TYPES["scan"]),
    lambda smp: scans.append((bytes(smp.payload.to_bytes()),
                              bytes(smp.attachment.to_bytes()) if smp.attachment else b"")),
)

# /cmd_vel as an rmw_zenoh publisher: a node token, a publisher token, attachments.
zid = str(s.info.zid())
hash_tw = ts.hash_rihs01(TYPES["cmd_vel"])
node_tok = f"@ros2_lv/{domain}/{zid}/0/0/NN/%/%/teleop"
pub_tok = f"@ros2_lv/{domain}/{zid}/0/1/MP/%/%/teleop/%cmd_vel/{dds(TYPES['cmd_vel'])}/{hash_tw}/::,10:,:,:,,"
tok1 = s.liveliness().declare_token(node_tok)
tok2 = s.liveliness().declare_token(pub_tok)
pub = s.declare_publisher(key("/cmd_vel", TYPES["cmd_vel"]))
my_gid = gid(pub_tok)
Twist = ts.types["geometry_msgs/msg/Twist"]

# A latched /peer_map as rmw_zenoh publishes one (transient local: an advanced publisher with a
# cache of 1), put once before the first /cmd_vel: a subscription made after that still gets it.
MAP = TYPES["map"]
hash_map = ts.hash_rihs01(MAP)
map_tok = f"@ros2_lv/{domain}/{zid}/0/3/MP/%/%/teleop/%peer_map/{dds(MAP)}/{hash_map}/:1:,1:,:,:,,"
tok3 = s.liveliness().declare_token(map_tok)
peer_map_pub = ze.declare_advanced_publisher(s, key("/peer_map", MAP), cache=ze.CacheConfig(max_samples=1),
                                            publisher_detection=True)
T = ts.types
grid = T[MAP](
    header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=7, nanosec=0), frame_id="peer"),
    info=T["nav_msgs/msg/MapMetaData"](
        map_load_time=T["builtin_interfaces/msg/Time"](sec=7, nanosec=0), resolution=0.1, width=2, height=2,
        origin=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))),
    data=np.array([0, 100, -1, 0], dtype="int8"))
peer_map_pub.put(bytes(ts.serialize_cdr(grid, MAP)),
                 attachment=attachment(1, gid(map_tok)))
Vector3 = ts.types["geometry_msgs/msg/Vector3"]

deadline = time.time() + 15.0
seq = 0
while time.time() < deadline and (len(scans) < 5 or not got_map or seq < 30):
    seq += 1
    msg = Twist(linear=Vector3(x=0.25, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=-0.5))
    pub.put(bytes(ts.serialize_cdr(msg, TYPES["cmd_vel"])),
            attachment=attachment(seq, my_gid))
    time.sleep(0.1)


def attachment_ok(att, gid):
    if len(att) != 33:
        return None
    n, t, ln, g = struct.unpack("<qqB16s", att)
    return {"seq": n, "time_ok": abs(t - time.time_ns()) < 60e9, "len": ln, "gid_ok": g == gid}


scan_out = []
for payload, att in scans[:5]:
    m = ts.deserialize_cdr(payload, TYPES["scan"])
    scan_out.append({"frame_id": m.header.frame_id, "ranges": len(m.ranges),
                     "angle_increment": float(m.angle_increment),
                     "attachment": attachment_ok(att, gid_of.get("/robot_a/scan"))})
out["scans"] = scan_out
map_out = []
for payload, att in got_map:
    m = ts.deserialize_cdr(payload, TYPES["map"])
    map_out.append({"frame_id": m.header.frame_id, "width": int(m.info.width), "height": int(m.info.height),
                    "resolution": float(m.info.resolution), "cells": len(m.data),
                    "attachment": attachment_ok(att, gid_of.get("/map"))})
out["map"] = map_out
out["cmd_vel_sent"] = seq
print(json.dumps(out))
sys.stdout.flush()
s.close()
