//! AMCL in a simulated corridor-and-rooms building: scans ray-cast from the true pose, odometry
//! with drift, the map rasterised from the same walls.
//!
//! It is one file because every scenario runs the filter in the same simulated building, along the
//! same path with the same drifting odometry and run loop.

use std::sync::Arc;

use super::IntegrityState;
use super::{Amcl, LikelihoodField, UpdateOutcome, scan_points, tests::shipped_params};
use crate::config::AmclParams;
use crate::config::value::Fraction;
use crate::geometry::{Polygon, cast_ray};
use crate::map::{FREE, OCCUPIED, OccupancyGrid, UNKNOWN};
use crate::rng::Rng;
use crate::scan::Scan;
use crate::se2::{Se2, angle_diff};

struct Building {
    walls: Vec<Polygon>,
    grid: OccupancyGrid,
    /// Where the building's corner stands in the map frame.
    at: [f64; 2],
}

fn wall(x0: f64, y0: f64, x1: f64, y1: f64) -> Polygon {
    Polygon::new(vec![[x0, y0], [x1, y0], [x1, y1], [x0, y1]]).unwrap()
}

/// 12 m × 8 m: a corridor along y = 3.5–4.5 with three doors on each side into six rooms, and two
/// features (a triangle in the top-right room, a box in the bottom-left one) that break the
/// building's symmetry.
fn building() -> Building {
    building_at([0.0, 0.0])
}

/// [`building`] with its corner at `at` in the map frame.
fn building_at(at: [f64; 2]) -> Building {
    let t = 0.1;
    let mut walls = vec![
        wall(0.0, 0.0, 12.0, t),
        wall(0.0, 8.0 - t, 12.0, 8.0),
        wall(0.0, 0.0, t, 8.0),
        wall(12.0 - t, 0.0, 12.0, 8.0),
    ];
    for y in [3.5, 4.5 - t] {
        let mut x = 0.0;
        for door in [1.5, 5.5, 9.5] {
            walls.push(wall(x, y, door, y + t));
            x = door + 1.0;
        }
        walls.push(wall(x, y, 12.0, y + t));
    }
    for x in [4.0, 8.0] {
        walls.push(wall(x, 0.0, x + t, 3.5));
        walls.push(wall(x, 4.5, x + t, 8.0));
    }
    walls.push(Polygon::new(vec![[10.0, 6.0], [11.2, 6.3], [10.4, 7.2]]).unwrap());
    walls.push(wall(1.0, 1.0, 1.6, 1.4));
    let res = 0.05;
    let mut grid = OccupancyGrid::filled(250, 170, res, Se2::new(at[0] - 0.25, at[1] - 0.25, 0.0), UNKNOWN);
    for j in 0..grid.height {
        for i in 0..grid.width {
            let [x, y] = grid.cell_center(i, j);
            let c = [x - at[0], y - at[1]];
            let inside = (0.0..=12.0).contains(&c[0]) && (0.0..=8.0).contains(&c[1]);
            if walls.iter().any(|w| w.contains(c)) {
                grid.set(i, j, OCCUPIED);
            } else if inside {
                grid.set(i, j, FREE);
            }
        }
    }
    Building { walls, grid, at }
}

impl Building {
    /// A 271-beam, 270° scan from `pose` (LiDAR at the base origin), with range noise.
    fn scan(&self, pose: &Se2, rng: &mut Rng) -> Scan {
        let geom = Scan::new(-135f64.to_radians(), 1f64.to_radians(), 0.05, 10.0, vec![f64::NAN; 271]);
        let local = Se2::new(pose.x - self.at[0], pose.y - self.at[1], pose.theta);
        ray_cast(&self.walls, &local, geom, rng)
    }
}

/// The beams of `geom` (ranges unused) cast from `pose` into `walls`, with 1 cm range noise; no
/// return within the scan's maximum range is NaN.
pub(super) fn ray_cast(walls: &[Polygon], pose: &Se2, geom: Scan, rng: &mut Rng) -> Scan {
    let scene: Vec<(Se2, &Polygon)> = walls.iter().map(|w| (Se2::IDENTITY, w)).collect();
    let max = geom.range_max_m;
    let ranges = (0..geom.len())
        .map(|i| {
            cast_ray([pose.x, pose.y], pose.theta + geom.angle(i), max, &scene)
                .map_or(f64::NAN, |r| r + rng.gaussian(0.01))
        })
        .collect();
    geom.with_ranges(ranges)
}

/// True poses every 0.1 m along a path through the corridor and into a room.
fn path() -> Vec<Se2> {
    let mut poses = Vec::new();
    for k in 0..=90 {
        poses.push(Se2::new(1.0 + 0.1 * f64::from(k), 4.0, 0.0));
    }
    for k in 1..=16 {
        poses.push(Se2::new(10.0, 4.0, f64::from(k) * std::f64::consts::FRAC_PI_2 / 16.0));
    }
    for k in 1..=25 {
        poses.push(Se2::new(10.0, 4.0 + 0.1 * f64::from(k), std::f64::consts::FRAC_PI_2));
    }
    poses
}

/// Odometry that drifts: each true increment with 1 % scale error and a heading bias of 0.3°/m, plus
/// noise — a plain differential drive on a good floor.
fn odometry(truth: &[Se2], rng: &mut Rng) -> Vec<Se2> {
    let mut odom = vec![Se2::new(0.5, -0.3, 0.2)];
    for w in truth.windows(2) {
        let inc = w[0].inverse() * w[1];
        let bias = 0.3f64.to_radians() * inc.x.abs();
        let noisy = Se2::new(
            inc.x * (1.01 + rng.gaussian(0.005)),
            inc.y + rng.gaussian(0.001),
            inc.theta * 1.01 + bias + rng.gaussian(0.001),
        );
        let last = *odom.last().unwrap();
        odom.push(last * noisy);
    }
    odom
}

