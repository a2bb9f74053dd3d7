//! The server's localisation without its actors, sans-IO: uplink messages in (with the time they
//! were received), fused frames, estimates and lost robots out. It holds everything that decides an
//! estimate — the scan buffers and sync gate, one Virtual-AMR pipeline per configuration, every
//! robot's own AMCL and one AMCL per virtual scan — so the server's localizer actor, `amr replay`
//! and `amr eval` all run this one code and give the same estimates for the same input.
//!
//! Order within one scan, the same everywhere: the robot's own AMCL first (its `T_odom^map`
//! correction), then the fusion with that correction (T1–T3 take relative poses from AMCL), then,
//! for each fused frame, AMCL on the virtual scan.
//!
//! Several configurations can run side by side on the same scans (`amr eval` compares T1–T4 this
//! way); the server runs one. Each filter owns its generator: robot `i`'s is seeded `seed + 1 + i`,
//! every virtual-scan filter `seed`, so a configuration's estimates do not depend on which others
//! run beside it.

use std::collections::VecDeque;
use std::sync::Arc;

use amr_core::amcl::{Amcl, LikelihoodField, UpdateOutcome, scan_points};
use amr_core::config::{AmclMotion, AmclParams, Configuration, IntegrityChecks, VamrParams};
use amr_core::geometry::Polygon;
use amr_core::se2::Se2;
use amr_core::vamr::frame::virtual_frame;
use amr_core::vamr::pipeline::{Oracle, Pipeline, Stage, UpdateError};
use amr_msgs::{
    Anchored, Estimate, EstimateIntegrity, EstimateSource, FusedFrame, MAX_BEAMS, ScanMsg, Uplink,
};

/// Scans kept per robot for pairing.
const BUFFER: usize = 3;

/// What the server accepts of a scan: limits wide enough for any 2D LiDAR a robot of ours could
/// carry (the TiM551: 271 beams 1° apart over 270°, 0.05–10 m; the densest common scanners
/// step about 0.1°), narrow enough that no scan can make the pipeline allocate without bound or
/// divide by nothing. At most [`MAX_BEAMS`] beams.
/// Smallest and largest angle between beams, rad (0.03° and 11.5°).
pub const MIN_ANGLE_STEP_RAD: f64 = 5e-4;
pub const MAX_ANGLE_STEP_RAD: f64 = 0.2;
/// Longest measuring range a scan may claim, m.
pub const MAX_RANGE_M: f64 = 100.0;
/// A scan stamped later than this after it was received is refused: the robot's clock is ahead
/// (its stamps would hold back every later scan of that robot), s.
pub const MAX_FUTURE_S: f64 = 0.5;

/// How far outside a teammate's outline its own filter's returns are still taken for its body:
/// the robots' estimates err by a few centimetres, and the teammate's newest scan (whose pose is
/// used) may be a scan period (67 ms for a TiM551, 1.5 cm at 0.22 m/s) older or newer, m.
pub(crate) const TEAMMATE_MARGIN_M: f64 = 0.1;

/// How long after the fusion last placed the robots its placement is carried on by odometry for the
/// teammate masks, s (then the robots' own estimates place them).
pub(crate) const PLACED_FOR_S: f64 = 2.0;

/// Spread of the initial particle clouds (a pose given by the operator or the scenario).
pub(crate) const INITIAL_STD_XY_M: f64 = 0.1;
pub(crate) const INITIAL_STD_YAW_RAD: f64 = 0.05;

/// One formation member as the fusion sees it.
#[derive(Debug, Clone)]
pub struct Member {
    pub id: String,
    pub lidar_to_base: Se2,
    pub chassis: Polygon,
    pub weight: f64,
    /// Its slot: lateral offset in V (for the expected search area).
    pub slot_y_m: f64,
}

/// Everything the core is built from.
#[derive(Debug, Clone)]
pub struct CoreSetup {
    /// In formation order; robot 0 is the reference.
    pub members: Vec<Member>,
    /// Run side by side on the same scans; each gives its own fused frames and estimates.
    pub configurations: Vec<Configuration>,
    pub vamr: VamrParams,
    /// The sync gate (Eq. 15): most spread of a set's stamps, and most age at fusion, s.
    pub max_spread_s: f64,
    pub max_age_s: f64,
    pub amcl: AmclParams,
    pub field: Arc<LikelihoodField>,
    /// Where the formation starts in the map: the origin of the slots. Each robot's own filter
    /// starts at its slot, a virtual-scan filter at V (the slots' weighted centroid).
    pub initial_v: Se2,
    pub seed: u64,
    /// Estimates replaced by the truth given with [`ServerCore::set_truth`]: evaluations only
    /// (the error budget); the server runs with none.
    pub oracle: Oracle,
    /// How V's estimate is started and cross-checked (`server.toml` `[integrity]`).
    pub checks: IntegrityChecks,
}

