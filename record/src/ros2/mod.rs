//! ROS 2 data in and out: rosbag2's MCAP files with CDR-encoded messages.
//!
//! - [`cdr`]: the CDR encoding, one implementation for the writer and the reader (from `amr-ros2`);
//! - [`msg`]: the message types (from `amr-ros2`) (`sensor_msgs/LaserScan`, `nav_msgs/Odometry`,
//!   `geometry_msgs/PoseWithCovarianceStamped`, `tf2_msgs/TFMessage`, `nav_msgs/OccupancyGrid`)
//!   with their schema text;
//! - [`Ros2Encoder`]: what `--record FILE --ros2` writes for each event (topics below);
//! - [`bag`]: reading a bag's scans and odometry for `amr localize --bag`;
//! - [`db3`]: reading rosbag2's sqlite3 storage (`.db3`) into the same messages as an MCAP bag;
//! - [`live`]: the same messages published live on a ROS 2 node (rmw_zenoh);
//! - [`inputs`]: what the node takes from ROS 2 (`/initialpose`, `/cmd_vel`), checked;
//! - [`amcl_node`]: our AMCL as a ROS 2 node in nav2_amcl's place (`amr amcl`).
//!
//! # rosbag2's MCAP profile
//!
//! As rosbag2_storage_mcap writes and reads it (ros2/rosbag2, `rosbag2_storage_mcap/src/
//! mcap_storage.cpp`; the MCAP well-known profile, <https://mcap.dev/spec/registry#ros2>): header
//! profile `ros2`; one schema per type, named `pkg/msg/Type`, encoding `ros2msg` (the `.msg` text,
//! each dependency after a line of 80 `=` and `MSG: pkg/Type`); channels with message encoding
//! `cdr` and the metadata key `offered_qos_profiles`, a YAML list of QoS profiles (below).
//!
//! **QoS.** rosbag2 reads `offered_qos_profiles` by the bag's metadata version
//! (`rosbag2_storage/src/rosbag2_storage/qos.cpp`): up to version 8 the policies are integers
//! (rmw's enums: history keep_last 1; reliability reliable 1; durability transient_local 1,
//! volatile 2; liveliness automatic 1), from 9 names. An MCAP file's version is taken from its
//! `rosbag2` metadata record; one without the key `serialized_metadata` is read as version 8
//! (`MCAPStorage::read_metadata`). So the writer writes the integer form and a `rosbag2` metadata
//! record without `serialized_metadata`: the form Humble reads, and the one later releases read
//! for such a file. `/map` and `/tf_static` are offered transient_local (depth 1), so that a
//! subscriber started after the one message (RViz, nav2's costmaps) still gets it; every topic is
//! offered reliable (a reliable offer matches reliable and best-effort subscribers alike).
//!
//! # Topics of `--record FILE --ros2`
//!
//! ROS 2 topic names allow only letters, digits, `_` and `/` (a token not starting with a digit;
//! rcl's topic name validation), so a robot id like `robot-a` becomes `robot_a` in topic names
//! ([`topic_name`]); frame ids keep the id (tf2 accepts any frame id without a leading `/`).
//!
//! | topic | type | what |
//! |---|---|---|
//! | `/<robot>/scan` | `sensor_msgs/msg/LaserScan` | each robot's scans, frame `<robot>/laser`; invalid beams NaN |
//! | `/virtual/scan` | `sensor_msgs/msg/LaserScan` | the virtual scan, frame `V`: 720 bins of 0.5° from −π, the nearest point per bin, empty bins NaN |
//! | `/<robot>/odom` | `nav_msgs/msg/Odometry` | odometry, frame `<robot>/odom`, child `<robot>` |
//! | `/amcl/V`, `/amcl/<robot>`, `/amcl/<robot>/own`, `/truth/...` | `geometry_msgs/msg/PoseWithCovarianceStamped` | as in the Foxglove recording, frame `map`; the covariance is the filter's (V's, carried to each robot by its offset; the robot's own; zero for the truth) |
//! | `/tf` | `tf2_msgs/msg/TFMessage` | map→`V/odom`, `V/odom`→V, map→`<robot>/odom`, `<robot>/odom`→`<robot>` (and map→`truth/...`) |
//! | `/tf_static` | `tf2_msgs/msg/TFMessage` | `<robot>`→`<robot>/laser`, once |
//! | `/map` | `nav_msgs/msg/OccupancyGrid` | the map, once, frame `map` |
//! | `/diagnostics` | `diagnostic_msgs/msg/DiagnosticArray` | "amr: V localisation" (V's integrity: OK tracking, WARN uncertain or disagreeing, ERROR lost; on a change, else once a second) and "amr: formation" (its phase and why, the plan's progress) |
//!
//! The other channels of a Foxglove recording (`/amr/...` exact records, particles, commands,
//! health, logs) have no ROS 2 type here and are not written: such a file is for `ros2 bag play`,
//! RViz and nav2, not for `amr replay`. A live view (`--foxglove`) still gets everything.

pub mod amcl_node;
pub mod bag;
pub mod db3;
mod encoder;
pub mod inputs;
pub mod live;
pub use amr_ros2::{cdr, msg};
pub use encoder::{Ros2Encoder, laser_scan, occupancy_grid, offset_covariance, points_scan, ros_covariance};

use std::collections::BTreeMap;