struct Run {
    errors_m: Vec<f64>,
    heading_errors_rad: Vec<f64>,
    poses: Vec<Se2>,
}

fn run(amcl: &mut Amcl, b: &Building, truth: &[Se2], odom: &[Se2], seed: u64, params: &AmclParams) -> Run {
    let mut rng = Rng::seed(seed);
    let mut out = Run { errors_m: Vec::new(), heading_errors_rad: Vec::new(), poses: Vec::new() };
    for (t, o) in truth.iter().zip(odom) {
        let scan = b.scan(t, &mut rng);
        let points = scan_points(&scan, &Se2::IDENTITY, params);
        if let UpdateOutcome::Updated { .. } = amcl.update(*o, &points, false) {
            let e = amcl.estimate().unwrap().pose;
            out.errors_m.push((e.x - t.x).hypot(e.y - t.y));
            out.heading_errors_rad.push(angle_diff(e.theta, t.theta).abs());
            out.poses.push(e);
        }
    }
    out
}

/// nav2's defaults assume poor odometry (α = 0.2: σ ≈ 13 cm per 0.3 m step) and a coarse sensor
/// (σ_hit = 0.2 m); for the odometry and the TiM-like scanner here they are set as a user would.
/// The odometry below errs by 1 % ± 0.5 % in distance and 0.3°/m in heading; α = 0.005 gives
/// σ_trans ≈ 7 % of the distance and σ_rot ≈ 1.2° per 0.3 m, still about five times that error.
fn tuned_params() -> AmclParams {
    let mut p = shipped_params();
    let a = crate::config::value::NonNegative::new(0.005).unwrap();
    (p.alpha1, p.alpha2, p.alpha3, p.alpha4) = (a, a, a, a);
    // A TiM551 is far better than nav2's generic σ_hit = 0.2 m, and the product model uses it.
    p.sigma_hit = crate::config::value::Positive::new(0.1).unwrap();
    p.laser_model_type = crate::config::LaserModel::LikelihoodFieldProb;
    p.max_beams = crate::config::value::Count::new(120).unwrap();
    // This odometry never slips (1 % scale error, no reversals): no heavy tail.
    p.odom_slip_share = crate::config::value::Fraction::new(0.0).unwrap();
    p
}

/// Tracking from a known pose (10 cm / 3° off, spread 10 cm / 3°) through the corridor and into a
/// room, with 1 % odometry scale error: every estimate from the first filter update on is within
/// 5 cm. Measured (seeded, so exact): 44 updates, worst 4.3 cm, RMS 1.9 cm, worst heading 0.28°
/// with the field measuring to the occupied cells' *faces*; today (132 updates at the shipped 0.05 m
/// update distance) worst 4.6 cm and RMS 2.6 cm with a field which
/// measures to the surface cells' *centres*: this map is rendered from polygons, so its walls lie on
/// cell faces, while maps built the way SLAM builds them (the ones robots get) have their surfaces
/// at the centres of the endpoint cells, where the face distance cost 1.5–2 cm RMS per scan
/// (`likelihood.rs`). The sim's map is the less realistic one, so the bound here is 3 cm.
///
/// History: with nav2's likelihood field (distance to occupied cell centres, 0 inside walls) and
/// α = 0.02 the worst was 5.3 cm; with that field and α = 0.005, 4.3–5.2 cm over the same 20 seeds.
/// The corridor's position along its length is fixed only by faces seen from one side, where nav2's
/// field is flat over the wall's thickness (see `likelihood.rs`); with the distance to the surface it
/// is 2.7–4.3 cm.
#[test]
fn tracking_from_a_known_pose_stays_close() {
    let b = building();
    let params = tuned_params();
    let field = Arc::new(LikelihoodField::new(&b.grid, &params, 10.0));
    let truth = path();
    let odom = odometry(&truth, &mut Rng::seed(11));
    let mut amcl = Amcl::new(params.clone(), field, 5);
    amcl.init_pose(Se2::new(1.05, 3.95, 0.03), 0.1, 0.05);
    let r = run(&mut amcl, &b, &truth, &odom, 21, &params);
    assert!(r.errors_m.len() > 30, "{} updates", r.errors_m.len());
    // From the first update (it already has the first scan) to the end:
    let worst = r.errors_m.iter().copied().fold(0.0, f64::max);
    let rms = (r.errors_m.iter().map(|e| e * e).sum::<f64>() / r.errors_m.len() as f64).sqrt();
    let worst_heading = r.heading_errors_rad.iter().copied().fold(0.0, f64::max);
    eprintln!(
        "tracking: {} updates, worst {worst:.4} m, RMS {rms:.4} m, worst heading {:.2}°",
        r.errors_m.len(),
        worst_heading.to_degrees()
    );
    assert!(worst <= 0.05, "worst position error {worst:.3} m over {:?}", r.errors_m);
    assert!(rms <= 0.03, "RMS position error {rms:.3} m");
    assert!(worst_heading <= 1f64.to_radians(), "worst heading error {:.2}°", worst_heading.to_degrees());
}

/// The same run with other seeds for the filter, the odometry noise and the range noise: the 5 cm
/// bound is not one lucky draw.
#[test]
fn tracking_holds_over_seeds() {
    let b = building();
    let params = tuned_params();
    let field = Arc::new(LikelihoodField::new(&b.grid, &params, 10.0));
    let truth = path();
    let mut worsts = Vec::new();
    for s in 0..20u64 {
        let odom = odometry(&truth, &mut Rng::seed(11 + 100 * s));
        let mut amcl = Amcl::new(params.clone(), Arc::clone(&field), 5 + s);
        amcl.init_pose(Se2::new(1.05, 3.95, 0.03), 0.1, 0.05);
        let r = run(&mut amcl, &b, &truth, &odom, 21 + s, &params);
        worsts.push(r.errors_m.iter().copied().fold(0.0, f64::max));
    }
    let worst = worsts.iter().copied().fold(0.0, f64::max);
    eprintln!("tracking over 20 seeds: worst {worst:.4} m");
    assert!(worst <= 0.05, "worst position error per seed {worsts:?}");
}