/// The end of a piece of work in [`ServerCore::offer`], for timing by the caller (the core has no
/// clock): the time since the previous lap belongs to it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lap {
    /// A robot's own AMCL update.
    RobotAmcl,
    /// A stage of one configuration's Virtual-AMR pipeline.
    Pipeline(Configuration, Stage),
    /// AMCL on that configuration's virtual scan (or V from robot 0's AMCL, in T1).
    VirtualAmcl(Configuration),
}

/// One configuration's fusion of a set of scans.
#[derive(Debug, Clone)]
pub struct Fusion {
    pub configuration: Configuration,
    pub result: Result<FusedFrame, UpdateError>,
    /// The heading search swept the full circle (first acquisition or a re-acquisition).
    pub full_search: bool,
    /// The heading search failed and the previous heading was kept.
    pub heading_failed: bool,
}

/// What one uplink message did.
#[derive(Debug, Default)]
pub struct Step {
    /// The formation index of the robot it came from (a scan of a formation member).
    pub robot: Option<usize>,
    /// The robot's own estimate, then each fused one.
    pub estimates: Vec<Estimate>,
    /// One per configuration, when the scan completed a set.
    pub fusions: Vec<Fusion>,
    /// Filters whose particles moved (an update ran).
    pub updated: Vec<EstimateSource>,
    /// The robot had been lost and is back (its track is re-acquired with the full heading search);
    /// the flag: no robot is lost any more.
    pub back: Option<bool>,
    /// Why a scan was not used.
    pub refused: Option<Refusal>,
    /// The robot's odometry started a new frame (it restarted): its filters were re-anchored.
    pub odometry_restarted: bool,
}

/// Why the core did not use a scan.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Refusal {
    #[error("robot `{0}` is not in the formation")]
    UnknownRobot(String),
    #[error("a scan without odometry")]
    NoOdometry,
    #[error("{0} beams (1..={MAX_BEAMS})")]
    BeamCount(usize),
    #[error(
        "angle step {0} rad (|step| in {MIN_ANGLE_STEP_RAD}..={MAX_ANGLE_STEP_RAD}, the sweep at most a turn)"
    )]
    AngleStep(f64),
    #[error("first beam angle {0} rad (within ±2π)")]
    AngleMin(f64),
    #[error("measuring range {0}..{1} m (0 <= min < max <= {MAX_RANGE_M})")]
    Range(f64, f64),
    #[error("stamp {stamp_s} s, received at {rx_s} s (finite, at most {MAX_FUTURE_S} s ahead)")]
    Stamp { stamp_s: f64, rx_s: f64 },
    #[error("a non-finite odometry pose")]
    Odometry,
    #[error("a scan not newer than the robot's last (duplicate or reordered)")]
    NotNewer,
}

impl Refusal {
    /// A short name for counters.
    #[must_use]
    pub fn kind(&self) -> &'static str {
        match self {
            Refusal::UnknownRobot(_) => "unknown-robot",
            Refusal::NoOdometry | Refusal::Odometry => "odometry",
            Refusal::BeamCount(_) | Refusal::AngleStep(_) | Refusal::AngleMin(_) | Refusal::Range(..) => {
                "geometry"
            }
            Refusal::Stamp { .. } => "stamp",
            Refusal::NotNewer => "not-newer",
        }
    }
}

