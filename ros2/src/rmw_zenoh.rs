//! rmw_zenoh's wire conventions: how a ROS 2 node that uses `rmw_zenoh_cpp` (the Zenoh middleware of
//! ROS 2, Jazzy and later; backported to Humble) names its data, announces itself and stamps each
//! sample. A process that follows them is a ROS 2 node to `ros2 topic list`, RViz and nav2 without
//! a ROS installation.
//!
//! Source: ros2/rmw_zenoh's `docs/design.md` (the revision that documents the format for other
//! implementations) and `rmw_zenoh_cpp/src/detail/{liveliness_utils,attachment_helpers,qos}.cpp`.
//!
//! - **Data**: a sample of topic `/ns/name` and type `pkg/msg/Type` is put on the key expression
//!   `<domain>/ns/name/pkg::msg::dds_::Type_/<type hash>` ([`data_key`]); its payload is the CDR
//!   message with its encapsulation header (as a DDS sample or a rosbag2 record).
//! - **Type hash**: REP 2011's `RIHS01_…` from Iron on; Humble's rmw_zenoh has none and writes
//!   `TypeHashNotSupported` ([`Distro`]).
//! - **Graph**: every node and every publisher or subscription holds a Zenoh liveliness token
//!   ([`node_token`], [`endpoint_token`]) under the admin space `@ros2_lv`; ROS 2 builds its graph
//!   from these alone. Names inside a token have `/` replaced by `%`, an empty field is `%`.
//! - **Attachment**: every sample carries 33 bytes ([`Attachment`]): the publisher's sequence
//!   number (from 1), the source time in nanoseconds since the UNIX epoch (both `i64` little
//!   endian), the length 16 (one byte) and the publisher's GID. A subscriber drops a sample
//!   without it.
//! - **GID**: the XXH3-128 hash of the entity's liveliness token ([`gid`]), its low 64 bits then
//!   its high 64 bits, each little endian.
//! - **QoS** in a token ([`Qos::to_keyexpr`]): `rel:dur:hist,depth:deadline:lifespan:liveliness`
//!   with every field equal to rmw_zenoh's default (reliable, volatile, keep-last 42, no deadline,
//!   lifespan or lease, automatic liveliness) left empty.

use std::fmt::Write as _;

/// The admin space of the liveliness tokens.
pub const ADMIN_SPACE: &str = "@ros2_lv";

/// Which ROS 2 release the peers run: it decides the type hash in key expressions and tokens.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Distro {
    /// Humble: no type hashes; the field reads `TypeHashNotSupported`.
    Humble,
    /// Iron, Jazzy, Kilted, Rolling: REP 2011 hashes.
    #[default]
    Jazzy,
}

impl Distro {
    /// The hash field for a type whose REP 2011 hash is `rihs01`.
    #[must_use]
    pub fn hash_field(self, rihs01: &str) -> &str {
        match self {
            Distro::Humble => "TypeHashNotSupported",
            Distro::Jazzy => rihs01,
        }
    }
}

impl std::str::FromStr for Distro {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "humble" => Ok(Distro::Humble),
            "iron" | "jazzy" | "kilted" | "rolling" => Ok(Distro::Jazzy),
            other => {
                Err(format!("unknown ROS 2 distribution {other:?} (humble, iron, jazzy, kilted, rolling)"))
            }
        }
    }
}

/// The DDS name of a ROS 2 type: `pkg/msg/Type` → `pkg::msg::dds_::Type_`. `None` if the name is
/// not of that form.
#[must_use]
pub fn dds_type_name(ros_type: &str) -> Option<String> {
    let mut parts = ros_type.split('/');
    let (Some(pkg), Some(kind), Some(name), None) = (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return None;
    };
    if pkg.is_empty() || name.is_empty() || !matches!(kind, "msg" | "srv" | "action") {
        return None;
    }
    Some(format!("{pkg}::{kind}::dds_::{name}_"))
}

/// The key expression a topic's samples are put on: the domain, the fully qualified topic name
/// without its leading and trailing `/`, the DDS type name and the hash field.
#[must_use]
pub fn data_key(domain: u32, topic: &str, dds_type: &str, hash: &str) -> String {
    format!("{domain}/{}/{dds_type}/{hash}", topic.trim_matches('/'))
}

/// `/` → `%`, and an empty name `%` (a token has no empty chunk).
#[must_use]
pub fn mangle(name: &str) -> String {
    if name.is_empty() { "%".to_owned() } else { name.replace('/', "%") }
}

/// What an endpoint is, as its token says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EntityKind {
    Publisher,
    Subscription,
}

impl EntityKind {
    fn as_str(self) -> &'static str {
        match self {
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
        }
    }
}