#[test]
fn same_seed_same_bits() {
    let b = building();
    let params = shipped_params();
    let field = Arc::new(LikelihoodField::new(&b.grid, &params, 10.0));
    let truth = path();
    let odom = odometry(&truth, &mut Rng::seed(11));
    let go = |seed| {
        let mut amcl = Amcl::new(params.clone(), Arc::clone(&field), seed);
        amcl.init_pose(Se2::new(1.05, 3.95, 0.03), 0.1, 0.05);
        let r = run(&mut amcl, &b, &truth[..40], &odom[..40], 21, &params);
        (r.poses, amcl.particles().to_vec())
    };
    let (a, pa) = go(5);
    let (b2, pb) = go(5);
    let bits = |v: &[Se2]| {
        v.iter().flat_map(|p| [p.x.to_bits(), p.y.to_bits(), p.theta.to_bits()]).collect::<Vec<_>>()
    };
    assert_eq!(bits(&a), bits(&b2));
    assert_eq!(pa, pb);
    let (c, _) = go(6);
    assert_ne!(bits(&a), bits(&c), "another seed draws other particles");
}

#[test]
fn global_localisation_converges() {
    let b = building();
    let mut params = shipped_params();
    params.max_particles = crate::config::value::Count::new(5000).unwrap();
    let field = Arc::new(LikelihoodField::new(&b.grid, &params, 10.0));
    let truth = path();
    let odom = odometry(&truth, &mut Rng::seed(12));
    let mut amcl = Amcl::new(params.clone(), field, 9);
    amcl.init_global();
    let r = run(&mut amcl, &b, &truth, &odom, 22, &params);
    let n = r.errors_m.len();
    let (last_err, last_heading) = (r.errors_m[n - 1], r.heading_errors_rad[n - 1]);
    assert!(
        last_err < 0.1 && last_heading < 5f64.to_radians(),
        "final error {last_err:.3} m, {:.1}°; errors {:?}",
        last_heading.to_degrees(),
        r.errors_m
    );
}

/// The kidnapping scenario: track along the corridor, then the robot is carried into the top-right
/// room (the one with the triangle) without the odometry seeing it, and drives on there. Returns,
/// for each update after the kidnapping, the position and heading error, and the number of
/// injecting resampling steps before and after the kidnapping.
struct Kidnapping {
    errors_after: Vec<(f64, f64)>,
    /// The integrity state at every update, before and after.
    states_before: Vec<IntegrityState>,
    states_after: Vec<IntegrityState>,
    injections_before: u64,
    injections_after: u64,
}

fn kidnapping(params: &AmclParams, seed: u64, destination: Se2) -> Kidnapping {
    let b = building();
    let field = Arc::new(LikelihoodField::new(&b.grid, params, 10.0));
    let before: Vec<Se2> = (0..30).map(|k| Se2::new(1.0 + 0.1 * f64::from(k), 4.0, 0.0)).collect();
    let after: Vec<Se2> = (0..60).map(|k| destination * Se2::new(0.03 * f64::from(k), 0.0, 0.0)).collect();
    let truth: Vec<Se2> = before.iter().chain(&after).copied().collect();
    // The odometry sees only the motion within each phase, not the jump.
    let mut odom = odometry(&before, &mut Rng::seed(13 + seed));
    let tail = odometry(&after, &mut Rng::seed(14 + seed));
    let joint = *odom.last().unwrap() * tail[0].inverse();
    odom.extend(tail.iter().map(|o| joint * *o));

    let mut amcl = Amcl::new(params.clone(), field, 17 + seed);
    amcl.init_pose(truth[0], 0.05, 0.02);
    let mut rng = Rng::seed(23 + seed);
    let mut out = Kidnapping {
        errors_after: Vec::new(),
        states_before: Vec::new(),
        states_after: Vec::new(),
        injections_before: 0,
        injections_after: 0,
    };
    for (k, (t, o)) in truth.iter().zip(&odom).enumerate() {
        let scan = b.scan(t, &mut rng);
        amcl.update(*o, &scan_points(&scan, &Se2::IDENTITY, params), true);
        let e = amcl.estimate().unwrap().pose;
        let state = amcl.integrity_state();
        if k < before.len() {
            out.states_before.push(state);
            if k == before.len() - 1 {
                assert!((e.x - t.x).hypot(e.y - t.y) < 0.2, "tracked before the kidnapping: {e:?} vs {t:?}");
                out.injections_before = amcl.injections();
            }
        } else {
            out.states_after.push(state);
            out.errors_after.push(((e.x - t.x).hypot(e.y - t.y), angle_diff(e.theta, t.theta).abs()));
        }
    }
    out.injections_after = amcl.injections();
    out
}

/// The first update after the kidnapping from which on every estimate is within 0.3 m and 10°.
fn recovered_from(errors: &[(f64, f64)]) -> Option<usize> {
    let ok = |e: &(f64, f64)| e.0 <= 0.3 && e.1 <= 10f64.to_radians();
    let last_bad = errors.iter().rposition(|e| !ok(e));
    match last_bad {
        None => Some(0),
        Some(i) if i + 1 < errors.len() => Some(i + 1),
        Some(_) => None,
    }
}

