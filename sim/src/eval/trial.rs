//! One trial's loop: the world stepped under the formation's control, every robot's own odometry,
//! and at each scan step the robots' scans offered to the server core, T1–T4 side by side.

use std::sync::Arc;
use std::time::Instant;

use amr_actors::server::core::{CoreSetup, Fusion, Lap, Member, ServerCore};
use amr_core::amcl::{Amcl, LikelihoodField};
use amr_core::config::Configuration;
use amr_core::formation::{FormationGains, limit_twist, member_command};
use amr_core::odometry::{Odometer, Travel};
use amr_core::plan::{Reference, reference};
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use amr_msgs::{Estimate, EstimateSource, ScanMsg, Uplink};
use hil_mocks::world::{World, tim551_beams};

use super::{
    CONFIGS, Points, Series, Setup, Trial, TrialFrame, VISIBILITY_EVERY, View, config_index, error, record,
    slots, v_of,
};

/// The sync gate of a trial: every robot scans at the same instant and the server receives the
/// scans 10 ms later.
const MAX_SPREAD_S: f64 = 0.05;
const MAX_AGE_S: f64 = 0.1;
const RX_DELAY_S: f64 = 0.01;
/// Time the robots stand still before the reference starts, s (their odometry learns the gyro
/// bias meanwhile; no scan is taken).
const STANDSTILL_S: f64 = 2.0;