/// A scan from the link, checked against what any real sensor can send.
fn check_scan(s: &ScanMsg, rx_s: f64) -> Result<Se2, Refusal> {
    let scan = &s.scan;
    let n = scan.len();
    if n == 0 || n > MAX_BEAMS {
        return Err(Refusal::BeamCount(n));
    }
    let step = scan.angle_increment_rad;
    let sweep = step.abs() * (n - 1) as f64;
    if !(step.is_finite() && (MIN_ANGLE_STEP_RAD..=MAX_ANGLE_STEP_RAD).contains(&step.abs()))
        || sweep > std::f64::consts::TAU
    {
        return Err(Refusal::AngleStep(step));
    }
    if !(scan.angle_min_rad.is_finite() && scan.angle_min_rad.abs() <= std::f64::consts::TAU) {
        return Err(Refusal::AngleMin(scan.angle_min_rad));
    }
    let (lo, hi) = (scan.range_min_m, scan.range_max_m);
    if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo < hi && hi <= MAX_RANGE_M) {
        return Err(Refusal::Range(lo, hi));
    }
    if !(s.stamp_s.is_finite() && rx_s.is_finite() && s.stamp_s <= rx_s + MAX_FUTURE_S) {
        return Err(Refusal::Stamp { stamp_s: s.stamp_s, rx_s });
    }
    let odom = s.odom.ok_or(Refusal::NoOdometry)?;
    if !(odom.x.is_finite() && odom.y.is_finite() && odom.theta.is_finite()) {
        return Err(Refusal::Odometry);
    }
    Ok(odom)
}

#[derive(Debug)]
struct Channel {
    configuration: Configuration,
    pipeline: Pipeline,
    /// AMCL on the virtual scan (T2–T4).
    filter: Option<Amcl>,
    /// The filter has been started from the robots' own estimates.
    started: bool,
    /// When this configuration last fused a set of scans (receive time), s.
    last_fused_s: Option<f64>,
    /// When V's filter, lost, last started again from the robots' estimates (receive time), s.
    last_restart_s: Option<f64>,
    seq: u64,
}

/// A scan as the core keeps it.
#[derive(Debug, Clone)]
struct Held {
    scan: Arc<amr_core::scan::Scan>,
    stamp_s: f64,
    rx_s: f64,
    odom: Se2,
    /// The true pose at the scan (evaluations only).
    truth: Option<Se2>,
}

/// The server's localisation (see the module documentation).
#[derive(Debug)]
pub struct ServerCore {
    members: Vec<Member>,
    amcl: AmclParams,
    robot_filters: Vec<Amcl>,
    /// Whose motion the virtual-scan filters' motion model samples (`fusion.amcl_motion`).
    amcl_motion: AmclMotion,
    /// Per robot: map ← odometry from its own AMCL.
    corrections: Vec<Option<Se2>>,
    channels: Vec<Channel>,
    /// Per robot: recent scans.
    scans: Vec<VecDeque<Held>>,
    /// Per robot: stamp of its last fused scan.
    fused_stamp: Vec<f64>,
    lost: Vec<bool>,
    /// Per robot: the odometry frame of its last scan (0: none yet).
    odom_frames: Vec<u64>,
    oracle: Oracle,
    /// Per robot: the true pose of its next scan (evaluations only).
    truth: Vec<Option<Se2>>,
    checks: IntegrityChecks,
    /// The sync gate's spread (`CoreSetup::max_spread_s`), s.
    max_spread_s: f64,
    /// Where the fusion last placed the robots, for the teammate masks ([`ServerCore::mask_teammates`]).
    placed: Option<Placed>,
}

/// Where a fusion that tracks the robots in each other's scans (T4, else T3) last placed them:
/// per robot its base in V and its odometry pose at that scan, and when the frame was received.
#[derive(Debug, Clone)]
struct Placed {
    robots: Vec<(Se2, Se2)>,
    rx_s: f64,
}

