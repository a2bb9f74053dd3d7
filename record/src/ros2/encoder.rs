//! The fleet's events as ROS 2 messages ([`Ros2Encoder`]): what `--record FILE --ros2` writes and
//! `--ros2-live` publishes (the topics are in the module above).

use std::collections::VecDeque;

use amr_core::map::OccupancyGrid as Grid;
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use amr_msgs::{EstimateSource, Uplink};

use super::msg::{
    self, DiagnosticArray, DiagnosticStatus, Header, LaserScan, OccupancyGrid, Odometry, Pose,
    PoseWithCovariance, PoseWithCovarianceStamped, Ros2Message, TfMessage, TransformStamped,
    TwistWithCovariance,
};
use super::topic_name;
use crate::encode::{Event, Out};
use crate::foxglove::nanos;

/// A `sensor_msgs/LaserScan` of a device scan: its own geometry, invalid beams NaN (REP 117's
/// "erroneous or invalid"; the scan does not say which were no-returns).
#[must_use]
pub fn laser_scan(stamp_s: f64, frame: &str, scan: &Scan) -> LaserScan {
    let n = scan.len();
    LaserScan {
        header: Header::new(stamp_s, frame),
        angle_min: scan.angle_min_rad as f32,
        angle_max: (scan.angle_min_rad + scan.angle_increment_rad * n.saturating_sub(1) as f64) as f32,
        angle_increment: scan.angle_increment_rad as f32,
        time_increment: 0.0,
        scan_time: 0.0,
        range_min: scan.range_min_m as f32,
        range_max: scan.range_max_m as f32,
        ranges: scan.ranges_m().iter().map(|r| *r as f32).collect(),
        intensities: Vec::new(),
    }
}

/// The virtual scan as a `sensor_msgs/LaserScan`: the Foxglove view's bins
/// ([`crate::foxglove::virtual_bins`]), empty bins NaN, `range_max` the farthest bin.
#[must_use]
pub fn points_scan(stamp_s: f64, frame: &str, points: &[[f64; 2]]) -> LaserScan {
    let (start, step, bins) = crate::foxglove::virtual_bins(points);
    let n = bins.len();
    let far = bins.iter().copied().fold(0.0f64, f64::max);
    LaserScan {
        header: Header::new(stamp_s, frame),
        angle_min: start as f32,
        angle_max: (start + step * n.saturating_sub(1) as f64) as f32,
        angle_increment: step as f32,
        time_increment: 0.0,
        scan_time: 0.0,
        range_min: 0.0,
        range_max: far.max(1.0) as f32,
        ranges: bins.iter().map(|r| if *r > 0.0 { *r as f32 } else { f32::NAN }).collect(),
        intensities: Vec::new(),
    }
}

fn pose_stamped(stamp_s: f64, frame: &str, p: &Se2, cov: Option<[[f64; 3]; 3]>) -> PoseWithCovarianceStamped {
    PoseWithCovarianceStamped {
        header: Header::new(stamp_s, frame),
        pose: PoseWithCovariance { pose: Pose::planar(p.x, p.y, p.theta), covariance: ros_covariance(cov) },
    }
}

/// A planar covariance (x, y, heading) as ROS's 6×6 row-major one (x, y, z, and rotations about x,
/// y, z): z and the tilts zero. None: all zero, ROS's "unknown".
#[must_use]
pub fn ros_covariance(cov: Option<[[f64; 3]; 3]>) -> [f64; 36] {
    let mut out = [0.0; 36];
    if let Some(c) = cov {
        let at = [0, 1, 5];
        for (i, row) in c.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                out[at[i] * 6 + at[j]] = *v;
            }
        }
    }
    out
}

