//! The relative-heading search (paper §4.3, Eq. 11–12; docs/method.md §5).
//!
//! `s(δθ) = (1/N_p) Σ_k 1[min_{q ∈ S_j, |idx(q) − idx(R(δθ)p_k + t)| ≤ W} |R(δθ)·p_k + t − q| < ε_d]`,
//! maximised over a grid of angles `Ω` (the full circle, or a window around the previous estimate).
//! With [`TargetScan::with_surface`] (ours; the shipped configuration) a point also counts when it
//! lies within `ε_d` of a segment between neighbouring target points of one surface.
//!
//! Exact and fast: as δθ varies, `R(δθ)·p_k + t` moves on a circle of radius `|p_k|` around `t`, so
//! it can come within `ε_d` of a target point `q` only on one arc, found in closed form (of a
//! segment, only inside the disc about its midpoint of its half-length plus `ε_d`: one arc too). The search
//! evaluates the indicator only at the grid steps inside those arcs (widened by a step for rounding),
//! with the same function the exhaustive sweep uses at every step. Every `(k, step)` whose indicator
//! is 1 lies inside some arc, so the score of every step, and therefore the argmax, equals the
//! exhaustive sweep's exactly ([`search_exhaustive`] is kept as the reference and the tests compare
//! them on random scenes).

use crate::scan::{BeamGeometry, BeamPoint, Scan};
use crate::se2::{Se2, normalize_angle};
use std::f64::consts::{PI, TAU};

/// The target scan `S_j`: points in the target robot's base frame, addressable by beam index.
#[derive(Debug, Clone)]
pub struct TargetScan {
    /// Point of each beam (base frame), `None` where the beam has no point.
    by_beam: Vec<Option<[f64; 2]>>,
    base_to_lidar: Se2,
    geometry: BeamGeometry,
    /// The points, sorted by their distance from the translation, for the arc search.
    points: Vec<[f64; 2]>,
    /// Per beam `m`: the target's surface runs from beam `m`'s point to beam `m + 1`'s (both
    /// present, their ranges within the jump). Empty: the paper's point targets.
    joined: Vec<bool>,
}

impl TargetScan {
    /// `points` are beam points in the base frame of a scan with `scan`'s geometry, mounted at
    /// `lidar_to_base`.
    #[must_use]
    pub fn new(scan: &Scan, lidar_to_base: &Se2, points: &[BeamPoint]) -> Self {
        let mut by_beam = vec![None; scan.len()];
        for b in points {
            if let Some(slot) = by_beam.get_mut(b.index) {
                *slot = Some(b.p);
            }
        }
        TargetScan {
            by_beam,
            base_to_lidar: lidar_to_base.inverse(),
            geometry: scan.geometry(),
            points: points.iter().map(|b| b.p).collect(),
            joined: Vec::new(),
        }
    }

    /// Ours, not the paper's: match against the target's surface, the segments between
    /// neighbouring beams whose ranges differ by at most `max_jump_m`, as well as its points. At
    /// the TiM551's 1°, neighbouring points on a wall 3 m away stand 5 cm apart, so a source point
    /// landing on the wall is within ε_d = 3 mm of a target *point* only by chance (Eq. 11 scores
    /// 0.02–0.05 at the true heading in open halls, and fails there); its distance to the
    /// surface is what the heading decides. `None` keeps the point targets.
    #[must_use]
    pub fn with_surface(mut self, max_jump_m: Option<f64>) -> Self {
        let Some(jump) = max_jump_m else {
            self.joined.clear();
            return self;
        };
        let lidar = self.base_to_lidar;
        let range = |p: &[f64; 2]| {
            let l = lidar.transform_point(*p);
            l[0].hypot(l[1])
        };
        self.joined = self
            .by_beam
            .iter()
            .zip(self.by_beam.iter().skip(1))
            .map(|(a, b)| matches!((a, b), (Some(a), Some(b)) if (range(a) - range(b)).abs() <= jump))
            .collect();
        self
    }

