//! The paper's experiments in simulated time (issue 8): the world, the Virtual-AMR pipeline and AMCL,
//! with T1–T4 run side by side on identical sensor streams.
//!
//! The pair follows its plan with the Eq. 20 controller closed on each robot's wheel odometry, never
//! on the estimates, so every configuration sees exactly the same scans. Per-robot AMCL runs once and
//! serves T1 (its midpoint is the estimate) and T2/T3 (relative pose sources); T2, T3 and T4 each have
//! their own pipeline and their own AMCL on the virtual scan. Errors of V's position are taken against
//! the true V (from the world) and against the paper's reference (its planned path + encoders, here the
//! odometry midpoint), each labelled.

use std::sync::Arc;

use amr_core::amcl::{Amcl, LikelihoodField, scan_points};
use amr_core::config::{AmclParams, Configuration, ScenarioConfig, VamrParams};
use amr_core::formation::{FormationGains, limit_twist, member_command, wheel_odometry_increment};
use amr_core::geometry::Polygon;
use amr_core::map::OccupancyGrid;
use amr_core::metrics::{AxisStats, MeanSd, Sample};
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use amr_core::vamr::frame::{PacketTimes, virtual_frame};
use amr_core::vamr::pipeline::{Pipeline, RobotPacket};
use serde::Serialize;

use crate::world::{Noise, RobotSpec, World, tim551_beams};
pub use amr_core::formation::slots;
pub use amr_core::plan::{Reference, reference};

