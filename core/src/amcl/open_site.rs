//! A kidnapped filter on a site far larger than a building: 100 m × 100 m of open ground with
//! sheds and walls scattered over it (none alike) and clutter the map does not hold, scanned 360°
//! out to 30 m. Uniform draws find the robot's basin there with a chance of about one in a few
//! million each (an endpoint 20 m away leaves the basin when the heading is 1–2° off); the
//! exhaustive place search finds it on the scan that turned the filter lost.

use std::f64::consts::PI;
use std::sync::Arc;

use super::scenarios::ray_cast;
use super::{Amcl, IntegrityState, LikelihoodField, scan_points, tests::shipped_params};
use crate::config::AmclParams;
use crate::geometry::Polygon;
use crate::map::{FREE, OCCUPIED, OccupancyGrid};
use crate::rng::Rng;
use crate::scan::Scan;
use crate::se2::{Se2, angle_diff};

const SIDE_M: f64 = 100.0;
const RES_M: f64 = 0.05;

struct Site {
    walls: Vec<Polygon>,
    /// What the map does not hold (parked cars, bins, people): scanned, not mapped.
    clutter: Vec<Polygon>,
    grid: OccupancyGrid,
}

/// Sheds (boxes of 2–8 m) and walls (0.3 m thick, 4–15 m long) at random places and headings,
/// a fence around it all; and clutter the map does not hold (150 boxes of 0.4–4.4 m by
/// 0.4–2 m).
fn site(seed: u64) -> Site {
    let mut rng = Rng::seed(seed);
    let rect = |c: [f64; 2], half: [f64; 2], a: f64| {
        let (s, k) = a.sin_cos();
        let corner = |u: f64, v: f64| [c[0] + k * u - s * v, c[1] + s * u + k * v];
        Polygon::new(vec![
            corner(-half[0], -half[1]),
            corner(half[0], -half[1]),
            corner(half[0], half[1]),
            corner(-half[0], half[1]),
        ])
    };
    let mut walls: Vec<Polygon> = Vec::new();
    let fence = [
        ([SIDE_M / 2.0, 0.15], [SIDE_M / 2.0, 0.15]),
        ([SIDE_M / 2.0, SIDE_M - 0.15], [SIDE_M / 2.0, 0.15]),
        ([0.15, SIDE_M / 2.0], [0.15, SIDE_M / 2.0]),
        ([SIDE_M - 0.15, SIDE_M / 2.0], [0.15, SIDE_M / 2.0]),
    ];
    walls.extend(fence.iter().filter_map(|(c, h)| rect(*c, *h, 0.0).ok()));
    for k in 0..70 {
        let c = [rng.range(5.0, SIDE_M - 5.0), rng.range(5.0, SIDE_M - 5.0)];
        let a = rng.range(0.0, PI);
        let half =
            if k % 2 == 0 { [rng.range(1.0, 4.0), rng.range(1.0, 4.0)] } else { [rng.range(2.0, 7.5), 0.15] };
        walls.extend(rect(c, half, a).ok());
    }
    let clutter: Vec<Polygon> = (0..150)
        .filter_map(|_| {
            let c = [rng.range(3.0, SIDE_M - 3.0), rng.range(3.0, SIDE_M - 3.0)];
            let half = [rng.range(0.2, 2.2), rng.range(0.2, 1.0)];
            rect(c, half, rng.range(0.0, PI)).ok()
        })
        .collect();
    let n = (SIDE_M / RES_M) as usize;
    let mut grid = OccupancyGrid::filled(n, n, RES_M, Se2::IDENTITY, FREE);
    for w in &walls {
        let (x0, y0, x1, y1) = w.bounds();
        let cell = |v: f64| ((v / RES_M).floor().max(0.0) as usize).min(n - 1);
        for j in cell(y0)..=cell(y1) {
            for i in cell(x0)..=cell(x1) {
                if w.contains(grid.cell_center(i, j)) {
                    grid.set(i, j, OCCUPIED);
                }
            }
        }
    }
    Site { walls, clutter, grid }
}

impl Site {
    /// A scan of `view` (one beam a degree, centred ahead) from `pose`, out to 30 m, with range
    /// noise.
    fn scan(&self, pose: &Se2, rng: &mut Rng, view: View) -> Scan {
        self.scan_among(pose, rng, view, &[])
    }

