//! Scan preprocessing (paper §4.1, docs/method.md §2): the 11-beam median filter and the 11-point
//! smoothing of Eq. 3. Their output feeds contour recognition and heading matching only; the points
//! fused into the virtual scan are the raw ones.

use crate::config::PreprocessParams;
use crate::scan::{BeamPoint, Scan};
use crate::se2::Se2;

/// Median filter over a sliding window of `window` beams (odd), the centre replaced by the median.
///
/// Invalid-beam rules: an invalid beam stays invalid (a median never turns a gap into a return), and
/// only the valid beams of a window vote. Edge policy: the window shrinks symmetrically at the ends
/// of the scan, so the first beam is its own median and the window stays centred.
#[must_use]
pub fn median_filter(scan: &Scan, window: usize) -> Scan {
    let half = window / 2;
    let r = scan.ranges_m();
    let n = r.len();
    let mut buf = Vec::with_capacity(window);
    let out = (0..n)
        .map(|i| {
            if r[i].is_nan() {
                return f64::NAN;
            }
            let h = half.min(i).min(n - 1 - i);
            buf.clear();
            buf.extend(r[i - h..=i + h].iter().copied().filter(|v| !v.is_nan()));
            median(&mut buf)
        })
        .collect();
    scan.with_ranges(out)
}

/// Median of a non-empty slice (mean of the two middle values for an even count).
fn median(v: &mut [f64]) -> f64 {
    v.sort_unstable_by(f64::total_cmp);
    let m = v.len() / 2;
    if v.len() % 2 == 1 { v[m] } else { 0.5 * (v[m - 1] + v[m]) }
}

/// Eq. 3: each valid beam's point replaced by the mean of the points of its window of `window`
/// beams (`ID_start = ID − window/2`, so the window is centred on the point it replaces; the paper's
/// `ID_start ..= ID_start + 10`). Only points of the same segment take part: the window stops at an
/// invalid beam or at a range jump larger than `jump_m` between neighbours, and shrinks symmetrically
/// so the mean stays centred. Points are in the sensor frame.
#[must_use]
pub fn smooth(scan: &Scan, window: usize, jump_m: f64) -> Vec<BeamPoint> {
    let half = window / 2;
    let r = scan.ranges_m();
    let n = r.len();
    let linked = |a: usize, b: usize| !r[a].is_nan() && !r[b].is_nan() && (r[a] - r[b]).abs() <= jump_m;
    let mut out = Vec::with_capacity(n);
    for (i, ri) in r.iter().enumerate() {
        if ri.is_nan() {
            continue;
        }
        // Reach on each side within the segment, then take the symmetric part.
        let left = (1..=half.min(i)).take_while(|&k| linked(i - k, i - k + 1)).count();
        let right = (1..=half.min(n - 1 - i)).take_while(|&k| linked(i + k - 1, i + k)).count();
        let h = left.min(right);
        let (mut sx, mut sy) = (0.0, 0.0);
        for j in i - h..=i + h {
            if let Some(p) = scan.point(j) {
                sx += p[0];
                sy += p[1];
            }
        }
        let k = (2 * h + 1) as f64;
        out.push(BeamPoint { index: i, p: [sx / k, sy / k] });
    }
    out
}

/// A preprocessed scan in the robot's base frame.
#[derive(Debug, Clone)]
pub struct Preprocessed {
    /// Median-filtered ranges (sensor frame geometry).
    pub filtered: Scan,
    /// Median-filtered valid beams as points in the base frame (for contour line fits).
    pub filtered_points: Vec<BeamPoint>,
    /// Smoothed points (Eq. 3) in the base frame (for segmentation and heading matching).
    pub smoothed_points: Vec<BeamPoint>,
}