    /// The surface segments, as their two end points.
    fn segments(&self) -> impl Iterator<Item = ([f64; 2], [f64; 2])> + '_ {
        self.joined
            .iter()
            .enumerate()
            .filter(|(_, j)| **j)
            .filter_map(|(m, _)| Some(((*self.by_beam.get(m)?)?, (*self.by_beam.get(m + 1)?)?)))
    }

    /// The (possibly out-of-range) beam index a base-frame point falls on.
    fn beam_of(&self, q: [f64; 2]) -> i64 {
        let l = self.base_to_lidar.transform_point(q);
        self.geometry.nearest_beam(l[1].atan2(l[0]))
    }
}

/// A grid of candidate angles: `angle(s) = normalize(start + s·step)`, `s ∈ [0, count)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AngleGrid {
    pub start_rad: f64,
    pub step_rad: f64,
    pub count: usize,
}

impl AngleGrid {
    /// All of (-180°, 180°] at `step_deg`.
    #[must_use]
    pub fn full(step_deg: f64) -> Self {
        let count = (360.0 / step_deg).round().max(1.0) as usize;
        let step_rad = TAU / count as f64;
        AngleGrid { start_rad: -PI + step_rad, step_rad, count }
    }

    /// `center ± window` at `step_deg`, centred exactly on `center_rad`.
    #[must_use]
    pub fn around(center_rad: f64, window_deg: f64, step_deg: f64) -> Self {
        let half = (window_deg / step_deg).round().max(0.0) as usize;
        let step_rad = step_deg.to_radians();
        AngleGrid { start_rad: center_rad - half as f64 * step_rad, step_rad, count: 2 * half + 1 }
    }

    #[must_use]
    pub fn angle(&self, s: usize) -> f64 {
        normalize_angle(self.start_rad + s as f64 * self.step_rad)
    }
}

/// Inputs of one search: `S_i` (source, in its base frame), `S_j` and the translation `t_ij`.
#[derive(Debug, Clone, Copy)]
pub struct HeadingProblem<'a> {
    pub source: &'a [BeamPoint],
    pub target: &'a TargetScan,
    pub translation: [f64; 2],
    /// ε_d.
    pub distance_gate_m: f64,
    /// W: the nearest neighbour is searched among beams `idx ± W`.
    pub window_beams: usize,
}

/// The result of a search.
#[derive(Debug, Clone, PartialEq)]
pub struct HeadingEstimate {
    /// Eq. 12: the best angle (first maximum in grid order).
    pub theta_rad: f64,
    /// `s(θ)` of the best angle.
    pub score: f64,
    /// The best score more than [`RUNNER_UP_EXCLUSION_DEG`] away from the best angle.
    pub runner_up: f64,
    /// Matches per grid step (`score · N_p`).
    pub counts: Vec<u32>,
}

/// Angles closer than this to the best one are the same peak, not a runner-up.
pub const RUNNER_UP_EXCLUSION_DEG: f64 = 1.0;

impl HeadingEstimate {
    #[must_use]
    pub fn margin(&self) -> f64 {
        self.score - self.runner_up
    }

    /// The source points matched at the best angle.
    #[must_use]
    pub fn matches(&self) -> u32 {
        self.counts.iter().copied().max().unwrap_or(0)
    }
}

impl<'a> HeadingProblem<'a> {
    /// A problem with the gate and window of the configured parameters.
    #[must_use]
    pub fn new(
        source: &'a [BeamPoint],
        target: &'a TargetScan,
        translation: [f64; 2],
        params: &crate::config::HeadingParams,
    ) -> Self {
        HeadingProblem {
            source,
            target,
            translation,
            distance_gate_m: params.distance_gate_m.get(),
            window_beams: params.neighbour_window_beams.usize(),
        }
    }
}

