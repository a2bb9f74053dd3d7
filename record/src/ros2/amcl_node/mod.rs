//! `amr amcl`: our AMCL as a ROS 2 node in nav2_amcl's place, on its topics, frames and parameter
//! file, so that a nav2 launch swaps one node for the other.
//!
//! | | topic | type | QoS (nav2_amcl's `amcl_node.cpp`) |
//! |---|---|---|---|
//! | in | `scan` (`scan_topic`) | `sensor_msgs/msg/LaserScan` | sensor data (best effort, depth 5) |
//! | in | `map` (`map_topic`) | `nav_msgs/msg/OccupancyGrid` | reliable, transient local, depth 1 |
//! | in | `initialpose` | `geometry_msgs/msg/PoseWithCovarianceStamped` | reliable, depth 10 |
//! | in | `/tf`, `/tf_static` | `tf2_msgs/msg/TFMessage` | reliable 100; reliable transient local |
//! | out | `amcl_pose` | `geometry_msgs/msg/PoseWithCovarianceStamped` | reliable, transient local, depth 1 |
//! | out | `particle_cloud` | `nav2_msgs/msg/ParticleCloud` | sensor data |
//! | out | `/tf` | `tf2_msgs/msg/TFMessage` | reliable 100: `global_frame_id` → `odom_frame_id` |
//! | out | `/diagnostics` | `diagnostic_msgs/msg/DiagnosticArray` | reliable 10: the integrity (ours) |
//!
//! As nav2_amcl: a scan waits (at most [`SCAN_QUEUE`] of them, nav2's message filter queue) until
//! `/tf` has odom → base at its stamp; the odometry is interpolated at the stamp, the laser's
//! mounting is base → the scan's frame (`/tf_static`, or `/tf`). `amcl_pose` carries the scan's
//! stamp and the filter's covariance, and is published when the filter updates; map → odom is
//! published for every scan, stamped `transform_tolerance` after it. A pose on `initialpose` in
//! the global frame restarts the filter there; a new map rebuilds it at the last pose.
//!
//! Unlike nav2_amcl, without an initial pose (`set_initial_pose`, or `initialpose`) the filter
//! localises globally from the first scan, and publishes nothing until its integrity monitor
//! reports it `tracking` (nav2_amcl would wait for an initial pose); and each update's integrity
//! goes to `/diagnostics` (OK tracking, WARN uncertain, ERROR lost).
//!
//! [`AmclNode`] is the node without I/O (messages in, messages out: unit-tested here);
//! [`run`] drives it on a [`Ros2Node`].

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;

use amr_core::amcl::IntegrityState;
use amr_core::amcl::log::{LogLocalizer, Start};
use amr_core::carmen::{LaserRecord, Record};
use amr_core::config::AmclParams;
use amr_core::config::nav2::Nav2Frames;
use amr_core::map::OccupancyGrid as Grid;
use amr_core::se2::Se2;
use amr_ros2::msg::{
    DiagnosticArray, DiagnosticStatus, Header, LaserScan, OccupancyGrid, Particle, ParticleCloud, Pose,
    PoseWithCovariance, PoseWithCovarianceStamped, Ros2Message, TfMessage, TransformStamped,
};
use amr_ros2::rmw_zenoh::Qos;
use amr_ros2::transport::{Ros2Error, Ros2Node, Ros2Publisher};

use super::bag::{mount, odom_at, planar, strip, to_scan};
use super::inputs::{Input, initial_pose_in};
use super::ros_covariance;

/// Scans waiting for their transform at most (nav2_amcl's message filter keeps 10).
pub const SCAN_QUEUE: usize = 10;
/// Odometry kept, s of it (tf2's buffer keeps 10 s).
pub const TF_CACHE_S: f64 = 10.0;

/// The node's settings.
#[derive(Debug, Clone)]
pub struct AmclNodeConfig {
    pub frames: Nav2Frames,
    pub params: AmclParams,
    /// Seed of the filter's draws.
    pub seed: u64,
}