/// Median filter, then smoothing, then into the base frame with `T_L^B`.
#[must_use]
pub fn preprocess(scan: &Scan, lidar_to_base: &Se2, params: &PreprocessParams) -> Preprocessed {
    let filtered = median_filter(scan, params.median_window_beams.usize());
    let smoothed = smooth(&filtered, params.smoothing_window_beams.usize(), params.segment_jump_m.get());
    let smoothed_points = smoothed
        .into_iter()
        .map(|b| BeamPoint { index: b.index, p: lidar_to_base.transform_point(b.p) })
        .collect();
    let filtered_points = filtered.points_in(lidar_to_base);
    Preprocessed { filtered, filtered_points, smoothed_points }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan(r: Vec<f64>) -> Scan {
        Scan::new(0.0, 0.01, 0.05, 10.0, r)
    }

    #[test]
    fn median_removes_an_isolated_outlier() {
        let mut r = vec![2.0; 30];
        r[15] = 5.0;
        let f = median_filter(&scan(r), 11);
        assert!(f.ranges_m().iter().all(|&v| v == 2.0));
    }

    #[test]
    fn median_by_hand() {
        // Window of 3 over [1, 5, 2, 8, 3]: ends shrink to themselves.
        let f = median_filter(&scan(vec![1.0, 5.0, 2.0, 8.0, 3.0]), 3);
        assert_eq!(f.ranges_m(), &[1.0, 2.0, 5.0, 3.0, 3.0]);
        // Window of 5: centre sees all five → 3; beams 1 and 3 see three each.
        let f = median_filter(&scan(vec![1.0, 5.0, 2.0, 8.0, 3.0]), 5);
        assert_eq!(f.ranges_m(), &[1.0, 2.0, 3.0, 3.0, 3.0]);
    }

    #[test]
    fn median_never_fills_gaps_and_ignores_invalid_votes() {
        let r = vec![2.0, f64::NAN, f64::NAN, 2.2, 0.0, 2.4, 2.6];
        let f = median_filter(&scan(r), 5);
        let out = f.ranges_m();
        assert!(out[1].is_nan() && out[2].is_nan() && out[4].is_nan());
        // Beam 3 (window 1..=5): valid votes 2.2 and 2.4 → 2.3.
        assert!((out[3] - 2.3).abs() < 1e-12);
        // A run of invalid beams stays a run of invalid beams.
        let g = median_filter(&scan(vec![f64::NAN; 20]), 11);
        assert_eq!(g.valid_count(), 0);
    }

    #[test]
    fn median_preserves_a_step_edge() {
        let mut r = vec![1.0; 20];
        r.extend(vec![3.0; 20]);
        let f = median_filter(&scan(r.clone()), 11);
        assert_eq!(f.ranges_m(), scan(r).ranges_m());
    }

    #[test]
    fn smoothing_is_the_mean_of_the_window_by_eq_3() {
        // Points on a straight wall y = 1 stay on it; the mean of 11 collinear points is their centre.
        let angles: Vec<f64> = (0..21).map(|i| 1.2 + 0.01 * f64::from(i)).collect();
        let r: Vec<f64> = angles.iter().map(|a| 1.0 / a.sin()).collect();
        let s = Scan::new(1.2, 0.01, 0.05, 10.0, r);
        let pts = smooth(&s, 11, 0.1);
        assert_eq!(pts.len(), 21);
        for b in &pts {
            assert!((b.p[1] - 1.0).abs() < 1e-12);
        }
        let c = pts[10];
        let expect_x: f64 = (5..=15).map(|j| s.point(j).unwrap()[0]).sum::<f64>() / 11.0;
        assert!((c.p[0] - expect_x).abs() < 1e-12);
        // The first point has no left neighbours: it is its own mean.
        assert_eq!(pts[0].p, s.point(0).unwrap());
    }

    #[test]
    fn smoothing_does_not_cross_jumps_or_gaps() {
        let mut r = vec![1.0; 10];
        r.extend(vec![3.0; 10]);
        r[15] = f64::NAN;
        let s = scan(r);
        let pts = smooth(&s, 11, 0.1);
        assert_eq!(pts.len(), 19);
        for b in &pts {
            let range = b.p[0].hypot(b.p[1]);
            assert!(
                (range - s.ranges_m()[b.index]).abs() < 0.01,
                "beam {} moved from {} to {range}",
                b.index,
                s.ranges_m()[b.index]
            );
        }
    }
}