/// A name usable as a ROS 2 topic: every character other than a letter, digit, `_` or `/`
/// becomes `_`, and a token starting with a digit gets a leading `_`.
#[must_use]
pub fn topic_name(name: &str) -> String {
    let mut out = String::with_capacity(name.len() + 2);
    let mut token_start = true;
    for c in name.chars() {
        if c == '/' {
            out.push('/');
            token_start = true;
            continue;
        }
        if token_start && c.is_ascii_digit() {
            out.push('_');
        }
        token_start = false;
        out.push(if c.is_ascii_alphanumeric() || c == '_' { c } else { '_' });
    }
    out
}

/// Topics whose one message a late subscriber must still get (offered transient_local).
#[must_use]
pub fn is_latched(topic: &str) -> bool {
    matches!(topic, "/map" | "/tf_static")
}

/// `offered_qos_profiles` of a topic we write, in the integer form of rosbag2's metadata version
/// 8 (see the module docs): one profile, reliable; keep-last 1 and transient_local for latched
/// topics, keep-last 100 (tf2's broadcaster depth) and volatile for the others. Durations `0 0`
/// are rmw's "unspecified" (the middleware's default, infinite).
#[must_use]
pub fn qos_yaml(topic: &str) -> String {
    let (depth, durability) = if is_latched(topic) { (1, 1) } else { (100, 2) };
    format!(
        "- history: 1\n  depth: {depth}\n  reliability: 1\n  durability: {durability}\n  \
         deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n  \
         liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n  \
         avoid_ros_namespace_conventions: false\n"
    )
}

/// Channel metadata of a topic (MCAP channel `metadata`).
#[must_use]
pub fn channel_metadata(topic: &str) -> BTreeMap<String, String> {
    BTreeMap::from([("offered_qos_profiles".to_owned(), qos_yaml(topic))])
}

/// The `ros2msg` schema text of a type name we write.
#[must_use]
pub fn schema_text(type_name: &str) -> String {
    msg::schema_text(type_name).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
    use super::*;

    #[test]
    fn topic_names_are_valid_ros2_names() {
        assert_eq!(topic_name("/robot-a/scan"), "/robot_a/scan");
        assert_eq!(topic_name("/amcl/robot-b/own"), "/amcl/robot_b/own");
        assert_eq!(topic_name("/2d/scan.x"), "/_2d/scan_x");
        assert_eq!(topic_name("/virtual/scan"), "/virtual/scan");
    }

    #[test]
    fn latched_topics_are_offered_transient_local() {
        assert!(qos_yaml("/map").contains("durability: 1\n"));
        assert!(qos_yaml("/tf_static").contains("durability: 1\n"));
        assert!(qos_yaml("/robot_a/scan").contains("durability: 2\n"));
        assert!(qos_yaml("/map").starts_with("- history: 1\n  depth: 1\n  reliability: 1\n"));
    }
}

#[cfg(test)]
mod fuzz {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
    use super::msg::{
        LaserScan, OccupancyGrid, Odometry, PoseWithCovarianceStamped, Ros2Message, TfMessage,
        TransformStamped,
    };
    use super::*;
    use amr_core::scan::Scan;
    use proptest::prelude::*;

    fn all_decoders(bytes: &[u8]) {
        let _ = LaserScan::from_cdr(bytes);
        let _ = Odometry::from_cdr(bytes);
        let _ = TfMessage::from_cdr(bytes);
        let _ = OccupancyGrid::from_cdr(bytes);
        let _ = PoseWithCovarianceStamped::from_cdr(bytes);
        let messages: Vec<crate::read::Recorded> = [
            ("/scan", LaserScan::TYPE),
            ("/odom", Odometry::TYPE),
            ("/tf", TfMessage::TYPE),
            ("/tf_static", TfMessage::TYPE),
        ]
        .iter()
        .map(|(topic, schema)| crate::read::Recorded {
            topic: (*topic).into(),
            schema: (*schema).into(),
            encoding: "cdr".into(),
            log_time_ns: 0,
            publish_time_ns: 0,
            data: bytes.to_vec(),
        })
        .collect();
        let _ = bag::read(&messages, &bag::BagOptions::default());
        let _ = bag::read(&messages, &bag::BagOptions { odom_from_tf: true, ..Default::default() });
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

        /// Any bytes: an error or a message, never a panic (nor a huge allocation).
        #[test]
        fn arbitrary_bytes_never_panic_a_decoder(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
            all_decoders(&bytes);
        }

        /// Past the header too: a valid encapsulation (either byte order) before arbitrary bytes.
        #[test]
        fn arbitrary_payloads_never_panic_a_decoder(
            big in any::<bool>(),
            payload in proptest::collection::vec(any::<u8>(), 0..400),
        ) {
            let mut bytes = vec![0, u8::from(!big), 0, 0];
            bytes.extend_from_slice(&payload);
            all_decoders(&bytes);
        }

        /// A real message damaged at one place.
        #[test]
        fn damaged_messages_never_panic_a_decoder(at in 0usize..2000, value in any::<u8>(), cut in 0usize..2000) {
            let s = Scan::new(-1.0, 0.1, 0.05, 10.0, (0..20).map(f64::from).collect());
            let tf = TfMessage { transforms: vec![TransformStamped::planar(1.0, "odom", "base_link", 1.0, 2.0, 3.0)] };
            for mut b in [laser_scan(1.0, "laser", &s).to_cdr(), tf.to_cdr()] {
                let i = at % b.len();
                b[i] = value;
                b.truncate(cut.min(b.len()));
                all_decoders(&b);
            }
        }
    }
}