impl HeadingProblem<'_> {
    /// The indicator of Eq. 11 for source point `k` at angle `theta`.
    fn hit(&self, p: [f64; 2], theta: f64) -> bool {
        let (s, c) = theta.sin_cos();
        let q = [c * p[0] - s * p[1] + self.translation[0], s * p[0] + c * p[1] + self.translation[1]];
        let idx = self.target.beam_of(q);
        let n = self.target.by_beam.len() as i64;
        let w = self.window_beams as i64;
        let (lo, hi) = ((idx - w).max(0), (idx + w).min(n - 1));
        let gate2 = self.distance_gate_m * self.distance_gate_m;
        let by_beam = &self.target.by_beam;
        (lo..=hi).any(|m| {
            let m = m as usize;
            by_beam[m].is_some_and(|t| {
                let (dx, dy) = (q[0] - t[0], q[1] - t[1]);
                dx * dx + dy * dy < gate2
            }) || (m < hi as usize
                && self.target.joined.get(m).copied().unwrap_or(false)
                && matches!((by_beam[m], by_beam[m + 1]), (Some(a), Some(b)) if segment_distance2(q, a, b) < gate2))
        })
    }

    fn finish(&self, grid: &AngleGrid, counts: Vec<u32>) -> Option<HeadingEstimate> {
        let n_p = self.source.len();
        if n_p == 0 || counts.is_empty() {
            return None;
        }
        let (best_s, &best) = counts
            .iter()
            .enumerate()
            .fold((0, &counts[0]), |acc, (s, c)| if *c > *acc.1 { (s, c) } else { acc });
        let theta = grid.angle(best_s);
        let excl = RUNNER_UP_EXCLUSION_DEG.to_radians();
        let runner = counts
            .iter()
            .enumerate()
            .filter(|(s, _)| (normalize_angle(grid.angle(*s) - theta)).abs() > excl)
            .map(|(_, c)| *c)
            .max()
            .unwrap_or(0);
        Some(HeadingEstimate {
            theta_rad: theta,
            score: f64::from(best) / n_p as f64,
            runner_up: f64::from(runner) / n_p as f64,
            counts,
        })
    }
}

/// The reference: Eq. 11 at every step of the grid, Eq. 12 over them.
#[must_use]
pub fn search_exhaustive(problem: &HeadingProblem<'_>, grid: &AngleGrid) -> Option<HeadingEstimate> {
    let counts = (0..grid.count)
        .map(|s| {
            let theta = grid.angle(s);
            problem.source.iter().filter(|b| problem.hit(b.p, theta)).count() as u32
        })
        .collect();
    problem.finish(grid, counts)
}

/// Reusable buffers for [`search`], so a running pipeline does not allocate per scan.
#[derive(Debug, Default, Clone)]
pub struct SearchScratch {
    sorted: Vec<(f64, f64, f64)>,
    stamp: Vec<u32>,
}