impl ServerCore {
    #[must_use]
    pub fn new(setup: CoreSetup) -> Self {
        let n = setup.members.len();
        let filter = |seed: u64, at: Se2, lidar: Se2| {
            let mut f = Amcl::new(setup.amcl.clone(), Arc::clone(&setup.field), seed);
            f.init_pose(at, INITIAL_STD_XY_M, INITIAL_STD_YAW_RAD);
            f.set_sensor_origin(Some([lidar.x, lidar.y]));
            f
        };
        let robot_filters = setup
            .members
            .iter()
            .enumerate()
            .map(|(i, m)| {
                filter(
                    setup.seed.wrapping_add(1 + i as u64),
                    setup.initial_v * Se2::new(0.0, m.slot_y_m, 0.0),
                    m.lidar_to_base,
                )
            })
            .collect();
        let y0 = setup.members.first().map_or(0.0, |m| m.slot_y_m);
        let channels = setup
            .configurations
            .iter()
            .map(|c| {
                let mut pipeline =
                    Pipeline::new(n, setup.vamr.clone(), *c, setup.max_spread_s, setup.max_age_s);
                for (i, m) in setup.members.iter().enumerate().skip(1) {
                    let observer = observer(&setup.members, i);
                    pipeline.set_observer(i, observer);
                    let y0 = setup.members.get(observer).map_or(y0, |o| o.slot_y_m);
                    pipeline.set_expected(i, [0.0, m.slot_y_m - y0], 0.5);
                    // The formation drives with parallel headings.
                    pipeline.set_expected_heading(i, 0.0);
                }
                pipeline.set_oracle(setup.oracle);
                // Not initialised here: it starts where the robots are when fusion begins
                // ([`ServerCore::start_v`]), not where the scenario says they should be.
                let filter = (*c != Configuration::T1)
                    .then(|| Amcl::new(virtual_params(&setup.amcl, n), Arc::clone(&setup.field), setup.seed));
                Channel {
                    configuration: *c,
                    pipeline,
                    filter,
                    started: false,
                    last_fused_s: None,
                    last_restart_s: None,
                    seq: 0,
                }
            })
            .collect();
        ServerCore {
            amcl: setup.amcl,
            robot_filters,
            amcl_motion: setup.vamr.fusion.amcl_motion,
            corrections: vec![None; n],
            channels,
            scans: vec![VecDeque::new(); n],
            fused_stamp: vec![f64::NEG_INFINITY; n],
            lost: vec![false; n],
            odom_frames: vec![0; n],
            oracle: setup.oracle,
            truth: vec![None; n],
            members: setup.members,
            checks: setup.checks,
            max_spread_s: setup.max_spread_s,
            placed: None,
        }
    }

    /// An operator's pose for V (RViz's "2D Pose Estimate", `/initialpose`): each robot's filter
    /// starts again in its slot around `v`, spread by `std_xy_m` and `std_yaw_rad`, and V's filters
    /// start again from the robots' estimates once these track (as after a gap in fusion). Until
    /// every estimate has verified itself again the formation holds. A pose that is not finite,
    /// or a spread that is not finite and positive, is refused (`false`).
    pub fn set_initial_pose(&mut self, v: Se2, std_xy_m: f64, std_yaw_rad: f64) -> bool {
        let spread_ok = |s: f64| s.is_finite() && s > 0.0;
        let finite = v.x.is_finite() && v.y.is_finite() && v.theta.is_finite();
        if !(finite && spread_ok(std_xy_m) && spread_ok(std_yaw_rad)) {
            return false;
        }
        for ((f, m), c) in self.robot_filters.iter_mut().zip(&self.members).zip(&mut self.corrections) {
            f.init_pose(v * Se2::new(0.0, m.slot_y_m, 0.0), std_xy_m, std_yaw_rad);
            *c = None;
        }
        for ch in &mut self.channels {
            ch.started = false;
            ch.last_fused_s = None;
        }
        tracing::info!(
            x = v.x,
            y = v.y,
            theta = v.theta,
            std_xy_m,
            std_yaw_rad,
            "an initial pose for V: the filters start again there"
        );
        true
    }

    /// The true pose of robot `i`'s next scan, for the oracle (evaluations only).
    pub fn set_truth(&mut self, i: usize, pose: Se2) {
        if let Some(t) = self.truth.get_mut(i) {
            *t = Some(pose);
        }
    }

    #[must_use]
    pub fn members(&self) -> &[Member] {
        &self.members
    }

    /// The formation index of robot `id`.
    #[must_use]
    pub fn index(&self, id: &str) -> Option<usize> {
        self.members.iter().position(|m| m.id == id)
    }

    /// The filter behind an estimate source (its particles, for recording and the live view).
    #[must_use]
    pub fn filter(&self, source: EstimateSource) -> Option<&Amcl> {
        match source {
            EstimateSource::Robot(i) => self.robot_filters.get(i),
            EstimateSource::Fused(c) => {
                self.channels.iter().find(|ch| ch.configuration == c).and_then(|ch| ch.filter.as_ref())
            }
        }
    }

