"""`amr amcl` live on a real log against `amr localize` offline on the same log: the figures of
docs/results.md's "amr amcl on ROS 2" table. Plays a prepared CARMEN log (`amr tools
carmen-prepare`: NAME-raw.log, NAME_map.yaml, NAME-gt.csv) through ros2_amcl_peer.py over rmw_zenoh
(our node is the graph's router on a local port), with the reference's first pose on /initialpose,
and localises the same log with `amr localize --nav2-params` from the same pose, the same
parameters (config/amcl.toml written in nav2's names) and seed. Scores both against the reference
at the stamps where the node published. Prints one Markdown table row per log.

usage: amcl_live_carmen.py AMR_BINARY LOG_DIR SPEED NAME...
"""
import csv
import json
import math
from pathlib import Path
import socket
import subprocess
import sys
import tempfile
import tomllib

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[3]
amr, logs, speed, names = sys.argv[1], Path(sys.argv[2]), sys.argv[3], sys.argv[4:]


def params(path):
    ours = tomllib.loads((REPO / "config" / "amcl.toml").read_text())
    lines = ["amcl:", "  ros__parameters:"]
    for k, v in ours.items():
        if not isinstance(v, dict) and not k.startswith("odom_slip"):
            lines.append(f"    {k}: {json.dumps(v)}")
    lines += ["    base_frame_id: base_link", "    scan_topic: scan", "    set_initial_pose: false"]
    path.write_text("\n".join(lines) + "\n")


def reference(name):
    with open(logs / f"{name}-gt.csv") as f:
        return {round(float(r["timestamp"]), 6): (float(r["x"]), float(r["y"])) for r in csv.DictReader(f)}


def score(poses, ref):
    """(RMSE m, share of poses more than 0.5 m off, poses matched) at the reference's stamps."""
    errs = [math.hypot(x - ref[t][0], y - ref[t][1]) for t, x, y in poses if t in ref]
    if not errs:
        return float("nan"), float("nan"), 0
    return math.sqrt(sum(e * e for e in errs) / len(errs)), sum(e > 0.5 for e in errs) / len(errs), len(errs)


print("| log | scans | poses live | RMSE live | > 0.5 m live | RMSE offline (same stamps) | > 0.5 m offline | "
      "largest live − offline |")
print("|---|---|---|---|---|---|---|---|")
for name in names:
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        p = d / "nav2_params.yaml"
        params(p)
        ref = reference(name)
        with open(logs / f"{name}-gt.csv") as f:
            r0 = next(csv.DictReader(f))
        initial = f"{r0['x']},{r0['y']},{r0['theta']}"
        port = socket.socket()
        port.bind(("127.0.0.1", 0))
        port_no = port.getsockname()[1]
        port.close()
        node = subprocess.Popen([amr, "amcl", "--ros2", "zenoh", "--params", str(p), "--ros2-domain", "12",
                                 "--ros2-router", f"tcp/127.0.0.1:{port_no}", "--seed", "0"],
                                stderr=subprocess.PIPE, text=True)
        peer = subprocess.run([sys.executable, str(HERE / "ros2_amcl_peer.py"), "zenoh", str(port_no), "12",
                               str(logs / f"{name}-raw.log"), str(logs / f"{name}_map.yaml"), initial, speed],
                              capture_output=True, text=True, check=True)
        node.send_signal(2)
        _, node_err = node.communicate(timeout=30)
        live = [(round(q["stamp"], 6), q["x"], q["y"]) for q in json.loads(peer.stdout)["poses"]]
        off_csv = d / "offline.csv"
        subprocess.run([amr, "localize", "--map", str(logs / f"{name}_map.yaml"), "--log",
                        str(logs / f"{name}-raw.log"), "--nav2-params", str(p), "--initial", initial,
                        "--seed", "0", "--out", str(off_csv)], check=True, capture_output=True)
        with open(off_csv) as f:
            offline = {round(float(r["timestamp"]), 6): (float(r["x"]), float(r["y"])) for r in csv.DictReader(f)}
        at = {t for t, _, _ in live}
        off_same = [(t, x, y) for t, (x, y) in offline.items() if t in at]
        diff = max((math.hypot(x - offline[t][0], y - offline[t][1]) for t, x, y in live if t in offline),
                   default=float("nan"))
        rl, fl, n = score(live, ref)
        ro, fo, _ = score(off_same, ref)
        scans = sum(1 for line in open(logs / f"{name}-raw.log") if line.startswith("FLASER"))
        print(f"| {name} | {scans} | {n} | {rl * 100:.1f} cm | {fl * 100:.1f} % | {ro * 100:.1f} cm | "
              f"{fo * 100:.1f} % | {diff * 100:.2f} cm |")
        sys.stdout.flush()
