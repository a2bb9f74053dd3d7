"""A ROS 2 operator of `amr sim --ros2-live zenoh --ros2-cmd-vel`, as an independent rmw_zenoh peer
(eclipse-zenoh, rosbags): it waits for V's estimate, gives V's pose on /initialpose (RViz's "2D
Pose Estimate", with RViz's covariance), then drives V with /cmd_vel at 10 Hz for DRIVE_S seconds
and falls silent. It prints V's estimates (time, x, y, theta) and when each phase began.

usage: ros2_teleop_peer.py PORT DOMAIN V_MPS W_RADPS DRIVE_S
"""
import json
from pathlib import Path
import math
import sys
import time

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[4] / "ros2" / "tests" / "peers"))
from rmw_zenoh_wire import TYPESTORE as ts, attachment, gid, open_peer, publisher_token  # noqa: E402
from rmw_zenoh_wire import key as wire_key  # noqa: E402

port, domain = sys.argv[1], int(sys.argv[2])
v_cmd, w_cmd, drive_s = float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])


def key(topic, t):
    return wire_key(domain, topic, t)


s = open_peer(port, timestamping=False)
zid = str(s.info.zid())
start = time.time()
estimates = []
PWCS = "geometry_msgs/msg/PoseWithCovarianceStamped"


def on_v(smp):
    m = ts.deserialize_cdr(bytes(smp.payload.to_bytes()), PWCS)
    p, q = m.pose.pose.position, m.pose.pose.orientation
    theta = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
    estimates.append([time.time() - start, p.x, p.y, theta])


sub = s.declare_subscriber(key("/amcl/V", PWCS), on_v)


def publisher(topic, ty, entity):
    tok = publisher_token(domain, zid, "operator", entity, topic, ty)
    token = s.liveliness().declare_token(tok)
    return s.declare_publisher(key(topic, ty)), gid(tok), token


node = s.liveliness().declare_token(f"@ros2_lv/{domain}/{zid}/0/0/NN/%/%/operator")
pose_pub, pose_gid, _t1 = publisher("/initialpose", PWCS, 1)
TWIST = "geometry_msgs/msg/Twist"
twist_pub, twist_gid, _t2 = publisher("/cmd_vel", TWIST, 2)
seqs = {"pose": 0, "twist": 0}


def put(pub, entity_gid, name, payload):
    seqs[name] += 1
    pub.put(payload, attachment=attachment(seqs[name], entity_gid))


out = {"phases": {}}
deadline = time.time() + 15.0
while not estimates and time.time() < deadline:
    time.sleep(0.1)
if not estimates:
    print(json.dumps({"error": "no estimate of V"}))
    sys.exit(0)

# "2D Pose Estimate" where V is.
_, x, y, th = estimates[-1]
T = ts.types
msg = T[PWCS](
    header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="map"),
    pose=T["geometry_msgs/msg/PoseWithCovariance"](
        pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))),
        covariance=np.array([0.25 if i in (0, 7) else 0.0685 if i == 35 else 0.0 for i in range(36)])))
put(pose_pub, pose_gid, "pose", bytes(ts.serialize_cdr(msg, PWCS)))
out["phases"]["initialpose"] = time.time() - start
time.sleep(3.0)

out["phases"]["drive"] = time.time() - start
V3 = T["geometry_msgs/msg/Vector3"]
tw = bytes(ts.serialize_cdr(T[TWIST](linear=V3(x=v_cmd, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=w_cmd)), TWIST))
end = time.time() + drive_s
while time.time() < end:
    put(twist_pub, twist_gid, "twist", tw)
    time.sleep(0.1)
out["phases"]["silent"] = time.time() - start
time.sleep(8.0)
out["phases"]["end"] = time.time() - start
out["estimates"] = estimates
print(json.dumps(out))
sys.stdout.flush()
s.close()
