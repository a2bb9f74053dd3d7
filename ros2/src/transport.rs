//! One ROS 2 node whichever middleware the peers use: rmw_zenoh's protocol ([`crate::node`]) or
//! DDS/RTPS ([`crate::dds`]). The fleet's live output and inputs are written against this.

use crate::dds::{DdsError, DdsNode, DdsPublisher, DdsSubscription};
use crate::node::{Node, NodeError, NodeOptions, Publisher, Subscription};
use crate::rmw_zenoh::Qos;

/// The middleware.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transport {
    /// rmw_zenoh (Jazzy and later; Humble's rmw_zenoh).
    Zenoh,
    /// DDS/RTPS (Humble's and Foxy's default: Fast DDS, Cyclone DDS).
    Dds,
}

/// Why the node or an endpoint could not be made.
#[derive(Debug, thiserror::Error)]
pub enum Ros2Error {
    #[error(transparent)]
    Zenoh(#[from] NodeError),
    #[error(transparent)]
    Dds(#[from] DdsError),
    #[error("DDS domains are 0 to 232 (got {0})")]
    Domain(u32),
}

/// A ROS 2 node.
#[derive(Debug)]
pub enum Ros2Node {
    Zenoh(Node),
    Dds(DdsNode),
}

/// A publisher of either node.
#[derive(Debug)]
pub enum Ros2Publisher {
    Zenoh(Publisher),
    Dds(DdsPublisher),
}

/// A subscription of either node.
#[derive(Debug)]
pub enum Ros2Subscription {
    Zenoh(Subscription),
    Dds(DdsSubscription),
}

impl Ros2Node {
    /// Open a node over `transport`: for Zenoh as `options` say; for DDS in domain
    /// `options.domain` (the rest of `options` is Zenoh's).
    pub async fn open(transport: Transport, options: &NodeOptions) -> Result<Ros2Node, Ros2Error> {
        Ok(match transport {
            Transport::Zenoh => Ros2Node::Zenoh(Node::open(options).await?),
            Transport::Dds => {
                let domain = u16::try_from(options.domain)
                    .ok()
                    .filter(|d| *d <= 232)
                    .ok_or(Ros2Error::Domain(options.domain))?;
                Ros2Node::Dds(DdsNode::open(domain)?)
            }
        })
    }

    pub async fn publisher(&self, topic: &str, ros_type: &str, qos: Qos) -> Result<Ros2Publisher, Ros2Error> {
        Ok(match self {
            Ros2Node::Zenoh(n) => Ros2Publisher::Zenoh(n.publisher(topic, ros_type, qos).await?),
            Ros2Node::Dds(n) => Ros2Publisher::Dds(n.publisher(topic, ros_type, qos)?),
        })
    }

    pub async fn subscription(
        &self,
        topic: &str,
        ros_type: &str,
        qos: Qos,
    ) -> Result<Ros2Subscription, Ros2Error> {
        Ok(match self {
            Ros2Node::Zenoh(n) => Ros2Subscription::Zenoh(n.subscription(topic, ros_type, qos).await?),
            Ros2Node::Dds(n) => Ros2Subscription::Dds(n.subscription(topic, ros_type, qos)?),
        })
    }

    /// Leave the graph (Zenoh: the tokens withdrawn at once; DDS: the participant dropped).
    pub async fn close(self) -> Result<(), Ros2Error> {
        match self {
            Ros2Node::Zenoh(n) => Ok(n.close().await?),
            Ros2Node::Dds(n) => {
                drop(n);
                Ok(())
            }
        }
    }

    /// Who the node is, for the log.
    #[must_use]
    pub fn describe(&self) -> String {
        match self {
            Ros2Node::Zenoh(n) => format!("rmw_zenoh, Zenoh id {}", n.info().zid),
            Ros2Node::Dds(n) => format!("DDS, {n:?}"),
        }
    }
}

impl Ros2Publisher {
    /// Publish one CDR message (with its encapsulation header).
    pub fn put(&self, cdr: Vec<u8>) -> Result<(), Ros2Error> {
        match self {
            Ros2Publisher::Zenoh(p) => Ok(p.put(cdr)?),
            Ros2Publisher::Dds(p) => Ok(p.put(cdr)?),
        }
    }
}

impl Ros2Subscription {
    /// The next message's CDR; `None` once the node is gone.
    pub async fn recv(&self) -> Option<Vec<u8>> {
        match self {
            Ros2Subscription::Zenoh(s) => s.recv().await.map(|r| r.payload),
            Ros2Subscription::Dds(s) => s.recv().await,
        }
    }

    /// What it is subscribed to, for the log.
    #[must_use]
    pub fn describe(&self) -> String {
        match self {
            Ros2Subscription::Zenoh(s) => s.key().to_owned(),
            Ros2Subscription::Dds(s) => format!("{s:?}"),
        }
    }
}
