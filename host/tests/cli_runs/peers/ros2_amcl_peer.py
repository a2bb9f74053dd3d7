"""A ROS 2 robot and its map server for `amr amcl`, as independent peers play them: the map from
map.yaml and its PGM image converted as nav2's map_server converts a trinary map, published
latched on /map; the laser's mounting on /tf_static; the odometry (odom -> base_link) on /tf and
the scans on /scan, in the order and at the pace of their stamps (SPEED times faster than they
were taken); optionally an initial pose on /initialpose first (RViz's "2D Pose Estimate", with its
covariance). It records what the node publishes (/amcl_pose, /particle_cloud, /tf) and prints one
JSON object. Messages are built and decoded by rosbags; on DDS, Eclipse Cyclone DDS carries them
(its types in cyclone_types.py: rosbags' CDR bytes and Cyclone's are the same bytes), on Zenoh,
eclipse-zenoh as rmw_zenoh's design document says (rmw_zenoh_wire.py).

usage: ros2_amcl_peer.py zenoh PORT DOMAIN RUN MAP_YAML INITIAL SPEED
       ros2_amcl_peer.py dds - DOMAIN RUN MAP_YAML INITIAL SPEED
RUN is the test's simulated run (JSON) or a CARMEN log (`.log`); INITIAL is x,y,theta or `none`.
"""
import json
import math
from pathlib import Path
import sys
import time

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parents[3] / "ros2" / "tests" / "peers"))
from rmw_zenoh_wire import TYPESTORE as ts  # noqa: E402
from rosbags.typesys import get_types_from_msg  # noqa: E402



def carmen(path):
    """A CARMEN log's FLASER scans (180 degrees from -90, readings of 80 m and more: no return) and
    its odometry (ODOM lines, and each FLASER's own odometry at the scan's stamp), laser at the
    robot's origin, as the run this peer plays."""
    scans, odometry = [], []
    for line in open(path):
        f = line.split()
        if not f:
            continue
        if f[0] == "ODOM" and len(f) >= 8:
            odometry.append({"stamp": float(f[7]), "x": float(f[1]), "y": float(f[2]), "theta": float(f[3])})
        elif f[0] == "FLASER":
            n = int(f[1])
            ranges = [float(r) for r in f[2:2 + n]]
            ox, oy, oth, ts_ = (float(v) for v in f[5 + n:9 + n])
            scans.append({"stamp": ts_, "ranges": [r if r < 80.0 else "inf" for r in ranges]})
            odometry.append({"stamp": ts_, "x": ox, "y": oy, "theta": oth})
    odometry.sort(key=lambda o: o["stamp"])
    n = len(scans[0]["ranges"])
    inc = math.pi / (n - 1) if n in (181, 361, 721) else math.pi / n
    return {"angle_min": -math.pi / 2, "angle_increment": inc, "angle_max": -math.pi / 2 + (n - 1) * inc,
            "range_min": 0.0, "range_max": 79.99, "scans": scans, "odometry": odometry,
            "mount": {"x": 0.0, "y": 0.0, "theta": 0.0}}


transport, port, domain = sys.argv[1], sys.argv[2], int(sys.argv[3])
sim = carmen(sys.argv[4]) if sys.argv[4].endswith(".log") else json.load(open(sys.argv[4]))
map_yaml = Path(sys.argv[5])
initial = None if sys.argv[6] == "none" else [float(v) for v in sys.argv[6].split(",")]
speed = float(sys.argv[7])

# nav2_msgs/ParticleCloud is not in rosbags' store: from its .msg files (comments left out).
_nav2 = get_types_from_msg("geometry_msgs/Pose pose\nfloat64 weight\n", "nav2_msgs/msg/Particle")
_nav2.update(get_types_from_msg("std_msgs/Header header\nParticle[] particles\n", "nav2_msgs/msg/ParticleCloud"))
ts.register(_nav2)
T = ts.types
SCAN, TF, MAP = "sensor_msgs/msg/LaserScan", "tf2_msgs/msg/TFMessage", "nav_msgs/msg/OccupancyGrid"
PWCS, CLOUD = "geometry_msgs/msg/PoseWithCovarianceStamped", "nav2_msgs/msg/ParticleCloud"