/// What the node publishes.
#[derive(Debug, Clone, PartialEq)]
pub enum Output {
    Pose(Box<PoseWithCovarianceStamped>),
    Particles(ParticleCloud),
    Tf(TfMessage),
    Diagnostics(DiagnosticArray),
}

/// What happened to the scans.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NodeStats {
    pub scans: u64,
    /// Fed to the filter.
    pub used: u64,
    /// Dropped: no map yet.
    pub without_map: u64,
    /// Dropped: older than the odometry kept, or pushed out of the queue waiting for it.
    pub without_odometry: u64,
    /// Dropped: not a usable scan.
    pub unusable: u64,
    pub poses: u64,
}

/// The odometry and the mountings, as `/tf` and `/tf_static` told them.
#[derive(Debug, Default)]
struct TfBuffer {
    /// odom → base samples in stamp order, the last [`TF_CACHE_S`].
    odom: VecDeque<(f64, Se2)>,
    /// Every other transform, child → (parent, transform), the latest winning.
    links: BTreeMap<String, (String, Se2)>,
}

/// The odometry at a stamp.
#[derive(Debug, Clone, Copy, PartialEq)]
enum OdomAt {
    At(Se2),
    /// Not yet: `/tf` has not reached the stamp.
    Later,
    /// Before the odometry kept.
    Gone,
}

impl TfBuffer {
    fn add(&mut self, msg: &TfMessage, odom_frame: &str, base_frame: &str) {
        for t in &msg.transforms {
            let p = planar(t);
            if !(p.x.is_finite() && p.y.is_finite() && p.theta.is_finite()) {
                continue;
            }
            let (parent, child) = (strip(&t.header.frame_id), strip(&t.child_frame_id));
            if parent == odom_frame && child == base_frame {
                let stamp = t.header.stamp.secs();
                let at = self.odom.partition_point(|(s, _)| *s <= stamp);
                self.odom.insert(at, (stamp, p));
            } else {
                self.links.insert(child.to_owned(), (parent.to_owned(), p));
            }
        }
        let newest = self.odom.back().map_or(f64::NEG_INFINITY, |(s, _)| *s);
        while self.odom.front().is_some_and(|(s, _)| *s < newest - TF_CACHE_S) {
            self.odom.pop_front();
        }
    }

    fn odom_at(&mut self, t: f64) -> OdomAt {
        match (self.odom.front(), self.odom.back()) {
            (Some((first, _)), Some((last, _))) if (*first..=*last).contains(&t) => {
                odom_at(self.odom.make_contiguous(), t).map_or(OdomAt::Gone, OdomAt::At)
            }
            (Some((first, _)), _) if t < *first => OdomAt::Gone,
            _ => OdomAt::Later,
        }
    }
}

/// nav2_amcl without its I/O.
#[derive(Debug)]
pub struct AmclNode {
    config: AmclNodeConfig,
    tf: TfBuffer,
    localizer: Option<LogLocalizer<'static>>,
    /// Where the filter starts (again).
    start: Start,
    /// Whether a pose may be published: an initial pose was given, or the filter has tracked.
    pose_known: bool,
    pending: VecDeque<LaserScan>,
    /// The last pose published, with its spread: where a new map restarts the filter.
    last: Option<(Se2, f64, f64)>,
    /// Frames whose mounting was not found (warned once each).
    unmounted: Vec<String>,
    pub stats: NodeStats,
}

impl AmclNode {
    #[must_use]
    pub fn new(config: AmclNodeConfig) -> Self {
        let start = Start::resolve(None, &config.params);
        AmclNode {
            pose_known: matches!(start, Start::Pose { .. }),
            start,
            config,
            tf: TfBuffer::default(),
            localizer: None,
            pending: VecDeque::new(),
            last: None,
            unmounted: Vec::new(),
            stats: NodeStats::default(),
        }
    }