    /// As [`Self::scan`], with `more` things the map does not hold standing about.
    fn scan_among(&self, pose: &Se2, rng: &mut Rng, view: View, more: &[Polygon]) -> Scan {
        let n = view.fov_deg as usize;
        let geom = Scan::new(
            -f64::from(view.fov_deg).to_radians() / 2.0,
            1f64.to_radians(),
            0.05,
            30.0,
            vec![f64::NAN; n],
        );
        let scene: Vec<Polygon> = self.walls.iter().chain(&self.clutter).chain(more).cloned().collect();
        ray_cast(&scene, pose, geom, rng)
    }

    fn free(&self, p: [f64; 2]) -> bool {
        let (i, j) = ((p[0] / RES_M) as usize, (p[1] / RES_M) as usize);
        self.grid.cells.get(j * self.grid.width + i).is_some_and(|c| *c == FREE)
            && !self.walls.iter().chain(&self.clutter).any(|w| w.contains(p))
    }
}

/// How the robot sees and drives: the sensor's field of view, the distance between scans, the
/// odometry's noise (a share of each increment, and as much sideways and 0.6× in radians per
/// metre), how far it is carried when kidnapped (m, the least and the most) and how far it drives
/// on after that (m).
#[derive(Debug, Clone, Copy)]
struct View {
    fov_deg: u16,
    step_m: f64,
    odom_noise: f64,
    carried_m: [f64; 2],
    drive_m: f64,
}

/// 360°, a scan every 0.1 m, the odometry exact, carried 3–5 m, driving on 4 m.
const FULL: View = View { fov_deg: 360, step_m: 0.1, odom_noise: 0.0, carried_m: [3.0, 5.0], drive_m: 4.0 };
/// 180° (the SICKs of the real logs), a scan every 0.3 m, the odometry 3 % off.
const HALF: View = View { fov_deg: 180, step_m: 0.3, odom_noise: 0.03, ..FULL };
/// As [`FULL`], carried 15–20 m (beyond the square around where it was tracked), driving on 1.5 m.
const FAR: View = View { carried_m: [15.0, 20.0], drive_m: 1.5, ..FULL };

/// A start and a destination `view.carried_m` from it, turned 1–3 rad, each with 4 m to drive
/// clear ahead; the start where the map explains most of the scan.
fn start_and_destination(s: &Site, field: &LikelihoodField, rng: &mut Rng, view: View) -> (Se2, Se2) {
    loop {
        let start = Se2::new(rng.range(10.0, 90.0), rng.range(10.0, 90.0), rng.range(-PI, PI));
        let d = rng.range(view.carried_m[0], view.carried_m[1]);
        let a = rng.range(-PI, PI);
        let dest = Se2::new(start.x + d * a.cos(), start.y + d * a.sin(), start.theta + rng.range(1.0, 3.0));
        let clear = |p: &Se2| {
            (0..=40).all(|k| {
                let q = *p * Se2::new(0.1 * f64::from(k), 0.0, 0.0);
                s.free([q.x, q.y])
            })
        };
        // The filter's level starts at what a tracked sensor explains in a building (0.75): a
        // start among clutter is called lost before anything happened, which is not what is
        // tested here. The start is where the map explains most of the scan.
        let explained = |p: &Se2| {
            let points = scan_points(&s.scan(p, &mut Rng::seed(1), view), &Se2::IDENTITY, &shipped_params());
            super::integrity::explained_share(field, p, &points, None, &shipped_params().integrity)
        };
        if clear(&start) && clear(&dest) && explained(&start).is_some_and(|e| e >= 0.7) {
            return (start, dest);
        }
    }
}

/// What one kidnapping did: after it, the first update reported `Lost`, the first from which on
/// every estimate is within 0.3 m and 10° of the truth, and the first `Tracking` within 0.3 m.
#[derive(Debug)]
struct Outcome {
    /// Reported `Lost` while tracked along the start (a half view among clutter can explain too
    /// little there): not a kidnapping to judge.
    lost_before: bool,
    lost: Option<usize>,
    back: Option<usize>,
    tracking: Option<usize>,
    /// Updates reported `Tracking` more than 0.3 m or 10° off once the loss was reported (what
    /// a server would drive on after the filter knew it was lost).
    tracking_off: usize,
}