/// The covariance of `v ∘ b` (a pose rigidly offset by `b` from `v`) from `v`'s: the first-order
/// propagation J Σ Jᵀ with J the Jacobian of the composition in `v`. What a robot placed by V
/// inherits from V's uncertainty (the fusion's own uncertainty of `b` is not in it).
#[must_use]
pub fn offset_covariance(cov: [[f64; 3]; 3], v: &Se2, b: &Se2) -> [[f64; 3]; 3] {
    let (s, c) = v.theta.sin_cos();
    let j = [[1.0, 0.0, -s * b.x - c * b.y], [0.0, 1.0, c * b.x - s * b.y], [0.0, 0.0, 1.0]];
    let mut js = [[0.0; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            js[i][k] = (0..3).map(|m| j[i][m] * cov[m][k]).sum();
        }
    }
    let mut out = [[0.0; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            out[i][k] = (0..3).map(|m| js[i][m] * j[k][m]).sum();
        }
    }
    out
}

fn tf(stamp_s: f64, parent: &str, child: &str, p: &Se2) -> TransformStamped {
    TransformStamped::planar(stamp_s, parent, child, p.x, p.y, p.theta)
}

/// The map as a `nav_msgs/OccupancyGrid`: same cell order (row-major from the origin's row).
#[must_use]
pub fn occupancy_grid(stamp_s: f64, map: &Grid) -> OccupancyGrid {
    OccupancyGrid {
        header: Header::new(stamp_s, "map"),
        map_load_time: msg::Time::from_secs(stamp_s),
        resolution: map.resolution_m as f32,
        width: u32::try_from(map.width).unwrap_or(u32::MAX),
        height: u32::try_from(map.height).unwrap_or(u32::MAX),
        origin: Pose::planar(map.origin.x, map.origin.y, map.origin.theta),
        data: map.cells.clone(),
    }
}

/// Turns events into ROS 2 messages (the table in the module docs).
#[derive(Debug, Clone)]
pub struct Ros2Encoder {
    robots: Vec<String>,
    /// V's odometry (`V/odom` → `V`) at the last fused frames, by stamp, and V's estimates whose
    /// frame has not come yet (a frame and its estimate come on two ports, in either order): each
    /// pair makes one `map` → `V/odom`.
    v_odoms: VecDeque<(f64, Se2)>,
    v_pending: VecDeque<(f64, Se2)>,
    /// Publish `map` → `V/odom` from our estimate of V; off when nav2_amcl localises V (it
    /// publishes that transform itself).
    v_map_tf: bool,
    /// V's integrity as last put on `/diagnostics`, and when: it goes out on a change, else at
    /// most once a second (estimates come at the scan rate).
    v_diag: Option<(f64, amr_msgs::IntegrityState, Option<u32>)>,
}

impl Ros2Encoder {
    /// `robots`: the formation's ids in order (names the estimates' robots).
    #[must_use]
    pub fn new(robots: Vec<String>) -> Self {
        Ros2Encoder {
            robots,
            v_odoms: VecDeque::new(),
            v_pending: VecDeque::new(),
            v_map_tf: true,
            v_diag: None,
        }
    }

    /// Leave `map` → `V/odom` to another localiser (nav2_amcl on `/virtual/scan`).
    #[must_use]
    pub fn without_v_map_tf(mut self) -> Self {
        self.v_map_tf = false;
        self
    }

    fn robot_name(&self, i: usize) -> String {
        self.robots.get(i).cloned().unwrap_or_else(|| format!("robot{i}"))
    }