def stamp(t):
    # From whole nanoseconds, so that a time a hair below a whole second carries into the seconds.
    ns = int(round(t * 1e9))
    return T["builtin_interfaces/msg/Time"](sec=ns // 1000000000, nanosec=ns % 1000000000)


def secs(s):
    return s.sec + s.nanosec * 1e-9


def quat(theta):
    return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2))


def yaw(q):
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def header(t, frame):
    return T["std_msgs/msg/Header"](stamp=stamp(t), frame_id=frame)


def pose(x, y, theta):
    return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0), orientation=quat(theta))


def tf(t, parent, child, x, y, theta):
    V3 = T["geometry_msgs/msg/Vector3"]
    return T[TF](transforms=[T["geometry_msgs/msg/TransformStamped"](
        header=header(t, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](translation=V3(x=x, y=y, z=0.0), rotation=quat(theta)))])


def cdr(msg, ty):
    return bytes(ts.serialize_cdr(msg, ty))


def read_map(path):
    """map_server's reading of a trinary map: p = (255 - v) / 255 (negate 0), occupied above
    occupied_thresh, free below free_thresh, else unknown; the image's bottom row first."""
    meta = {}
    for line in path.read_text().splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            meta[k.strip()] = v.strip()
    raw = (path.parent / meta["image"].strip("\"'")).read_bytes()
    fields, i = [], 0
    while len(fields) < 4:
        while raw[i:i + 1].isspace():
            i += 1
        if raw[i:i + 1] == b"#":
            i = raw.index(b"\n", i)
            continue
        j = i
        while not raw[j:j + 1].isspace():
            j += 1
        fields.append(raw[i:j])
        i = j
    assert fields[0] == b"P5", fields
    w, h = int(fields[1]), int(fields[2])
    px = np.frombuffer(raw[i + 1:i + 1 + w * h], dtype=np.uint8).reshape(h, w)
    p = (255.0 - px) / 255.0 if int(meta.get("negate", "0")) == 0 else px / 255.0
    cells = np.full((h, w), -1, dtype=np.int8)
    cells[p > float(meta["occupied_thresh"])] = 100
    cells[p < float(meta["free_thresh"])] = 0
    origin = [float(v) for v in meta["origin"].strip("[]").split(",")]
    res = float(meta["resolution"])
    return T[MAP](
        header=header(0.0, "map"),
        info=T["nav_msgs/msg/MapMetaData"](map_load_time=stamp(0.0), resolution=res, width=w, height=h,
                                           origin=pose(origin[0], origin[1], origin[2])),
        data=cells[::-1].reshape(-1))