/// The tracking test's sensor settings with nav2's suggested recovery alphas 0.001 / 0.1 (docs.nav2.org)
/// and nav2's default 500–2000 particles; the integrity monitor's re-seeding off, so that what
/// recovers is the alphas' injection alone.
fn recovery_params() -> AmclParams {
    let mut p = tuned_params();
    p.recovery_alpha_slow = Fraction::new(0.001).unwrap();
    p.recovery_alpha_fast = Fraction::new(0.1).unwrap();
    p.integrity.reseed_share = 0.0;
    p
}

/// Without the alphas (nav2's default, and ours), the integrity monitor finds the kidnapping and
/// re-localises: on every seed the filter reports `Lost` within 3 updates of being carried off,
/// is back within 0.3 m / 10° and reports `Tracking` within 10, and never reported `Lost` before.
#[test]
fn a_kidnapped_filter_reports_lost_and_relocalises_by_itself() {
    let params = tuned_params();
    assert_eq!(params.recovery_alpha_slow.get(), 0.0);
    let to = Se2::new(8.6, 5.2, 0.0);
    for seed in 0..6 {
        let r = kidnapping(&params, seed, to);
        let lost = r.states_after.iter().position(|s| *s == IntegrityState::Lost);
        let back = recovered_from(&r.errors_after);
        let tracking = lost.and_then(|l| {
            r.states_after[l..].iter().position(|s| *s == IntegrityState::Tracking).map(|k| k + l)
        });
        eprintln!("seed {seed}: lost at {lost:?}, within 0.3 m from {back:?}, tracking at {tracking:?}");
        assert!(!r.states_before.contains(&IntegrityState::Lost), "seed {seed}: {:?}", r.states_before);
        assert!(lost.is_some_and(|l| l < 3), "seed {seed}: {:?}", r.states_after);
        assert!(back.is_some_and(|b| b < 10), "seed {seed}: {:?}", r.errors_after);
        assert!(tracking.is_some_and(|t| t < 10), "seed {seed}: {:?}", r.states_after);
    }
}

/// A robot standing still whose filter was started somewhere else (a restarted server starts its
/// filters where it last saw the formation, or where the configuration says) re-localises without
/// moving: standing still skips the motion update, but a lost filter is updated all the same, so
/// it re-seeds from the scan. A formation holds while a robot is lost, so this robot would stand
/// still for good otherwise. On every seed: `Lost` within 3 scans, within 0.3 m / 10° within 10,
/// and `Tracking` within 25 (measured, seeds 0–5: lost at the second scan, back from the third,
/// tracking from the 17th–20th: the building's mirror image, facing the other way at (10, 4),
/// explains 98 % of the scans, and the two are carried as twins until the scans, all from one
/// place, tell them apart).
#[test]
fn a_lost_filter_relocalises_while_the_robot_stands_still() {
    let params = tuned_params();
    let b = building();
    let field = Arc::new(LikelihoodField::new(&b.grid, &params, 10.0));
    let truth = Se2::new(2.0, 4.0, 0.0);
    let odom = Se2::new(0.4, -0.3, 0.2);
    for seed in 0..6 {
        let mut amcl = Amcl::new(params.clone(), Arc::clone(&field), 31 + seed);
        amcl.init_pose(Se2::new(8.6, 5.2, 0.0), 0.1, 0.05);
        let mut rng = Rng::seed(37 + seed);
        let (mut states, mut errors) = (Vec::new(), Vec::new());
        for _ in 0..40 {
            let scan = b.scan(&truth, &mut rng);
            amcl.update(odom, &scan_points(&scan, &Se2::IDENTITY, &params), false);
            let e = amcl.estimate().unwrap().pose;
            states.push(amcl.integrity_state());
            errors.push(((e.x - truth.x).hypot(e.y - truth.y), angle_diff(e.theta, truth.theta).abs()));
        }
        let lost = states.iter().position(|s| *s == IntegrityState::Lost);
        let back = recovered_from(&errors);
        let tracking =
            lost.and_then(|l| states[l..].iter().position(|s| *s == IntegrityState::Tracking).map(|k| k + l));
        eprintln!("seed {seed}: lost at {lost:?}, within 0.3 m from {back:?}, tracking at {tracking:?}");
        assert!(lost.is_some_and(|l| l < 3), "seed {seed}: {states:?}");
        assert!(back.is_some_and(|b| b < 10), "seed {seed}: {errors:?}");
        assert!(tracking.is_some_and(|t| t < 25), "seed {seed}: {states:?}");
        assert_eq!(states.last(), Some(&IntegrityState::Tracking), "seed {seed}: {states:?}");
    }
}

/// A robot lifted while standing still and set down elsewhere (or pushed, its wheels slipping):
/// the odometry sees nothing, so no motion triggers an update; the tracking filter judges the pose
/// on every 10th scan all the same, on any scan that falls below the lost bar, and on every scan
/// once one was bad, so it reports `Lost` within 3 scans of being carried off, then re-localises
/// without moving, tracking again within 10 (measured, seeds 0–5: lost at the second scan, back
/// from the third, tracking from the seventh). Never lost while it stood where it was tracked.
#[test]
fn a_robot_carried_off_while_standing_still_is_reported_lost_where_it_stands() {
    let params = tuned_params();
    let b = building();
    let field = Arc::new(LikelihoodField::new(&b.grid, &params, 10.0));
    let (here, there) = (Se2::new(2.0, 4.0, 0.0), Se2::new(8.6, 5.2, 0.0));
    let odom = Se2::new(0.4, -0.3, 0.2);
    for seed in 0..6 {
        let mut amcl = Amcl::new(params.clone(), Arc::clone(&field), 51 + seed);
        amcl.init_pose(here, 0.05, 0.02);
        let mut rng = Rng::seed(53 + seed);
        let mut states = Vec::new();
        let mut errors = Vec::new();
        for k in 0..50 {
            let truth = if k < 20 { here } else { there };
            let scan = b.scan(&truth, &mut rng);
            amcl.update(odom, &scan_points(&scan, &Se2::IDENTITY, &params), false);
            let e = amcl.pose_at(&odom).unwrap();
            states.push(amcl.integrity_state());
            errors.push(((e.x - truth.x).hypot(e.y - truth.y), angle_diff(e.theta, truth.theta).abs()));
        }
        let (before, after) = states.split_at(20);
        let lost = after.iter().position(|s| *s == IntegrityState::Lost);
        let back = recovered_from(&errors[20..]);
        let tracking =
            lost.and_then(|l| after[l..].iter().position(|s| *s == IntegrityState::Tracking).map(|k| k + l));
        eprintln!("seed {seed}: lost at {lost:?}, within 0.3 m from {back:?}, tracking at {tracking:?}");
        assert_eq!(before.last(), Some(&IntegrityState::Tracking), "seed {seed}: {before:?}");
        assert!(!before.contains(&IntegrityState::Lost), "seed {seed}: {before:?}");
        assert!(lost.is_some_and(|l| l < 3), "seed {seed}: {after:?}");
        assert!(back.is_some_and(|b| b < 10), "seed {seed}: {:?}", &errors[20..]);
        assert!(tracking.is_some_and(|t| t < 10), "seed {seed}: {after:?}");
    }
}