    /// V's integrity as a diagnostic status: tracking and agreed with the robots' own estimates
    /// OK, uncertain or disagreeing WARN (the formation holds), lost ERROR.
    fn v_integrity_status(&self, i: &amr_msgs::EstimateIntegrity) -> DiagnosticStatus {
        use amr_msgs::IntegrityState as S;
        let disagrees = i.disagrees.map(|k| self.robot_name(k as usize));
        let (level, message) = match (i.state, &disagrees) {
            (S::Lost, _) => (DiagnosticStatus::ERROR, "lost: re-localising".to_owned()),
            (S::Uncertain, _) if i.ambiguous => {
                (DiagnosticStatus::WARN, "uncertain: another place explains the scans as well".to_owned())
            }
            (S::Uncertain, _) => {
                (DiagnosticStatus::WARN, "uncertain: the map explains too little of the scan".to_owned())
            }
            (S::Tracking, Some(r)) => {
                (DiagnosticStatus::WARN, format!("tracking, but {r}'s own estimate disagrees"))
            }
            (S::Tracking, None) => (DiagnosticStatus::OK, "tracking".to_owned()),
        };
        let mut values = vec![
            ("state".to_owned(), i.state.as_str().to_owned()),
            ("explained".to_owned(), format!("{:.3}", i.explained)),
            ("level".to_owned(), format!("{:.3}", i.level)),
            ("ambiguous".to_owned(), i.ambiguous.to_string()),
        ];
        if let Some(r) = disagrees {
            values.push(("disagrees".to_owned(), r));
        }
        DiagnosticStatus {
            level,
            name: "amr: V localisation".into(),
            message,
            hardware_id: "V".into(),
            values,
        }
    }

    /// The messages for `event`, seen at `now_s` on the fleet clock.
    #[must_use]
    pub fn encode(&mut self, now_s: f64, event: &Event) -> Vec<Out> {
        let mut b = Batch { log_time_ns: nanos(now_s), out: Vec::new() };
        match event {
            Event::Uplink(Uplink::Scan(s), _) | Event::Scan(s) => {
                let frame = format!("{}/laser", s.robot);
                b.emit(&format!("/{}/scan", s.robot), s.stamp_s, &laser_scan(s.stamp_s, &frame, &s.scan));
            }
            Event::Uplink(Uplink::Odom { robot, msg: o }, _) | Event::Odom(robot, o) => {
                Self::odom(&mut b, robot, o)
            }
            Event::Fused(f) => {
                if let Some(points) = &f.points {
                    b.emit("/virtual/scan", f.stamp_s, &points_scan(f.stamp_s, "V", points));
                }
                // V's odometry, as a robot's: `V/odom` → `V` (REP 105), for a localiser of V.
                let mut transforms = vec![tf(f.stamp_s, "V/odom", "V", &f.v_odom)];
                if let Some(k) = self.v_pending.iter().position(|(t, _)| *t == f.stamp_s)
                    && let Some((_, vm)) = self.v_pending.remove(k)
                {
                    transforms.push(tf(f.stamp_s, "map", "V/odom", &(vm * f.v_odom.inverse())));
                }
                push_bounded(&mut self.v_odoms, (f.stamp_s, f.v_odom));
                b.emit("/tf", f.stamp_s, &TfMessage { transforms });
            }
            Event::Estimate(e) => match e.source {
                EstimateSource::Fused(_) => self.v_estimate(&mut b, e),
                EstimateSource::Robot(i) => {
                    if let Some(Some(a)) = e.robots.get(i) {
                        let topic = format!("/amcl/{}/own", self.robot_name(i));
                        b.emit(&topic, e.stamp_s, &pose_stamped(e.stamp_s, "map", &a.map, e.covariance));
                    }
                }
            },
            Event::Truth { stamp_s, v: vt, robots } => {
                b.emit("/truth/V", *stamp_s, &pose_stamped(*stamp_s, "map", vt, None));
                let mut transforms = vec![tf(*stamp_s, "map", "truth/V", vt)];
                for (i, p) in robots.iter().enumerate() {
                    let name = self.robot_name(i);
                    b.emit(&format!("/truth/{name}"), *stamp_s, &pose_stamped(*stamp_s, "map", p, None));
                    transforms.push(tf(*stamp_s, "map", &format!("truth/{name}"), p));
                }
                b.emit("/tf", *stamp_s, &TfMessage { transforms });
            }
            Event::Formation(f) => Self::formation(&mut b, now_s, f),
            Event::Map(g) => b.emit("/map", now_s, &occupancy_grid(now_s, g)),
            Event::Mounts(mounts) => {
                let transforms = mounts.iter().map(|(r, p)| tf(now_s, r, &format!("{r}/laser"), p)).collect();
                b.emit("/tf_static", now_s, &TfMessage { transforms });
            }
            // No ROS 2 type here: see the module docs.
            Event::Uplink(..)
            | Event::Status(_)
            | Event::Particles(_)
            | Event::Command(..)
            | Event::Imu(..)
            | Event::Wheels(..)
            | Event::Health(..)
            | Event::Safety(..)
            | Event::Downlink(..)
            | Event::Log(_)
            | Event::EvalEstimate { .. }
            | Event::EvalVirtualScan { .. } => {}
        }
        b.out
    }