    /// One uplink message, received at `rx_s` (also the time of fusion: the sync gate's age
    /// test and the acquisition latency use it). Only scans of formation members do anything;
    /// a scan no real sensor could send is refused with the reason (no input can make the core
    /// panic or allocate without bound: `tests::any_uplink_is_used_or_refused_never_a_panic`).
    pub fn offer(&mut self, msg: &Uplink, rx_s: f64, lap: &mut dyn FnMut(Lap)) -> Step {
        let mut step = Step::default();
        let Uplink::Scan(s) = msg else { return step };
        let Some(i) = self.index(&s.robot) else {
            step.refused = Some(Refusal::UnknownRobot(s.robot.clone()));
            return step;
        };
        step.robot = Some(i);
        let odom = match check_scan(s, rx_s) {
            Ok(odom) => odom,
            Err(r) => {
                step.refused = Some(r);
                return step;
            }
        };
        if self.scans[i].back().is_some_and(|b| b.stamp_s >= s.stamp_s) {
            step.refused = Some(Refusal::NotNewer);
            return step;
        }
        if self.odom_frames[i] != 0 && s.odom_frame != self.odom_frames[i] {
            self.odometry_restarted(i);
            step.odometry_restarted = true;
        }
        self.odom_frames[i] = s.odom_frame;
        self.robot_amcl(i, s, odom, rx_s, &mut step);
        lap(Lap::RobotAmcl);
        let buf = &mut self.scans[i];
        let truth = self.truth.get_mut(i).and_then(Option::take);
        buf.push_back(Held { scan: Arc::clone(&s.scan), stamp_s: s.stamp_s, rx_s, odom, truth });
        while buf.len() > BUFFER {
            buf.pop_front();
        }
        if self.lost[i] {
            self.lost[i] = false;
            self.retrack(i);
            step.back = Some(!self.lost.iter().any(|l| *l));
        }
        if let Some(set) = self.pick(i) {
            self.fuse(&set, rx_s, lap, &mut step);
        }
        step
    }

    /// Robots whose last scan arrived more than `lost_after_s` before `now_s`: the ones newly lost.
    pub(crate) fn check_lost(&mut self, now_s: f64, lost_after_s: f64) -> Vec<usize> {
        let mut newly = Vec::new();
        for i in 0..self.members.len() {
            let last = self.scans[i].back().map(|h| h.rx_s);
            if last.is_some_and(|t| now_s - t > lost_after_s) && !self.lost[i] {
                self.lost[i] = true;
                newly.push(i);
            }
        }
        newly
    }

    /// Robot `i` is lost (as a recording says).
    pub fn mark_lost(&mut self, i: usize) {
        if let Some(l) = self.lost.get_mut(i) {
            *l = true;
        }
    }

    /// Robot `i`'s odometry started again at the origin of a new frame (the robot or its odometry
    /// restarted). Nothing of the old frame may meet the new: its AMCL keeps its
    /// particles but takes the next odometry pose as the new reference (no motion step across the
    /// frames), its held scans and its map ← odometry correction go, and the pipelines track it
    /// afresh; when it is the first robot, V's odometry (composed from its frame) restarts too.
    fn odometry_restarted(&mut self, i: usize) {
        tracing::warn!(robot = %self.members[i].id, "odometry restarted in a new frame: re-anchoring its filters");
        if let Some(f) = self.robot_filters.get_mut(i) {
            f.odometry_restarted();
        }
        if let Some(b) = self.scans.get_mut(i) {
            b.clear();
        }
        if let Some(c) = self.corrections.get_mut(i) {
            *c = None;
        }
        // Its odometry poses of the last placement are of the old frame.
        self.placed = None;
        self.retrack(i);
        if i == 0 {
            for f in self.channels.iter_mut().filter_map(|ch| ch.filter.as_mut()) {
                f.odometry_restarted();
            }
        }
    }

    /// Every pipeline tracks robot `i` afresh (full heading search); the pipelines track the
    /// others relative to the first robot, so for the first robot that is every other one.
    fn retrack(&mut self, i: usize) {
        let n = self.members.len();
        for ch in &mut self.channels {
            if i > 0 {
                ch.pipeline.reset_robot(i);
            } else {
                for k in 1..n {
                    ch.pipeline.reset_robot(k);
                }
            }
        }
    }

