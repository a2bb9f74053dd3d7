//! A ROS 2 node on DDS/RTPS, the middleware of ROS 2 up to Humble by default (Fast DDS, Cyclone
//! DDS) and the paper's Foxy: RustDDS underneath, the ROS 2 conventions on top, as the rmw
//! implementations for DDS name things (ROS 2 design article "Topic and Service name mapping to
//! DDS"; rmw_cyclonedds, rmw_fastrtps):
//!
//! - a topic `/ns/name` is the DDS topic `rt/ns/name`;
//! - a type `pkg/msg/Type` is the DDS type `pkg::msg::dds_::Type_`;
//! - a sample is the message's CDR (XCDR1, plain, little endian here) behind its 4-byte
//!   encapsulation header, as a rosbag2 record or an rmw_zenoh payload;
//! - QoS are DDS's own: reliability, durability, history depth.
//!
//! Discovery is DDS's (SPDP/SEDP, multicast by default): the tests run it in a network namespace of
//! their own. The node appears to ROS 2 tools by its topics (`ros2 topic list`); the
//! `ros_discovery_info` graph that lists it in `ros2 node list` is not written.

use std::sync::Arc;

use futures_util::StreamExt as _;
use rustdds::no_key::{DataWriter, DefaultDecoder, DeserializerAdapter, SerializerAdapter};
use rustdds::{DomainParticipant, QosPolicyBuilder, RepresentationIdentifier, TopicKind, policy};
use tokio::sync::Mutex;

use crate::rmw_zenoh::{Durability, Qos, Reliability, dds_type_name};

/// A ROS 2 message as CDR with its encapsulation header (what [`crate::msg::Ros2Message::to_cdr`]
/// gives and `from_cdr` reads).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Cdr(pub Vec<u8>);

/// Hands [`Cdr`] to RustDDS and back: RustDDS writes and strips the encapsulation header itself.
#[derive(Debug, Clone, Copy)]
pub struct CdrAdapter;

/// Why a sample could not be passed on.
#[derive(Debug, thiserror::Error)]
pub enum CdrAdapterError {
    #[error("a sample shorter than its encapsulation header")]
    NoHeader,
    #[error("a sample in representation {0:?}, not plain CDR")]
    Representation(RepresentationIdentifier),
}

impl SerializerAdapter<Cdr> for CdrAdapter {
    type Error = CdrAdapterError;
    fn output_encoding() -> RepresentationIdentifier {
        RepresentationIdentifier::CDR_LE
    }
    fn to_bytes(value: &Cdr) -> Result<rustdds::bytes::Bytes, CdrAdapterError> {
        let body = value.0.get(4..).ok_or(CdrAdapterError::NoHeader)?;
        Ok(rustdds::bytes::Bytes::copy_from_slice(body))
    }
}

impl DeserializerAdapter<Cdr> for CdrAdapter {
    type Error = CdrAdapterError;
    type Decoded = Cdr;
    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &[RepresentationIdentifier::CDR_LE, RepresentationIdentifier::CDR_BE]
    }
    fn transform_decoded(decoded: Cdr) -> Cdr {
        decoded
    }
}

/// Puts the encapsulation header back in front of the body RustDDS hands over.
#[derive(Debug, Clone, Copy)]
pub struct CdrDecoder;

impl<'de> rustdds::no_key::Decode<'de, Cdr> for CdrDecoder {
    type Error = CdrAdapterError;
    fn decode_bytes(
        self,
        input: &'de [u8],
        encoding: RepresentationIdentifier,
    ) -> Result<Cdr, CdrAdapterError> {
        let header = if encoding == RepresentationIdentifier::CDR_LE {
            [0x00, 0x01, 0x00, 0x00]
        } else if encoding == RepresentationIdentifier::CDR_BE {
            [0x00, 0x00, 0x00, 0x00]
        } else {
            return Err(CdrAdapterError::Representation(encoding));
        };
        let mut v = Vec::with_capacity(input.len() + 4);
        v.extend_from_slice(&header);
        v.extend_from_slice(input);
        Ok(Cdr(v))
    }
}

impl DefaultDecoder<Cdr> for CdrAdapter {
    type Decoder = CdrDecoder;
    const DECODER: CdrDecoder = CdrDecoder;
}

/// Why the DDS node or an endpoint could not be made.
#[derive(Debug, thiserror::Error)]
pub enum DdsError {
    #[error("DDS: {0}")]
    Dds(String),
    #[error("{0} is not a ROS 2 type name (pkg/msg/Type)")]
    Type(String),
    #[error("{0} is not a valid ROS 2 topic name")]
    Topic(String),
}

fn derr(e: impl std::fmt::Debug) -> DdsError {
    DdsError::Dds(format!("{e:?}"))
}

/// A ROS 2 node on DDS: one domain participant.
pub struct DdsNode {
    participant: DomainParticipant,
    publisher: rustdds::Publisher,
    subscriber: rustdds::Subscriber,
}

impl std::fmt::Debug for DdsNode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DdsNode").field("domain", &self.participant.domain_id()).finish_non_exhaustive()
    }
}