    /// A robot's odometry, and `<robot>/odom` → `<robot>` on `/tf`.
    fn odom(b: &mut Batch, robot: &str, o: &amr_msgs::OdomMsg) {
        let frame = format!("{robot}/odom");
        let odom = Odometry {
            header: Header::new(o.stamp_s, &frame),
            child_frame_id: robot.to_owned(),
            pose: PoseWithCovariance {
                pose: Pose::planar(o.pose.x, o.pose.y, o.pose.theta),
                covariance: [0.0; 36],
            },
            twist: TwistWithCovariance {
                linear: [o.twist.0, 0.0, 0.0],
                angular: [0.0, 0.0, o.twist.1],
                covariance: [0.0; 36],
            },
        };
        b.emit(&format!("/{robot}/odom"), o.stamp_s, &odom);
        let transforms = vec![tf(o.stamp_s, &frame, robot, &o.pose)];
        b.emit("/tf", o.stamp_s, &TfMessage { transforms });
    }

    /// V's estimate with its covariance, each robot's place in it, `map` → `V/odom` and each
    /// robot's `map` → `<robot>/odom`, and V's integrity on `/diagnostics` (on a change, else once
    /// a second).
    fn v_estimate(&mut self, b: &mut Batch, e: &amr_msgs::Estimate) {
        let mut transforms = Vec::new();
        if let Some(vm) = &e.v {
            b.emit("/amcl/V", e.stamp_s, &pose_stamped(e.stamp_s, "map", vm, e.covariance));
            // `map` → `V/odom` at the frame of the same stamp (here, or when it comes).
            if self.v_map_tf {
                match self.v_odoms.iter().find(|(t, _)| *t == e.stamp_s) {
                    Some((_, vo)) => transforms.push(tf(e.stamp_s, "map", "V/odom", &(*vm * vo.inverse()))),
                    None => push_bounded(&mut self.v_pending, (e.stamp_s, *vm)),
                }
            }
        }
        for (i, a) in e.robots.iter().enumerate() {
            let Some(a) = a else { continue };
            let name = self.robot_name(i);
            let cov = e.v.zip(e.covariance).map(|(v, c)| offset_covariance(c, &v, &(v.inverse() * a.map)));
            b.emit(&format!("/amcl/{name}"), e.stamp_s, &pose_stamped(e.stamp_s, "map", &a.map, cov));
            let map_odom = a.map * a.odom.inverse();
            transforms.push(tf(e.stamp_s, "map", &format!("{name}/odom"), &map_odom));
        }
        if !transforms.is_empty() {
            b.emit("/tf", e.stamp_s, &TfMessage { transforms });
        }
        let i = e.integrity;
        let changed = self.v_diag.is_none_or(|(t, st, d)| {
            st != i.state || d != i.disagrees || e.stamp_s - t >= 1.0 || e.stamp_s < t
        });
        if changed {
            self.v_diag = Some((e.stamp_s, i.state, i.disagrees));
            let status = self.v_integrity_status(&i);
            b.emit(
                "/diagnostics",
                e.stamp_s,
                &DiagnosticArray { header: Header::new(e.stamp_s, ""), status: vec![status] },
            );
        }
    }