/// The fast exact search: same scores as [`search_exhaustive`] on every step.
#[must_use]
pub fn search(
    problem: &HeadingProblem<'_>,
    grid: &AngleGrid,
    scratch: &mut SearchScratch,
) -> Option<HeadingEstimate> {
    let t = problem.translation;
    let eps = problem.distance_gate_m;
    // Rounding margin: distances and angles here are computed differently from `hit`, so widen.
    let eps_wide = eps * (1.0 + 1e-9) + 1e-12;
    // Targets as (distance from t, direction from t, reach), sorted by distance: a point reaches
    // ε_d around it; a surface segment ε_d around it, inside the disc about its midpoint of its
    // half-length plus ε_d.
    scratch.sorted.clear();
    let polar = |q: [f64; 2], reach: f64| {
        let (dx, dy) = (q[0] - t[0], q[1] - t[1]);
        (dx.hypot(dy), dy.atan2(dx), reach)
    };
    scratch.sorted.extend(problem.target.points.iter().map(|q| polar(*q, eps_wide)));
    scratch.sorted.extend(problem.target.segments().map(|(a, b)| {
        let half = 0.5 * (b[0] - a[0]).hypot(b[1] - a[1]);
        polar([0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1])], (half + eps) * (1.0 + 1e-9) + 1e-12)
    }));
    scratch.sorted.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
    let reach_max = scratch.sorted.iter().map(|c| c.2).fold(eps_wide, f64::max);
    scratch.stamp.clear();
    scratch.stamp.resize(grid.count, 0);
    let mut counts = vec![0u32; grid.count];
    let (sorted, stamp) = (&scratch.sorted, &mut scratch.stamp);

    for (k, b) in problem.source.iter().enumerate() {
        let tag = k as u32 + 1;
        let r = b.p[0].hypot(b.p[1]);
        let alpha = b.p[1].atan2(b.p[0]);
        let mut visit = |s: usize, counts: &mut Vec<u32>| {
            if stamp[s] != tag {
                stamp[s] = tag;
                if problem.hit(b.p, grid.angle(s)) {
                    counts[s] += 1;
                }
            }
        };
        if r <= eps_wide {
            // The point barely moves with δθ: every step is a candidate.
            for s in 0..grid.count {
                visit(s, &mut counts);
            }
            continue;
        }
        let first = sorted.partition_point(|(d, _, _)| *d < r - reach_max);
        for &(d, phi, reach) in sorted[first..].iter().take_while(|(d, _, _)| *d <= r + reach_max) {
            if (d - r).abs() > reach {
                continue;
            }
            // |r·e^{iψ} − d·e^{iφ}| < ρ  ⇔  cos(ψ − φ) > (r² + d² − ρ²) / (2 r d).
            let c = if d > 0.0 { (r * r + d * d - reach * reach) / (2.0 * r * d) } else { -1.0 };
            let half = if c <= -1.0 { PI } else { c.min(1.0).acos() };
            // ψ = α + δθ, so δθ ∈ φ − α ± half.
            for s in steps_within(grid, phi - alpha, half) {
                visit(s, &mut counts);
            }
        }
    }
    problem.finish(grid, counts)
}

/// Squared distance from `q` to the segment `a`–`b`.
fn segment_distance2(q: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (ux, uy) = (b[0] - a[0], b[1] - a[1]);
    let (wx, wy) = (q[0] - a[0], q[1] - a[1]);
    let len2 = ux * ux + uy * uy;
    let f = if len2 > 0.0 { ((wx * ux + wy * uy) / len2).clamp(0.0, 1.0) } else { 0.0 };
    let (dx, dy) = (wx - f * ux, wy - f * uy);
    dx * dx + dy * dy
}

