"""rmw_zenoh's wire conventions as the test peers write them, from ros2/rmw_zenoh's design document
alone (not from our Rust code): key expressions, liveliness tokens, GIDs, attachments, and a Zenoh
session configured as rmw_zenoh configures its own. Shared by the peers of ros2/tests and
host/tests/cli_runs.
"""
import json
import struct
import time

import xxhash
import zenoh
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def dds(t):
    """`pkg/msg/Type` -> `pkg::msg::dds_::Type_`."""
    pkg, kind, name = t.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def key(domain, topic, t):
    """The key expression of `topic` of type `t` in `domain` (Jazzy: the type's RIHS01 hash)."""
    return f"{domain}/{topic.strip('/')}/{dds(t)}/{TYPESTORE.hash_rihs01(t)}"


def open_peer(port, timestamping=True):
    """A peer session that joins the router on tcp/127.0.0.1:PORT and listens on loopback."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    if timestamping:
        conf.insert_json5("timestamping/enabled", "true")
    return zenoh.open(conf)


def gid(token):
    """An entity's GID: XXH3-128 of its liveliness token, low 64 bits first, little endian."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def attachment(seq, entity_gid):
    """The 33 bytes on every sample: sequence number, source time (ns), length 16, GID."""
    return struct.pack("<qqB16s", seq, time.time_ns(), 16, entity_gid)


def publisher_token(domain, zid, node, entity, topic, t, qos="::,10:,:,:,,"):
    """The liveliness token of publisher `entity` of node `node` (root namespace and enclave)."""
    return (f"@ros2_lv/{domain}/{zid}/0/{entity}/MP/%/%/{node}/{topic.replace('/', '%')}/{dds(t)}/"
            f"{TYPESTORE.hash_rihs01(t)}/{qos}")