    /// A new map: the filter is rebuilt on it, at the last pose published if there is one.
    pub fn on_map(&mut self, m: &OccupancyGrid) -> Result<(), String> {
        let grid = grid_of(m)?;
        if strip(&m.header.frame_id) != self.config.frames.global_frame_id {
            tracing::warn!(frame = %m.header.frame_id, global = %self.config.frames.global_frame_id, "the map is not in the global frame");
        }
        if let Some((pose, std_xy_m, std_yaw_rad)) = self.last {
            self.start = Start::Pose { pose, std_xy_m, std_yaw_rad };
        }
        tracing::info!(
            width = grid.width,
            height = grid.height,
            resolution = grid.resolution_m,
            "map received"
        );
        self.localizer =
            Some(LogLocalizer::owning(grid, self.config.params.clone(), self.start, self.config.seed));
        Ok(())
    }

    /// A pose on `initialpose`: the filter starts again there.
    pub fn on_initial_pose(&mut self, m: &PoseWithCovarianceStamped) -> Result<(), String> {
        let Input::InitialPose { v, std_xy_m, std_yaw_rad } =
            initial_pose_in(m, &self.config.frames.global_frame_id)?
        else {
            return Err("not a pose".to_owned());
        };
        self.start = Start::Pose { pose: v, std_xy_m, std_yaw_rad };
        self.pose_known = true;
        if let Some(l) = &mut self.localizer {
            l.restart(self.start);
        }
        tracing::info!(x = v.x, y = v.y, theta = v.theta, "initial pose: the filter starts again there");
        Ok(())
    }

    /// Transforms (`/tf` or `/tf_static`); scans that waited for them are processed.
    pub fn on_tf(&mut self, m: &TfMessage) -> Vec<Output> {
        let f = &self.config.frames;
        self.tf.add(m, &f.odom_frame_id, &f.base_frame_id);
        self.process()
    }

    /// A scan: processed once `/tf` reaches its stamp.
    pub fn on_scan(&mut self, m: LaserScan) -> Vec<Output> {
        self.stats.scans += 1;
        if self.pending.len() == SCAN_QUEUE {
            self.pending.pop_front();
            self.stats.without_odometry += 1;
        }
        let at = self.pending.partition_point(|s| s.header.stamp.secs() <= m.header.stamp.secs());
        self.pending.insert(at, m);
        self.process()
    }

    fn process(&mut self) -> Vec<Output> {
        let mut out = Vec::new();
        while let Some(scan) = self.pending.front() {
            match self.tf.odom_at(scan.header.stamp.secs()) {
                OdomAt::Later => break,
                OdomAt::Gone => self.stats.without_odometry += 1,
                OdomAt::At(odom) => {
                    let Some(scan) = self.pending.pop_front() else { break };
                    self.update(&scan, odom, &mut out);
                    continue;
                }
            }
            self.pending.pop_front();
        }
        out
    }

