//! A ROS 2 node on rmw_zenoh: a Zenoh session configured as rmw_zenoh configures its own, the node's
//! liveliness token, and publishers and subscriptions that follow [`crate::rmw_zenoh`]'s
//! conventions. ROS 2 nodes (`ros2 topic echo`, RViz, nav2) on rmw_zenoh see it as one of theirs.
//!
//! The session is the ROS 2 graph's, not the fleet's: by default a peer that connects to the
//! `rmw_zenohd` router on this host (`tcp/localhost:7447`) and listens on a free local port, as
//! rmw_zenoh's default session configuration does (peers exchange data directly; the router only
//! introduces them, by gossip). Multicast scouting stays off.

use std::sync::atomic::{AtomicI64, AtomicU32, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

use serde_json::json;
use zenoh::Wait as _;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::qos::{CongestionControl, Reliability as ZReliability};
use zenoh::sample::Sample;
use zenoh_ext::{
    AdvancedPublisher, AdvancedPublisherBuilderExt as _, AdvancedSubscriber,
    AdvancedSubscriberBuilderExt as _, CacheConfig, HistoryConfig, MissDetectionConfig, RecoveryConfig,
};

use crate::rmw_zenoh::{
    self, Attachment, Distro, Durability, EntityKind, NodeInfo, Qos, Reliability, data_key, dds_type_name,
    endpoint_token, node_token,
};

/// How the session joins the ROS 2 graph.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Mode {
    /// rmw_zenoh's default: a peer that connects to the router and listens for other peers.
    #[default]
    Peer,
    /// Through the router only (for a process that cannot accept connections).
    Client,
    /// Be the router itself (no `rmw_zenohd` running; ROS nodes connect here).
    Router,
}

/// Where and who the node is.
#[derive(Debug, Clone)]
pub struct NodeOptions {
    /// `ROS_DOMAIN_ID`.
    pub domain: u32,
    /// The namespace (`/` for none) and the node's name.
    pub namespace: String,
    pub name: String,
    pub distro: Distro,
    pub mode: Mode,
    /// Zenoh endpoints to connect to (`tcp/host:port`); rmw_zenoh's router by default.
    pub connect: Vec<String>,
    /// Zenoh endpoints to listen on.
    pub listen: Vec<String>,
}

impl NodeOptions {
    /// A node `name` in the root namespace of domain 0, joining a router on this host as rmw_zenoh
    /// does.
    #[must_use]
    pub fn new(name: &str) -> Self {
        NodeOptions {
            domain: 0,
            namespace: "/".into(),
            name: name.into(),
            distro: Distro::default(),
            mode: Mode::Peer,
            connect: vec!["tcp/localhost:7447".into()],
            listen: vec!["tcp/localhost:0".into()],
        }
    }

    fn config(&self) -> Result<zenoh::Config, NodeError> {
        let mut c = zenoh::Config::default();
        let mode = match self.mode {
            Mode::Peer => "peer",
            Mode::Client => "client",
            Mode::Router => "router",
        };
        for (key, value) in [
            ("mode", json!(mode)),
            ("connect/endpoints", json!(self.connect)),
            ("listen/endpoints", json!(self.listen)),
            ("scouting/multicast/enabled", json!(false)),
            ("scouting/gossip/enabled", json!(true)),
            // Advanced publishers (transient local) order their cache by timestamps.
            ("timestamping/enabled", json!(true)),
        ] {
            c.insert_json5(key, &value.to_string())
                .map_err(|e| NodeError::Config { key: key.into(), reason: e.to_string() })?;
        }
        Ok(c)
    }
}

/// Why the node or one of its endpoints could not be made.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("zenoh setting {key}: {reason}")]
    Config { key: String, reason: String },
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("{0} is not a ROS 2 type this node knows (pkg/msg/Type with a known type hash)")]
    UnknownType(String),
    #[error("{0} is not a valid ROS 2 topic name")]
    Topic(String),
}

fn zerr(e: impl std::fmt::Display) -> NodeError {
    NodeError::Zenoh(e.to_string())
}

/// A ROS 2 node on rmw_zenoh.
pub struct Node {
    session: zenoh::Session,
    info: NodeInfo,
    distro: Distro,
    next_entity: AtomicU32,
    _token: LivelinessToken,
}