/// A node: where it is and what it is called.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeInfo {
    pub domain: u32,
    /// The Zenoh session id, lowercase hex as Zenoh prints it.
    pub zid: String,
    /// The node's id within the session.
    pub node_id: u32,
    /// The SROS enclave, `/` when none.
    pub enclave: String,
    /// The namespace, `/` when none.
    pub namespace: String,
    pub name: String,
}

/// The liveliness token of a node: `@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/
/// <namespace>/<name>`.
#[must_use]
pub fn node_token(n: &NodeInfo) -> String {
    format!(
        "{ADMIN_SPACE}/{}/{}/{}/{}/NN/{}/{}/{}",
        n.domain,
        n.zid,
        n.node_id,
        n.node_id,
        mangle(&n.enclave),
        mangle(&n.namespace),
        mangle(&n.name)
    )
}

/// The liveliness token of a publisher or subscription `entity_id` of node `n`: the node's fields,
/// then the fully qualified topic, the DDS type name, the hash field and the QoS.
#[must_use]
pub fn endpoint_token(
    n: &NodeInfo,
    entity_id: u32,
    kind: EntityKind,
    topic: &str,
    dds_type: &str,
    hash: &str,
    qos: &Qos,
) -> String {
    format!(
        "{ADMIN_SPACE}/{}/{}/{}/{entity_id}/{}/{}/{}/{}/{}/{}/{}/{}",
        n.domain,
        n.zid,
        n.node_id,
        kind.as_str(),
        mangle(&n.enclave),
        mangle(&n.namespace),
        mangle(&n.name),
        mangle(topic),
        mangle(dds_type),
        mangle(hash),
        qos.to_keyexpr()
    )
}

/// An entity's GID: XXH3-128 of its liveliness token, the low 64 bits then the high 64 bits,
/// each little endian (rmw_zenoh copies the two halves of the hash as they lie in memory).
#[must_use]
pub fn gid(token: &str) -> [u8; 16] {
    let h = xxhash_rust::xxh3::xxh3_128(token.as_bytes());
    h.to_le_bytes()
}

/// Reliability, as rmw's enum numbers it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reliability {
    Reliable = 1,
    BestEffort = 2,
}

/// Durability, as rmw's enum numbers it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Durability {
    /// A late subscriber gets the last `depth` samples (`/map`, `/tf_static`).
    TransientLocal = 1,
    Volatile = 2,
}

/// The QoS of an endpoint (history is keep-last; deadline, lifespan and liveliness at their
/// defaults).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    pub reliability: Reliability,
    pub durability: Durability,
    pub depth: u32,
}

/// rmw_zenoh's default depth (`qos.cpp`).
const DEFAULT_DEPTH: u32 = 42;

impl Qos {
    /// rclcpp's `SensorDataQoS`: best effort, volatile, keep-last 5 (what nav2_amcl and RViz
    /// subscribe scans with).
    pub const SENSOR_DATA: Qos =
        Qos { reliability: Reliability::BestEffort, durability: Durability::Volatile, depth: 5 };
    /// A latched topic: reliable, transient local, keep-last 1 (`/map`, `/tf_static`).
    pub const LATCHED: Qos =
        Qos { reliability: Reliability::Reliable, durability: Durability::TransientLocal, depth: 1 };

    /// Reliable, volatile, keep-last `depth`.
    #[must_use]
    pub const fn reliable(depth: u32) -> Qos {
        Qos { reliability: Reliability::Reliable, durability: Durability::Volatile, depth }
    }

    /// The QoS field of a liveliness token (rmw_zenoh's `qos_to_keyexpr`): every policy equal to
    /// rmw_zenoh's default is left empty.
    #[must_use]
    pub fn to_keyexpr(&self) -> String {
        let mut s = String::new();
        if self.reliability != Reliability::Reliable {
            let _ = write!(s, "{}", self.reliability as u8);
        }
        s.push(':');
        if self.durability != Durability::Volatile {
            let _ = write!(s, "{}", self.durability as u8);
        }
        // History keep-last is the default: empty; then the depth.
        s.push_str(":,");
        if self.depth != DEFAULT_DEPTH {
            let _ = write!(s, "{}", self.depth);
        }
        // Deadline, lifespan, liveliness (kind, lease): defaults.
        s.push_str(":,:,:,,");
        s
    }
}

/// The attachment of every sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attachment {
    /// The publisher's sequence number, from 1.
    pub sequence: i64,
    /// When it was published, ns since the UNIX epoch.
    pub source_time_ns: i64,
    pub gid: [u8; 16],
}

/// The attachment's length in bytes.
pub const ATTACHMENT_LEN: usize = 33;

