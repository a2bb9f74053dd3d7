//! Neighbour contour recognition (paper §4.2, Eq. 4–7; docs/method.md §3) against a configured
//! chassis outline.
//!
//! The paper fits lines to N points on each side of a candidate corner, checks the corner against the
//! chassis angle α, and walks from the corner to the centre by the known offset (β, d_c). Here the
//! outline is any simple polygon, so the same idea becomes: split the candidate points into straight
//! segments (total least squares, which has no trouble with vertical lines where Eq. 4's slope is
//! singular), and match them to the outline —
//! - two segments meeting at an angle that one of the outline's corners has → that corner, whose
//!   offset from the centre is known;
//! - a face (the other robot seen side-on, or one side of a corner whose other side has too few
//!   points) → one of the outline's edges of that length, placed by the face's visible ends, each
//!   refined to halfway between the last beam on the face and the first beam past it.
//!
//! Each hypothesis places the whole outline; the one whose outline fits the points best wins, and its
//! RMS distance is the quality figure. The paper's rectangle with L, H1, H2 is the default outline.
//!
//! Scan order is counter-clockwise about the sensor, so a convex body is traversed clockwise: the
//! points before a corner lie along the outline edge `k → k+1`, those after it along `k → k−1`.

use crate::config::ContourParams;
use crate::geometry::Polygon;
use crate::scan::{BeamPoint, Scan};
use crate::se2::{Se2, angle_diff, normalize_angle};

use super::tracker::Roi;

/// What the recogniser looks at.
#[derive(Debug, Clone, Copy)]
pub struct ContourInput<'a> {
    /// The raw scan (sensor frame): line fits use the raw points, end refinement uses its beams.
    pub scan: &'a Scan,
    /// Median-filtered points in the observer's base frame: candidates and segmentation.
    pub filtered: &'a [BeamPoint],
    pub lidar_to_base: Se2,
    /// The neighbour's outline, centred on its base frame.
    pub chassis: &'a Polygon,
    /// Where the neighbour's centre may be; `None` searches the whole scan.
    pub roi: Option<Roi>,
    /// Neighbouring points farther apart than this belong to different objects.
    pub jump_m: f64,
}

/// Which part of the outline was recognised.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Feature {
    /// Two faces meeting at outline vertex `vertex`.
    Corner { vertex: usize },
    /// One face, outline edge `edge` (`vertex edge → edge+1`), with `ends` (1 or 2) of its ends seen.
    Face { edge: usize, ends: u8 },
}

/// One measurement `z` of the neighbour's centre in the observer's base frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContourMeasurement {
    pub center: [f64; 2],
    /// The outline's orientation for the chosen hypothesis (ambiguous for symmetric outlines; the
    /// heading search, not this, gives the relative heading).
    pub heading_rad: f64,
    /// Quality: RMS distance of the cluster's points from the placed outline.
    pub rms_m: f64,
    pub points_used: usize,
    pub feature: Feature,
}

/// A fitted straight segment, oriented in scan order.
#[derive(Debug, Clone, Copy)]
struct Segment {
    /// Position in the cluster's point list.
    first: usize,
    last: usize,
    centroid: [f64; 2],
    dir: [f64; 2],
    rms: f64,
    /// Scan-order ends projected onto the line.
    start: [f64; 2],
    end: [f64; 2],
}

impl Segment {
    fn len(&self) -> f64 {
        (self.end[0] - self.start[0]).hypot(self.end[1] - self.start[1])
    }

    fn project(&self, p: [f64; 2]) -> [f64; 2] {
        let t = (p[0] - self.centroid[0]) * self.dir[0] + (p[1] - self.centroid[1]) * self.dir[1];
        [self.centroid[0] + t * self.dir[0], self.centroid[1] + t * self.dir[1]]
    }
}

