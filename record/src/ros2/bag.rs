//! A ROS 2 bag's scans and odometry as the localizer's records (`amr localize --bag`): the
//! CARMEN path's [`Record`]s, so both feed the same [`amr_core::amcl::log::LogLocalizer`].
//!
//! - Scans: `sensor_msgs/msg/LaserScan` on the scan topic (default `/scan`), each at its header
//!   stamp, beam `i` at `angle_min + i·angle_increment`; ranges outside `[range_min, range_max]`,
//!   zero, NaN or ±inf are invalid (as [`Scan::new`] rules).
//! - Odometry: `nav_msgs/msg/Odometry` on the odometry topic (default `/odom`), its
//!   `pose.pose`; or, if that topic is not in the bag (or `odom_from_tf` is set), the transform
//!   odom frame → base frame (defaults `odom`, `base_link`) on `/tf`. Each scan gets the odometry
//!   at its own stamp, interpolated between the two samples around it (a sample at most
//!   [`MAX_ODOM_GAP_S`] away if it is outside them); a scan with none is counted, as CARMEN's are.
//! - The laser's mounting: the transform base frame → the scan's `frame_id` from `/tf_static`
//!   (through intermediate frames if need be), projected on the plane (x, y, yaw); without one the
//!   scan's frame is taken as the base, with a warning.
//! - A message that does not decode (damaged, another encapsulation, a scan without a usable
//!   geometry) is skipped and reported in [`BagLog::skipped`], as CARMEN's unreadable lines are.

use std::collections::BTreeMap;

use amr_core::carmen::{LaserRecord, Record};
use amr_core::scan::Scan;
use amr_core::se2::{Se2, angle_diff};

use super::cdr::CdrError;
use super::msg::{LaserScan, Odometry, Ros2Message, TfMessage, TransformStamped, yaw};
use crate::read::Recorded;

/// Which topics and frames to take.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BagOptions {
    pub scan_topic: String,
    pub odom_topic: String,
    /// Take odometry from `/tf` even if the odometry topic is there.
    pub odom_from_tf: bool,
    pub tf_topic: String,
    pub tf_static_topic: String,
    pub odom_frame: String,
    pub base_frame: String,
}

impl Default for BagOptions {
    fn default() -> Self {
        BagOptions {
            scan_topic: "/scan".into(),
            odom_topic: "/odom".into(),
            odom_from_tf: false,
            tf_topic: "/tf".into(),
            tf_static_topic: "/tf_static".into(),
            odom_frame: "odom".into(),
            base_frame: "base_link".into(),
        }
    }
}

/// Odometry farther than this from a scan's stamp is not used for it, s (a bag's odometry runs
/// at 10–50 Hz; a gap of half a second means the odometry stopped).
pub const MAX_ODOM_GAP_S: f64 = 0.5;

/// Message type names (MCAP schema names in rosbag2's profile).
const LASER_SCAN: &str = LaserScan::TYPE;
const ODOMETRY: &str = Odometry::TYPE;
const TF: &str = TfMessage::TYPE;

/// A message that was skipped.
#[derive(Debug, Clone, PartialEq)]
pub struct Skipped {
    pub topic: String,
    pub log_time_ns: u64,
    pub reason: String,
}

/// Where the odometry came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum OdomSource {
    Topic(String),
    Tf { parent: String, child: String },
}

impl std::fmt::Display for OdomSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OdomSource::Topic(t) => write!(f, "{t} (nav_msgs/msg/Odometry)"),
            OdomSource::Tf { parent, child } => write!(f, "/tf {parent} → {child}"),
        }
    }
}

/// What was read.
#[derive(Debug, Clone)]
pub struct BagLog {
    /// Laser records in stamp order, each with the odometry at its stamp (if any).
    pub records: Vec<Record>,
    pub odometry: OdomSource,
    /// Odometry samples used.
    pub odometry_samples: usize,
    /// The laser in the base per scan frame, and whether it came from `/tf_static`.
    pub mounts: BTreeMap<String, (Se2, bool)>,
    pub skipped: Vec<Skipped>,
}

/// Why a bag cannot be localised at all.
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    #[error("no topic {topic} in the bag (its topics: {found})")]
    NoTopic { topic: String, found: String },
    #[error("topic {topic} is {found} in encoding `{encoding}`, not {expected} in `cdr`")]
    WrongType { topic: String, found: String, encoding: String, expected: &'static str },
    #[error(
        "no odometry: neither {topic} nor a transform {parent} → {child} on {tf} (transforms there: {seen})"
    )]
    NoOdometry { topic: String, tf: String, parent: String, child: String, seen: String },
}