/// The robot tracked along 3 m, then carried `view.carried_m` off and turned, driving on
/// `view.drive_m`; the odometry sees the driving (with `view`'s noise), not the jump.
fn kidnapped(s: &Site, field: &Arc<LikelihoodField>, params: &AmclParams, seed: u64, view: View) -> Outcome {
    let mut rng = Rng::seed(100 + seed);
    let mut noise = Rng::seed(900 + seed);
    let (start, dest) = start_and_destination(s, field, &mut rng, view);
    let drive = |from: Se2, m: f64| -> Vec<Se2> {
        (0..(m / view.step_m).round() as i32)
            .map(|k| from * Se2::new(view.step_m * f64::from(k), 0.0, 0.0))
            .collect()
    };
    let (before, after) = (drive(start, 3.0), drive(dest, view.drive_m));
    let mut amcl = Amcl::new(params.clone(), Arc::clone(field), 7 + seed);
    amcl.init_pose(before[0], 0.05, 0.02);
    let mut odom = Se2::new(1.0, 2.0, 0.3);
    let mut out = Outcome { lost_before: false, lost: None, back: None, tracking: None, tracking_off: 0 };
    let mut last_bad = None;
    for (k, t) in before.iter().chain(&after).enumerate() {
        if k > 0 && k != before.len() {
            let prev = if k < before.len() { before[k - 1] } else { after[k - before.len() - 1] };
            let step = prev.inverse() * *t;
            let d = step.translation_norm() * view.odom_noise;
            odom = odom
                * Se2::new(
                    step.x + noise.gaussian(d),
                    step.y + noise.gaussian(d),
                    step.theta + noise.gaussian(0.6 * d),
                );
        }
        let scan = s.scan(t, &mut rng, view);
        amcl.update(odom, &scan_points(&scan, &Se2::IDENTITY, params), true);
        let Some(e) = amcl.estimate().map(|e| e.pose) else { continue };
        let ok =
            (e.x - t.x).hypot(e.y - t.y) <= 0.3 && angle_diff(e.theta, t.theta).abs() <= 10f64.to_radians();
        if k < before.len() {
            out.lost_before |= amcl.integrity_state() == IntegrityState::Lost;
            continue;
        }
        let n = k - before.len();
        if out.lost.is_none() && amcl.integrity_state() == IntegrityState::Lost {
            out.lost = Some(n);
        }
        if out.lost.is_some()
            && out.tracking.is_none()
            && ok
            && amcl.integrity_state() == IntegrityState::Tracking
        {
            out.tracking = Some(n);
        }
        if !ok {
            last_bad = Some(n);
            out.tracking_off +=
                usize::from(out.lost.is_some() && amcl.integrity_state() == IntegrityState::Tracking);
        }
    }
    out.back = match last_bad {
        None => Some(0),
        Some(b) if b + 1 < after.len() => Some(b + 1),
        Some(_) => None,
    };
    out
}

/// With the place search, on every seed: `Lost` within 3 updates of the kidnapping and within
/// 0.3 m and 10° from within 10 on; `Tracking` within 10 on two of the four (measured: back from
/// the 2nd update on every seed, `tracking` from the 4th, 17th, 11th and 4th: where the scans at
/// the destination hold more clutter than where the level was learned, the estimate at the robot
/// explains the scans about as well as the tracking bar asks, and waits; `verify_margin`, off by
/// default, see the test after). The level learned by range band on the 3 m tracked before holds
/// that place's clutter by range (seed 1: 0.92 of the endpoints 5–10 m away explained there, 0.66
/// at the destination): with one level for all ranges `tracking` came from the 7th and 14th
/// updates on seeds 1 and 2, three of the four within 10. On real logs the bands follow the
/// sensor, not a place (docs/results.md, "The level by range"). With uniform draws
/// alone the same filter is back within 10 updates on at most one seed (measured: seed 3 from the
/// 3rd, seed 2 from the 19th, never on seeds 0 and 1).
#[test]
fn a_robot_kidnapped_on_a_large_site_is_found_again() {
    let s = site(3);
    let field = Arc::new(LikelihoodField::new(&s.grid, &shipped_params(), 30.0));
    let (mut tracked, mut without_back) = (0, 0);
    let mut uniform = shipped_params();
    uniform.integrity.place_search = false;
    for seed in 0..4 {
        let with = kidnapped(&s, &field, &shipped_params(), seed, FULL);
        let without = kidnapped(&s, &field, &uniform, seed, FULL);
        eprintln!("seed {seed}: with the search {with:?}; uniform draws alone {without:?}");
        assert!(!with.lost_before && !without.lost_before, "seed {seed}: lost before the kidnapping");
        assert!(with.lost.is_some_and(|l| l < 3), "seed {seed}: {with:?}");
        assert!(with.back.is_some_and(|b| b < 10), "seed {seed}: {with:?}");
        tracked += usize::from(with.tracking.is_some_and(|t| t < 10));
        without_back += usize::from(without.back.is_some_and(|b| b < 10));
    }
    assert!(tracked >= 2, "tracking within 10 updates on {tracked} of 4 seeds");
    assert!(without_back <= 1, "uniform draws came back within 10 updates on {without_back} of 4 seeds");
}

