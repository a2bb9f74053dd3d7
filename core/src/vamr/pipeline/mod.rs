//! One fused update as named steps: `gate` (robot count and sync gate) → `preprocess` (every
//! scan, and the heading search's targets) → per non-reference robot `locate` (its relative
//! position: the contour tracker or AMCL) and `orient` (its relative heading: the search or AMCL)
//! → `compose` (along the observer chain) → `fuse` (virtual frame, body masks, virtual scan)
//! (docs/method.md §6, §9). T1–T4 are names for where `locate` and `orient` take their answers
//! ([`Configuration::sources`]).
//!
//! Robot 0 is the reference. Every other robot has an *observer*, a robot before it that tracks its
//! centre in its own scan and against whose scan its heading is searched; by default robot 0
//! observes all (with two robots this is the paper's A and B). In a longer line the far robots are
//! hidden from robot 0 behind its neighbours, so each is observed by its neighbour nearer to robot 0
//! ([`Pipeline::set_observer`]) and its pose relative to robot 0 is composed along the chain.
//!
//! For error budgets (`amr eval --budget`; docs/method.md §9) an [`Oracle`] replaces the tracker's
//! position or the heading search's heading by the truth carried in the packets: evaluation only,
//! never on a robot. It is a stand-in applied between the steps ([`Pipeline::set_oracle`]): the
//! steps themselves know nothing of it, and still run (their state evolves as without it).

use crate::config::{Configuration, HeadingFrom, PositionFrom, VamrParams};
use crate::geometry::Polygon;
use crate::scan::Scan;
use crate::se2::Se2;

use super::contour::{ContourInput, ContourMeasurement, recognize};
use super::frame::{PacketTimes, SyncFailure, robots_in_virtual, sync_gate, virtual_frame};
use super::fusion::{FusionInput, VirtualScan, fuse};
use super::heading::{HeadingProblem, SearchScratch, TargetScan, search};
use super::preprocess::{Preprocessed, preprocess};
use super::tracker::{Roi, TrackOutcome, Tracker};

mod heading_track;

use heading_track::HeadingTrack;
pub use heading_track::{DRIFT_RATE_MEMORY_S, MAX_REFUSED};

/// One robot's packet for a fused update.
#[derive(Debug, Clone, Copy)]
pub struct RobotPacket<'a> {
    pub scan: &'a Scan,
    pub times: PacketTimes,
    pub lidar_to_base: Se2,
    pub chassis: &'a Polygon,
    /// Fusion weight `w_i` (Eq. 16).
    pub weight: f64,
    /// The robot's own AMCL pose `T_{B_i}^M`, where the configuration takes relative position or
    /// heading from AMCL (T1–T3).
    pub amcl_pose: Option<Se2>,
    /// The robot's true pose in any frame common to the set (a simulation's world), for an
    /// [`Oracle`]; `None` everywhere but in evaluations.
    pub truth: Option<Se2>,
    /// The robot's odometry pose at the scan, if known: between updates the relative heading is
    /// carried forward by the robots' odometry turns (see [`Pipeline`]).
    pub odom: Option<Se2>,
}

/// Which estimates an evaluation replaces by the truth ([`RobotPacket::truth`]), to measure each
/// one's share of the error (the error budget). The default replaces nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Oracle {
    /// The relative position (the contour tracker's, or AMCL's in T1–T2).
    pub position: bool,
    /// The relative heading (the heading search's, or AMCL's in T1 and T3).
    pub heading: bool,
    /// V's odometry: composed with the true relative poses instead of the estimated ones (applied
    /// by whoever composes it: the server core).
    pub odometry: bool,
}

/// Where a relative pose component came from in this update.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    Amcl,
    Tracker,
    /// The heading search ran a full (-180°, 180°] sweep.
    FullSearch,
    /// The heading search ran around the previous estimate.
    RefinedSearch,
    /// The search failed (score below `min_score`, no distinct peak, or fewer matches than
    /// `min_matches`) or its estimate was refused (`prior_gate_deg` from the prediction): the
    /// previous estimate, carried forward by the robots' odometry, was used.
    PreviousHeading,
}

