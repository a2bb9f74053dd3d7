//! The paper's experiments in simulated time: the world, the Virtual-AMR pipeline and AMCL, with
//! T1–T4 run side by side on identical sensor streams.
//!
//! The pair follows its plan with the Eq. 20 controller closed on each robot's true pose, never on
//! the estimates, so every configuration sees exactly the same scans and the formation keeps the
//! scenario's geometry. The localisers get each robot's own odometry (wheels and gyro, as `amr
//! robot` computes it, with the systematic wheel errors of the world's noise). The localisation is the
//! server's own sans-IO core (`amr_actors::server::core`), the code `amr server` and `amr replay`
//! run: per-robot AMCL runs once and serves T1 (V from the robots' own poses) and T2/T3 (relative
//! pose sources); T2, T3 and T4 each have their own pipeline and their own AMCL on the virtual scan.
//! Errors of V's position are taken against
//! the true V (from the world) and against the paper's reference (its planned path + encoders, here the
//! odometry midpoint), each labelled.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use amr_core::amcl::Amcl;
use amr_core::config::{AmclParams, Configuration, ScenarioConfig, VamrParams};
use amr_core::map::OccupancyGrid;
use amr_core::metrics::{AxisStats, MeanSd, Sample};
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use amr_core::vamr::frame::virtual_frame;
use amr_msgs::Uplink;
use hil_mocks::world::{Noise, RobotSpec};
use serde::Serialize;

use crate::survey::SurveyOptions;

mod trial;

pub use amr_core::formation::slots;
pub use amr_core::plan::{Reference, reference};
pub use trial::run_trial_observed;

/// AMCL's map in an evaluation.
#[derive(Debug, Clone)]
pub enum EvalMap {
    /// This map in every trial (the site's own).
    Given(OccupancyGrid),
    /// Each trial's own survey of the site: a map is one more draw of the trial, as the robots'
    /// noise is, and the trials' spread includes how good the survey happened to be.
    Surveyed(Surveys),
}

/// Surveys of one site ([`crate::survey::surveyed_map`] on `like`'s grid), one per trial seed, each
/// made once and shared by every clone (a study's configurations on one site run the same seeds).
#[derive(Debug, Clone)]
pub struct Surveys {
    site: hil_mocks::world::Site,
    like: OccupancyGrid,
    options: SurveyOptions,
    made: Arc<Mutex<BTreeMap<u64, Arc<OccupancyGrid>>>>,
}

/// The survey's seed is the trial's, on a stream of its own (not the trial world's noise).
const SURVEY_STREAM: u64 = 0x5ee0_0000_0000_0000;

impl Surveys {
    #[must_use]
    pub fn new(site: hil_mocks::world::Site, like: OccupancyGrid, options: SurveyOptions) -> Self {
        Surveys { site, like, options, made: Arc::default() }
    }

    /// The survey of the trial seeded with `seed`.
    #[must_use]
    pub fn of_trial(&self, seed: u64) -> Arc<OccupancyGrid> {
        let lock = || self.made.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(m) = lock().get(&seed) {
            return Arc::clone(m);
        }
        // Made outside the lock: trials of other seeds survey in parallel.
        let map = Arc::new(crate::survey::surveyed_map(
            &self.site,
            &self.like,
            &self.options,
            seed ^ SURVEY_STREAM,
        ));
        Arc::clone(lock().entry(seed).or_insert(map))
    }
}

impl EvalMap {
    /// The map of the trial seeded with `seed`.
    #[must_use]
    pub fn for_trial(&self, seed: u64) -> Cow<'_, OccupancyGrid> {
        match self {
            EvalMap::Given(m) => Cow::Borrowed(m),
            EvalMap::Surveyed(s) => Cow::Owned(OccupancyGrid::clone(&s.of_trial(seed))),
        }
    }
}

/// Everything a run needs besides the seed.
#[derive(Debug, Clone)]
pub struct Setup {
    /// What the world ray-casts (the paper's site's polygons, or a map's occupied cells).
    pub site: hil_mocks::world::Site,
    pub map: EvalMap,
    pub robot: RobotSpec,
    pub vamr: VamrParams,
    pub amcl: AmclParams,
    pub noise: Noise,
    pub scenario: ScenarioConfig,
    /// Physics steps per LiDAR scan (the scan rate is `1 / (physics_dt · this)`).
    pub physics_dt_s: f64,
    pub steps_per_scan: usize,
    /// Robots in the formation (the paper: 2).
    pub robots: usize,
    /// Estimates of T2–T4 replaced by the truth (the error budget); none in a normal evaluation.
    pub oracle: amr_core::vamr::pipeline::Oracle,
}

