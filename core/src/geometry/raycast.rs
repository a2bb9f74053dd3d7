//! Ray casting against polygons: synthetic scans for tests and the simulated LiDAR.

use super::Polygon;
use crate::se2::Se2;

/// Distance along a ray from `origin` in direction `(cos θ, sin θ)` to the first crossing of any
/// edge of `polygons` (each placed by its pose), or `None` within `max_range_m`.
#[must_use]
pub fn cast_ray(
    origin: [f64; 2],
    angle_rad: f64,
    max_range_m: f64,
    polygons: &[(Se2, &Polygon)],
) -> Option<f64> {
    let (s, c) = angle_rad.sin_cos();
    let dir = [c, s];
    let mut best: Option<f64> = None;
    for (pose, poly) in polygons {
        let v = poly.vertices();
        let n = v.len();
        for i in 0..n {
            let a = pose.transform_point(v[i]);
            let b = pose.transform_point(v[(i + 1) % n]);
            if let Some(t) = ray_segment(origin, dir, a, b)
                && t <= max_range_m
                && best.is_none_or(|d| t < d)
            {
                best = Some(t);
            }
        }
    }
    best
}

/// Parameter `t ≥ 0` where the ray `origin + t·dir` crosses segment `a`–`b`.
fn ray_segment(o: [f64; 2], d: [f64; 2], a: [f64; 2], b: [f64; 2]) -> Option<f64> {
    let e = [b[0] - a[0], b[1] - a[1]];
    let denom = d[0] * e[1] - d[1] * e[0];
    if denom.abs() < 1e-15 {
        return None; // parallel
    }
    let w = [a[0] - o[0], a[1] - o[1]];
    let t = (w[0] * e[1] - w[1] * e[0]) / denom;
    let u = (w[0] * d[1] - w[1] * d[0]) / denom;
    (t >= 0.0 && (0.0..=1.0).contains(&u)).then_some(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hits_the_nearest_edge() {
        let room = Polygon::centered_rectangle(4.0, 2.0).unwrap();
        let box1 = Polygon::centered_rectangle(0.4, 0.4).unwrap();
        let scene = [(Se2::IDENTITY, &room), (Se2::new(1.0, 0.0, 0.3), &box1)];
        // Straight ahead: the box (rotated by 0.3 rad) is hit before the wall at x = 2.
        let d = cast_ray([0.0, 0.0], 0.0, 10.0, &scene).unwrap();
        let half_diag_along_x = 0.2 / 0.3f64.cos(); // the face x' = -0.2 of the rotated box, on the x axis
        assert!((d - (1.0 - half_diag_along_x)).abs() < 1e-12, "{d}");
        // Straight up: the wall at y = 1.
        assert!(
            (cast_ray([0.0, 0.0], std::f64::consts::FRAC_PI_2, 10.0, &scene).unwrap() - 1.0).abs() < 1e-12
        );
        // Out of range.
        assert_eq!(cast_ray([0.0, 0.0], std::f64::consts::FRAC_PI_2, 0.5, &scene), None);
    }
}