/// The DDS QoS of a ROS 2 QoS (keep-last `depth`).
fn dds_qos(q: &Qos) -> rustdds::QosPolicies {
    let reliability = match q.reliability {
        Reliability::Reliable => policy::Reliability::Reliable { max_blocking_time: rustdds::Duration::ZERO },
        Reliability::BestEffort => policy::Reliability::BestEffort,
    };
    let durability = match q.durability {
        Durability::TransientLocal => policy::Durability::TransientLocal,
        Durability::Volatile => policy::Durability::Volatile,
    };
    QosPolicyBuilder::new()
        .reliability(reliability)
        .durability(durability)
        .history(policy::History::KeepLast { depth: i32::try_from(q.depth).unwrap_or(i32::MAX) })
        .build()
}

/// The DDS topic name of a ROS 2 topic: `rt` and the fully qualified name.
#[must_use]
pub fn dds_topic_name(topic: &str) -> String {
    format!("rt/{}", topic.trim_matches('/'))
}

impl DdsNode {
    /// Join DDS domain `domain` (`ROS_DOMAIN_ID`).
    pub fn open(domain: u16) -> Result<DdsNode, DdsError> {
        let participant = DomainParticipant::new(domain).map_err(derr)?;
        let qos = QosPolicyBuilder::new().build();
        let publisher = participant.create_publisher(&qos).map_err(derr)?;
        let subscriber = participant.create_subscriber(&qos).map_err(derr)?;
        Ok(DdsNode { participant, publisher, subscriber })
    }

    fn topic(
        &self,
        topic: &str,
        ros_type: &str,
        qos: &rustdds::QosPolicies,
    ) -> Result<rustdds::Topic, DdsError> {
        let ty = dds_type_name(ros_type).ok_or_else(|| DdsError::Type(ros_type.into()))?;
        let topic = crate::node::qualified("/", topic).map_err(|_| DdsError::Topic(topic.into()))?;
        self.participant.create_topic(dds_topic_name(&topic), ty, qos, TopicKind::NoKey).map_err(derr)
    }

    /// A writer of `ros_type` on the ROS 2 topic `topic`.
    pub fn publisher(&self, topic: &str, ros_type: &str, qos: Qos) -> Result<DdsPublisher, DdsError> {
        let q = dds_qos(&qos);
        let t = self.topic(topic, ros_type, &q)?;
        let writer = self.publisher.create_datawriter_no_key::<Cdr, CdrAdapter>(&t, Some(q)).map_err(derr)?;
        Ok(DdsPublisher { writer })
    }

    /// A reader of `ros_type` on the ROS 2 topic `topic`.
    pub fn subscription(&self, topic: &str, ros_type: &str, qos: Qos) -> Result<DdsSubscription, DdsError> {
        let q = dds_qos(&qos);
        let t = self.topic(topic, ros_type, &q)?;
        let reader =
            self.subscriber.create_datareader_no_key::<Cdr, CdrAdapter>(&t, Some(q)).map_err(derr)?;
        Ok(DdsSubscription { stream: Arc::new(Mutex::new(reader.async_sample_stream())) })
    }
}

/// One DDS writer.
pub struct DdsPublisher {
    writer: DataWriter<Cdr, CdrAdapter>,
}

impl std::fmt::Debug for DdsPublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DdsPublisher").finish_non_exhaustive()
    }
}

impl DdsPublisher {
    /// Write one CDR message (with its encapsulation header). Never waits for a reliable reader:
    /// a full history drops the oldest.
    pub fn put(&self, cdr: Vec<u8>) -> Result<(), DdsError> {
        self.writer.write(Cdr(cdr), None).map_err(derr)
    }
}

/// One DDS reader.
pub struct DdsSubscription {
    stream: Arc<Mutex<rustdds::no_key::DataReaderStream<Cdr, CdrAdapter>>>,
}

impl std::fmt::Debug for DdsSubscription {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DdsSubscription").finish_non_exhaustive()
    }
}

impl DdsSubscription {
    /// The next sample's CDR (with its encapsulation header); `None` once the reader is gone.
    /// Samples that do not decode are skipped.
    pub async fn recv(&self) -> Option<Vec<u8>> {
        let mut s = self.stream.lock().await;
        loop {
            match s.next().await? {
                Ok(sample) => return Some(sample.into_value().0),
                Err(e) => tracing::debug!(error = ?e, "DDS: a sample skipped"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]
    use super::*;
    use rustdds::no_key::Decode as _;

    #[test]
    fn names_follow_the_ros2_dds_mapping() {
        assert_eq!(dds_topic_name("/robot_a/scan"), "rt/robot_a/scan");
        assert_eq!(dds_topic_name("/map"), "rt/map");
    }

    #[test]
    fn the_header_goes_to_rustdds_and_comes_back() {
        let msg = vec![0x00, 0x01, 0x00, 0x00, 1, 2, 3, 4];
        let body = <CdrAdapter as SerializerAdapter<Cdr>>::to_bytes(&Cdr(msg.clone())).unwrap();
        assert_eq!(&body[..], &[1, 2, 3, 4]);
        assert_eq!(CdrDecoder.decode_bytes(&body, RepresentationIdentifier::CDR_LE).unwrap(), Cdr(msg));
        let be = CdrDecoder.decode_bytes(&[9], RepresentationIdentifier::CDR_BE).unwrap();
        assert_eq!(be.0, [0, 0, 0, 0, 9]);
        assert!(CdrDecoder.decode_bytes(&[9], RepresentationIdentifier::PL_CDR_LE).is_err());
        assert!(<CdrAdapter as SerializerAdapter<Cdr>>::to_bytes(&Cdr(vec![0, 1])).is_err());
    }
}