/// A search of the whole map cut short by its budget (`search_budget` 20 000 squares here, where
/// a scan explained poorly asks little and prunes little: freiburg-campus, a real log kept out of
/// tuning, stops at the shipped 4 million) finds the robot all the same when it was carried no
/// further than `near_search_m` from where it was tracked: the square around that place is
/// searched with a budget of its own. On every seed of four: `Lost` at the 2nd update, within 0.3 m and 10°
/// from the 3rd (measured: `tracking` from the 5th, 16th, 12th and 5th, never off the robot).
/// Without the square, the same budget leaves the filter to uniform draws: back within 10
/// updates on none of the four (measured: seed 2 from the 20th, the others in none of the 40).
#[test]
fn a_search_stopped_by_its_budget_finds_the_robot_near_where_it_was_tracked() {
    let s = site(3);
    let field = Arc::new(LikelihoodField::new(&s.grid, &shipped_params(), 30.0));
    let mut near = shipped_params();
    near.integrity.search_budget = 20_000;
    let mut without = near.clone();
    without.integrity.near_search_m = 0.0;
    let mut without_back = 0;
    for seed in 0..4 {
        let with = kidnapped(&s, &field, &near, seed, FULL);
        let alone = kidnapped(&s, &field, &without, seed, FULL);
        eprintln!("seed {seed}: the square searched {with:?}; not searched {alone:?}");
        assert!(!with.lost_before, "seed {seed}: lost before the kidnapping");
        assert!(with.lost.is_some_and(|l| l < 3), "seed {seed}: {with:?}");
        assert!(with.back.is_some_and(|b| b < 10) && with.tracking_off == 0, "seed {seed}: {with:?}");
        without_back += usize::from(alone.back.is_some_and(|b| b < 10));
    }
    assert!(without_back <= 1, "without the square, back within 10 updates on {without_back} of 4 seeds");
}

/// A robot carried 15–20 m, beyond the square around where it was tracked, with the search of
/// the whole map stopped at its budget (20 000 squares) and not (the shipped 4 million): reported
/// `lost`, and never `tracking` off the robot after that, over 15 updates on every seed of four;
/// with the search cut short, `lost` at the 2nd update (with `search_carried_updates` set, once
/// the search has been carried on over its updates: the 6th, 6th, 2nd and 2nd measured at 4).
/// Measured: cut short, `lost` at the 2nd update on every seed, back on the robot on none
/// (driven on 4 m, on seed 2 from the 28th update); the whole map searched, `lost` at the 2nd,
/// 8th, 2nd and 3rd, back on seeds 1 and 2 (from the 9th and 6th). Where the robot is not found again it stays `lost`: on seed 0 it
/// stands by the site's fence, and a place 28 m along the fence explains its scans as well
/// (0.63–0.67 each, update after update, over 4 m); the two are carried as twins, and the filter
/// is never `tracking` at either.
#[test]
fn a_robot_carried_beyond_the_square_is_reported_lost() {
    let s = site(3);
    let field = Arc::new(LikelihoodField::new(&s.grid, &shipped_params(), 30.0));
    let mut cut = shipped_params();
    cut.integrity.search_budget = 20_000;
    for seed in 0..4 {
        let short = kidnapped(&s, &field, &cut, seed, FAR);
        let whole = kidnapped(&s, &field, &shipped_params(), seed, FAR);
        eprintln!("seed {seed}: the search cut short {short:?}; the whole map {whole:?}");
        assert!(!short.lost_before && !whole.lost_before, "seed {seed}: lost before the kidnapping");
        let carried = cut.integrity.search_carried_updates as usize;
        assert!(
            short.lost.is_some_and(|l| l <= 1 + carried) && short.tracking_off == 0,
            "seed {seed}: {short:?}"
        );
        assert!(whole.lost.is_some_and(|l| l < 10) && whole.tracking_off == 0, "seed {seed}: {whole:?}");
    }
}