/// A robot standing still whose filter was started a little off (a restarted server's filters
/// start where it last saw the formation): the estimate is close enough that the map explains
/// part of the scan, so the filter is neither tracking nor lost. Standing still, it polishes its
/// estimate by matching the scan to the map, and turns `Tracking` on the right pose.
#[test]
fn a_filter_started_a_little_off_verifies_itself_while_the_robot_stands_still() {
    let params = tuned_params();
    let b = building();
    let field = Arc::new(LikelihoodField::new(&b.grid, &params, 10.0));
    let truth = Se2::new(2.0, 4.0, 0.0);
    let odom = Se2::new(0.4, -0.3, 0.2);
    for (seed, off) in
        [(0, Se2::new(0.25, 0.1, 0.08)), (1, Se2::new(-0.2, -0.15, -0.1)), (2, Se2::new(0.0, 0.3, 0.05))]
    {
        let mut amcl = Amcl::new(params.clone(), Arc::clone(&field), 41 + seed);
        amcl.init_pose(truth * off, 0.05, 0.02);
        let mut rng = Rng::seed(43 + seed);
        let mut states = Vec::new();
        for _ in 0..30 {
            let scan = b.scan(&truth, &mut rng);
            amcl.update(odom, &scan_points(&scan, &Se2::IDENTITY, &params), false);
            states.push(amcl.integrity_state());
        }
        let e = amcl.estimate().unwrap().pose;
        let err = ((e.x - truth.x).hypot(e.y - truth.y), angle_diff(e.theta, truth.theta).abs());
        eprintln!("seed {seed}: {states:?} error {err:?}");
        assert_eq!(states.last(), Some(&IntegrityState::Tracking), "seed {seed}: {states:?}");
        assert!(err.0 < 0.05 && err.1 < 2f64.to_radians(), "seed {seed}: {err:?}");
    }
}

/// A filter that tracked the first `updates` poses of `truth` from the first (a tight cloud), with
/// the odometry and the scans' generator it ran on (seed `seed`; the filter's, `seed + 1`).
struct Tracked {
    amcl: Amcl,
    odom: Vec<Se2>,
    rng: Rng,
}

fn tracked_along(b: &Building, params: &AmclParams, truth: &[Se2], updates: usize, seed: u64) -> Tracked {
    let mut rng = Rng::seed(seed);
    let odom = odometry(truth, &mut rng);
    let field = Arc::new(LikelihoodField::new(&b.grid, params, 10.0));
    let mut amcl = Amcl::new(params.clone(), field, seed + 1);
    amcl.init_pose(truth[0], 0.02, 0.01);
    for (t, o) in truth.iter().zip(&odom).take(updates) {
        let scan = b.scan(t, &mut rng);
        amcl.update(*o, &scan_points(&scan, &Se2::IDENTITY, params), false);
    }
    Tracked { amcl, odom, rng }
}

/// Every particle moved as one by `shift` in the frame of the estimate at odometry `odom`.
fn move_cloud(amcl: &mut Amcl, odom: &Se2, shift: Se2) {
    let at = amcl.pose_at(odom).unwrap();
    let e = amcl.estimate().unwrap().pose;
    // `at` moved by `shift` in its own frame is the estimate moved by the same map-frame motion.
    amcl.move_estimate_to(&e, &(at * shift * at.inverse() * e));
}