    fn robot_amcl(&mut self, i: usize, s: &ScanMsg, odom: Se2, rx_s: f64, step: &mut Step) {
        let mut points =
            self.members.get(i).map_or_else(Vec::new, |m| scan_points(&s.scan, &m.lidar_to_base, &self.amcl));
        self.mask_teammates(i, odom, rx_s, &mut points);
        let (Some(filter), Some(m)) = (self.robot_filters.get_mut(i), self.members.get(i)) else { return };
        let before = filter.integrity_state();
        if matches!(filter.update(odom, &points, false), UpdateOutcome::Updated { .. }) {
            step.updated.push(EstimateSource::Robot(i));
        }
        if let Some(now) = filter.integrity().filter(|n| n.state != before) {
            tracing::info!(
                robot = %m.id, from = %before, to = %now.state, explained = now.explained, level = now.level,
                "the robot's own localisation changed state"
            );
        }
        let Some(map) = filter.pose_at(&odom) else { return };
        self.corrections[i] = Some(map * odom.inverse());
        let mut robots = vec![None; self.members.len()];
        robots[i] = Some(Anchored { map, odom, stamp_s: s.stamp_s });
        step.estimates.push(Estimate {
            source: EstimateSource::Robot(i),
            stamp_s: s.stamp_s,
            v: None,
            robots,
            integrity: EstimateIntegrity::of(filter.integrity()),
            covariance: filter.estimate().map(|e| e.covariance),
        });
    }

    /// Drop from robot `i`'s points (its base frame, at odometry pose `odom`, received at `rx_s`)
    /// those on a teammate's body. The map does not hold the teammates, and side by side a
    /// neighbour is much of what a robot's LiDAR returns (two robots 0.5 m apart in a hall with
    /// racks on one side: about 40 % of the returns): judged with them the filter took its right
    /// place for a wrong one, and re-seeded itself metres off where racks explained the body.
    ///
    /// The teammates stand where the fusion last placed them relative to robot `i` (its contour
    /// tracker finds each in its neighbour's scan), carried on by each robot's odometry since; a
    /// robot's own estimate is no guide to where its body is in a neighbour's scan when it cannot
    /// see the site itself (on `short-racks` the blind robot's estimate drifted, the mask missed
    /// its body, and its neighbour judged itself lost). Before the fusion has placed them, or
    /// [`PLACED_FOR_S`] after it last did, the robots' own estimates place them (unless `lost`).
    fn mask_teammates(&self, i: usize, odom: Se2, rx_s: f64, points: &mut Vec<[f64; 2]>) {
        let latest = |j: usize| self.scans.get(j).and_then(|b| b.back()).map(|h| h.odom);
        let placed = self
            .placed
            .as_ref()
            .filter(|p| rx_s - p.rx_s <= PLACED_FOR_S && p.robots.len() == self.members.len());
        // Robot j in robot i's base frame, for every teammate placed.
        let teammates: Vec<(usize, Se2)> = if let Some(p) = placed {
            let (b_i, o_i) = p.robots[i];
            let moved_i = o_i.inverse() * odom;
            (0..self.members.len())
                .filter(|&j| j != i)
                .filter_map(|j| {
                    let (b_j, o_j) = p.robots[j];
                    let moved_j = o_j.inverse() * latest(j)?;
                    Some((j, moved_i.inverse() * b_i.inverse() * b_j * moved_j))
                })
                .collect()
        } else {
            let Some(here) = self.robot_filters.get(i).and_then(|f| f.pose_at(&odom)) else { return };
            (0..self.members.len())
                .filter(|&j| j != i)
                .filter_map(|j| {
                    let f = self.robot_filters.get(j)?;
                    if f.integrity_state() == amr_core::amcl::IntegrityState::Lost {
                        return None;
                    }
                    let there = self.corrections.get(j).copied().flatten()? * latest(j)?;
                    Some((j, here.inverse() * there))
                })
                .collect()
        };
        // Points of robot i's base frame into each teammate's.
        let bodies: Vec<(Se2, &Polygon)> = teammates
            .into_iter()
            .filter_map(|(j, rel)| Some((rel.inverse(), &self.members.get(j)?.chassis)))
            .collect();
        if bodies.is_empty() {
            return;
        }
        points.retain(|p| {
            !bodies
                .iter()
                .any(|(to_j, chassis)| chassis.contains_inflated(to_j.transform_point(*p), TEAMMATE_MARGIN_M))
        });
    }