/// Global localisation (no initial pose) on the same site, the robot driving 2 m: with the place
/// search the filter is within 0.3 m of the robot from the first update on every seed and reports
/// `Tracking` there within 10 updates (measured: 2–9 cm off, `tracking` from the 2nd or 3rd);
/// placed by uniform draws alone (2 000 particles, each the best of 200 poses), it is within
/// 0.3 m after the first update on at most two seeds of four (measured: seeds 1 and 2; 72 m and
/// 99 m off on seeds 0 and 3). (Driven on to 4 m, on
/// seed 0 the robot enters clutter where the estimate at it explains 0.46–0.52 of the scans, a
/// rival 68 m away explains them as a tracked place does, wins, and the filter follows it: what
/// docs/integrity.md's Limits say of rivals in clutter.)
#[test]
fn global_localisation_on_a_large_site_finds_the_robot_on_the_first_scan() {
    let s = site(3);
    let field = Arc::new(LikelihoodField::new(&s.grid, &shipped_params(), 30.0));
    let mut uniform_found = 0;
    for seed in 0..4 {
        let run = |place_search: bool| {
            let mut rng = Rng::seed(200 + seed);
            let (start, _) = start_and_destination(&s, &field, &mut rng, FULL);
            let mut params = shipped_params();
            params.integrity.place_search = place_search;
            let mut amcl = Amcl::new(params.clone(), Arc::clone(&field), 11 + seed);
            amcl.init_global();
            let mut errors = Vec::new();
            let mut tracking = None;
            for k in 0..20 {
                let t = start * Se2::new(0.1 * f64::from(k), 0.0, 0.0);
                let odom = Se2::new(2.0, -1.0, 0.5) * Se2::new(0.1 * f64::from(k), 0.0, 0.0);
                let scan = s.scan(&t, &mut rng, FULL);
                amcl.update(odom, &scan_points(&scan, &Se2::IDENTITY, &params), true);
                let Some(e) = amcl.estimate().map(|e| e.pose) else { continue };
                let ok = (e.x - t.x).hypot(e.y - t.y) <= 0.3
                    && angle_diff(e.theta, t.theta).abs() <= 10f64.to_radians();
                if ok && tracking.is_none() && amcl.integrity_state() == IntegrityState::Tracking {
                    tracking = Some(k);
                }
                errors.push((e.x - t.x).hypot(e.y - t.y));
            }
            (errors, tracking)
        };
        let (with, tracking) = run(true);
        let (without, _) = run(false);
        eprintln!(
            "seed {seed}: with the search {:.2} m off after the first update, worst after {:.2} m, tracking from {tracking:?}; uniform draws alone {:.2} m",
            with[0],
            with.iter().skip(1).fold(0.0f64, |a, e| a.max(*e)),
            without[0]
        );
        assert!(with.iter().all(|e| *e <= 0.3), "seed {seed}: {with:?}");
        assert!(tracking.is_some_and(|t| t < 10), "seed {seed}: tracking from {tracking:?}");
        uniform_found += usize::from(without[0] <= 0.3);
    }
    assert!(
        uniform_found <= 2,
        "uniform draws within 0.3 m after the first update on {uniform_found} of 4 seeds"
    );
}