/// A driving robot whose filter's cloud slipped 12–14 cm and about 2° (a tight cloud, as one held
/// loosely by scans full of clutter drifts) while it was in doubt: after the update its estimate is
/// matched to the map and the cloud moved by the correction, within 4 cm and 0.5° of the robot.
/// The weighting alone leaves a tight cloud about where it slipped: it has no particle at the
/// robot (without the match, 11–14 cm off after the update). The same 250 m from the map's
/// origin, where a turn of 2° about the origin moves a pose 9 m: the match is judged by how far it
/// moves the estimate, not the origin.
#[test]
fn an_estimate_in_doubt_is_matched_to_the_map_after_the_update() {
    let params = tuned_params();
    for at in [[0.0, 0.0], [150.0, -200.0]] {
        let b = building_at(at);
        let truth: Vec<Se2> = path().iter().map(|p| Se2::new(p.x + at[0], p.y + at[1], p.theta)).collect();
        for (seed, slip) in [
            (0, Se2::new(0.05, -0.12, -0.03)),
            (1, Se2::new(-0.05, 0.12, 0.03)),
            (2, Se2::new(0.0, 0.12, -0.03)),
        ] {
            let Tracked { mut amcl, odom, mut rng } = tracked_along(&b, &params, &truth, 20, 90 + seed);
            assert_eq!(amcl.integrity_state(), IntegrityState::Tracking, "at {at:?} seed {seed}");
            // The cloud slips as one, and the filter is in doubt (as after `init_pose`).
            let (t, o) = (truth[20], odom[20]);
            move_cloud(&mut amcl, &o, slip);
            amcl.monitor.restart(IntegrityState::Uncertain);
            let error = |e: Se2| ((e.x - t.x).hypot(e.y - t.y), angle_diff(e.theta, t.theta).abs());
            let before = error(amcl.pose_at(&o).unwrap());
            let scan = b.scan(&t, &mut rng);
            amcl.update(o, &scan_points(&scan, &Se2::IDENTITY, &params), true);
            let after = error(amcl.estimate().unwrap().pose);
            eprintln!("at {at:?} seed {seed}: before {before:?}, after {after:?}, {:?}", amcl.integrity());
            assert!(before.0 > 0.1, "at {at:?} seed {seed}: slipped {before:?}");
            assert_eq!(amcl.integrity_state(), IntegrityState::Uncertain, "at {at:?} seed {seed}");
            assert!(
                after.0 < 0.04 && after.1 < 0.5f64.to_radians(),
                "at {at:?} seed {seed}: {before:?} -> {after:?}"
            );
        }
    }
}

/// A filter carried a little way along the corridor, or turned on the spot (a kidnapping whose
/// first, poorly explained scan the search found the truth on): the estimate explains most of each
/// scan after, below the uncertain bar but too much for a rival to explain `switch_margin` (0.3)
/// more. The rival at the truth explains the scans as a tracked place does and wins on that. Where
/// it stands away from the estimate (0.8 m, 1 m, a turn of 17°), the filter is `lost` on the
/// second scan, on the robot from the third and `tracking` from the fifth. (Winning only by the
/// margin, the filter stayed `uncertain` at the wrong place.) Turned 14°, the estimate is within
/// 10° of the rival after the first update: the rival corrects it, the filter is on the robot from
/// the second scan and never `lost` (declared lost, it was called lost for 2 scans while on it).
/// The search is off here (`alternative_draws` 0): what is tested is how the rival at the truth
/// wins. With it on, the search also finds the corridor's mirror image, which explains the scans
/// as well as the truth ([`a_filter_in_a_corridor_that_mirrors_itself_is_lost_among_twins`]).
#[test]
fn a_rival_at_the_truth_beats_an_estimate_that_explains_most_of_the_scan() {
    let mut params = tuned_params();
    params.integrity.alternative_draws = 0;
    let b = building();
    let truth = path();
    let shifts = [
        Se2::new(0.8, 0.0, 0.0),
        Se2::new(1.0, 0.0, 0.0),
        Se2::new(0.0, 0.0, 0.3),
        Se2::new(0.0, 0.0, -0.25),
    ];
    for (seed, shift) in (0..).zip(shifts) {
        let Tracked { mut amcl, odom, mut rng } = tracked_along(&b, &params, &truth, 30, 70 + seed);
        assert_eq!(amcl.integrity_state(), IntegrityState::Tracking, "seed {seed}");
        // The cloud carried off as one, and the truth carried as a rival.
        move_cloud(&mut amcl, &odom[30], shift);
        amcl.rivals.push(super::rivals::Rival::found(truth[30], odom[30]));
        let mut seen = Vec::new();
        for (t, o) in truth.iter().zip(&odom).skip(31).take(8) {
            let scan = b.scan(t, &mut rng);
            amcl.update(*o, &scan_points(&scan, &Se2::IDENTITY, &params), false);
            let e = amcl.estimate().unwrap().pose;
            let judged = amcl.monitor.last().map_or(0.0, |i| i.explained / i.level);
            let error = ((e.x - t.x).hypot(e.y - t.y), angle_diff(e.theta, t.theta).abs());
            seen.push((amcl.integrity_state(), judged, error));
        }
        eprintln!("seed {seed}: {seen:?}");
        let p = params.integrity;
        let (_, first, _) = seen[0];
        assert!(
            first >= p.lost_ratio && first < p.uncertain_ratio,
            "seed {seed}: explains {first} of the level"
        );
        let corrected = seed == 3;
        if corrected {
            assert!(seen.iter().all(|(s, _, _)| *s != IntegrityState::Lost), "seed {seed}: {seen:?}");
            assert!(seen[1..].iter().all(|(_, _, e)| e.0 < 0.06 && e.1 < 0.03), "seed {seed}: {seen:?}");
        } else {
            assert_eq!(seen[1].0, IntegrityState::Lost, "seed {seed}: {seen:?}");
        }
        assert!(seen[2..].iter().all(|(_, _, e)| e.0 < 0.06 && e.1 < 0.03), "seed {seed}: {seen:?}");
        assert!(seen[4..].iter().all(|(s, _, _)| *s == IntegrityState::Tracking), "seed {seed}: {seen:?}");
    }
}