class ZenohWire:
    """rmw_zenoh as its design document gives it: tokens, key expressions, attachments."""

    def __init__(self):
        import zenoh.ext as ze
        from rmw_zenoh_wire import attachment, gid, key, open_peer, publisher_token
        self.ze, self.attachment, self.gid, self.key, self.token = ze, attachment, gid, key, publisher_token
        self.s = open_peer(port)
        self.zid = str(self.s.info.zid())
        self.tokens = [self.s.liveliness().declare_token(f"@ros2_lv/{domain}/{self.zid}/0/0/NN/%/%/robot")]
        self.entity = 0
        self.got = {}

    def publisher(self, topic, ty, latched=False):
        self.entity += 1
        qos = ":1:,1:,:,:,," if latched else "::,10:,:,:,,"
        tok = self.token(domain, self.zid, "robot", self.entity, topic, ty, qos)
        self.tokens.append(self.s.liveliness().declare_token(tok))
        k = self.key(domain, topic, ty)
        if latched:
            pub = self.ze.declare_advanced_publisher(self.s, k, cache=self.ze.CacheConfig(max_samples=1),
                                                     publisher_detection=True)
        else:
            pub = self.s.declare_publisher(k)
        g, seq = self.gid(tok), [0]

        def put(data):
            seq[0] += 1
            pub.put(data, attachment=self.attachment(seq[0], g))
        return put

    def subscribe(self, topic, ty, latched=False):
        got = self.got.setdefault(topic, [])
        keep = lambda smp: got.append(bytes(smp.payload.to_bytes()))  # noqa: E731
        k = self.key(domain, topic, ty)
        if latched:
            sub = self.ze.declare_advanced_subscriber(
                self.s, k, history=self.ze.HistoryConfig(detect_late_publishers=True), handler=keep)
        else:
            sub = self.s.declare_subscriber(k, keep)
        self.tokens.append(sub)

    def node_ready(self):
        """The node's subscriptions to /scan and /tf are in the graph."""
        found = set()
        for r in self.s.liveliness().get(f"@ros2_lv/{domain}/**", timeout=2.0):
            if r.ok is not None:
                f = str(r.ok.key_expr).split("/")
                if len(f) == 13 and f[5] == "MS":
                    found.add(f[9].replace("%", "/"))
        return {"/scan", "/tf", "/map", "/initialpose"} <= found

    def pump(self):
        pass

    def close(self):
        self.s.close()


class DdsWire:
    """ROS 2 over DDS as its middlewares name topics and types (`rt/...`), with Cyclone DDS."""

    def __init__(self):
        from cyclonedds.core import Policy, Qos
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.pub import DataWriter
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic
        import cyclone_types
        self.types = {SCAN: cyclone_types.LaserScan, TF: cyclone_types.TFMessage, MAP: cyclone_types.OccupancyGrid,
                      PWCS: cyclone_types.PoseWithCovarianceStamped, CLOUD: cyclone_types.ParticleCloud}
        self.DataWriter, self.DataReader, self.Topic = DataWriter, DataReader, Topic
        self.dp = DomainParticipant(domain)
        rel = Policy.Reliability.Reliable(max_blocking_time=0)
        self.qos = {
            "sensor": Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5)),
            "reliable": Qos(rel, Policy.Durability.Volatile, Policy.History.KeepLast(100)),
            "latched": Qos(rel, Policy.Durability.TransientLocal, Policy.History.KeepLast(1)),
        }
        self.topics, self.readers, self.writers, self.got = {}, {}, [], {}

    def topic(self, topic, ty):
        if topic not in self.topics:
            self.topics[topic] = self.Topic(self.dp, "rt" + topic, self.types[ty])
        return self.topics[topic]

    def publisher(self, topic, ty, latched=False):
        qos = self.qos["latched" if latched else "sensor" if ty == SCAN else "reliable"]
        w = self.DataWriter(self.dp, self.topic(topic, ty), qos=qos)
        self.writers.append(w)
        cls = self.types[ty]
        return lambda data: w.write(cls.deserialize(data))

    def subscribe(self, topic, ty, latched=False):
        qos = self.qos["latched" if latched else "sensor" if ty == CLOUD else "reliable"]
        self.readers[topic] = self.DataReader(self.dp, self.topic(topic, ty), qos=qos)
        self.got.setdefault(topic, [])

    def node_ready(self):
        return all(len(w.get_matched_subscriptions()) > 0 for w in self.writers)

    def pump(self):
        for topic, r in self.readers.items():
            for m in r.take(100):
                self.got[topic].append(bytes(m.serialize()))

    def close(self):
        pass