    /// The formation's phase, its reason and the plan's progress on `/diagnostics`.
    fn formation(b: &mut Batch, now_s: f64, f: &amr_actors::server::formation::FormationStatus) {
        let (level, text) = crate::encode::formation_line(f);
        let mut values = vec![
            ("plan_s".to_owned(), format!("{:.2}", f.plan_s)),
            ("plan_len_s".to_owned(), format!("{:.2}", f.plan_len_s)),
        ];
        if let Some(i) = f.v_integrity {
            values.push(("v_integrity".to_owned(), i.state.as_str().to_owned()));
        }
        let status = DiagnosticStatus {
            level: diagnostic_level(level),
            name: "amr: formation".into(),
            message: text,
            hardware_id: "V".into(),
            values,
        };
        b.emit(
            "/diagnostics",
            now_s,
            &DiagnosticArray { header: Header::new(now_s, ""), status: vec![status] },
        );
    }
}

/// The messages of one event.
/// A log level as a diagnostic level.
fn diagnostic_level(l: crate::foxglove::Level) -> u8 {
    use crate::foxglove::Level;
    match l {
        Level::Error | Level::Fatal => DiagnosticStatus::ERROR,
        Level::Warning => DiagnosticStatus::WARN,
        _ => DiagnosticStatus::OK,
    }
}

/// Frames or estimates kept to pair at most (a few fusion periods).
const PAIRING: usize = 16;

fn push_bounded(q: &mut VecDeque<(f64, Se2)>, x: (f64, Se2)) {
    if q.len() == PAIRING {
        q.pop_front();
    }
    q.push_back(x);
}

struct Batch {
    log_time_ns: u64,
    out: Vec<Out>,
}