/// Carried 0.8 m and 1 m along the corridor, with the search on: the estimate explains 0.8–0.85
/// of the level, below the uncertain bar, and the search finds, beside the truth, the corridor's
/// mirror image (the building turned by 180°), which explains the scans as well. Neither leads the
/// other, so neither wins; both beat the estimate, which is wrong whichever is right: the filter
/// is `lost` (not `uncertain` at the wrong place while the twins block each other), and
/// not `tracking` anywhere while the twins explain the scans alike, even where its estimate has
/// gone to one of them. Measured: `lost` on the 3rd scan, the estimate moving between the truth
/// and the twin (3 m off, turned 180°) and on the truth from the 9th and the 6th scan, `lost` and
/// ambiguous for all 20 scans (the corridor mirrors itself all along them).
#[test]
fn a_filter_in_a_corridor_that_mirrors_itself_is_lost_among_twins() {
    let params = tuned_params();
    let b = building();
    let truth = path();
    for (seed, shift) in [(0, Se2::new(0.8, 0.0, 0.0)), (1, Se2::new(1.0, 0.0, 0.0))] {
        let Tracked { mut amcl, odom, mut rng } = tracked_along(&b, &params, &truth, 30, 70 + seed);
        assert_eq!(amcl.integrity_state(), IntegrityState::Tracking, "seed {seed}");
        move_cloud(&mut amcl, &odom[30], shift);
        amcl.rivals.push(super::rivals::Rival::found(truth[30], odom[30]));
        let mut seen = Vec::new();
        for (t, o) in truth.iter().zip(&odom).skip(31).take(20) {
            let scan = b.scan(t, &mut rng);
            amcl.update(*o, &scan_points(&scan, &Se2::IDENTITY, &params), false);
            let e = amcl.estimate().unwrap().pose;
            let error = ((e.x - t.x).hypot(e.y - t.y), angle_diff(e.theta, t.theta).abs());
            seen.push((amcl.integrity_state(), amcl.integrity().is_some_and(|i| i.ambiguous), error));
        }
        eprintln!("seed {seed}: {seen:?}");
        assert!(seen[..3].iter().any(|(s, _, _)| *s == IntegrityState::Lost), "seed {seed}: {seen:?}");
        let off = |e: &(f64, f64)| e.0 > 0.5 || e.1 > 10f64.to_radians();
        assert!(
            !seen.iter().any(|(s, _, e)| *s == IntegrityState::Tracking && off(e)),
            "seed {seed}: tracking while off: {seen:?}"
        );
    }
}

/// Kidnapped-robot recovery with α_slow/α_fast: after being carried from the corridor into the room
/// with the triangle, the estimate is back within 0.3 m / 10° within 30 updates and stays there to
/// the end (60 updates); without the recovery alphas nothing is injected and the estimate stays
/// lost. Measured (seeded): back from update 13. The injection probability peaks near 0.18 and
/// decays to 0 within about 40 updates of recovering; before the kidnapping nothing is injected.
///
/// Before the changes in `Amcl::resample`/`Amcl::weigh` (nav2's reset of the averages, uniform
/// injection, the averages of the product model's raw likelihood) the filter did not recover in
/// any seed tried. Not asserted here: a kidnapping into the bottom-right room, whose twin (bottom
/// middle) differs by 10 cm of width and by what the doors show. There (robot at (9.0, 1.5)
/// driving 1.8 m east) 8 of 10 seeds recovered within 2–25 updates and stayed; in 2 the estimate
/// stayed in the twin room for all 60 updates.
#[test]
fn kidnapped_robot_recovers_with_recovery_alphas() {
    let params = recovery_params();
    let to = Se2::new(8.6, 5.2, 0.0);
    let r = kidnapping(&params, 0, to);
    assert!(r.injections_after > r.injections_before, "the kidnapping must trigger injection");
    let from = recovered_from(&r.errors_after);
    eprintln!(
        "kidnapping: recovered from update {from:?} of {}; injecting steps {} before, {} in all",
        r.errors_after.len(),
        r.injections_before,
        r.injections_after
    );
    assert!(from.is_some_and(|n| n <= 30), "errors after the kidnapping: {:?}", r.errors_after);
    // Injection draws from the filter's own generator: the same seed gives the same bits.
    let again = kidnapping(&params, 0, to);
    let bits =
        |k: &Kidnapping| k.errors_after.iter().map(|e| (e.0.to_bits(), e.1.to_bits())).collect::<Vec<_>>();
    assert_eq!(bits(&r), bits(&again));

    let mut plain = params.clone();
    plain.recovery_alpha_slow = Fraction::new(0.0).unwrap();
    plain.recovery_alpha_fast = Fraction::new(0.0).unwrap();
    let r = kidnapping(&plain, 0, to);
    assert_eq!((r.injections_before, r.injections_after), (0, 0), "no injection without the alphas");
    let last = r.errors_after.last().unwrap();
    assert!(last.0 > 1.0, "without recovery the estimate stays lost: {last:?}");
    assert_eq!(r.states_after.last(), Some(&IntegrityState::Lost), "and says so");
}

/// The same kidnapping with other seeds (filter, odometry and range noise): every seed recovers
/// before the end, and three in four within 30 updates. Measured (seeded, so exact), seeds 1–8:
/// from update 2, 16, 3, 47, 6, 2, 3, 24; over seeds 1–40 the median is 7 and 4 of 40 take more
/// than 30 updates (31–49). With the far side of the rendered walls counted as surface (the choice
/// `likelihood.rs` rejects) the median is 6 and 1 of 40 takes more than 30 (32); the two differ
/// here only in the outer walls' outer layer, which borders unknown cells; why that delays
/// recovery in a few seeds was not looked into.
#[test]
fn kidnapping_recovery_over_seeds() {
    let params = recovery_params();
    let mut froms = Vec::new();
    for seed in 1..=8 {
        let r = kidnapping(&params, seed, Se2::new(8.6, 5.2, 0.0));
        froms.push(recovered_from(&r.errors_after));
    }
    eprintln!("kidnapping over seeds 1-8: recovered from updates {froms:?}");
    assert!(froms.iter().all(Option::is_some), "not recovered by the end: {froms:?}");
    let quick = froms.iter().filter(|f| f.is_some_and(|n| n <= 30)).count();
    assert!(quick * 4 >= froms.len() * 3, "{froms:?}");
}