impl std::fmt::Debug for Node {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Node").field("info", &self.info).finish_non_exhaustive()
    }
}

/// A fully qualified topic name: `/` first, no `/` last, in `namespace` if relative.
pub(crate) fn qualified(namespace: &str, topic: &str) -> Result<String, NodeError> {
    let full = if topic.starts_with('/') {
        topic.to_owned()
    } else {
        format!("{}/{topic}", namespace.trim_end_matches('/'))
    };
    let ok = full.len() > 1
        && !full.ends_with('/')
        && !full.contains("//")
        && full.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '/')
        && full.split('/').skip(1).all(|t| !t.starts_with(|c: char| c.is_ascii_digit()));
    if ok { Ok(full) } else { Err(NodeError::Topic(topic.to_owned())) }
}

impl Node {
    /// Open the session and announce the node.
    pub async fn open(options: &NodeOptions) -> Result<Node, NodeError> {
        let session = zenoh::open(options.config()?).await.map_err(zerr)?;
        let info = NodeInfo {
            domain: options.domain,
            zid: session.zid().to_string(),
            node_id: 0,
            enclave: "/".into(),
            namespace: options.namespace.clone(),
            name: options.name.clone(),
        };
        let token = session.liveliness().declare_token(node_token(&info)).await.map_err(zerr)?;
        Ok(Node { session, info, distro: options.distro, next_entity: AtomicU32::new(1), _token: token })
    }

    #[must_use]
    pub fn info(&self) -> &NodeInfo {
        &self.info
    }

    /// The key expression and the token of a new endpoint.
    fn endpoint(
        &self,
        kind: EntityKind,
        topic: &str,
        ros_type: &str,
        qos: &Qos,
    ) -> Result<(String, String), NodeError> {
        let topic = qualified(&self.info.namespace, topic)?;
        let dds = dds_type_name(ros_type).ok_or_else(|| NodeError::UnknownType(ros_type.into()))?;
        let rihs = crate::msg::type_hash(ros_type).ok_or_else(|| NodeError::UnknownType(ros_type.into()))?;
        let hash = self.distro.hash_field(rihs);
        let id = self.next_entity.fetch_add(1, Ordering::Relaxed);
        let token = endpoint_token(&self.info, id, kind, &topic, &dds, hash, qos);
        Ok((data_key(self.info.domain, &topic, &dds, hash), token))
    }

    /// A publisher of `ros_type` (`pkg/msg/Type`) on `topic` (relative names are in the node's
    /// namespace). A transient-local one keeps its last `depth` samples for subscribers that
    /// come later, as rmw_zenoh's do.
    pub async fn publisher(&self, topic: &str, ros_type: &str, qos: Qos) -> Result<Publisher, NodeError> {
        let (key, token) = self.endpoint(EntityKind::Publisher, topic, ros_type, &qos)?;
        let gid = rmw_zenoh::gid(&token);
        let mut b = self.session.declare_publisher(key.clone()).advanced();
        b = match qos.reliability {
            Reliability::Reliable => b.reliability(ZReliability::Reliable),
            Reliability::BestEffort => b.reliability(ZReliability::BestEffort),
        };
        b = b.congestion_control(CongestionControl::Drop);
        if qos.durability == Durability::TransientLocal {
            let depth = usize::try_from(qos.depth).unwrap_or(usize::MAX);
            b = b.cache(CacheConfig::default().max_samples(depth)).publisher_detection();
            if qos.reliability == Reliability::Reliable {
                b = b.sample_miss_detection(
                    MissDetectionConfig::default().sporadic_heartbeat(std::time::Duration::from_millis(500)),
                );
            }
        }
        let inner = b.await.map_err(zerr)?;
        let token = self.session.liveliness().declare_token(token).await.map_err(zerr)?;
        Ok(Publisher { inner, gid, key, sequence: AtomicI64::new(0), _token: token })
    }