/// One configuration's errors over one trial.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Series {
    /// Against the true pose of V.
    pub truth: Vec<Sample>,
    /// Against the paper-style reference (odometry).
    pub reference: Vec<Sample>,
    /// Scans for which the configuration produced no estimate (e.g. a failed heading search before
    /// any success).
    pub missing: usize,
    /// Estimates the server would not drive on: V not `Tracking`, or disagreeing with a robot's
    /// own estimate (they count in the errors all the same).
    pub unverified: usize,
    /// Pipeline updates (T2–T4) and, of those, the ones whose heading search failed (the paper's
    /// failure rate, Tables 6–7).
    pub updates: usize,
    pub heading_failures: usize,
    /// Error of the relative heading used for fusion (T2–T4), radians.
    pub heading_errors_rad: Vec<f64>,
    /// Wall-clock time spent in the pipeline (T2–T4), seconds. Not serialised: it differs from run
    /// to run, the rest does not.
    #[serde(skip)]
    pub pipeline_s: f64,
    /// V's estimate at every scan (`[x, y, θ]` in the map), `None` where there was none.
    pub estimates: Vec<Option<[f64; 3]>>,
    /// Per robot (formation order), the error of where this configuration places it, against its
    /// true pose, at every scan it placed it. V's error is a mean over the robots: with equal
    /// weights, errors of opposite sign cancel in it, and a robot whose own estimate drifts counts
    /// only 1/N. What each robot is told of its own pose is the error that drives it.
    pub robots: Vec<Vec<Sample>>,
}

/// One trial: per configuration (T1–T4, in that order).
#[derive(Debug, Clone, Serialize)]
pub struct Trial {
    pub seed: u64,
    pub scans: usize,
    pub series: Vec<(Configuration, Series)>,
    /// Time of every scan, s.
    pub times_s: Vec<f64>,
    /// The true V at every scan, `[x, y, θ]` in the map.
    pub truth_v: Vec<[f64; 3]>,
    /// Every robot's true position at every scan.
    pub truth_robots: Vec<Vec<[f64; 2]>>,
    /// T4's particle cloud (positions) after the last scan.
    pub final_particles_t4: Vec<[f64; 2]>,
    /// What each robot's LiDAR could see, averaged over every [`VISIBILITY_EVERY`]th scan.
    pub visibility: Vec<View>,
}

/// One robot's view over a trial (how much the others hide of the site), shares in 0..=1.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct View {
    /// Of its beams, the share whose first return is another robot's body.
    pub occluded: f64,
    /// Of the site returns it would have alone, the share left with the others about.
    pub site_left: f64,
    /// Of its beams, the share that returns from the site (what it localises on).
    pub site: f64,
}

/// Visibility is counted on every this many scans (it costs two more ray casts per beam).
pub const VISIBILITY_EVERY: usize = 5;

const CONFIGS: [Configuration; 4] =
    [Configuration::T1, Configuration::T2, Configuration::T3, Configuration::T4];

/// Eq. 16 for N robots with equal weights, in the map frame.
pub fn v_of(poses: &[Se2]) -> Se2 {
    let Some(first) = poses.first() else { return Se2::IDENTITY };
    let rel: Vec<(Se2, f64)> = poses.iter().map(|p| (first.inverse() * *p, 1.0)).collect();
    *first * virtual_frame(&rel)
}

fn error(est: &Se2, truth: &Se2) -> Sample {
    Sample { e_x: est.x - truth.x, e_y: est.y - truth.y }
}

/// One scan's result for configuration `c`: the errors of its estimate, or a miss.
fn record(
    series: &mut [(Configuration, Series)],
    c: Configuration,
    est: Option<(Se2, bool)>,
    v_true: &Se2,
    v_ref: &Se2,
) {
    if let Some(s) = series.iter_mut().find(|(k, _)| *k == c).map(|(_, s)| s) {
        s.estimates.push(est.map(|(e, _)| [e.x, e.y, e.theta]));
        match est {
            Some((e, verified)) => {
                s.unverified += usize::from(!verified);
                s.truth.push(error(&e, v_true));
                s.reference.push(error(&e, v_ref));
            }
            None => s.missing += 1,
        }
    }
}

/// Run one trial with `seed`.
#[must_use]
pub fn run_trial(setup: &Setup, seed: u64) -> Trial {
    run_trial_observed(setup, seed, &mut |_| {})
}

/// A virtual scan's points in V, shared with the fused frame that carried them.
pub type Points = Arc<Vec<[f64; 2]>>;