/// Total least squares line through `pts`, oriented from the first point towards the last.
fn fit(pts: &[[f64; 2]], first: usize, last: usize) -> Option<Segment> {
    let p = &pts[first..=last];
    let n = p.len() as f64;
    if p.len() < 2 {
        return None;
    }
    let (mx, my) = (p.iter().map(|q| q[0]).sum::<f64>() / n, p.iter().map(|q| q[1]).sum::<f64>() / n);
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for q in p {
        let (dx, dy) = (q[0] - mx, q[1] - my);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    // Principal direction of the scatter matrix.
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let mut dir = [theta.cos(), theta.sin()];
    let (a, b) = (p[0], p[p.len() - 1]);
    if (b[0] - a[0]) * dir[0] + (b[1] - a[1]) * dir[1] < 0.0 {
        dir = [-dir[0], -dir[1]];
    }
    let normal = [-dir[1], dir[0]];
    let ss: f64 = p.iter().map(|q| ((q[0] - mx) * normal[0] + (q[1] - my) * normal[1]).powi(2)).sum();
    let mut seg = Segment { first, last, centroid: [mx, my], dir, rms: (ss / n).sqrt(), start: a, end: b };
    seg.start = seg.project(a);
    seg.end = seg.project(b);
    Some(seg)
}

/// Split-and-merge: split at the point farthest from the chord while it is farther than `thresh`.
fn split(pts: &[[f64; 2]], first: usize, last: usize, thresh: f64, out: &mut Vec<(usize, usize)>) {
    let (a, b) = (pts[first], pts[last]);
    let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
    let len = ex.hypot(ey);
    let mut worst = (0.0, first);
    if len > 0.0 && last > first + 1 {
        for (i, p) in pts.iter().enumerate().take(last).skip(first + 1) {
            let d = ((p[0] - a[0]) * ey - (p[1] - a[1]) * ex).abs() / len;
            if d > worst.0 {
                worst = (d, i);
            }
        }
    }
    if worst.0 > thresh {
        split(pts, first, worst.1, thresh, out);
        split(pts, worst.1, last, thresh, out);
    } else {
        out.push((first, last));
    }
}

/// Intersection of two lines given by point and direction.
fn intersect(p: [f64; 2], u: [f64; 2], q: [f64; 2], v: [f64; 2]) -> Option<[f64; 2]> {
    let den = u[0] * v[1] - u[1] * v[0];
    if den.abs() < 1e-9 {
        return None;
    }
    let t = ((q[0] - p[0]) * v[1] - (q[1] - p[1]) * v[0]) / den;
    Some([p[0] + t * u[0], p[1] + t * u[1]])
}

fn angle_of(v: [f64; 2]) -> f64 {
    v[1].atan2(v[0])
}

fn sub(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

struct Recognizer<'a> {
    input: ContourInput<'a>,
    params: &'a ContourParams,
}

impl Recognizer<'_> {
    /// The raw point of beam `i` in the base frame.
    fn raw(&self, i: usize) -> Option<[f64; 2]> {
        self.input.scan.point(i).map(|p| self.input.lidar_to_base.transform_point(p))
    }

    /// Refine a face end: halfway between the last beam on the face (`inner`) and where the next beam
    /// (`outer`) crosses the face line, if that beam went past the face (farther or no return).
    /// `None` if the next beam was stopped short (something in front: the end is occluded).
    fn clean_end(&self, seg: &Segment, inner: usize, outer: Option<usize>) -> Option<[f64; 2]> {
        let hit = self.raw(inner).map(|p| seg.project(p))?;
        let Some(outer) = outer.filter(|&o| o < self.input.scan.len()) else {
            return None; // the end of the sweep: we do not know where the face ends
        };
        let origin = [self.input.lidar_to_base.x, self.input.lidar_to_base.y];
        let a = self.input.lidar_to_base.theta + self.input.scan.angle(outer);
        let ray = [a.cos(), a.sin()];
        let Some(cross) = intersect(origin, ray, seg.centroid, seg.dir) else { return Some(hit) };
        let t_line = (cross[0] - origin[0]) * ray[0] + (cross[1] - origin[1]) * ray[1];
        let beyond = match self.input.scan.ranges_m().get(outer) {
            Some(r) if !r.is_nan() => {
                let r_base = self.raw(outer).map_or(*r, |p| (p[0] - origin[0]).hypot(p[1] - origin[1]));
                r_base > t_line + self.input.jump_m.min(0.05)
            }
            _ => true,
        };
        if !beyond {
            return None;
        }
        if t_line <= 0.0 {
            return Some(hit);
        }
        Some([(hit[0] + cross[0]) / 2.0, (hit[1] + cross[1]) / 2.0])
    }

    /// Edge-length tolerance: two beam spacings at the segment's range plus 1 cm.
    fn tolerance(&self, seg: &Segment) -> f64 {
        let origin = [self.input.lidar_to_base.x, self.input.lidar_to_base.y];
        let r = (seg.centroid[0] - origin[0]).hypot(seg.centroid[1] - origin[1]);
        2.0 * r * self.input.scan.angle_increment_rad.abs() + 0.01
    }

    fn score(&self, pts: &[[f64; 2]], center: [f64; 2], heading: f64) -> f64 {
        let inv = Se2::new(center[0], center[1], heading).inverse();
        let ss: f64 = pts
            .iter()
            .map(|p| self.input.chassis.distance_to_boundary(inv.transform_point(*p)).powi(2))
            .sum();
        (ss / pts.len().max(1) as f64).sqrt()
    }

    fn hypotheses(&self, beams: &[usize], segs: &[Segment]) -> Vec<(Feature, [f64; 2], f64)> {
        let poly = self.input.chassis;
        let v = poly.vertices();
        let n = v.len();
        let n_fit = self.params.line_fit_points.usize();
        let tol_angle = self.params.corner_angle_tolerance_deg.get().to_radians();
        let mut out = Vec::new();
        // Corners: consecutive segments with enough points each.
        let count = |s: &Segment| s.last - s.first + 1;
        for w in segs.windows(2) {
            let (a, b) = (w[0], w[1]);
            // N points on the longer side (Table 2), at least half of that on the shorter one.
            if count(&a).max(count(&b)) < n_fit || count(&a).min(count(&b)) < n_fit.div_ceil(2).max(3) {
                continue;
            }
            let Some(c) = intersect(a.centroid, a.dir, b.centroid, b.dir) else { continue };
            let u1 = [-a.dir[0], -a.dir[1]];
            let u2 = b.dir;
            let observed = (angle_of(u2) - angle_of(u1)).rem_euclid(std::f64::consts::TAU);
            for k in 0..n {
                if angle_diff(poly.interior_angle(k), observed).abs() > tol_angle {
                    continue;
                }
                let (e_next, e_prev) = (sub(v[(k + 1) % n], v[k]), sub(v[(k + n - 1) % n], v[k]));
                let (len_next, len_prev) = (e_next[0].hypot(e_next[1]), e_prev[0].hypot(e_prev[1]));
                if a.len() > len_next + self.tolerance(&a) || b.len() > len_prev + self.tolerance(&b) {
                    continue;
                }
                let psi1 = angle_of(u1) - angle_of(e_next);
                let psi2 = angle_of(u2) - angle_of(e_prev);
                let psi = normalize_angle(psi1 + angle_diff(psi2, psi1) / 2.0);
                let vk = Se2::new(0.0, 0.0, psi).transform_point(v[k]);
                out.push((Feature::Corner { vertex: k }, [c[0] - vk[0], c[1] - vk[1]], psi));
            }
        }
        // Faces: the other robot seen side-on, or a corner whose short side is too short to fit.
        for s in segs.iter().filter(|s| count(s) >= n_fit) {
            let first_beam = beams[s.first];
            let last_beam = beams[s.last];
            let start = self.clean_end(s, first_beam, first_beam.checked_sub(1));
            let end = self.clean_end(s, last_beam, Some(last_beam + 1));
            let observed_len = match (start, end) {
                (Some(p), Some(q)) => Some((q[0] - p[0]).hypot(q[1] - p[1])),
                _ => None,
            };
            for k in 0..n {
                let (vk, vk1) = (v[k], v[(k + 1) % n]);
                let e = sub(vk1, vk);
                let len = e[0].hypot(e[1]);
                let tol = self.tolerance(s);
                if s.len() > len + tol || observed_len.is_some_and(|l| (l - len).abs() > tol) {
                    continue;
                }
                let psi = normalize_angle(angle_of(s.dir) - angle_of([-e[0], -e[1]]));
                let rot = Se2::new(0.0, 0.0, psi);
                let from_start = start.map(|p| sub(p, rot.transform_point(vk1)));
                let from_end = end.map(|p| sub(p, rot.transform_point(vk)));
                let (center, ends) = match (from_start, from_end) {
                    (Some(a), Some(b)) => ([(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0], 2),
                    (Some(a), None) | (None, Some(a)) => (a, 1),
                    (None, None) => continue,
                };
                out.push((Feature::Face { edge: k, ends }, center, psi));
            }
        }
        out
    }
}

/// Find the neighbour's outline in the observer's scan and measure its centre.
#[must_use]
pub fn recognize(input: ContourInput<'_>, params: &ContourParams) -> Option<ContourMeasurement> {
    let rec = Recognizer { input, params };
    let (_, _, x1, y1) = input.chassis.bounds();
    let (x0, y0, _, _) = input.chassis.bounds();
    let reach = x0.abs().max(x1.abs()).hypot(y0.abs().max(y1.abs()));
    let near_roi = |p: [f64; 2]| match input.roi {
        Some(roi) => {
            (p[0] - roi.center[0]).abs() <= roi.half_width[0] + reach
                && (p[1] - roi.center[1]).abs() <= roi.half_width[1] + reach
        }
        None => true,
    };
    let candidates: Vec<&BeamPoint> = input.filtered.iter().filter(|b| near_roi(b.p)).collect();
    // Clusters of neighbouring beams.
    let mut clusters: Vec<Vec<usize>> = Vec::new();
    let mut prev: Option<&BeamPoint> = None;
    for b in candidates {
        let joined = prev.is_some_and(|p| {
            b.index <= p.index + 2 && (b.p[0] - p.p[0]).hypot(b.p[1] - p.p[1]) <= input.jump_m
        });
        match clusters.last_mut() {
            Some(c) if joined => c.push(b.index),
            _ => clusters.push(vec![b.index]),
        }
        prev = Some(b);
    }
    let n_fit = params.line_fit_points.usize();
    let thresh = (2.0 * params.max_fit_rms_m.get()).max(0.01);
    let mut best: Option<ContourMeasurement> = None;
    for beams in clusters.into_iter().filter(|c| c.len() >= n_fit) {
        let (beams, pts): (Vec<usize>, Vec<[f64; 2]>) =
            beams.iter().filter_map(|&i| rec.raw(i).map(|p| (i, p))).unzip();
        if pts.len() < n_fit {
            continue;
        }
        let mut pieces = Vec::new();
        split(&pts, 0, pts.len() - 1, thresh, &mut pieces);
        // A split point is the sample nearest a corner and may lie on either face: fit neither
        // neighbour with it.
        let last_piece = pieces.len() - 1;
        let segs: Vec<Segment> = pieces
            .iter()
            .enumerate()
            .filter_map(|(i, &(a, b))| {
                let first = if i == 0 { a } else { a + 1 };
                let last = if i == last_piece { b } else { b - 1 };
                (first < last).then(|| fit(&pts, first, last)).flatten()
            })
            .filter(|s| s.rms <= params.max_fit_rms_m.get())
            .collect();
        for (feature, center, heading) in rec.hypotheses(&beams, &segs) {
            if let Some(roi) = input.roi
                && !roi.contains(center)
            {
                continue;
            }
            let rms = rec.score(&pts, center, heading);
            if rms <= params.max_fit_rms_m.get() && best.is_none_or(|b| rms < b.rms_m) {
                best = Some(ContourMeasurement {
                    center,
                    heading_rad: heading,
                    rms_m: rms,
                    points_used: pts.len(),
                    feature,
                });
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vamr::shipped_params;

    #[test]
    fn total_least_squares_handles_the_vertical_line_that_eq_4_cannot() {
        // x = 0.5 for every point: Eq. 4's denominator N Σx² − (Σx)² is 0.
        let pts: Vec<[f64; 2]> = (0..10).map(|i| [0.5, 0.1 * f64::from(i)]).collect();
        let s = fit(&pts, 0, 9).unwrap();
        assert!(s.dir[0].abs() < 1e-12 && (s.dir[1] - 1.0).abs() < 1e-12, "{:?}", s.dir);
        assert!(s.rms < 1e-12);
        assert!((s.len() - 0.9).abs() < 1e-12);
        // For a non-vertical line TLS and Eq. 4 agree on exact data: y = 2x + 1 has slope a = 2.
        let pts: Vec<[f64; 2]> = (0..10).map(|i| [0.1 * f64::from(i), 0.2 * f64::from(i) + 1.0]).collect();
        let s = fit(&pts, 0, 9).unwrap();
        assert!((s.dir[1] / s.dir[0] - 2.0).abs() < 1e-12);
        // Eq. 7's θ_l = atan2(a, 1).
        assert!((angle_of(s.dir) - 2f64.atan2(1.0)).abs() < 1e-12);
    }

    #[test]
    fn corner_to_centre_by_hand() {
        // The paper's default outline: a 0.40 m square. Its corner is d_c = 0.2·√2 from the centre,
        // along the corner's bisector. Place the square at (1.0, 0.3) turned 60° (the line of sight is
        // at 16.7°, so a corner points at the sensor and both faces show) and look from the origin
        // with beams spaced 0.5° apart.
        let chassis = Polygon::centered_rectangle(0.4, 0.4).unwrap();
        let pose = Se2::from_degrees(1.0, 0.3, 60.0);
        let beams = Scan::new(-30f64.to_radians(), 0.5f64.to_radians(), 0.05, 10.0, vec![f64::NAN; 121]);
        let scene = [(pose, &chassis)];
        let ranges = (0..beams.len())
            .map(|i| crate::geometry::cast_ray([0.0, 0.0], beams.angle(i), 10.0, &scene).unwrap_or(f64::NAN))
            .collect();
        let scan = beams.with_ranges(ranges);
        let params = shipped_params();
        let m = recognize(
            ContourInput {
                scan: &scan,
                filtered: &scan.points_in(&Se2::IDENTITY),
                lidar_to_base: Se2::IDENTITY,
                chassis: &chassis,
                roi: None,
                jump_m: 0.1,
            },
            &params.contour,
        )
        .unwrap();
        assert!(matches!(m.feature, Feature::Corner { .. }), "{m:?}");
        assert!((m.center[0] - 1.0).abs() < 1e-9 && (m.center[1] - 0.3).abs() < 1e-9, "{m:?}");
        // The square's orientation is found modulo its 90° symmetry.
        let quarter = (m.heading_rad - 60f64.to_radians()).rem_euclid(std::f64::consts::FRAC_PI_2);
        assert!(
            quarter < 1e-9 || std::f64::consts::FRAC_PI_2 - quarter < 1e-9,
            "{}",
            m.heading_rad.to_degrees()
        );
        assert!(m.rms_m < 1e-9);
    }

    #[test]
    fn a_long_wall_is_not_a_robot_and_the_roi_excludes_others() {
        let chassis = Polygon::centered_rectangle(0.4, 0.4).unwrap();
        let wall = Polygon::centered_rectangle(6.0, 2.0).unwrap();
        let beams = Scan::new(-135f64.to_radians(), 1f64.to_radians(), 0.05, 10.0, vec![f64::NAN; 271]);
        let scene = [(Se2::IDENTITY, &wall), (Se2::from_degrees(1.0, 0.0, 10.0), &chassis)];
        let ranges = (0..beams.len())
            .map(|i| crate::geometry::cast_ray([0.0, 0.0], beams.angle(i), 10.0, &scene).unwrap_or(f64::NAN))
            .collect();
        let scan = beams.with_ranges(ranges);
        let params = shipped_params();
        let input = |roi| ContourInput {
            scan: &scan,
            filtered: &[],
            lidar_to_base: Se2::IDENTITY,
            chassis: &chassis,
            roi,
            jump_m: 0.1,
        };
        let pts = scan.points_in(&Se2::IDENTITY);
        let with = |roi| recognize(ContourInput { filtered: &pts, ..input(roi) }, &params.contour);
        let found = with(None).unwrap();
        assert!((found.center[0] - 1.0).abs() < 0.01 && found.center[1].abs() < 0.01, "{found:?}");
        // An ROI elsewhere (the room's corner) finds nothing: walls do not fit a 0.4 m outline.
        let roi = Roi { center: [2.8, 0.8], half_width: [0.3, 0.3] };
        assert_eq!(with(Some(roi)), None);
    }
}