/// Everything a run needs besides the seed.
#[derive(Debug, Clone)]
pub struct Setup {
    pub site: Vec<Polygon>,
    pub map: OccupancyGrid,
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
}

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
    est: Option<Se2>,
    v_true: &Se2,
    v_ref: &Se2,
) {
    if let Some(s) = series.iter_mut().find(|(k, _)| *k == c).map(|(_, s)| s) {
        s.estimates.push(est.map(|e| [e.x, e.y, e.theta]));
        match est {
            Some(e) => {
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

/// One scan step of a trial, as a recorder sees it (`amr eval --record`).
#[derive(Debug)]
pub struct TrialFrame<'a> {
    /// Simulated time, s.
    pub t_s: f64,
    /// Each robot's scan, its true pose and its odometry pose (in the map, from the known start).
    pub scans: &'a [Scan],
    pub truth: &'a [Se2],
    pub odom: &'a [Se2],
    /// Each configuration's estimate of V at this step (None: none yet).
    pub estimates: &'a [(Configuration, Option<Se2>)],
    /// T2–T4: the virtual scan (points in V) each fused, when it did.
    pub virtual_scans: &'a [(Configuration, Option<Vec<[f64; 2]>>)],
    /// T2–T4: the AMCL filter on each one's virtual scan (its particles, for a recorder).
    pub filters: &'a [(Configuration, &'a Amcl)],
}

/// [`run_trial`], calling `observe` after every scan step.
pub fn run_trial_observed(setup: &Setup, seed: u64, observe: &mut dyn FnMut(&TrialFrame<'_>)) -> Trial {
    let sc = &setup.scenario;
    let slots = slots(setup.robots, sc.spacing_m.get());
    let start_v = sc.start_pose();
    let mut world = World::new(setup.site.clone(), setup.noise, seed);
    let robots: Vec<usize> = slots
        .iter()
        .map(|y| world.add_robot(setup.robot.clone(), start_v * Se2::new(0.0, *y, 0.0)))
        .collect();
    let reference = reference(sc, setup.physics_dt_s);
    let field = Arc::new(LikelihoodField::new(&setup.map, &setup.amcl, tim551_beams().range_max_m));
    let mut own: Vec<Amcl> = robots
        .iter()
        .enumerate()
        .map(|(i, r)| {
            let mut f = Amcl::new(
                setup.amcl.clone(),
                Arc::clone(&field),
                seed.wrapping_mul(31).wrapping_add(i as u64),
            );
            f.init_pose(world.pose(*r).unwrap_or(start_v), 0.1, 0.05);
            f
        })
        .collect();
    let mut pipelines: Vec<(Configuration, Pipeline, Amcl)> = CONFIGS[1..]
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let mut f = Amcl::new(
                setup.amcl.clone(),
                Arc::clone(&field),
                seed.wrapping_mul(37).wrapping_add(10 + k as u64),
            );
            f.init_pose(start_v, 0.1, 0.05);
            let mut p = Pipeline::new(setup.robots, setup.vamr.clone(), *c, 0.05, 0.1);
            // The formation's slots: where robot 0 should find each of the others.
            for (i, y) in slots.iter().enumerate().skip(1) {
                p.set_expected(i, [0.0, y - slots[0]], 0.5);
            }
            (*c, p, f)
        })
        .collect();
    // Odometry poses in the map frame, starting from the known start poses.
    let mut odom: Vec<Se2> = robots.iter().map(|r| world.pose(*r).unwrap_or(start_v)).collect();
    let mut last_enc: Vec<[f64; 2]> =
        robots.iter().map(|r| world.encoders_rad(*r).unwrap_or([0.0; 2])).collect();
    let mut last_cmd = vec![(0.0, 0.0); robots.len()];
    let mut series: Vec<(Configuration, Series)> = CONFIGS.iter().map(|c| (*c, Series::default())).collect();
    let beams = tim551_beams();
    let gains = FormationGains::DEFAULT;
    let lim = &sc.limits;
    let mut scans = 0;
    let (mut times_s, mut truth_v, mut truth_robots) =
        (Vec::new(), Vec::new(), vec![Vec::new(); robots.len()]);
    for (step, r) in reference.iter().enumerate() {
        // Control, closed on odometry.
        for (i, rid) in robots.iter().enumerate() {
            let in_v = r.pose.inverse() * odom[i];
            let cmd = member_command(r.v_mps, r.w_radps, slots[i], &in_v, &gains);
            let cmd = limit_twist(
                cmd,
                last_cmd[i],
                setup.physics_dt_s,
                lim.max_speed_mps.get(),
                lim.max_yaw_rate_radps.get(),
                lim.max_accel_mps2.get(),
            );
            last_cmd[i] = cmd;
            world.command(*rid, cmd.0, cmd.1);
        }
        world.step(setup.physics_dt_s);
        for (i, rid) in robots.iter().enumerate() {
            let enc = world.encoders_rad(*rid).unwrap_or(last_enc[i]);
            let inc = wheel_odometry_increment(
                enc[0] - last_enc[i][0],
                enc[1] - last_enc[i][1],
                setup.robot.wheel_radius_m,
                setup.robot.track_width_m,
            );
            odom[i] = odom[i] * inc;
            last_enc[i] = enc;
        }
        if step % setup.steps_per_scan != 0 {
            continue;
        }
        scans += 1;
        let t = world.time_s();
        let scan_list: Vec<_> =
            robots.iter().map(|rid| world.scan(*rid, &beams).unwrap_or_else(|| beams.clone())).collect();
        let truth: Vec<Se2> = robots.iter().map(|rid| world.pose(*rid).unwrap_or(start_v)).collect();
        let v_true = v_of(&truth);
        let v_ref = v_of(&odom);
        times_s.push(t);
        truth_v.push([v_true.x, v_true.y, v_true.theta]);
        for (track, p) in truth_robots.iter_mut().zip(&truth) {
            track.push([p.x, p.y]);
        }
        let mut own_pose = Vec::new();
        for (i, f) in own.iter_mut().enumerate() {
            let pts = scan_points(&scan_list[i], &setup.robot.lidar_mount, &setup.amcl);
            f.update(odom[i], &pts, false);
            own_pose.push(f.pose_at(&odom[i]));
        }
        let t1 = own_pose.iter().copied().collect::<Option<Vec<Se2>>>().map(|p| v_of(&p));
        record(&mut series, Configuration::T1, t1, &v_true, &v_ref);
        let mut estimates = vec![(Configuration::T1, t1)];
        let mut virtual_scans = Vec::with_capacity(pipelines.len());
        let true_heading = (truth[0].inverse() * truth[1]).theta;
        for (c, pipeline, vamcl) in &mut pipelines {
            let packets: Vec<RobotPacket<'_>> = scan_list
                .iter()
                .zip(&own_pose)
                .map(|(s, p)| RobotPacket {
                    scan: s,
                    times: PacketTimes { stamp_s: t, received_s: t + 0.01 },
                    lidar_to_base: setup.robot.lidar_mount,
                    chassis: &setup.robot.chassis,
                    weight: 1.0,
                    amcl_pose: *p,
                })
                .collect();
            let started = std::time::Instant::now();
            let result = pipeline.update(&packets);
            let elapsed = started.elapsed().as_secs_f64();
            if let Some(s) = series.iter_mut().find(|(k, _)| k == c).map(|(_, s)| s) {
                s.updates += 1;
                s.pipeline_s += elapsed;
                match &result {
                    Ok(u) => {
                        let failed = u.pairs.first().is_some_and(|p| {
                            p.heading_source == amr_core::vamr::pipeline::Source::PreviousHeading
                        });
                        s.heading_failures += usize::from(failed);
                        if let Some(rel) = u.relative.get(1) {
                            s.heading_errors_rad.push(amr_core::se2::angle_diff(rel.theta, true_heading));
                        }
                    }
                    Err(amr_core::vamr::pipeline::UpdateError::NoHeading { .. }) => s.heading_failures += 1,
                    Err(_) => {}
                }
            }
            let mut fused_points = None;
            let est = result.ok().and_then(|u| {
                let points: Vec<[f64; 2]> = u.virtual_scan.as_ref()?.points.iter().map(|(p, _)| *p).collect();
                let v_odom = odom[0] * u.v_in_reference;
                vamcl.update(v_odom, &points, false);
                fused_points = Some(points);
                vamcl.pose_at(&v_odom)
            });
            record(&mut series, *c, est, &v_true, &v_ref);
            estimates.push((*c, est));
            virtual_scans.push((*c, fused_points));
        }
        let filters: Vec<(Configuration, &Amcl)> = pipelines.iter().map(|(c, _, f)| (*c, f)).collect();
        observe(&TrialFrame {
            t_s: t,
            scans: &scan_list,
            truth: &truth,
            odom: &odom,
            estimates: &estimates,
            virtual_scans: &virtual_scans,
            filters: &filters,
        });
    }
    let final_particles_t4 = pipelines
        .iter()
        .find(|(c, _, _)| *c == Configuration::T4)
        .map(|(_, _, f)| f.particles().iter().map(|p| [p.pose.x, p.pose.y]).collect())
        .unwrap_or_default();
    Trial { seed, scans, series, times_s, truth_v, truth_robots, final_particles_t4 }
}

/// Pooled and trial-level statistics of one configuration.
#[derive(Debug, Clone, Serialize)]
pub struct ConfigSummary {
    pub configuration: String,
    pub pooled_truth: Option<AxisStats>,
    pub pooled_reference: Option<AxisStats>,
    /// Trial-level 2D RMSE against the truth, mean ± SD over trials.
    pub trial_rmse_2d: Option<MeanSd>,
    pub missing: usize,
    /// The paper's trial-level 2D RMSE, mean and SD (Tables 15–16), when it gives one.
    pub paper_rmse_2d: Option<(f64, f64)>,
}

/// The paper's trial-level 2D RMSE (spec §10).
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
            ConfigSummary {
                configuration: format!("{c:?}"),
                pooled_truth: pooled(|s| &s.truth),
                pooled_reference: pooled(|s| &s.reference),
                trial_rmse_2d: MeanSd::of(&per_trial),
                missing: all.iter().map(|s| s.missing).sum(),
                paper_rmse_2d: paper_rmse(scenario, *c),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests;