pub(crate) fn strip(frame: &str) -> &str {
    frame.strip_prefix('/').unwrap_or(frame)
}

pub(crate) fn planar(t: &TransformStamped) -> Se2 {
    Se2::new(t.translation[0], t.translation[1], yaw(t.rotation))
}

/// The topics of `messages` with their type and encoding.
fn topics(messages: &[Recorded]) -> BTreeMap<&str, (&str, &str)> {
    let mut t = BTreeMap::new();
    for m in messages {
        t.entry(m.topic.as_str()).or_insert((m.schema.as_str(), m.encoding.as_str()));
    }
    t
}

fn check_type(
    topics: &BTreeMap<&str, (&str, &str)>,
    topic: &str,
    expected: &'static str,
) -> Result<bool, BagError> {
    match topics.get(topic) {
        None => Ok(false),
        Some((schema, encoding)) if *schema == expected && *encoding == "cdr" => Ok(true),
        Some((schema, encoding)) => Err(BagError::WrongType {
            topic: topic.to_owned(),
            found: (*schema).to_owned(),
            encoding: (*encoding).to_owned(),
            expected,
        }),
    }
}

/// Every message of `topic`, decoded; those that do not decode go to `skipped`.
fn decode_all<'a, M: Ros2Message>(
    messages: &'a [Recorded],
    topic: &'a str,
    skipped: &'a mut Vec<Skipped>,
) -> impl Iterator<Item = M> + 'a {
    messages.iter().filter(move |m| m.topic == topic).filter_map(move |m| match M::from_cdr(&m.data) {
        Ok(v) => Some(v),
        Err(e) => {
            skipped.push(Skipped {
                topic: m.topic.clone(),
                log_time_ns: m.log_time_ns,
                reason: e.to_string(),
            });
            None
        }
    })
}

/// A scan as the localizer's [`Scan`], or why it cannot be one.
pub(crate) fn to_scan(m: &LaserScan) -> Result<Scan, CdrError> {
    let (min, inc) = (f64::from(m.angle_min), f64::from(m.angle_increment));
    if !min.is_finite() || !inc.is_finite() || inc == 0.0 || m.ranges.is_empty() {
        return Err(CdrError::Invalid(format!(
            "a scan without a usable geometry (angle_min {min}, angle_increment {inc}, {} ranges)",
            m.ranges.len()
        )));
    }
    let ranges = m.ranges.iter().map(|r| f64::from(*r)).collect();
    Ok(Scan::new(min, inc, f64::from(m.range_min), f64::from(m.range_max), ranges))
}

/// The odometry at `t` from samples sorted by stamp.
pub(crate) fn odom_at(samples: &[(f64, Se2)], t: f64) -> Option<Se2> {
    let i = samples.partition_point(|(s, _)| *s < t);
    match (i.checked_sub(1).and_then(|j| samples.get(j)), samples.get(i)) {
        (Some((ta, a)), Some((tb, b))) => {
            let f = if tb > ta { (t - ta) / (tb - ta) } else { 0.0 };
            Some(Se2::new(
                a.x + (b.x - a.x) * f,
                a.y + (b.y - a.y) * f,
                a.theta + angle_diff(b.theta, a.theta) * f,
            ))
        }
        (Some((ta, a)), None) => (t - ta <= MAX_ODOM_GAP_S).then_some(*a),
        (None, Some((tb, b))) => (tb - t <= MAX_ODOM_GAP_S).then_some(*b),
        (None, None) => None,
    }
}

/// The pose of `frame` in `base` from static transforms (child → (parent, transform)).
pub(crate) fn mount(statics: &BTreeMap<String, (String, Se2)>, base: &str, frame: &str) -> Option<Se2> {
    let mut pose = Se2::IDENTITY;
    let mut at = frame;
    // A chain of static frames is short; a loop in a damaged bag ends here.
    for _ in 0..64 {
        if at == base {
            return Some(pose);
        }
        let (parent, t) = statics.get(at)?;
        pose = *t * pose;
        at = parent;
    }
    None
}