/// Grid steps whose angle lies within `half` of `center` (mod 2π), widened by one step each side.
fn steps_within(grid: &AngleGrid, center: f64, half: f64) -> impl Iterator<Item = usize> + '_ {
    let full = half >= PI;
    let offset = (center - grid.start_rad).rem_euclid(TAU);
    let span = grid.step_rad * grid.count as f64;
    [-TAU, 0.0, TAU].into_iter().flat_map(move |shift| {
        let (lo, hi) = if full {
            (0, grid.count as i64 - 1)
        } else {
            let c = offset + shift;
            if c + half < -grid.step_rad || c - half > span + grid.step_rad {
                (1, 0)
            } else {
                (
                    ((c - half) / grid.step_rad).floor() as i64 - 1,
                    ((c + half) / grid.step_rad).ceil() as i64 + 1,
                )
            }
        };
        let (lo, hi) = (lo.max(0), hi.min(grid.count as i64 - 1));
        // With `full`, emit once (the shift loop would repeat it).
        let emit = !full || shift == 0.0;
        (lo..=hi).filter(move |_| emit).map(|s| s as usize)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Polygon, cast_ray};
    use proptest::prelude::*;

    fn tim551() -> Scan {
        Scan::new(-135f64.to_radians(), 1f64.to_radians(), 0.05, 10.0, vec![f64::NAN; 271])
    }

    /// A scan from `pose` (the LiDAR's pose in the world) of `scene`.
    fn cast(geom: &Scan, pose: Se2, scene: &[(Se2, &Polygon)]) -> Scan {
        let ranges = (0..geom.len())
            .map(|i| {
                cast_ray([pose.x, pose.y], pose.theta + geom.angle(i), geom.range_max_m, scene)
                    .unwrap_or(f64::NAN)
            })
            .collect();
        geom.with_ranges(ranges)
    }

    fn room_with_clutter() -> Vec<Polygon> {
        vec![
            Polygon::centered_rectangle(6.0, 3.1).unwrap(),
            Polygon::new(vec![[1.0, 0.8], [1.6, 0.9], [1.3, 1.3]]).unwrap(),
            Polygon::new(vec![[-2.0, -1.2], [-1.5, -1.2], [-1.5, -0.9], [-2.0, -0.9]]).unwrap(),
        ]
    }

    struct Scene {
        geom: Scan,
        mount: Se2,
        source: Vec<BeamPoint>,
        target: TargetScan,
        truth: Se2,
    }

    /// Robot i at `pose_i`, robot j at `pose_j` in a room; the truth is `T_{B_i}^{B_j}`.
    fn scene(pose_i: Se2, pose_j: Se2) -> Scene {
        let geom = tim551();
        let mount = Se2::from_degrees(0.175, 0.0, 0.0);
        let polys = room_with_clutter();
        let refs: Vec<(Se2, &Polygon)> = polys.iter().map(|p| (Se2::IDENTITY, p)).collect();
        let scan_i = cast(&geom, pose_i * mount, &refs);
        let scan_j = cast(&geom, pose_j * mount, &refs);
        let source = scan_i.points_in(&mount);
        let target = TargetScan::new(&scan_j, &mount, &scan_j.points_in(&mount));
        Scene { geom, mount, source, target, truth: pose_j.inverse() * pose_i }
    }

    fn problem<'a>(s: &'a Scene, eps: f64) -> HeadingProblem<'a> {
        HeadingProblem {
            source: &s.source,
            target: &s.target,
            translation: [s.truth.x, s.truth.y],
            distance_gate_m: eps,
            window_beams: 10,
        }
    }

    /// A problem with the robots' frames coinciding, the paper's ε_d and ±10 beams.
    fn at_origin<'a>(source: &'a [BeamPoint], target: &'a TargetScan) -> HeadingProblem<'a> {
        HeadingProblem { source, target, translation: [0.0, 0.0], distance_gate_m: 0.003, window_beams: 10 }
    }

    #[test]
    fn score_by_hand() {
        // Two target points; a source point that lands exactly on one at δθ = 90°.
        let geom = tim551();
        let target_pts = [BeamPoint { index: 225, p: [0.0, 1.0] }, BeamPoint { index: 135, p: [1.0, 0.0] }];
        let target = TargetScan::new(&geom, &Se2::IDENTITY, &target_pts);
        let source = [BeamPoint { index: 135, p: [1.0, 0.0] }, BeamPoint { index: 0, p: [5.0, 5.0] }];
        let pb = at_origin(&source, &target);
        let grid = AngleGrid::full(0.1);
        let e = search_exhaustive(&pb, &grid).unwrap();
        // At δθ = 0 the first source point sits on the second target point. At 1 m a 0.1° turn moves
        // it 1.75 mm (< ε_d = 3 mm) and 0.2° moves it 3.49 mm (> ε_d): steps −0.1°, 0, +0.1° hit.
        let zero = grid.count / 2 - 1;
        assert!(grid.angle(zero).abs() < 1e-12);
        assert_eq!(&e.counts[zero - 2..=zero + 2], &[0, 1, 1, 1, 0]);
        // Near 90° it sits on the first target point: s = 1/2 again; the first maximum (−0.1°) wins.
        assert!((e.score - 0.5).abs() < 1e-12);
        assert!((e.theta_rad.to_degrees() + 0.1).abs() < 1e-9, "{}", e.theta_rad.to_degrees());
        assert!((e.runner_up - 0.5).abs() < 1e-12, "the 90° peak is the runner-up");
        assert!(e.margin().abs() < 1e-12);
    }

    /// A source point halfway between two neighbouring target points scores only against the
    /// surface between them, and not across a range jump.
    #[test]
    fn the_surface_between_neighbouring_beams_scores() {
        let geom = tim551();
        // Beams 135 and 136 (0° and 1°) on a wall 3 m ahead: 5.2 cm apart.
        let wall = |b: usize| {
            let a = geom.angle(b);
            BeamPoint { index: b, p: [3.0, 3.0 * a.tan()] }
        };
        let target_pts = [wall(135), wall(136)];
        let mid = [3.0, 0.5 * (target_pts[0].p[1] + target_pts[1].p[1])];
        let source = [BeamPoint { index: 135, p: mid }];
        let grid = AngleGrid::around(0.0, 0.0, 0.1);
        let score = |target: &TargetScan| {
            let pb = at_origin(&source, target);
            let fast = search(&pb, &grid, &mut SearchScratch::default());
            assert_eq!(fast, search_exhaustive(&pb, &grid));
            fast.map_or(0.0, |e| e.score)
        };
        let points = TargetScan::new(&geom, &Se2::IDENTITY, &target_pts);
        assert_eq!(score(&points), 0.0, "2.6 cm from either point");
        assert_eq!(score(&points.clone().with_surface(Some(0.1))), 1.0, "on the segment");
        // The same two points as the edges of two objects 20 cm apart in range: no surface.
        let far = BeamPoint { index: 136, p: [3.2, 3.2 * geom.angle(136).tan()] };
        let jump = TargetScan::new(&geom, &Se2::IDENTITY, &[target_pts[0], far]).with_surface(Some(0.1));
        let source = [BeamPoint { index: 135, p: [3.1, 0.5 * (target_pts[0].p[1] + far.p[1])] }];
        let pb = at_origin(&source, &jump);
        assert_eq!(search_exhaustive(&pb, &grid).map_or(0.0, |e| e.score), 0.0, "across a jump");
    }

    #[test]
    fn full_search_finds_the_relative_heading() {
        for (pi, pj) in [
            (Se2::from_degrees(0.3, 0.45, 0.0), Se2::from_degrees(0.3, -0.45, 0.0)),
            (Se2::from_degrees(-0.5, 0.3, 12.34), Se2::from_degrees(0.4, -0.5, -31.0)),
            (Se2::from_degrees(1.0, -0.2, 170.0), Se2::from_degrees(-0.8, 0.6, -100.55)),
        ] {
            let s = scene(pi, pj);
            let mut scratch = SearchScratch::default();
            let e = search(&problem(&s, 0.003), &AngleGrid::full(0.1), &mut scratch).unwrap();
            let err = normalize_angle(e.theta_rad - s.truth.theta).to_degrees();
            assert!(
                err.abs() <= 0.2,
                "error {err}° (truth {}°), score {}",
                s.truth.theta.to_degrees(),
                e.score
            );
            assert!(e.margin() > 0.0, "a clear peak: {} vs {}", e.score, e.runner_up);
            let _ = (&s.geom, &s.mount);
        }
    }

    #[test]
    fn refined_search_around_the_previous_estimate() {
        let s = scene(Se2::from_degrees(-0.5, 0.3, 12.34), Se2::from_degrees(0.4, -0.5, -31.0));
        let grid = AngleGrid::around(s.truth.theta + 2f64.to_radians(), 5.0, 0.1);
        let mut scratch = SearchScratch::default();
        let fast = search(&problem(&s, 0.003), &grid, &mut scratch).unwrap();
        let slow = search_exhaustive(&problem(&s, 0.003), &grid).unwrap();
        assert_eq!(fast, slow);
        assert!(normalize_angle(fast.theta_rad - s.truth.theta).to_degrees().abs() <= 0.2);
    }

    #[test]
    fn grids() {
        let g = AngleGrid::full(0.1);
        assert_eq!(g.count, 3600);
        assert!((g.angle(g.count - 1) - PI).abs() < 1e-12, "the grid ends at +180°");
        assert!((g.angle(0) + PI - 0.1f64.to_radians()).abs() < 1e-12, "and starts just above -180°");
        let a = AngleGrid::around(3.13, 1.0, 0.1);
        assert_eq!(a.count, 21);
        assert!((a.angle(10) - 3.13).abs() < 1e-12);
        assert!(a.angle(20) < 0.0, "wraps past +180°");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// The fast search scores every grid step exactly as the exhaustive sweep does, for random
        /// poses, gates, windows and grids (full and refined), against points or the surface.
        #[test]
        fn fast_search_equals_the_exhaustive_sweep(
            xi in -1.5..1.5f64, yi in -0.8..0.8f64, ti in -180.0..180.0f64,
            xj in -1.5..1.5f64, yj in -0.8..0.8f64, tj in -180.0..180.0f64,
            eps_mm in 1.0..30.0f64, window in 0usize..12, refined in any::<bool>(),
            t_err in (-0.05..0.05f64, -0.05..0.05f64), step in prop::sample::select(vec![0.1, 0.25, 0.5, 1.0, 0.7]),
            surface in prop::option::of(0.01..0.3f64),
        ) {
            let mut s = scene(Se2::from_degrees(xi, yi, ti), Se2::from_degrees(xj, yj, tj));
            s.target = s.target.clone().with_surface(surface);
            let mut pb = problem(&s, eps_mm / 1000.0);
            pb.window_beams = window;
            // A translation estimate that is a little off, as the tracker's would be.
            pb.translation = [s.truth.x + t_err.0, s.truth.y + t_err.1];
            let grid = if refined { AngleGrid::around(s.truth.theta, 10.0, step) } else { AngleGrid::full(step) };
            let mut scratch = SearchScratch::default();
            let fast = search(&pb, &grid, &mut scratch);
            let slow = search_exhaustive(&pb, &grid);
            prop_assert_eq!(fast, slow);
        }
    }
}

