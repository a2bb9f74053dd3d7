//! The fleet live on ROS 2: what a `--record FILE --ros2` bag would hold, published as it happens on
//! a ROS 2 node ([`amr_ros2::transport`]: rmw_zenoh or DDS), with the QoS ROS 2 tools expect of each
//! topic.
//!
//! The recorder hands each encoded message to [`Ros2Live::publish`], which never blocks: a bounded
//! queue feeds one task that owns the node's publishers (one per topic, made on its first message).
//! When the queue is full (a stalled network) messages are dropped and counted, never waited for:
//! the recorder, and the fleet behind it, go on.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use amr_ros2::msg::{Clock, Ros2Message as _, Time};
use amr_ros2::rmw_zenoh::Qos;
use amr_ros2::transport::{Ros2Node, Ros2Publisher};
use tokio::sync::mpsc;

use crate::encode::Out;

/// Messages queued for the node at most.
const QUEUE: usize = 1024;

/// The QoS a topic is offered with: scans as sensor data (best effort, depth 5: what RViz and
/// nav2_amcl subscribe with, and a reliable offer would also match), `/map` and `/tf_static`
/// latched (a subscriber that comes later still gets them), `/tf` reliable with a deep queue (as
/// tf2's broadcaster), everything else reliable, depth 10.
#[must_use]
pub fn qos_for(topic: &str) -> Qos {
    if super::is_latched(topic) {
        Qos::LATCHED
    } else if topic.ends_with("/scan") {
        Qos::SENSOR_DATA
    } else if topic == "/tf" {
        Qos::reliable(100)
    } else {
        Qos::reliable(10)
    }
}

/// A live ROS 2 output.
#[derive(Debug, Clone)]
pub struct Ros2Live {
    tx: mpsc::Sender<Out>,
    stats: Arc<LiveStats>,
    /// The last `/clock` sent, ns.
    clock_ns: Arc<AtomicU64>,
    /// nav2_amcl localises V: `map` → `V/odom` is left to it.
    nav2_amcl: bool,
}

/// `/clock` goes out at most this often, ns (100 Hz).
const CLOCK_EVERY_NS: u64 = 10_000_000;

/// What the output did.
#[derive(Debug, Default)]
pub struct LiveStats {
    pub published: AtomicU64,
    /// Dropped: the queue was full, or the node could not publish.
    pub dropped: AtomicU64,
    /// Topics whose publisher could not be made (an unknown type).
    pub refused: AtomicU64,
}

impl Ros2Live {
    /// Publish on `node` from now on (call from within a tokio runtime), until every handle is
    /// dropped.
    #[must_use]
    pub fn start(node: Arc<Ros2Node>) -> Ros2Live {
        let (tx, rx) = mpsc::channel(QUEUE);
        let stats = Arc::new(LiveStats::default());
        tokio::spawn(run(node, rx, Arc::clone(&stats)));
        Ros2Live { tx, stats, clock_ns: Arc::new(AtomicU64::new(0)), nav2_amcl: false }
    }

    /// nav2_amcl localises V from `/virtual/scan` (the paper's mode): `map` → `V/odom` is not
    /// published from our estimate, nav2_amcl publishes it.
    #[must_use]
    pub fn for_nav2_amcl(mut self) -> Self {
        self.nav2_amcl = true;
        self
    }

    #[must_use]
    pub fn nav2_amcl(&self) -> bool {
        self.nav2_amcl
    }

    /// The fleet's clock, as `/clock` (`rosgraph_msgs/Clock`): ROS 2 nodes started with
    /// `use_sim_time` follow it (in `amr sim` the fleet clock counts from the start of the run).
    /// At most every 10 ms of it; never backwards.
    pub fn clock(&self, now_s: f64) {
        let ns = crate::foxglove::nanos(now_s);
        let last = self.clock_ns.load(Ordering::Relaxed);
        if ns < last.saturating_add(CLOCK_EVERY_NS) && last != 0 {
            return;
        }
        self.clock_ns.store(ns, Ordering::Relaxed);
        let msg = Clock { clock: Time::from_secs(now_s) };
        self.publish(&Out {
            topic: "/clock".into(),
            schema: Clock::TYPE,
            log_time_ns: ns,
            publish_time_ns: ns,
            data: msg.to_cdr(),
        });
    }

    /// Queue one message (a CDR-encoded ROS 2 message from [`super::Ros2Encoder`]).
    pub fn publish(&self, out: &Out) {
        if self.tx.try_send(out.clone()).is_err() {
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    #[must_use]
    pub fn stats(&self) -> &LiveStats {
        &self.stats
    }
}

async fn run(node: Arc<Ros2Node>, mut rx: mpsc::Receiver<Out>, stats: Arc<LiveStats>) {
    let mut publishers: BTreeMap<String, Option<Ros2Publisher>> = BTreeMap::new();
    while let Some(out) = rx.recv().await {
        if !publishers.contains_key(&out.topic) {
            let made = match node.publisher(&out.topic, out.schema, qos_for(&out.topic)).await {
                Ok(p) => Some(p),
                Err(e) => {
                    tracing::warn!(topic = %out.topic, error = %e, "ROS 2: not published");
                    stats.refused.fetch_add(1, Ordering::Relaxed);
                    None
                }
            };
            publishers.insert(out.topic.clone(), made);
        }
        let Some(Some(p)) = publishers.get(&out.topic) else { continue };
        match p.put(out.data) {
            Ok(()) => stats.published.fetch_add(1, Ordering::Relaxed),
            Err(e) => {
                tracing::debug!(topic = %out.topic, error = %e, "ROS 2: a message was not sent");
                stats.dropped.fetch_add(1, Ordering::Relaxed)
            }
        };
    }
    drop(publishers);
    // The last holder closes the session (its tokens withdrawn at once).
    if let Ok(node) = Arc::try_unwrap(node)
        && let Err(e) = node.close().await
    {
        tracing::debug!(error = %e, "ROS 2: closing the node");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_get_the_qos_ros2_tools_subscribe_with() {
        assert_eq!(qos_for("/map"), Qos::LATCHED);
        assert_eq!(qos_for("/tf_static"), Qos::LATCHED);
        assert_eq!(qos_for("/robot_a/scan"), Qos::SENSOR_DATA);
        assert_eq!(qos_for("/virtual/scan"), Qos::SENSOR_DATA);
        assert_eq!(qos_for("/tf"), Qos::reliable(100));
        assert_eq!(qos_for("/amcl/V"), Qos::reliable(10));
    }
}