/// The bag's static transforms, child → (parent, transform), the last one of each child winning.
fn statics(
    messages: &[Recorded],
    topics: &BTreeMap<&str, (&str, &str)>,
    opts: &BagOptions,
    skipped: &mut Vec<Skipped>,
) -> BTreeMap<String, (String, Se2)> {
    let mut statics = BTreeMap::new();
    if check_type(topics, &opts.tf_static_topic, TF).unwrap_or(false) {
        for m in decode_all::<TfMessage>(messages, &opts.tf_static_topic, skipped) {
            for t in &m.transforms {
                let p = planar(t);
                if p.x.is_finite() && p.y.is_finite() && p.theta.is_finite() {
                    statics.insert(
                        strip(&t.child_frame_id).to_owned(),
                        (strip(&t.header.frame_id).to_owned(), p),
                    );
                }
            }
        }
    }
    statics
}

/// Read the scans and odometry of a bag's messages (in file order, as [`crate::read`] gives them).
pub fn read(messages: &[Recorded], opts: &BagOptions) -> Result<BagLog, BagError> {
    let topics = topics(messages);
    let list = || topics.iter().map(|(t, (s, _))| format!("{t} [{s}]")).collect::<Vec<_>>().join(", ");
    if !check_type(&topics, &opts.scan_topic, LASER_SCAN)? {
        return Err(BagError::NoTopic { topic: opts.scan_topic.clone(), found: list() });
    }
    let mut skipped = Vec::new();

    // Odometry: the topic, else /tf.
    let use_topic = !opts.odom_from_tf && check_type(&topics, &opts.odom_topic, ODOMETRY)?;
    let (odom_frame, base_frame) = (strip(&opts.odom_frame), strip(&opts.base_frame));
    let mut samples: Vec<(f64, Se2)> = Vec::new();
    let odometry = if use_topic {
        for o in decode_all::<Odometry>(messages, &opts.odom_topic, &mut skipped) {
            let (x, y, th) = o.pose.pose.planar_parts();
            samples.push((o.header.stamp.secs(), Se2::new(x, y, th)));
        }
        OdomSource::Topic(opts.odom_topic.clone())
    } else {
        let has_tf = check_type(&topics, &opts.tf_topic, TF)?;
        let mut seen = BTreeMap::<(String, String), usize>::new();
        if has_tf {
            for m in decode_all::<TfMessage>(messages, &opts.tf_topic, &mut skipped) {
                for t in &m.transforms {
                    let (parent, child) = (strip(&t.header.frame_id), strip(&t.child_frame_id));
                    if parent == odom_frame && child == base_frame {
                        samples.push((t.header.stamp.secs(), planar(t)));
                    } else {
                        *seen.entry((parent.to_owned(), child.to_owned())).or_default() += 1;
                    }
                }
            }
        }
        if samples.is_empty() {
            let seen = seen.keys().map(|(p, c)| format!("{p} → {c}")).collect::<Vec<_>>();
            return Err(BagError::NoOdometry {
                topic: opts.odom_topic.clone(),
                tf: opts.tf_topic.clone(),
                parent: odom_frame.to_owned(),
                child: base_frame.to_owned(),
                seen: if seen.is_empty() { "none".into() } else { seen.join(", ") },
            });
        }
        OdomSource::Tf { parent: odom_frame.to_owned(), child: base_frame.to_owned() }
    };
    samples.retain(|(t, p)| t.is_finite() && p.x.is_finite() && p.y.is_finite() && p.theta.is_finite());
    samples.sort_by(|a, b| a.0.total_cmp(&b.0));

    let statics = statics(messages, &topics, opts, &mut skipped);

    let mut mounts: BTreeMap<String, (Se2, bool)> = BTreeMap::new();
    let mut scans: Vec<(f64, Scan, Se2)> = Vec::new();
    for m in messages.iter().filter(|m| m.topic == opts.scan_topic) {
        let decoded = LaserScan::from_cdr(&m.data).and_then(|s| Ok((to_scan(&s)?, s)));
        let (scan, msg) = match decoded {
            Ok(v) => v,
            Err(e) => {
                skipped.push(Skipped {
                    topic: m.topic.clone(),
                    log_time_ns: m.log_time_ns,
                    reason: e.to_string(),
                });
                continue;
            }
        };
        let frame = strip(&msg.header.frame_id).to_owned();
        let (laser_in_base, _) =
            *mounts.entry(frame.clone()).or_insert_with(|| match mount(&statics, base_frame, &frame) {
                Some(p) => (p, true),
                None => (Se2::IDENTITY, false),
            });
        scans.push((msg.header.stamp.secs(), scan, laser_in_base));
    }
    scans.sort_by(|a, b| a.0.total_cmp(&b.0));
    let records = scans
        .into_iter()
        .map(|(t, scan, laser_in_robot)| {
            Record::Laser(Box::new(LaserRecord {
                scan,
                odometry: odom_at(&samples, t),
                laser_in_robot,
                logged_pose: None,
                timestamp_s: t,
            }))
        })
        .collect();
    Ok(BagLog { records, odometry, odometry_samples: samples.len(), mounts, skipped })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
    use super::*;
    use crate::ros2::msg::Header;

    fn rec(topic: &str, schema: &str, t_ns: u64, data: Vec<u8>) -> Recorded {
        Recorded {
            topic: topic.into(),
            schema: schema.into(),
            encoding: "cdr".into(),
            log_time_ns: t_ns,
            publish_time_ns: t_ns,
            data,
        }
    }

    fn scan(t: f64, frame: &str) -> Vec<u8> {
        LaserScan {
            header: Header::new(t, frame),
            angle_min: -1.0,
            angle_max: 1.0,
            angle_increment: 1.0,
            range_min: 0.1,
            range_max: 10.0,
            ranges: vec![1.0, 2.0, 3.0],
            ..Default::default()
        }
        .to_cdr()
    }

    fn tf(t: f64, parent: &str, child: &str, x: f64, theta: f64) -> Vec<u8> {
        TfMessage { transforms: vec![TransformStamped::planar(t, parent, child, x, 0.0, theta)] }.to_cdr()
    }

    #[test]
    fn odometry_from_tf_is_interpolated_and_the_mount_chained() {
        let msgs = vec![
            rec("/tf_static", TF, 0, tf(0.0, "base_link", "mount", 0.5, 0.0)),
            rec("/tf_static", TF, 0, tf(0.0, "/mount", "laser", 0.0, 0.5)),
            rec("/tf", TF, 1, tf(1.0, "odom", "base_link", 1.0, 0.0)),
            rec("/tf", TF, 2, tf(2.0, "map", "odom", 7.0, 0.0)),
            rec("/tf", TF, 3, tf(2.0, "odom", "base_link", 2.0, 0.2)),
            rec("/scan", LASER_SCAN, 4, scan(1.5, "laser")),
            rec("/scan", LASER_SCAN, 5, vec![0, 1, 0, 0, 9]),
            rec("/scan", LASER_SCAN, 6, scan(9.0, "laser")),
        ];
        let log = read(&msgs, &BagOptions::default()).unwrap();
        assert_eq!(log.odometry, OdomSource::Tf { parent: "odom".into(), child: "base_link".into() });
        assert_eq!(log.odometry_samples, 2);
        assert_eq!(log.skipped.len(), 1, "{:?}", log.skipped);
        assert_eq!(log.records.len(), 2);
        let Record::Laser(l) = &log.records[0] else { panic!() };
        let o = l.odometry.unwrap();
        assert!((o.x - 1.5).abs() < 1e-12 && (o.theta - 0.1).abs() < 1e-12, "{o:?}");
        assert!((l.laser_in_robot.x - 0.5).abs() < 1e-12 && (l.laser_in_robot.theta - 0.5).abs() < 1e-12);
        let Record::Laser(l) = &log.records[1] else { panic!() };
        assert_eq!(l.odometry, None, "7 s after the last odometry");
        assert!(log.mounts["laser"].1);
    }

    #[test]
    fn missing_topics_and_odometry_are_clear_errors() {
        let msgs = vec![rec("/scan", LASER_SCAN, 1, scan(1.0, "laser"))];
        let e = read(&msgs, &BagOptions { scan_topic: "/front".into(), ..Default::default() }).unwrap_err();
        assert!(
            e.to_string().contains("no topic /front")
                && e.to_string().contains("/scan [sensor_msgs/msg/LaserScan]"),
            "{e}"
        );
        let e = read(&msgs, &BagOptions::default()).unwrap_err();
        assert!(e.to_string().contains("no odometry"), "{e}");
        let mut odd = msgs.clone();
        odd.push(Recorded { encoding: "json".into(), ..rec("/odom", ODOMETRY, 1, vec![]) });
        let e = read(&odd, &BagOptions::default()).unwrap_err();
        assert!(matches!(e, BagError::WrongType { .. }), "{e}");
    }
}