    fn update(&mut self, m: &LaserScan, odom: Se2, out: &mut Vec<Output>) {
        let Some(localizer) = &mut self.localizer else {
            self.stats.without_map += 1;
            return;
        };
        let scan = match to_scan(m) {
            Ok(s) => s,
            Err(e) => {
                tracing::debug!(error = %e, "a scan that cannot be used");
                self.stats.unusable += 1;
                return;
            }
        };
        let frames = &self.config.frames;
        let frame = strip(&m.header.frame_id);
        let laser_in_robot = mount(&self.tf.links, &frames.base_frame_id, frame).unwrap_or_else(|| {
            if !self.unmounted.iter().any(|f| f == frame) {
                tracing::warn!(frame, base = %frames.base_frame_id, "no transform from the base to the scan's frame: the scan's frame is taken as the base");
                self.unmounted.push(frame.to_owned());
            }
            Se2::IDENTITY
        });
        let stamp = m.header.stamp.secs();
        let record = Record::Laser(Box::new(LaserRecord {
            scan,
            odometry: Some(odom),
            laser_in_robot,
            logged_pose: None,
            timestamp_s: stamp,
        }));
        self.stats.used += 1;
        let Some(fed) = localizer.feed(&record) else { return };
        let Some(p) = fed.pose else { return };
        let state = p.integrity.map(|i| i.state);
        if !self.pose_known && state == Some(IntegrityState::Tracking) {
            tracing::info!(x = p.pose.x, y = p.pose.y, theta = p.pose.theta, "localised globally");
            self.pose_known = true;
        }
        if !self.pose_known {
            return;
        }
        let global = &frames.global_frame_id;
        let updated = matches!(fed.outcome, amr_core::amcl::UpdateOutcome::Updated { .. });
        if updated || self.last.is_none() {
            let covariance = ros_covariance(Some(p.covariance));
            out.push(Output::Pose(Box::new(PoseWithCovarianceStamped {
                header: Header { stamp: m.header.stamp, frame_id: global.clone() },
                pose: PoseWithCovariance { pose: Pose::planar(p.pose.x, p.pose.y, p.pose.theta), covariance },
            })));
            self.stats.poses += 1;
            let spread = (p.covariance[0][0].max(p.covariance[1][1]).sqrt(), p.covariance[2][2].sqrt());
            self.last = Some((p.pose, spread.0, spread.1));
            if let Some(f) = localizer.filter() {
                let particles = f
                    .particles()
                    .iter()
                    .map(|q| Particle {
                        pose: Pose::planar(q.pose.x, q.pose.y, q.pose.theta),
                        weight: q.weight,
                    })
                    .collect();
                out.push(Output::Particles(ParticleCloud {
                    header: Header { stamp: m.header.stamp, frame_id: global.clone() },
                    particles,
                }));
            }
            if let Some(i) = p.integrity {
                out.push(Output::Diagnostics(diagnostics(stamp, i)));
            }
        }
        if frames.tf_broadcast {
            let map_odom = p.pose * odom.inverse();
            let t = TransformStamped::planar(
                stamp + frames.transform_tolerance_s,
                global,
                &frames.odom_frame_id,
                map_odom.x,
                map_odom.y,
                map_odom.theta,
            );
            out.push(Output::Tf(TfMessage { transforms: vec![t] }));
        }
    }
}

/// The integrity as `/diagnostics` shows it.
fn diagnostics(stamp: f64, i: amr_core::amcl::Integrity) -> DiagnosticArray {
    let level = match i.state {
        IntegrityState::Tracking => DiagnosticStatus::OK,
        IntegrityState::Uncertain => DiagnosticStatus::WARN,
        IntegrityState::Lost => DiagnosticStatus::ERROR,
    };
    DiagnosticArray {
        header: Header::new(stamp, ""),
        status: vec![DiagnosticStatus {
            level,
            name: "amcl: localisation".into(),
            message: i.state.to_string(),
            hardware_id: String::new(),
            values: vec![
                ("explained".into(), format!("{:.3}", i.explained)),
                ("level".into(), format!("{:.3}", i.level)),
                ("ambiguous".into(), i.ambiguous.to_string()),
            ],
        }],
    }
}

/// A map message as the filter's grid (its cells as nav2_amcl reads them: 0 free, 100 occupied,
/// anything else unknown), or why it cannot be one.
pub fn grid_of(m: &OccupancyGrid) -> Result<Grid, String> {
    let (w, h) = (m.width as usize, m.height as usize);
    let resolution = f64::from(m.resolution);
    if !(resolution.is_finite() && resolution > 0.0) {
        return Err(format!("a map with resolution {resolution}"));
    }
    if w.checked_mul(h) != Some(m.data.len()) || w == 0 {
        return Err(format!("a map of {w} × {h} cells with {} values", m.data.len()));
    }
    let (x, y, theta) = m.origin.planar_parts();
    if !(x.is_finite() && y.is_finite() && theta.is_finite()) {
        return Err("a map whose origin is not finite".to_owned());
    }
    Ok(Grid {
        width: w,
        height: h,
        resolution_m: resolution,
        origin: Se2::new(x, y, theta),
        cells: m.data.clone(),
    })
}

/// A topic name as nav2 gives it (relative names in the root namespace) made absolute.
fn absolute(topic: &str) -> String {
    if topic.starts_with('/') { topic.to_owned() } else { format!("/{topic}") }
}

/// The node's publishers.
struct Publishers {
    pose: Ros2Publisher,
    particles: Ros2Publisher,
    tf: Ros2Publisher,
    diagnostics: Ros2Publisher,
}