/// A sensor with a half view (180°, as the SICKs of the real logs), a scan every 0.3 m and the
/// odometry 3 % off, on the same site: one scan facing clutter can be explained better at other
/// places than at the robot's, and the places found for the scan that turned the filter lost may
/// not hold it. Searching the map again while still lost (`search_again_every`, every 5 lost
/// updates) finds the robot on more seeds, never later (measured: of the 24 seeds, none lost
/// before the kidnapping, back on it by the end of the drive on 16 against 15 with the search on
/// turning lost alone; with `lost_needs_place` off, which searches less often, 16 against 13 of
/// the 23 not lost before).
#[test]
fn a_robot_with_a_half_view_is_found_again_by_searching_again() {
    let s = site(3);
    let field = Arc::new(LikelihoodField::new(&s.grid, &shipped_params(), 30.0));
    let again = shipped_params();
    assert!(again.integrity.search_again_every > 0, "the shipped filter searches again");
    let mut single = shipped_params();
    single.integrity.search_again_every = 0;
    let (mut back, mut back_single, mut tracking, mut tracking_single) = (0, 0, 0, 0);
    for seed in 0..24 {
        let with = kidnapped(&s, &field, &again, seed, HALF);
        let without = kidnapped(&s, &field, &single, seed, HALF);
        eprintln!("seed {seed}: searching again {with:?}; on turning lost alone {without:?}");
        if with.lost_before || without.lost_before {
            continue;
        }
        let within = |o: Option<usize>| o.is_some_and(|b| b < 10);
        back += usize::from(with.back.is_some());
        back_single += usize::from(without.back.is_some());
        tracking += usize::from(within(with.tracking));
        tracking_single += usize::from(within(without.tracking));
        assert!(
            without.back.is_none() || with.back.is_some_and(|b| Some(b) <= without.back),
            "seed {seed}: back later searching again: {with:?} against {without:?}"
        );
    }
    eprintln!(
        "back at all: {back} against {back_single}; tracking within 10: {tracking} against {tracking_single}"
    );
    assert!(back > back_single, "back {back}/{back_single}, tracking within 10 {tracking}/{tracking_single}");
}

/// Found again among clutter the map does not hold, the estimate at the robot explains the scans
/// less than where the level was learned, below the tracking bar, and a filter that waits for
/// the bar waits as long as the clutter lasts. With `verify_margin` set (off in the shipped
/// defaults, docs/results.md), the search made again while lost finds that no other place
/// explains the scan as well as the estimate, and the filter tracks again; never at a wrong
/// place. Measured (360° view, seeds 0–5): `tracking` within 10 updates
/// on all 6 (from the 4th or 6th), against 4 without (seed 2 from the 14th, seed 4 not by the
/// end of the drive); no update `tracking` off the robot once lost, with or without.
#[test]
fn a_robot_found_again_among_clutter_is_verified_by_the_whole_map() {
    let s = site(3);
    let field = Arc::new(LikelihoodField::new(&s.grid, &shipped_params(), 30.0));
    let by_share = shipped_params();
    assert!(by_share.integrity.verify_margin <= 0.0, "the shipped filter does not verify");
    let mut verified = shipped_params();
    verified.integrity.verify_margin = 0.05;
    let within = |o: &Outcome| o.tracking.is_some_and(|t| t < 10);
    let (mut with, mut without) = (0, 0);
    for seed in 0..6 {
        let a = kidnapped(&s, &field, &verified, seed, FULL);
        let b = kidnapped(&s, &field, &by_share, seed, FULL);
        eprintln!("seed {seed}: verified {a:?}; by the share alone {b:?}");
        assert!(!a.lost_before && a.lost.is_some_and(|l| l < 3), "seed {seed}: {a:?}");
        assert_eq!((a.tracking_off, b.tracking_off), (0, 0), "seed {seed}: tracking off the robot");
        assert!(within(&a), "seed {seed}: not tracking within 10 updates: {a:?}");
        with += usize::from(within(&a));
        without += usize::from(within(&b));
    }
    assert!(without + 2 <= with, "tracking within 10: {with} verified, {without} by the share alone");
}