impl Attachment {
    /// As zenoh-ext's serializer writes the tuple `(i64, i64, [u8; 16])`: two little-endian
    /// integers, the array's length as a one-byte LEB128, the bytes.
    #[must_use]
    pub fn to_bytes(&self) -> [u8; ATTACHMENT_LEN] {
        let mut b = [0u8; ATTACHMENT_LEN];
        b[..8].copy_from_slice(&self.sequence.to_le_bytes());
        b[8..16].copy_from_slice(&self.source_time_ns.to_le_bytes());
        b[16] = 16;
        b[17..].copy_from_slice(&self.gid);
        b
    }

    /// Read an attachment; `None` if the bytes are not one.
    #[must_use]
    pub fn parse(b: &[u8]) -> Option<Attachment> {
        if b.len() != ATTACHMENT_LEN || b[16] != 16 {
            return None;
        }
        let i64_at = |k: usize| b.get(k..k + 8).and_then(|s| s.try_into().ok()).map(i64::from_le_bytes);
        Some(Attachment {
            sequence: i64_at(0)?,
            source_time_ns: i64_at(8)?,
            gid: b.get(17..)?.try_into().ok()?,
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]
    use super::*;

    /// The design document's example node (`listener` in domain 2).
    fn listener() -> NodeInfo {
        NodeInfo {
            domain: 2,
            zid: "aac3178e146ba6f1fc6e6a4085e77f21".into(),
            node_id: 0,
            enclave: "/".into(),
            namespace: "/".into(),
            name: "listener".into(),
        }
    }

    const STRING_HASH: &str = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18";

    #[test]
    fn tokens_read_as_the_design_document_writes_them() {
        let n = listener();
        assert_eq!(node_token(&n), "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener");
        let dds = dds_type_name("std_msgs/msg/String").unwrap();
        assert_eq!(dds, "std_msgs::msg::dds_::String_");
        assert_eq!(
            endpoint_token(
                &n,
                10,
                EntityKind::Subscription,
                "/chatter",
                &dds,
                STRING_HASH,
                &Qos::reliable(10)
            ),
            "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/\
             std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/\
             ::,10:,:,:,,"
        );
        assert_eq!(data_key(0, "/chatter", &dds, STRING_HASH), format!("0/chatter/{dds}/{STRING_HASH}"));
        assert_eq!(
            data_key(0, "/robot1/chatter/", &dds, "TypeHashNotSupported"),
            format!("0/robot1/chatter/{dds}/TypeHashNotSupported")
        );
    }

    #[test]
    fn qos_fields_are_empty_where_rmw_zenoh_has_its_default() {
        assert_eq!(Qos::reliable(DEFAULT_DEPTH).to_keyexpr(), "::,:,:,:,,");
        assert_eq!(Qos::SENSOR_DATA.to_keyexpr(), "2::,5:,:,:,,");
        assert_eq!(Qos::LATCHED.to_keyexpr(), ":1:,1:,:,:,,");
        assert_eq!(Qos::reliable(100).to_keyexpr(), "::,100:,:,:,,");
    }

    #[test]
    fn type_names_and_hash_fields() {
        assert_eq!(dds_type_name("sensor_msgs/msg/LaserScan").unwrap(), "sensor_msgs::msg::dds_::LaserScan_");
        assert_eq!(dds_type_name("sensor_msgs/LaserScan"), None);
        assert_eq!(dds_type_name("a/b/c/d"), None);
        assert_eq!(Distro::Humble.hash_field(STRING_HASH), "TypeHashNotSupported");
        assert_eq!(Distro::Jazzy.hash_field(STRING_HASH), STRING_HASH);
        assert_eq!("Humble".parse::<Distro>().unwrap(), Distro::Humble);
        assert!("foxy".parse::<Distro>().is_err());
    }

    #[test]
    fn the_gid_is_the_tokens_xxh3_128_low_half_first() {
        // XXH3-128 of the empty input, from xxHash's own test vectors (xxhsum's sanity check):
        // 0x99aa06d3014798d86001c324468d497f.
        let g = gid("");
        assert_eq!(g[..8], 0x6001_c324_468d_497f_u64.to_le_bytes());
        assert_eq!(g[8..], 0x99aa_06d3_0147_98d8_u64.to_le_bytes());
    }

    #[test]
    fn attachments_round_trip_and_refuse_other_bytes() {
        let a = Attachment { sequence: 7, source_time_ns: 1_700_000_000_123_456_789, gid: [0xab; 16] };
        let b = a.to_bytes();
        assert_eq!(b[..8], [7, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(b[16], 16);
        assert_eq!(Attachment::parse(&b), Some(a));
        assert_eq!(Attachment::parse(&b[..32]), None);
        let mut bad = b;
        bad[16] = 15;
        assert_eq!(Attachment::parse(&bad), None);
    }
}