impl Publishers {
    fn put(&self, o: &Output) -> Result<(), Ros2Error> {
        match o {
            Output::Pose(m) => self.pose.put(m.to_cdr()),
            Output::Particles(m) => self.particles.put(m.to_cdr()),
            Output::Tf(m) => self.tf.put(m.to_cdr()),
            Output::Diagnostics(m) => self.diagnostics.put(m.to_cdr()),
        }
    }
}

/// Run the node on `node` until `stop` resolves (or the node's subscriptions end).
pub async fn run(
    node: Arc<Ros2Node>,
    config: AmclNodeConfig,
    stop: impl std::future::Future<Output = ()>,
) -> Result<NodeStats, Ros2Error> {
    let f = config.frames.clone();
    let scans = node.subscription(&absolute(&f.scan_topic), LaserScan::TYPE, Qos::SENSOR_DATA).await?;
    let maps = node.subscription(&absolute(&f.map_topic), OccupancyGrid::TYPE, Qos::LATCHED).await?;
    let poses = node.subscription("/initialpose", PoseWithCovarianceStamped::TYPE, Qos::reliable(10)).await?;
    let tf = node.subscription("/tf", TfMessage::TYPE, Qos::reliable(100)).await?;
    let tf_static = node.subscription("/tf_static", TfMessage::TYPE, Qos::LATCHED).await?;
    let publishers = Publishers {
        pose: node.publisher("/amcl_pose", PoseWithCovarianceStamped::TYPE, Qos::LATCHED).await?,
        particles: node.publisher("/particle_cloud", ParticleCloud::TYPE, Qos::SENSOR_DATA).await?,
        tf: node.publisher("/tf", TfMessage::TYPE, Qos::reliable(100)).await?,
        diagnostics: node.publisher("/diagnostics", DiagnosticArray::TYPE, Qos::reliable(10)).await?,
    };
    let mut amcl = AmclNode::new(config);
    tokio::pin!(stop);
    let mut refused = 0_u64;
    loop {
        let outputs = tokio::select! {
            () = &mut stop => break,
            m = scans.recv() => match m.map(|b| LaserScan::from_cdr(&b)) {
                None => break,
                Some(Ok(s)) => amcl.on_scan(s),
                Some(Err(e)) => { refused += 1; tracing::debug!(error = %e, "a scan that does not decode"); Vec::new() }
            },
            m = maps.recv() => match m.map(|b| OccupancyGrid::from_cdr(&b).map_err(|e| e.to_string()).and_then(|g| amcl.on_map(&g))) {
                None => break,
                Some(Ok(())) => Vec::new(),
                Some(Err(e)) => { refused += 1; tracing::warn!(error = %e, "a map refused"); Vec::new() }
            },
            m = poses.recv() => match m.map(|b| PoseWithCovarianceStamped::from_cdr(&b).map_err(|e| e.to_string()).and_then(|p| amcl.on_initial_pose(&p))) {
                None => break,
                Some(Ok(())) => Vec::new(),
                Some(Err(e)) => { refused += 1; tracing::warn!(error = %e, "an initial pose refused"); Vec::new() }
            },
            m = tf.recv() => match m.map(|b| TfMessage::from_cdr(&b)) {
                None => break,
                Some(Ok(t)) => amcl.on_tf(&t),
                Some(Err(e)) => { refused += 1; tracing::debug!(error = %e, "a /tf message that does not decode"); Vec::new() }
            },
            m = tf_static.recv() => match m.map(|b| TfMessage::from_cdr(&b)) {
                None => break,
                Some(Ok(t)) => amcl.on_tf(&t),
                Some(Err(e)) => { refused += 1; tracing::debug!(error = %e, "a /tf_static message that does not decode"); Vec::new() }
            },
        };
        for o in &outputs {
            if let Err(e) = publishers.put(o) {
                tracing::debug!(error = %e, "a message was not sent");
            }
        }
    }
    if refused > 0 {
        tracing::warn!(messages = refused, "messages refused (not decodable or not usable)");
    }
    Ok(amcl.stats)
}

#[cfg(test)]
mod tests;