/// [`run_trial`](super::run_trial), calling `observe` after every scan step.
///
/// The localisation is the server's own [`ServerCore`], running T1–T4 side by side on the same
/// scans (each configuration's estimates are what the server would give in that configuration
/// alone, but for one thing: the robots' own filters, which T1 is, mask their teammates where T4's
/// fusion placed them, where a server running T1 or T2 alone places them by the robots' own
/// estimates): robot `i`'s scans reach it as the uplink of `robot<i>`, with the odometry pose at
/// the scan, received 10 ms (`RX_DELAY_S`) after they were taken.
pub fn run_trial_observed(setup: &Setup, seed: u64, observe: &mut dyn FnMut(&TrialFrame<'_>)) -> Trial {
    let sc = &setup.scenario;
    let slots = slots(setup.robots, sc.spacing_m.get());
    let start_v = sc.start_pose();
    let mut world = World::new(setup.site.clone(), setup.noise, seed);
    let robots: Vec<usize> = slots
        .iter()
        .map(|y| world.add_robot(setup.robot.clone(), start_v * Se2::new(0.0, *y, 0.0)))
        .collect();
    let ids: Vec<String> = (0..robots.len()).map(|i| format!("robot{i}")).collect();
    let reference = reference(sc, setup.robots, setup.physics_dt_s);
    let mut core = server_core(setup, seed, &slots, &ids);
    let mut odometry = Odometry::new(&mut world, &robots, start_v);
    // The robots stand still first, as after power-up: their odometry learns each gyro's bias.
    for _ in 0..(STANDSTILL_S / setup.physics_dt_s).round() as usize {
        world.step(setup.physics_dt_s);
        odometry.step(&mut world, &robots, setup);
    }
    let mut last_cmd = vec![(0.0, 0.0); robots.len()];
    let mut series: Vec<(Configuration, Series)> = CONFIGS.iter().map(|c| (*c, Series::default())).collect();
    let beams = tim551_beams();
    let mut scans = 0;
    let (mut times_s, mut truth_v, mut truth_robots) =
        (Vec::new(), Vec::new(), vec![Vec::new(); robots.len()]);
    let mut views: Vec<(f64, f64, f64, usize)> = vec![(0.0, 0.0, 0.0, 0); robots.len()];
    for (step, r) in reference.iter().enumerate() {
        follow(&mut world, &robots, r, &odometry.odom, &slots, &mut last_cmd, setup);
        world.step(setup.physics_dt_s);
        odometry.step(&mut world, &robots, setup);
        if step % setup.steps_per_scan != 0 {
            continue;
        }
        scans += 1;
        if (scans - 1) % VISIBILITY_EVERY == 0 {
            count_views(&mut views, &world, &robots, &beams);
        }
        let t = world.time_s();
        let scan_list: Vec<Arc<Scan>> = robots
            .iter()
            .map(|rid| Arc::new(world.scan(*rid, &beams).unwrap_or_else(|| beams.clone())))
            .collect();
        let truth: Vec<Se2> = robots.iter().map(|rid| world.pose(*rid).unwrap_or(start_v)).collect();
        let v_true = v_of(&truth);
        let v_ref = v_of(&odometry.odom);
        times_s.push(t);
        truth_v.push([v_true.x, v_true.y, v_true.theta]);
        for (track, p) in truth_robots.iter_mut().zip(&truth) {
            track.push([p.x, p.y]);
        }
        let step = ScanStep { t, seq: scans as u64, scans: &scan_list, truth: &truth, odom: &odometry.odom };
        let round = offer(&mut core, setup, &ids, &step, &mut series);
        for (c, est) in &round.estimates {
            record(&mut series, *c, *est, &v_true, &v_ref);
        }
        for ((_, s), placed) in series.iter_mut().zip(&round.placed) {
            s.robots.resize(truth.len(), Vec::new());
            for ((errors, est), t) in s.robots.iter_mut().zip(placed).zip(&truth) {
                if let Some(e) = est {
                    errors.push(error(e, t));
                }
            }
        }
        let filters: Vec<(Configuration, &Amcl)> = CONFIGS[1..]
            .iter()
            .filter_map(|c| core.filter(EstimateSource::Fused(*c)).map(|f| (*c, f)))
            .collect();
        let frame_estimates: Vec<(Configuration, Option<Se2>)> =
            round.estimates.iter().map(|(c, e)| (*c, e.map(|(v, _)| v))).collect();
        observe(&TrialFrame {
            t_s: t,
            scans: &scan_list,
            truth: &truth,
            odom: &odometry.odom,
            estimates: &frame_estimates,
            virtual_scans: &round.virtual_scans,
            filters: &filters,
            uplink: &round.offered,
        });
    }
    let final_particles_t4 = core
        .filter(EstimateSource::Fused(Configuration::T4))
        .map(|f| f.particles().iter().map(|p| [p.pose.x, p.pose.y]).collect())
        .unwrap_or_default();
    let visibility = views
        .iter()
        .map(|(o, l, site, n)| {
            let n = (*n).max(1) as f64;
            View { occluded: o / n, site_left: l / n, site: site / n }
        })
        .collect();
    Trial { seed, scans, series, times_s, truth_v, truth_robots, final_particles_t4, visibility }
}

/// The server's sans-IO core for a trial: every robot a member, T1–T4 side by side, V's filter
/// started at the scenario's start pose.
fn server_core(setup: &Setup, seed: u64, slots: &[f64], ids: &[String]) -> ServerCore {
    ServerCore::new(CoreSetup {
        members: slots
            .iter()
            .zip(ids)
            .map(|(y, id)| Member {
                id: id.clone(),
                lidar_to_base: setup.robot.lidar_mount,
                chassis: setup.robot.chassis.clone(),
                weight: 1.0,
                slot_y_m: *y,
            })
            .collect(),
        configurations: CONFIGS.to_vec(),
        vamr: setup.vamr.clone(),
        max_spread_s: MAX_SPREAD_S,
        max_age_s: MAX_AGE_S,
        amcl: setup.amcl.clone(),
        field: Arc::new(LikelihoodField::new(
            &setup.map.for_trial(seed),
            &setup.amcl,
            tim551_beams().range_max_m,
        )),
        initial_v: setup.scenario.start_pose(),
        seed,
        oracle: setup.oracle,
        checks: amr_core::config::IntegrityChecks::default(),
    })
}

/// Each robot's own odometry (wheels for distance, the gyro for heading), as `amr robot` computes
/// it, as poses in the map frame from the known start poses.
struct Odometry {
    starts: Vec<Se2>,
    odom: Vec<Se2>,
    odometers: Vec<Odometer>,
    last_enc: Vec<[f64; 2]>,
}

impl Odometry {
    fn new(world: &mut World, robots: &[usize], start_v: Se2) -> Self {
        let starts: Vec<Se2> = robots.iter().map(|r| world.pose(*r).unwrap_or(start_v)).collect();
        Odometry {
            odom: starts.clone(),
            starts,
            odometers: vec![Odometer::new(); robots.len()],
            last_enc: robots.iter().map(|r| world.encoders_rad(*r).unwrap_or([0.0; 2])).collect(),
        }
    }

    /// One physics step: the gyro and the wheels' travel since the last.
    fn step(&mut self, world: &mut World, robots: &[usize], setup: &Setup) {
        let t = world.time_s();
        for (i, rid) in robots.iter().enumerate() {
            if let Some(rate) = world.gyro_radps(*rid) {
                self.odometers[i].gyro(t, rate);
            }
            let enc = world.encoders_rad(*rid).unwrap_or(self.last_enc[i]);
            let r = setup.robot.wheel_radius_m;
            let travel = Travel {
                stamp_s: t,
                dt_s: setup.physics_dt_s,
                left_m: (enc[0] - self.last_enc[i][0]) * r,
                right_m: (enc[1] - self.last_enc[i][1]) * r,
            };
            self.odometers[i].step(&travel, setup.robot.track_width_m);
            self.odom[i] = self.starts[i] * self.odometers[i].pose();
            self.last_enc[i] = enc;
        }
    }
}

/// Control, closed on the true poses: the formation holds its geometry whatever the odometry's
/// systematic errors, so that T1–T4 are compared on one sensor stream and one occlusion geometry.
/// (Closed on odometry, a 0.5 % track-width error alone turns a robot 1.8° a lap away from its
/// slot, and after a few laps of `turning` the formation is no longer the one the scenario
/// describes.)
fn follow(
    world: &mut World,
    robots: &[usize],
    r: &Reference,
    odom: &[Se2],
    slots: &[f64],
    last_cmd: &mut [(f64, f64)],
    setup: &Setup,
) {
    let lim = &setup.scenario.limits;
    for (i, rid) in robots.iter().enumerate() {
        let in_v = r.pose.inverse() * world.pose(*rid).unwrap_or(odom[i]);
        let cmd = member_command(r.v_mps, r.w_radps, slots[i], &in_v, &FormationGains::DEFAULT);
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
}

/// What each robot's LiDAR sees now, added to its running sums.
fn count_views(views: &mut [(f64, f64, f64, usize)], world: &World, robots: &[usize], beams: &Scan) {
    for (acc, rid) in views.iter_mut().zip(robots) {
        if let Some(v) = world.visibility(*rid, beams) {
            acc.0 += v.on_robots as f64 / v.beams.max(1) as f64;
            acc.1 += if v.site_alone == 0 { 1.0 } else { v.site_left as f64 / v.site_alone as f64 };
            acc.2 += v.site_left as f64 / v.beams.max(1) as f64;
            acc.3 += 1;
        }
    }
}

/// One scan step's inputs.
struct ScanStep<'a> {
    t: f64,
    seq: u64,
    scans: &'a [Arc<Scan>],
    truth: &'a [Se2],
    odom: &'a [Se2],
}

/// What the server core gave for one scan step.
struct Round {
    /// V and whether it was verified, per configuration.
    estimates: Vec<(Configuration, Option<(Se2, bool)>)>,
    /// Per configuration, where it placed each robot.
    placed: Vec<Vec<Option<Se2>>>,
    /// T2–T4: the virtual scan each fused, when it did.
    virtual_scans: Vec<(Configuration, Option<Points>)>,
    /// The uplinks offered, with the time each was received.
    offered: Vec<(Uplink, f64)>,
}

/// Offer each robot's scan to the server core; the pipelines' timings, updates and heading
/// errors go into `series`.
fn offer(
    core: &mut ServerCore,
    setup: &Setup,
    ids: &[String],
    step: &ScanStep<'_>,
    series: &mut [(Configuration, Series)],
) -> Round {
    let n = step.scans.len();
    let mut round = Round {
        estimates: CONFIGS.iter().map(|c| (*c, None)).collect(),
        placed: vec![vec![None; n]; CONFIGS.len()],
        virtual_scans: CONFIGS[1..].iter().map(|c| (*c, None)).collect(),
        offered: Vec::with_capacity(n),
    };
    let true_heading = step.truth.get(1).map(|b| (step.truth[0].inverse() * *b).theta);
    for (i, scan) in step.scans.iter().enumerate() {
        if setup.oracle != amr_core::vamr::pipeline::Oracle::default() {
            core.set_truth(i, step.truth[i]);
        }
        let msg = Uplink::Scan(ScanMsg {
            robot: ids[i].clone(),
            seq: step.seq,
            stamp_s: step.t,
            received_s: step.t,
            scan: Arc::clone(scan),
            odom: Some(step.odom[i]),
            odom_frame: 1,
        });
        let mut last = Instant::now();
        let mut pipeline_s = [0.0; 4];
        let out = core.offer(&msg, step.t + RX_DELAY_S, &mut |lap| {
            let now = Instant::now();
            if let Lap::Pipeline(c, _) = lap {
                pipeline_s[config_index(c)] += now.duration_since(last).as_secs_f64();
            }
            last = now;
        });
        for f in &out.fusions {
            fused(f, &pipeline_s, true_heading, series, &mut round.virtual_scans);
        }
        for e in &out.estimates {
            place(e, &mut round);
        }
        round.offered.push((msg, step.t + RX_DELAY_S));
    }
    round
}

/// A pipeline's fusion into its configuration's series: time spent, update, heading failure and
/// error; its virtual scan kept for the frame.
fn fused(
    f: &Fusion,
    pipeline_s: &[f64; 4],
    true_heading: Option<f64>,
    series: &mut [(Configuration, Series)],
    virtual_scans: &mut [(Configuration, Option<Points>)],
) {
    let k = config_index(f.configuration);
    let Some((_, s)) = series.get_mut(k) else { return };
    s.pipeline_s += pipeline_s[k];
    if f.configuration == Configuration::T1 {
        return;
    }
    s.updates += 1;
    s.heading_failures += usize::from(f.heading_failed);
    if let Ok(frame) = &f.result {
        if let (Some(truth), [(b0, _), (b1, _), ..]) = (true_heading, frame.robots.as_slice()) {
            s.heading_errors_rad.push(amr_core::se2::angle_diff((b0.inverse() * *b1).theta, truth));
        }
        if let Some(slot) = virtual_scans.iter_mut().find(|(c, _)| *c == f.configuration) {
            slot.1.clone_from(&frame.points);
        }
    }
}

/// A fused estimate: V (and whether it is verified) and where it places each robot.
fn place(e: &Estimate, round: &mut Round) {
    if let (EstimateSource::Fused(c), Some(v)) = (e.source, e.v) {
        round.estimates[config_index(c)].1 = Some((v, e.integrity.verified()));
        for (slot, a) in round.placed[config_index(c)].iter_mut().zip(&e.robots) {
            if let Some(a) = a {
                *slot = Some(a.map);
            }
        }
    }
}