/// What happened for one non-reference robot.
#[derive(Debug, Clone, PartialEq)]
pub struct PairReport {
    pub contour: Option<ContourMeasurement>,
    pub track: Option<TrackOutcome>,
    pub position_source: Source,
    pub heading_source: Source,
    pub heading_score: Option<f64>,
    pub heading_margin: Option<f64>,
    /// The heading search swept the full circle (an acquisition), whether or not it found a
    /// heading (`heading_source` says what was used).
    pub full_search: bool,
}

/// The result of one fused update.
#[derive(Debug, Clone)]
pub struct FusedUpdate {
    /// `T_{B_i}^{B_0}` (the first is the identity).
    pub relative: Vec<Se2>,
    /// `T_V^{B_0}`.
    pub v_in_reference: Se2,
    /// `T_{B_i}^V`.
    pub bases_in_v: Vec<Se2>,
    /// The virtual scan (T2–T4); T1 localises each robot on its own scan instead.
    pub virtual_scan: Option<VirtualScan>,
    /// One per non-reference robot.
    pub pairs: Vec<PairReport>,
}

/// A stage of one fused update, for latency accounting (the paper's Table 4). The core has no
/// clock: [`Pipeline::update_with_laps`] calls its `lap` argument as each stage ends, and the caller
/// charges the time since the previous lap to that stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stage {
    /// Sync gate and preprocessing of every scan.
    Preprocess,
    /// Contour recognition and the tracker (T3, T4), once per non-reference robot.
    Tracking,
    /// The heading search (T2, T4), once per non-reference robot.
    Heading,
    /// Virtual frame, body masks and the virtual scan.
    VirtualScan,
}