    /// Choose one unfused scan per robot, closest in time to robot `from`'s newest; none while a
    /// robot has no unfused scan within the sync gate's spread of it (its scan of that instant
    /// may still be on its way). Taking the nearest scan whatever its time consumed each robot's
    /// scan one period off its partner's after one robot's scans came late once, and every later
    /// pair failed the gate (a period, 67 ms, against 50): fusion never came back.
    fn pick(&self, from: usize) -> Option<Vec<Held>> {
        let t = self.scans.get(from)?.back()?.stamp_s;
        let mut set = Vec::with_capacity(self.members.len());
        for (i, buf) in self.scans.iter().enumerate() {
            let best = buf
                .iter()
                .filter(|h| h.stamp_s > self.fused_stamp[i])
                .min_by(|a, b| (a.stamp_s - t).abs().total_cmp(&(b.stamp_s - t).abs()))?;
            if (best.stamp_s - t).abs() > self.max_spread_s {
                return None;
            }
            set.push(best.clone());
        }
        Some(set)
    }
}

/// AMCL's parameters for a virtual scan fused from `robots` robots: each robot's beams keep their
/// budget, `max_beams` × `robots` in all. With one robot's budget the fused scan would be thinned
/// to the information of one scan, and T4 would localise on half the beams that T1's two filters
/// use together (`amr eval --budget` found this, not the relative pose, to be why T4 localised
/// worse than T1; docs/method.md §7). The cost of its sensor update is then that of T1's filters together.
#[must_use]
pub fn virtual_params(amcl: &AmclParams, robots: usize) -> AmclParams {
    let mut p = amcl.clone();
    // V is not looked for over the whole map: a lost V starts again where the robots' own
    // tracking estimates put it (`Channel::restart_lost_v`), as it started. Its scan is composed
    // from several robots' by relative poses that can be wrong (T1–T3 take them from the robots'
    // own filters), and a place elsewhere that explained a virtual scan assembled with a drifting
    // robot's estimate better carried V 11 m off (`short-racks`, T2).
    p.integrity.alternative_draws = 0;
    p.integrity.reseed_share = 0.0;
    let beams = i64::from(amcl.max_beams.get()).saturating_mul(robots.max(1) as i64);
    if let Ok(c) = amr_core::config::value::Count::new(beams) {
        p.max_beams = c;
    }
    p
}

/// The robot that observes robot `i` of a line formation (docs/method.md §6): the nearest robot before
/// it on its side of robot 0, between robot 0 and it, so that nothing stands between them; robot
/// 0 when none is.
fn observer(members: &[Member], i: usize) -> usize {
    let (Some(first), Some(me)) = (members.first(), members.get(i)) else { return 0 };
    let d = me.slot_y_m - first.slot_y_m;
    members[..i]
        .iter()
        .enumerate()
        .skip(1)
        .filter(|(_, m)| {
            let dm = m.slot_y_m - first.slot_y_m;
            dm * d > 0.0 && dm.abs() < d.abs()
        })
        .min_by(|(_, a), (_, b)| {
            (a.slot_y_m - me.slot_y_m).abs().total_cmp(&(b.slot_y_m - me.slot_y_m).abs())
        })
        .map_or(0, |(k, _)| k)
}

/// The mean of poses (positions averaged, headings by their mean direction); `None` for none.
fn mean_pose(poses: impl Iterator<Item = Se2>) -> Option<Se2> {
    let (mut n, mut x, mut y, mut c, mut s) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in poses {
        n += 1.0;
        x += p.x;
        y += p.y;
        c += p.theta.cos();
        s += p.theta.sin();
    }
    (n > 0.0).then(|| Se2::new(x / n, y / n, s.atan2(c)))
}

/// The first robot whose own estimate (`own`, where tracking) is farther from where V at `v`
/// places it than the checks allow.
fn disagreeing(v: Se2, bases_in_v: &[Se2], own: &[Option<Se2>], checks: &IntegrityChecks) -> Option<u32> {
    let max_rad = checks.max_disagreement_deg.to_radians();
    bases_in_v
        .iter()
        .zip(own)
        .position(|(b, o)| {
            o.is_some_and(|o| {
                let d = o.inverse() * (v * *b);
                d.translation_norm() > checks.max_disagreement_m || d.theta.abs() > max_rad
            })
        })
        .map(|i| i as u32)
}

/// V in the first robot's frame from the robots' true poses, when every one is known.
fn true_v_in_first(set: &[Held], members: &[Member]) -> Option<Se2> {
    let first = set.first()?.truth?;
    let rel: Option<Vec<(Se2, f64)>> =
        set.iter().zip(members).map(|(h, m)| h.truth.map(|t| (first.inverse() * t, m.weight))).collect();
    Some(virtual_frame(&rel?))
}

mod fuse;
#[cfg(test)]
mod tests;