/// Global localisation with few particles for the map (500, in 96 m² and all headings): uniform
/// particles rarely put one in the truth's basin; placed on the first scan (best of
/// `GLOBAL_CANDIDATES` uniform poses each) they do. Checked right after the first update: how many
/// particles lie within 0.2 m and 5° of the truth. (Whether the filter then keeps the right place
/// is another matter: this corridor has a twin 4 m along it that its first scans cannot tell apart.
/// On four real CARMEN logs the placed filter was within 0.5 m from scan 0 or 1 in 12 of 12 runs,
/// the uniform one in none: `amr bench localize`.)
#[test]
fn global_localisation_places_particles_on_the_first_scan() {
    let b = building();
    let mut params = shipped_params();
    params.max_particles = crate::config::value::Count::new(500).unwrap();
    // The uniform placement alone (the place search puts particles at the truth either way).
    params.integrity.place_search = false;
    let field = Arc::new(LikelihoodField::new(&b.grid, &params, 10.0));
    let truth = Se2::new(1.0, 4.0, 0.0);
    let near_truth = |candidates: usize, seed: u64| {
        let mut amcl = Amcl::new(params.clone(), Arc::clone(&field), seed);
        amcl.global_candidates = candidates;
        amcl.init_global();
        let scan = b.scan(&truth, &mut Rng::seed(seed));
        let points = scan_points(&scan, &Se2::IDENTITY, &params);
        assert!(matches!(amcl.update(Se2::IDENTITY, &points, false), UpdateOutcome::Updated { .. }));
        amcl.particles()
            .iter()
            .filter(|p| {
                (p.pose.x - truth.x).hypot(p.pose.y - truth.y) < 0.2
                    && angle_diff(p.pose.theta, truth.theta).abs() < 5f64.to_radians()
            })
            .count()
    };
    for seed in 1..=4 {
        let (placed, uniform) = (near_truth(super::GLOBAL_CANDIDATES, seed), near_truth(1, seed));
        assert!(
            placed >= 5 && uniform <= 1,
            "seed {seed}: {placed} placed particles near the truth, {uniform} uniform"
        );
    }
}

/// Carried 5 m along the corridor: the estimate still explains about 60 % of what it explains where
/// it is right (the corridor's walls), between the lost and the uncertain ratio, so the share alone
/// says `Uncertain` and nothing more. The filter looks for places that explain the scan far
/// better, judges them against the estimate on the next scans, and then reports `Lost` and
/// re-localises at the one the scans pick. This building is its own twin turned by 180° (but for
/// two small obstacles): the search may find the twin first, and a filter that switched to the
/// first place found settled in the twin, 6.6 m off, and reported `Tracking` there (1 seed of 12
/// with the first place judged alone; 5 of 24 with its evidence summed). Places are looked for at
/// the tracking bar (the estimate explains the scans below the uncertain bar), so the truth and
/// its twin are both found, and both beat the estimate: it is `lost` then, whichever is right, and
/// not `tracking` until the scans tell the two apart. Measured, seeds 0–23 (updates counted from
/// 0): uncertain from the 2nd, lost at the 2nd, within 0.3 m from the 3rd–6th, tracking from the
/// 14th (8th on one seed). Looking only for places that explain `switch_margin` more than the
/// estimate, the truth was found late (lost at the 8th on 9 seeds of 12, at the 17th on 3);
/// looking at the tracking bar but waiting for one rival to lead, the twins blocked each other
/// (lost at the 13th on 11 seeds). Without the search (`alternative_draws` 0): uncertain until
/// the 27th, when the share happened to dip below the lost ratio.
#[test]
fn a_filter_carried_to_a_plausible_wrong_place_finds_a_better_one_and_reports_lost() {
    let to = Se2::new(9.0, 4.0, 0.0);
    let mut without = tuned_params();
    without.integrity.alternative_draws = 0;
    for seed in 0..24 {
        let r = kidnapping(&tuned_params(), seed, to);
        let lost = r.states_after.iter().position(|s| *s == IntegrityState::Lost);
        let back = recovered_from(&r.errors_after);
        let tracking = lost.and_then(|l| {
            r.states_after[l..].iter().position(|s| *s == IntegrityState::Tracking).map(|k| k + l)
        });
        eprintln!("seed {seed}: lost at {lost:?}, within 0.3 m from {back:?}, tracking at {tracking:?}");
        assert!(!r.states_before.contains(&IntegrityState::Lost), "seed {seed}");
        // Off by 5 m, and once it doubted, not tracking again until it is back.
        let doubted = r.states_after.iter().position(|s| *s != IntegrityState::Tracking);
        let again = doubted.and_then(|d| {
            r.states_after[d..].iter().position(|s| *s == IntegrityState::Tracking).map(|k| k + d)
        });
        assert!(doubted.is_some_and(|d| d <= 2), "seed {seed}: {:?}", r.states_after);
        assert!(again.is_some_and(|t| back.is_some_and(|b| t >= b)), "seed {seed}: {:?}", r.states_after);
        assert!(lost.is_some_and(|l| l <= 3), "seed {seed}: {:?}", r.states_after);
        assert!(back.is_some_and(|b| b < 8), "seed {seed}: {:?}", r.errors_after);
        assert!(tracking.is_some_and(|t| t < 16), "seed {seed}: {:?}", r.states_after);
        let off = |e: &(f64, f64)| e.0 > 0.5 || e.1 > 10f64.to_radians();
        assert!(
            !r.states_after
                .iter()
                .zip(&r.errors_after)
                .skip(2)
                .any(|(s, e)| *s == IntegrityState::Tracking && off(e)),
            "seed {seed}: tracking while off: {:?}",
            r.states_after
        );
        // The share alone: uncertain, off by 5 m, for longer.
        let w = kidnapping(&without, seed, to);
        assert!(
            w.states_after[2..20].iter().all(|s| *s == IntegrityState::Uncertain),
            "seed {seed}: {:?}",
            w.states_after
        );
        assert!(w.errors_after[..20].iter().all(|e| e.0 > 4.0), "seed {seed}");
    }
}