/// The paper's KD-tree search as its text describes it (§4.3): a k-d tree over `S_j`, queried for the
/// nearest neighbour of every source point at every grid step. Kept only as the baseline of the
/// benchmark; its nearest neighbour is global (no ±W beam window), so its scores can differ slightly
/// from Eq. 11 as specified.
#[cfg(feature = "kdtree-baseline")]
pub mod kdtree_baseline {
    use super::{AngleGrid, BeamPoint};
    use kiddo::SquaredEuclidean;
    use kiddo::immutable::float::kdtree::ImmutableKdTree;

    /// The best angle and its score.
    #[must_use]
    pub fn search(
        source: &[BeamPoint],
        target: &[[f64; 2]],
        translation: [f64; 2],
        gate_m: f64,
        grid: &AngleGrid,
    ) -> Option<(f64, f64)> {
        if source.is_empty() || target.is_empty() {
            return None;
        }
        let tree: ImmutableKdTree<f64, u32, 2, 32> = ImmutableKdTree::new_from_slice(target);
        let gate2 = gate_m * gate_m;
        let mut best = (0usize, 0usize);
        for s in 0..grid.count {
            let (sn, cs) = grid.angle(s).sin_cos();
            let hits = source
                .iter()
                .filter(|b| {
                    let q = [
                        cs * b.p[0] - sn * b.p[1] + translation[0],
                        sn * b.p[0] + cs * b.p[1] + translation[1],
                    ];
                    tree.nearest_one::<SquaredEuclidean>(&q).distance < gate2
                })
                .count();
            if hits > best.1 {
                best = (s, hits);
            }
        }
        Some((grid.angle(best.0), best.1 as f64 / source.len() as f64))
    }
}