/// One scan step of a trial, as a recorder sees it (`amr eval --record`).
#[derive(Debug)]
pub struct TrialFrame<'a> {
    /// Simulated time, s.
    pub t_s: f64,
    /// Each robot's scan, its true pose and its odometry pose (in the map, from the known start).
    pub scans: &'a [Arc<Scan>],
    pub truth: &'a [Se2],
    pub odom: &'a [Se2],
    /// Each configuration's estimate of V at this step (None: none yet).
    pub estimates: &'a [(Configuration, Option<Se2>)],
    /// T2–T4: the virtual scan (points in V) each fused, when it did.
    pub virtual_scans: &'a [(Configuration, Option<Points>)],
    /// T2–T4: the AMCL filter on each one's virtual scan (its particles, for a recorder).
    pub filters: &'a [(Configuration, &'a Amcl)],
    /// What the server core was given at this step: each robot's scan as its uplink (robot `i`
    /// is `robot<i>`), with the time it was received. A recording of these replays the trial.
    pub uplink: &'a [(Uplink, f64)],
}

fn config_index(c: Configuration) -> usize {
    CONFIGS.iter().position(|k| *k == c).unwrap_or(0)
}

/// Pooled and trial-level statistics of one configuration.
#[derive(Debug, Clone, Serialize)]
pub struct ConfigSummary {
    pub configuration: String,
    pub pooled_truth: Option<AxisStats>,
    pub pooled_reference: Option<AxisStats>,
    /// Trial-level 2D RMSE against the truth, mean ± SD over trials.
    pub trial_rmse_2d: Option<MeanSd>,
    /// Per robot, its own trial-level 2D RMSE (where the configuration placed it), mean ± SD over
    /// trials; and per trial the worst robot's, mean ± SD.
    pub robot_rmse_2d: Vec<Option<MeanSd>>,
    pub worst_robot_rmse_2d: Option<MeanSd>,
    pub missing: usize,
    /// Estimates not verified (V not tracking, or disagreeing with a robot), over all trials.
    pub unverified: usize,
    /// The paper's trial-level 2D RMSE, mean and SD (Tables 15–16), when it gives one.
    pub paper_rmse_2d: Option<(f64, f64)>,
}

/// The paper's trial-level 2D RMSE (Tables 15–16; docs/method.md §10).
#[must_use]
pub fn paper_rmse(scenario: &str, c: Configuration) -> Option<(f64, f64)> {
    let row = match scenario {
        "straight" => [(0.2401, 0.0365), (0.1595, 0.0215), (0.1210, 0.0187), (0.0412, 0.0083)],
        "turning" => [(0.3047, 0.0563), (0.2191, 0.0395), (0.2401, 0.0417), (0.0511, 0.0104)],
        _ => return None,
    };
    Some(row[CONFIGS.iter().position(|k| *k == c)?])
}

/// Summaries of several trials, T1–T4.
#[must_use]
pub fn summarise(scenario: &str, trials: &[Trial]) -> Vec<ConfigSummary> {
    CONFIGS
        .iter()
        .map(|c| {
            let all: Vec<&Series> =
                trials.iter().filter_map(|t| t.series.iter().find(|(k, _)| k == c).map(|(_, s)| s)).collect();
            let pooled = |f: fn(&Series) -> &Vec<Sample>| {
                AxisStats::of(&all.iter().flat_map(|s| f(s).iter().copied()).collect::<Vec<_>>())
            };
            let per_trial: Vec<f64> =
                all.iter().filter_map(|s| AxisStats::of(&s.truth).map(|a| a.d2.rmse)).collect();
            let n_robots = all.iter().map(|s| s.robots.len()).max().unwrap_or(0);
            let robot_rmse =
                |s: &Series, i: usize| s.robots.get(i).and_then(|e| AxisStats::of(e)).map(|a| a.d2.rmse);
            let robot_rmse_2d = (0..n_robots)
                .map(|i| MeanSd::of(&all.iter().filter_map(|s| robot_rmse(s, i)).collect::<Vec<_>>()))
                .collect();
            let worst: Vec<f64> = all
                .iter()
                .filter_map(|s| (0..s.robots.len()).filter_map(|i| robot_rmse(s, i)).reduce(f64::max))
                .collect();
            ConfigSummary {
                configuration: format!("{c:?}"),
                pooled_truth: pooled(|s| &s.truth),
                pooled_reference: pooled(|s| &s.reference),
                trial_rmse_2d: MeanSd::of(&per_trial),
                robot_rmse_2d,
                worst_robot_rmse_2d: MeanSd::of(&worst),
                missing: all.iter().map(|s| s.missing).sum(),
                unverified: all.iter().map(|s| s.unverified).sum(),
                paper_rmse_2d: paper_rmse(scenario, *c),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests;