/// People standing round the robot at `pose`, 1 m off, eight of them 0.5 m wide at every 36°
/// but two (a crowd it drives with): they hide about 60 % of a 360° view.
fn crowd(pose: &Se2) -> Vec<Polygon> {
    (0..10)
        .filter(|k| *k % 5 != 2 && *k % 5 != 4)
        .filter_map(|k| {
            let a = pose.theta + f64::from(k) * 36f64.to_radians();
            let c = [pose.x + a.cos(), pose.y + a.sin()];
            let (s, k) = a.sin_cos();
            let corner = |u: f64, v: f64| [c[0] + k * u - s * v, c[1] + s * u + k * v];
            Polygon::new(vec![
                corner(-0.25, -0.25),
                corner(0.25, -0.25),
                corner(0.25, 0.25),
                corner(-0.25, 0.25),
            ])
            .ok()
        })
        .collect()
}

/// What a robot tracked along 3 m and then driving on `drive` updates in a crowd (its estimate
/// at it all along) was reported: `lost` updates, and updates `tracking` more than 0.3 m off.
fn in_a_crowd(
    s: &Site,
    field: &Arc<LikelihoodField>,
    params: &AmclParams,
    seed: u64,
    drive: usize,
) -> (usize, usize) {
    let mut rng = Rng::seed(300 + seed);
    let (start, _) = start_and_destination(s, field, &mut rng, FULL);
    let mut amcl = Amcl::new(params.clone(), Arc::clone(field), 5 + seed);
    amcl.init_pose(start, 0.05, 0.02);
    let (mut lost, mut off) = (0, 0);
    for k in 0..30 + drive {
        let t = start * Se2::new(0.1 * k as f64, 0.0, 0.0);
        let odom = Se2::new(1.0, 2.0, 0.3) * Se2::new(0.1 * k as f64, 0.0, 0.0);
        let people = if k < 30 { Vec::new() } else { crowd(&t) };
        let scan = s.scan_among(&t, &mut rng, FULL, &people);
        amcl.update(odom, &scan_points(&scan, &Se2::IDENTITY, params), true);
        let Some(e) = amcl.estimate().map(|e| e.pose) else { continue };
        let state = amcl.integrity_state();
        if k >= 30 {
            lost += usize::from(state == IntegrityState::Lost);
            off += usize::from((e.x - t.x).hypot(e.y - t.y) > 0.3 && state == IntegrityState::Tracking);
        }
    }
    (lost, off)
}

/// A robot tracked into a crowd (people about it hide 40 % of its view; its estimate stays at it)
/// turns lost on its shares, and the search of the whole map stops at its budget (1 million
/// squares here; a complete search of this site for such a scan counts 4–5 million). Decided at
/// once on the nothing found (the default), the filter is `lost` on every seed of four. Carried on
/// over the next updates (`search_carried_updates` at 4), the search completes where five budgets suffice
/// and decides as a search of the whole map made at once does. Measured: carried on, held and
/// never `lost` on seed 3, whose search completes; on seed 0 its search needs more than five
/// budgets (`lost` after them); on seeds 1 and 2 the whole map searched at once finds places
/// that explain the crowd's scans better than the estimate, and turns lost too (so does the
/// search carried on). Never `tracking` off the robot.
#[test]
fn a_robot_in_a_crowd_is_held_while_a_search_stopped_by_its_budget_is_carried_on() {
    let s = site(3);
    let field = Arc::new(LikelihoodField::new(&s.grid, &shipped_params(), 30.0));
    let mut carried = shipped_params();
    carried.integrity.search_budget = 1_000_000;
    carried.integrity.search_carried_updates = 4;
    let mut at_once = carried.clone();
    at_once.integrity.search_carried_updates = 0;
    let mut held = 0;
    for seed in 0..4 {
        let a = in_a_crowd(&s, &field, &carried, seed, 8);
        let b = in_a_crowd(&s, &field, &at_once, seed, 8);
        eprintln!("seed {seed}: (lost, tracking off) carried on {a:?}, decided at once {b:?}");
        assert!(b.0 > 0, "seed {seed}: decided at once on a search stopped by its budget, not lost: {b:?}");
        assert!(a.0 <= b.0, "seed {seed}: lost more often carried on: {a:?} against {b:?}");
        assert_eq!((a.1, b.1), (0, 0), "seed {seed}: tracking off the robot");
        held += usize::from(a.0 == 0);
    }
    assert!(held >= 1, "carried on, never lost on {held} of 4 seeds");
}