wire = ZenohWire() if transport == "zenoh" else DdsWire()
wire.subscribe("/amcl_pose", PWCS, latched=True)
wire.subscribe("/particle_cloud", CLOUD)
wire.subscribe("/tf", TF)
put_map = wire.publisher("/map", MAP, latched=True)
put_static = wire.publisher("/tf_static", TF, latched=True)
put_tf = wire.publisher("/tf", TF)
put_scan = wire.publisher("/scan", SCAN)
put_pose = wire.publisher("/initialpose", PWCS)

out = {"waited_s": None}
t0 = time.time()
while time.time() - t0 < 30.0 and not wire.node_ready():
    time.sleep(0.2)
out["waited_s"] = time.time() - t0
put_map(cdr(read_map(map_yaml), MAP))
m = sim["mount"]
put_static(cdr(tf(0.0, "base_link", "laser", m["x"], m["y"], m["theta"]), TF))
time.sleep(1.0)
if initial is not None:
    cov = np.zeros(36)
    cov[0], cov[7], cov[35] = 0.25, 0.25, 0.0685
    put_pose(cdr(T[PWCS](header=header(0.0, "map"), pose=T["geometry_msgs/msg/PoseWithCovariance"](
        pose=pose(*initial), covariance=cov)), PWCS))
    time.sleep(0.5)

# The robot's stream in the order of its stamps: odometry at its stamp, each scan 10 ms after it.
events = [(o["stamp"], "odom", o) for o in sim["odometry"]] + [(s["stamp"] + 0.01, "scan", s) for s in sim["scans"]]
events.sort(key=lambda e: e[0])
begin, first = time.time(), events[0][0]
for t, kind, e in events:
    wait = begin + (t - first) / speed - time.time()
    if wait > 0:
        time.sleep(wait)
    if kind == "odom":
        put_tf(cdr(tf(e["stamp"], "odom", "base_link", e["x"], e["y"], e["theta"]), TF))
    else:
        ranges = np.array([float(r) for r in e["ranges"]], dtype=np.float32)  # "nan", "inf" too
        put_scan(cdr(T[SCAN](header=header(e["stamp"], "laser"), angle_min=sim["angle_min"],
                             angle_max=sim["angle_max"], angle_increment=sim["angle_increment"], time_increment=0.0,
                             scan_time=0.2, range_min=sim["range_min"], range_max=sim["range_max"], ranges=ranges,
                             intensities=np.array([], dtype=np.float32)), SCAN))
    wire.pump()
end = time.time() + 2.0
while time.time() < end:
    wire.pump()
    time.sleep(0.05)

out["poses"] = []
for b in wire.got["/amcl_pose"]:
    p = ts.deserialize_cdr(b, PWCS)
    q = p.pose.pose
    c = p.pose.covariance
    out["poses"].append({"stamp": secs(p.header.stamp), "frame": p.header.frame_id, "x": q.position.x,
                         "y": q.position.y, "theta": yaw(q.orientation), "cov": [c[0], c[7], c[35]]})
out["clouds"] = []
for b in wire.got["/particle_cloud"]:
    c = ts.deserialize_cdr(b, CLOUD)
    w = np.array([p.weight for p in c.particles])
    xs = np.array([p.pose.position.x for p in c.particles])
    ys = np.array([p.pose.position.y for p in c.particles])
    out["clouds"].append({"stamp": secs(c.header.stamp), "frame": c.header.frame_id, "n": len(c.particles),
                          "weights": float(w.sum()), "x": float((w * xs).sum() / w.sum()),
                          "y": float((w * ys).sum() / w.sum())})
out["map_odom"] = []
for b in wire.got["/tf"]:
    for x in ts.deserialize_cdr(b, TF).transforms:
        if (x.header.frame_id, x.child_frame_id) == ("map", "odom"):
            tr = x.transform
            out["map_odom"].append({"stamp": secs(x.header.stamp), "x": tr.translation.x, "y": tr.translation.y,
                                    "theta": yaw(tr.rotation)})
print(json.dumps(out))
sys.stdout.flush()
wire.close()