/// Why an update produced no fused measurement.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum UpdateError {
    #[error("the packets fail the sync gate: {0:?}")]
    Sync(SyncFailure),
    #[error("the pipeline was built for {expected} robots, got {got}")]
    RobotCount { expected: usize, got: usize },
    #[error("no relative position for robot {robot}: {why}")]
    NoPosition { robot: usize, why: &'static str },
    #[error("no relative heading for robot {robot}: {why}")]
    NoHeading { robot: usize, why: &'static str },
}

/// One non-reference robot's state across updates.
#[derive(Debug, Clone)]
struct Pair {
    /// Its observer (a robot before it).
    observer: usize,
    tracker: Tracker,
    heading: HeadingTrack,
    /// Where it is expected (its formation slot, in its observer's frame): the search area while
    /// its track is being acquired.
    expected: Option<Roi>,
}

/// The pipeline's state across updates: one tracker and heading track per non-reference robot.
#[derive(Debug)]
pub struct Pipeline {
    params: VamrParams,
    configuration: Configuration,
    max_spread_s: f64,
    max_age_s: f64,
    pairs: Vec<Pair>,
    /// Each non-reference robot's observer, robot 1 first (a copy of the pairs', for
    /// [`Pipeline::observers`]).
    observers: Vec<usize>,
    oracle: Oracle,
    scratch: SearchScratch,
}

/// `a⁻¹ ∘ b` when both are known.
fn between(a: Option<Se2>, b: Option<Se2>) -> Option<Se2> {
    a.zip(b).map(|(a, b)| a.inverse() * b)
}

impl Pipeline {
    #[must_use]
    pub fn new(
        robots: usize,
        params: VamrParams,
        configuration: Configuration,
        max_spread_s: f64,
        max_age_s: f64,
    ) -> Self {
        let others = robots.saturating_sub(1);
        let pair = Pair {
            observer: 0,
            tracker: Tracker::new(params.tracker),
            heading: HeadingTrack::new(&params.heading),
            expected: None,
        };
        Pipeline {
            pairs: vec![pair; others],
            observers: vec![0; others],
            oracle: Oracle::default(),
            params,
            configuration,
            max_spread_s,
            max_age_s,
            scratch: SearchScratch::default(),
        }
    }

    #[must_use]
    pub fn configuration(&self) -> Configuration {
        self.configuration
    }

    fn pair_mut(&mut self, robot: usize) -> Option<&mut Pair> {
        robot.checked_sub(1).and_then(|i| self.pairs.get_mut(i))
    }

    /// Acquire robot `robot`'s track near `center` (its observer's base frame), within
    /// `half_width_m`, instead of over the whole scan. With three or more robots this is what tells
    /// an observer which body is which; the formation's configured slots give it.
    pub fn set_expected(&mut self, robot: usize, center: [f64; 2], half_width_m: f64) {
        if let Some(pair) = self.pair_mut(robot) {
            pair.expected = Some(Roi { center, half_width: [half_width_m; 2] });
        }
    }

    /// Robot `robot`'s heading relative to its observer is expected to be `heading_rad` (a
    /// formation drives with parallel headings: 0). When acquiring its heading finds no distinct
    /// peak, this is taken instead, carried forward by odometry and refined by the next searches
    /// (without it such an update has no heading and fuses nothing).
    pub fn set_expected_heading(&mut self, robot: usize, heading_rad: f64) {
        if let Some(pair) = self.pair_mut(robot) {
            pair.heading.expected = Some(heading_rad);
        }
    }

    /// Robot `robot` is observed by robot `observer` (which must come before it; default 0).
    /// Ignored for an out-of-range robot or an observer not before it.
    pub fn set_observer(&mut self, robot: usize, observer: usize) {
        if observer < robot
            && let Some(pair) = self.pair_mut(robot)
        {
            pair.observer = observer;
            self.observers[robot - 1] = observer;
        }
    }

    /// Each non-reference robot's observer, robot 1 first.
    #[must_use]
    pub fn observers(&self) -> &[usize] {
        &self.observers
    }

    /// Replace estimates by the truth (evaluations only).
    pub fn set_oracle(&mut self, oracle: Oracle) {
        self.oracle = oracle;
    }

    /// Forget robot `robot`'s track and heading (its data stopped): the next update acquires it
    /// again in its expected area with the full heading search. The robots it observes are tracked
    /// in its scans, so they are acquired afresh too.
    pub fn reset_robot(&mut self, robot: usize) {
        let (tracker, heading) = (self.params.tracker, self.params.heading);
        if let Some(pair) = self.pair_mut(robot) {
            pair.tracker = Tracker::new(tracker);
            pair.heading.forget(&heading);
        }
        let observed: Vec<usize> =
            (1..=self.pairs.len()).filter(|k| self.pairs[k - 1].observer == robot && *k != robot).collect();
        for k in observed {
            self.reset_robot(k);
        }
    }

    /// Switch T1–T4 between updates (trackers and headings are kept).
    pub fn set_configuration(&mut self, configuration: Configuration) {
        self.configuration = configuration;
    }

    /// One synchronised set of packets, robot 0 first.
    pub fn update(&mut self, packets: &[RobotPacket<'_>]) -> Result<FusedUpdate, UpdateError> {
        self.update_with_laps(packets, &mut |_| {})
    }

    /// [`Pipeline::update`], calling `lap(stage)` as each stage ends.
    pub fn update_with_laps(
        &mut self,
        packets: &[RobotPacket<'_>],
        lap: &mut dyn FnMut(Stage),
    ) -> Result<FusedUpdate, UpdateError> {
        let t_s = self.gate(packets)?;
        let (position_from, heading_from) = self.configuration.sources();
        let (pre, targets) = self.preprocess(packets, heading_from);
        lap(Stage::Preprocess);
        let mut relative = vec![Se2::IDENTITY];
        let mut pairs = Vec::new();
        for i in 1..packets.len() {
            let observer = self.pairs[i - 1].observer;
            let (reference, other) = (&packets[observer], &packets[i]);
            let from_truth = between(reference.truth, other.truth);
            let mut report = PairReport::new();
            let position = self.locate(i, position_from, packets, &pre[observer], t_s, &mut report);
            // The oracle stands in for a failed estimate too (its row of the budget has no misses
            // of its own).
            let position = match (self.oracle.position, from_truth) {
                (true, Some(t)) => [t.x, t.y],
                _ => position?,
            };
            lap(Stage::Tracking);
            let theta = match &targets[observer] {
                Some(target) => self.orient(i, packets, &pre[i], target, position, t_s, &mut report),
                None => between(reference.amcl_pose, other.amcl_pose)
                    .map(|r| r.theta)
                    .ok_or(UpdateError::NoHeading { robot: i, why: "no AMCL poses" }),
            };
            let theta = match (self.oracle.heading, from_truth) {
                (true, Some(t)) => t.theta,
                _ => theta?,
            };
            lap(Stage::Heading);
            relative.push(compose(&relative, observer, position, theta));
            pairs.push(report);
        }
        let (v_in_reference, bases_in_v, virtual_scan) = self.fuse(packets, &relative);
        lap(Stage::VirtualScan);
        Ok(FusedUpdate { relative, v_in_reference, bases_in_v, virtual_scan, pairs })
    }

    /// The robot count and the sync gate: the update's stamp, or why nothing is fused (a gate
    /// failure is a miss for every track).
    fn gate(&mut self, packets: &[RobotPacket<'_>]) -> Result<f64, UpdateError> {
        let expected = self.pairs.len() + 1;
        if packets.len() != expected {
            return Err(UpdateError::RobotCount { expected, got: packets.len() });
        }
        let t_s = packets[0].times.stamp_s;
        let times: Vec<PacketTimes> = packets.iter().map(|p| p.times).collect();
        if let Err(e) = sync_gate(&times, self.max_spread_s, self.max_age_s) {
            // Not fused, and a miss for every track (docs/method.md §4, §6).
            for pair in &mut self.pairs {
                if matches!(pair.tracker.update(t_s, None), TrackOutcome::Lost) {
                    pair.heading.reacquire = true;
                }
            }
            return Err(UpdateError::Sync(e));
        }
        Ok(t_s)
    }

    /// Every scan preprocessed and, when the heading is searched, each observer's scan as the
    /// search's target (built once per observer).
    fn preprocess<'p>(
        &self,
        packets: &[RobotPacket<'p>],
        heading_from: HeadingFrom,
    ) -> (Vec<Preprocessed>, Vec<Option<TargetScan>>) {
        let pre: Vec<Preprocessed> =
            packets.iter().map(|p| preprocess(p.scan, &p.lidar_to_base, &self.params.preprocess)).collect();
        let mut targets: Vec<Option<TargetScan>> = Vec::new();
        targets.resize_with(packets.len(), || None);
        if heading_from == HeadingFrom::Search {
            for pair in &self.pairs {
                let o = pair.observer;
                if targets[o].is_none() {
                    targets[o] = Some(
                        TargetScan::new(packets[o].scan, &packets[o].lidar_to_base, &pre[o].smoothed_points)
                            .with_surface(self.params.heading.surface_jump_m()),
                    );
                }
            }
        }
        (pre, targets)
    }

    /// Robot `i`'s position relative to its observer: the contour tracker's in the observer's
    /// scan (`observed`: its preprocessing), or the robots' AMCL poses'.
    fn locate(
        &mut self,
        i: usize,
        from: PositionFrom,
        packets: &[RobotPacket<'_>],
        observed: &Preprocessed,
        t_s: f64,
        report: &mut PairReport,
    ) -> Result<[f64; 2], UpdateError> {
        let pair = &mut self.pairs[i - 1];
        let (reference, other) = (&packets[pair.observer], &packets[i]);
        if from == PositionFrom::Amcl {
            return between(reference.amcl_pose, other.amcl_pose)
                .map(|rel| [rel.x, rel.y])
                .ok_or(UpdateError::NoPosition { robot: i, why: "no AMCL poses" });
        }
        let contour = recognize(
            ContourInput {
                scan: reference.scan,
                filtered: &observed.filtered_points,
                lidar_to_base: reference.lidar_to_base,
                chassis: other.chassis,
                roi: pair.tracker.roi(t_s).or(pair.expected),
                jump_m: self.params.preprocess.segment_jump_m.get(),
            },
            &self.params.contour,
        );
        let outcome = pair.tracker.update(t_s, contour.map(|c| c.center));
        if matches!(outcome, TrackOutcome::Lost) {
            // Re-acquire: full ROI and full heading search next time. The heading is kept:
            // odometry carries it across the loss, and a failed full search falls back on it (the
            // formation's expected heading is far worse mid-turn: 16° off, measured on
            // hall-turning with three robots 1 m apart).
            pair.heading.reacquire = true;
        }
        report.contour = contour;
        report.track = Some(outcome);
        report.position_source = Source::Tracker;
        pair.tracker
            .state()
            .map(|s| s.position())
            .ok_or(UpdateError::NoPosition { robot: i, why: "no track" })
    }

    /// Robot `i`'s heading relative to its observer by the search against the observer's scan
    /// (`target`), at `position`: predicted by odometry, searched, gated, blended or fallen back
    /// on ([`HeadingTrack`]).
    #[allow(clippy::too_many_arguments, reason = "the step's inputs, each named")]
    fn orient(
        &mut self,
        i: usize,
        packets: &[RobotPacket<'_>],
        own: &Preprocessed,
        target: &TargetScan,
        position: [f64; 2],
        t_s: f64,
        report: &mut PairReport,
    ) -> Result<f64, UpdateError> {
        let (other, reference) = (&packets[i], &packets[self.pairs[i - 1].observer]);
        let h = &self.params.heading;
        let track = &mut self.pairs[i - 1].heading;
        let yaws = other.odom.zip(reference.odom).map(|(a, b)| (a.theta, b.theta));
        track.predict(t_s, yaws, h);
        let (grid, mode) = track.search_grid(h);
        report.full_search = mode == Source::FullSearch;
        let problem = HeadingProblem::new(&own.smoothed_points, target, position, h);
        let estimate = search(&problem, &grid, &mut self.scratch);
        report.heading_score = estimate.as_ref().map(|e| e.score);
        report.heading_margin = estimate.as_ref().map(|e| e.margin());
        let (theta, source) = track.settle(estimate, mode, h, i);
        report.heading_source = source;
        theta
    }

    /// The virtual frame, each base in it, and (but in T1, where each robot localises on its own
    /// scan) the virtual scan.
    fn fuse(&self, packets: &[RobotPacket<'_>], relative: &[Se2]) -> (Se2, Vec<Se2>, Option<VirtualScan>) {
        let weighted: Vec<(Se2, f64)> = relative.iter().zip(packets).map(|(t, p)| (*t, p.weight)).collect();
        let v_in_reference = virtual_frame(&weighted);
        let bases_in_v = robots_in_virtual(&v_in_reference, &weighted);
        let virtual_scan = (self.configuration != Configuration::T1).then(|| {
            let inputs: Vec<FusionInput<'_>> = packets
                .iter()
                .zip(&bases_in_v)
                .map(|(p, b)| FusionInput {
                    scan: p.scan,
                    lidar_to_base: p.lidar_to_base,
                    chassis: p.chassis,
                    base_in_v: *b,
                })
                .collect();
            fuse(
                &inputs,
                self.params.fusion.mask_inflation_m.get(),
                self.params.fusion.virtual_bin_deg.map(|d| d.get().to_radians()),
            )
        });
        (v_in_reference, bases_in_v, virtual_scan)
    }
}

/// Robot `i`'s pose relative to robot 0: its observer's, composed with its own relative to the
/// observer.
fn compose(relative: &[Se2], observer: usize, position: [f64; 2], theta: f64) -> Se2 {
    relative[observer] * Se2::new(position[0], position[1], theta)
}

impl PairReport {
    /// Nothing measured yet; both parts from AMCL until a step says otherwise.
    fn new() -> Self {
        PairReport {
            contour: None,
            track: None,
            position_source: Source::Amcl,
            heading_source: Source::Amcl,
            heading_score: None,
            heading_margin: None,
            full_search: false,
        }
    }
}