    /// A subscription to `ros_type` on `topic`: the samples as they come, with their attachment. A
    /// transient-local one also gets the last `depth` samples of publishers that published before
    /// it existed (their caches, as rmw_zenoh's subscriptions query them).
    pub async fn subscription(
        &self,
        topic: &str,
        ros_type: &str,
        qos: Qos,
    ) -> Result<Subscription, NodeError> {
        let (key, token) = self.endpoint(EntityKind::Subscription, topic, ros_type, &qos)?;
        let inner = if qos.durability == Durability::TransientLocal {
            let depth = usize::try_from(qos.depth).unwrap_or(usize::MAX);
            let mut b = self
                .session
                .declare_subscriber(key.clone())
                .advanced()
                .history(HistoryConfig::default().detect_late_publishers().max_samples(depth))
                .subscriber_detection();
            if qos.reliability == Reliability::Reliable {
                b = b.recovery(RecoveryConfig::default().heartbeat());
            }
            Inner::Advanced(Box::new(b.await.map_err(zerr)?))
        } else {
            Inner::Plain(self.session.declare_subscriber(key.clone()).await.map_err(zerr)?)
        };
        let token = self.session.liveliness().declare_token(token).await.map_err(zerr)?;
        Ok(Subscription { inner, key, _token: token })
    }

    /// Withdraw the node's tokens and close the session.
    pub async fn close(self) -> Result<(), NodeError> {
        self.session.close().await.map_err(zerr)
    }
}

/// One publisher: its key expression, GID and sequence numbers.
pub struct Publisher {
    inner: AdvancedPublisher<'static>,
    gid: [u8; 16],
    key: String,
    sequence: AtomicI64,
    _token: LivelinessToken,
}

impl std::fmt::Debug for Publisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Publisher").field("key", &self.key).finish_non_exhaustive()
    }
}

impl Publisher {
    /// Publish one CDR message (with its encapsulation header) and its attachment. A sample that
    /// cannot go out at once (congestion) is dropped, never waited for.
    pub fn put(&self, cdr: Vec<u8>) -> Result<(), NodeError> {
        let sequence = self.sequence.fetch_add(1, Ordering::Relaxed) + 1;
        let now = SystemTime::now().duration_since(UNIX_EPOCH).unwrap_or_default();
        let source_time_ns = i64::try_from(now.as_nanos()).unwrap_or(i64::MAX);
        let attachment = Attachment { sequence, source_time_ns, gid: self.gid }.to_bytes();
        self.inner.put(cdr).attachment(attachment.to_vec()).wait().map_err(zerr)
    }

    #[must_use]
    pub fn key(&self) -> &str {
        &self.key
    }

    #[must_use]
    pub fn gid(&self) -> [u8; 16] {
        self.gid
    }
}

/// A received sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Received {
    /// The CDR message.
    pub payload: Vec<u8>,
    /// `None` if the sample had no valid rmw_zenoh attachment.
    pub attachment: Option<Attachment>,
}

type Fifo = zenoh::handlers::FifoChannelHandler<Sample>;

/// A plain subscriber, or one that also asks late publishers for their history.
enum Inner {
    Plain(Subscriber<Fifo>),
    Advanced(Box<AdvancedSubscriber<Fifo>>),
}

/// One subscription.
pub struct Subscription {
    inner: Inner,
    key: String,
    _token: LivelinessToken,
}

impl std::fmt::Debug for Subscription {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Subscription").field("key", &self.key).finish_non_exhaustive()
    }
}

impl Subscription {
    /// The next sample; `None` once the session is closed.
    pub async fn recv(&self) -> Option<Received> {
        let s = match &self.inner {
            Inner::Plain(p) => p.recv_async().await.ok()?,
            Inner::Advanced(a) => a.recv_async().await.ok()?,
        };
        Some(Received {
            payload: s.payload().to_bytes().into_owned(),
            attachment: s.attachment().and_then(|a| Attachment::parse(&a.to_bytes())),
        })
    }

    #[must_use]
    pub fn key(&self) -> &str {
        &self.key
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]
    use super::*;

    #[test]
    fn topic_names_are_qualified_and_checked() {
        assert_eq!(qualified("/", "scan").unwrap(), "/scan");
        assert_eq!(qualified("/fleet", "scan").unwrap(), "/fleet/scan");
        assert_eq!(qualified("/fleet", "/robot_a/scan").unwrap(), "/robot_a/scan");
        for bad in ["/", "scan/", "/a//b", "/robot-a/scan", "/2d/scan"] {
            assert!(qualified("/", bad).is_err(), "{bad}");
        }
    }
}