impl Batch {
    fn emit<M: Ros2Message>(&mut self, topic: &str, stamp_s: f64, msg: &M) {
        self.out.push(Out {
            topic: topic_name(topic),
            schema: M::TYPE,
            log_time_ns: self.log_time_ns,
            publish_time_ns: nanos(stamp_s),
            data: msg.to_cdr(),
        });
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
    use super::*;

    #[test]
    fn an_offset_pose_inherits_vs_covariance_by_the_composition_s_jacobian() {
        let cov = [[0.04, 0.01, 0.003], [0.01, 0.09, -0.002], [0.003, -0.002, 0.0025]];
        let (v, b) = (Se2::new(3.0, -1.0, 0.7), Se2::new(0.4, -0.6, 0.2));
        // The Jacobian by central differences of v ∘ b in (x, y, θ) of v.
        let h = 1e-6;
        let mut j = [[0.0; 3]; 3];
        for k in 0..3 {
            let mut d = [0.0; 3];
            d[k] = h;
            let plus = Se2::new(v.x + d[0], v.y + d[1], v.theta + d[2]) * b;
            let minus = Se2::new(v.x - d[0], v.y - d[1], v.theta - d[2]) * b;
            let diff = [plus.x - minus.x, plus.y - minus.y, plus.theta - minus.theta];
            for (i, di) in diff.iter().enumerate() {
                j[i][k] = di / (2.0 * h);
            }
        }
        let got = offset_covariance(cov, &v, &b);
        for i in 0..3 {
            for k in 0..3 {
                let want: f64 = (0..3)
                    .flat_map(|m| (0..3).map(move |n| (m, n)))
                    .map(|(m, n)| j[i][m] * cov[m][n] * j[k][n])
                    .sum();
                assert!((got[i][k] - want).abs() < 1e-9, "[{i}][{k}]: {} vs {want}", got[i][k]);
            }
        }
        // No offset: the same covariance.
        assert_eq!(offset_covariance(cov, &v, &Se2::IDENTITY), cov);
        // ROS's layout; none: all zero.
        let r = ros_covariance(Some(cov));
        assert_eq!((r[0], r[1], r[5], r[30], r[35], r[14]), (0.04, 0.01, 0.003, 0.003, 0.0025, 0.0));
        assert_eq!(ros_covariance(None), [0.0; 36]);
    }

    /// The `map` → `V/odom` transforms of a run of events.
    fn v_map_tfs(enc: &mut Ros2Encoder, events: &[Event]) -> Vec<(f64, Se2)> {
        let mut out = Vec::new();
        for ev in events {
            for o in enc.encode(0.0, ev).iter().filter(|o| o.topic == "/tf") {
                for t in TfMessage::from_cdr(&o.data).unwrap().transforms {
                    if t.header.frame_id == "map" && t.child_frame_id == "V/odom" {
                        let [x, y, _] = t.translation;
                        out.push((t.header.stamp.secs(), Se2::new(x, y, msg::yaw(t.rotation))));
                    }
                }
            }
        }
        out
    }

    #[test]
    fn vs_map_to_odom_pairs_each_estimate_with_its_frame_in_either_order() {
        use amr_core::config::Configuration;
        use amr_msgs::{Estimate, EstimateIntegrity, FusedFrame, StageTimes};
        let frame = |t: f64, vo: Se2| {
            Event::Fused(FusedFrame {
                seq: 1,
                configuration: Configuration::T4,
                stamp_s: t,
                oldest_stamp_s: t,
                v_odom: vo,
                points: None,
                robots: vec![],
                times: StageTimes::default(),
            })
        };
        let estimate = |t: f64, v: Se2| {
            Event::Estimate(Estimate {
                source: EstimateSource::Fused(Configuration::T4),
                stamp_s: t,
                v: Some(v),
                robots: vec![],
                integrity: EstimateIntegrity::default(),
                covariance: None,
            })
        };
        let (vo1, vo2, v1, v2) = (
            Se2::new(1.0, 0.0, 0.1),
            Se2::new(1.2, 0.1, 0.2),
            Se2::new(5.0, 2.0, 1.0),
            Se2::new(5.2, 2.1, 1.1),
        );
        // Frame then estimate, then estimate then frame; a frame with no estimate gives nothing.
        let events =
            [frame(1.0, vo1), estimate(1.0, v1), estimate(2.0, v2), frame(3.0, vo1), frame(2.0, vo2)];
        let got = v_map_tfs(&mut Ros2Encoder::new(vec![]), &events);
        assert_eq!(got.len(), 2, "{got:?}");
        for ((t, m), (t_want, v, vo)) in got.iter().zip([(1.0, v1, vo1), (2.0, v2, vo2)]) {
            let want = v * vo.inverse();
            assert!(
                *t == t_want && (m.x - want.x).abs() < 1e-9 && (m.y - want.y).abs() < 1e-9,
                "{m:?} {want:?}"
            );
            assert!((amr_core::se2::angle_diff(m.theta, want.theta)).abs() < 1e-9);
        }
        // nav2_amcl publishes it: none from us.
        assert!(v_map_tfs(&mut Ros2Encoder::new(vec![]).without_v_map_tf(), &events).is_empty());
    }

    #[test]
    fn a_scan_keeps_its_geometry_and_invalid_beams() {
        let s = Scan::new(-1.0, 0.25, 0.05, 10.0, vec![1.0, f64::NAN, 20.0, 2.0]);
        let m = LaserScan::from_cdr(&laser_scan(3.5, "a/laser", &s).to_cdr()).unwrap();
        assert_eq!(m.angle_min, -1.0);
        assert_eq!(m.angle_increment, 0.25);
        assert_eq!(m.angle_max, -0.25);
        assert_eq!(m.ranges[0], 1.0);
        assert!(m.ranges[1].is_nan() && m.ranges[2].is_nan());
        assert_eq!(m.header.frame_id, "a/laser");
    }
}
