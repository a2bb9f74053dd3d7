//! SE(2): planar rigid transforms, the one pose type of the project.
//!
//! `T_B^A` (docs/method.md §1, paper Eq. 13) maps a point expressed in frame B into frame A:
//! `p_A = R(θ)·p_B + t`. Composition follows the frame chain: `T_C^A = T_B^A * T_C^B`.
//! Angles are radians and always normalised to (-π, π].

use std::f64::consts::{PI, TAU};
use std::ops::Mul;

/// Normalise an angle to (-π, π].
///
/// Non-finite input stays non-finite (NaN in, NaN out); callers validate their inputs.
#[must_use]
pub fn normalize_angle(angle_rad: f64) -> f64 {
    // Most angles are in range already, or one turn off (a sum or difference of two normalised
    // angles): no division for those (`rem_euclid` is a library call, and this runs for every
    // particle of every filter update). In range the angle is returned exactly.
    if angle_rad > -PI && angle_rad <= PI {
        return angle_rad;
    }
    let a = if angle_rad > 0.0 { angle_rad - TAU } else { angle_rad + TAU };
    if a > -PI && a <= PI {
        return a;
    }
    // rem_euclid gives [0, 2π] (2π itself only through rounding of tiny negative inputs).
    let a = angle_rad.rem_euclid(TAU);
    if a > PI { a - TAU } else { a }
}

/// Signed shortest angular difference `a − b`, in (-π, π].
#[must_use]
pub fn angle_diff(a_rad: f64, b_rad: f64) -> f64 {
    normalize_angle(a_rad - b_rad)
}

/// A planar rigid transform (rotation `theta` then translation `(x, y)`), or equivalently the pose
/// of frame B expressed in frame A.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Se2 {
    pub x: f64,
    pub y: f64,
    /// Rotation in radians, in (-π, π] when built through [`Se2::new`].
    pub theta: f64,
}

impl Se2 {
    pub const IDENTITY: Se2 = Se2 { x: 0.0, y: 0.0, theta: 0.0 };

    /// A transform with its angle normalised to (-π, π].
    #[must_use]
    pub fn new(x: f64, y: f64, theta_rad: f64) -> Self {
        Se2 { x, y, theta: normalize_angle(theta_rad) }
    }

    /// A transform from a heading given in degrees (configuration and output edges only).
    #[must_use]
    pub fn from_degrees(x: f64, y: f64, theta_deg: f64) -> Self {
        Self::new(x, y, theta_deg.to_radians())
    }

    /// `T⁻¹`: maps A back into B.
    #[must_use]
    pub fn inverse(&self) -> Self {
        let (s, c) = self.theta.sin_cos();
        Se2 { x: -(c * self.x + s * self.y), y: s * self.x - c * self.y, theta: normalize_angle(-self.theta) }
    }

    /// `self * other`: apply `other` first, then `self` (`T_C^A = T_B^A * T_C^B`).
    #[must_use]
    pub fn compose(&self, other: &Se2) -> Self {
        let (s, c) = self.theta.sin_cos();
        Se2 {
            x: self.x + c * other.x - s * other.y,
            y: self.y + s * other.x + c * other.y,
            theta: normalize_angle(self.theta + other.theta),
        }
    }

    /// Map a point from frame B into frame A.
    #[must_use]
    pub fn transform_point(&self, p: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.theta.sin_cos();
        [self.x + c * p[0] - s * p[1], self.y + s * p[0] + c * p[1]]
    }

    /// Rotate a vector (no translation), e.g. a velocity.
    #[must_use]
    pub fn rotate_vector(&self, v: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.theta.sin_cos();
        [c * v[0] - s * v[1], s * v[0] + c * v[1]]
    }

    /// The transform a fraction `t` of the way from `self` (t = 0) to `other` (t = 1): the
    /// translation linearly, the rotation along the shorter arc. This is how pose buffers such as
    /// ROS tf interpolate between two stamped poses. `t` outside [0, 1] extrapolates.
    #[must_use]
    pub fn interpolate(&self, other: &Se2, t: f64) -> Self {
        Se2::new(
            self.x + t * (other.x - self.x),
            self.y + t * (other.y - self.y),
            self.theta + t * angle_diff(other.theta, self.theta),
        )
    }

    /// Distance of the translation part from the origin.
    #[must_use]
    pub fn translation_norm(&self) -> f64 {
        self.x.hypot(self.y)
    }

    /// True when translations agree within `tol_m` and rotations within `tol_rad` (on the circle).
    #[must_use]
    pub fn approx_eq(&self, other: &Se2, tol_m: f64, tol_rad: f64) -> bool {
        (self.x - other.x).abs() <= tol_m
            && (self.y - other.y).abs() <= tol_m
            && angle_diff(self.theta, other.theta).abs() <= tol_rad
    }
}

impl Mul for Se2 {
    type Output = Se2;
    fn mul(self, rhs: Se2) -> Se2 {
        self.compose(&rhs)
    }
}

impl Mul<&Se2> for &Se2 {
    type Output = Se2;
    fn mul(self, rhs: &Se2) -> Se2 {
        self.compose(rhs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const EPS: f64 = 1e-9;

    fn close(a: [f64; 2], b: [f64; 2], tol: f64) -> bool {
        (a[0] - b[0]).abs() <= tol && (a[1] - b[1]).abs() <= tol
    }

    #[test]
    fn normalisation_edges() {
        assert_eq!(normalize_angle(PI), PI);
        assert_eq!(normalize_angle(-PI), PI, "-π maps to +π: the range is (-π, π]");
        assert_eq!(normalize_angle(3.0 * PI), PI);
        assert_eq!(normalize_angle(0.0), 0.0);
        assert!((normalize_angle(1.5 * PI) + 0.5 * PI).abs() < EPS);
        assert!((normalize_angle(-1.5 * PI) - 0.5 * PI).abs() < EPS);
        // A tiny negative angle must stay tiny and negative (or zero), never jump to ±π.
        let tiny = normalize_angle(-1e-20);
        assert!(tiny <= 0.0 && tiny > -1e-12, "{tiny}");
        assert!(normalize_angle(f64::NAN).is_nan());
    }

    #[test]
    fn hand_computed_composition() {
        // B sits at (1, 0) in A, turned +90°. A point 1 m ahead of B is at (1, 1) in A.
        let t_ab = Se2::from_degrees(1.0, 0.0, 90.0);
        assert!(close(t_ab.transform_point([1.0, 0.0]), [1.0, 1.0], EPS));
        // C sits 2 m ahead of B, turned another +90°: in A it is at (1, 2) facing 180°.
        let t_bc = Se2::from_degrees(2.0, 0.0, 90.0);
        let t_ac = t_ab * t_bc;
        assert!(t_ac.approx_eq(&Se2::from_degrees(1.0, 2.0, 180.0), EPS, EPS), "{t_ac:?}");
        // The inverse takes A's origin into B: 1 m to B's left, at (0, 1).
        let o_in_b = t_ab.inverse().transform_point([0.0, 0.0]);
        assert!(close(o_in_b, [0.0, 1.0], EPS), "{o_in_b:?}");
    }

    #[test]
    fn lidar_extrinsic_of_table_3() {
        // T_L^B = (0.175, 0, 0°): a return 1 m straight ahead of the LiDAR is 1.175 m ahead of the base.
        let t_bl = Se2::from_degrees(0.175, 0.0, 0.0);
        assert!(close(t_bl.transform_point([1.0, 0.0]), [1.175, 0.0], EPS));
    }

    #[test]
    fn interpolation_takes_the_short_arc() {
        let a = Se2::from_degrees(0.0, 0.0, 170.0);
        let b = Se2::from_degrees(2.0, -2.0, -170.0);
        let mid = a.interpolate(&b, 0.5);
        assert!(mid.approx_eq(&Se2::from_degrees(1.0, -1.0, 180.0), EPS, EPS), "{mid:?}");
        assert!(a.interpolate(&b, 0.0).approx_eq(&a, EPS, EPS));
        assert!(a.interpolate(&b, 1.0).approx_eq(&b, EPS, EPS));
    }

    fn pose() -> impl Strategy<Value = Se2> {
        (-50.0..50.0f64, -50.0..50.0f64, -10.0..10.0f64).prop_map(|(x, y, t)| Se2::new(x, y, t))
    }

    proptest! {
        #[test]
        fn normalised_angle_is_in_range_and_equivalent(a in -1.0e6..1.0e6f64) {
            let n = normalize_angle(a);
            prop_assert!(n > -PI && n <= PI, "{} -> {}", a, n);
            // Same direction on the circle.
            prop_assert!((n.sin() - a.sin()).abs() < 1e-6 && (n.cos() - a.cos()).abs() < 1e-6);
        }

        #[test]
        fn inverse_round_trip(t in pose(), p in (-20.0..20.0f64, -20.0..20.0f64)) {
            let p = [p.0, p.1];
            prop_assert!((t * t.inverse()).approx_eq(&Se2::IDENTITY, 1e-9, 1e-9));
            prop_assert!((t.inverse() * t).approx_eq(&Se2::IDENTITY, 1e-9, 1e-9));
            prop_assert!(close(t.inverse().transform_point(t.transform_point(p)), p, 1e-9));
        }

        #[test]
        fn composition_is_associative(a in pose(), b in pose(), c in pose()) {
            prop_assert!(((a * b) * c).approx_eq(&(a * (b * c)), 1e-9, 1e-12));
        }

        #[test]
        fn composition_matches_applying_in_turn(a in pose(), b in pose(), p in (-20.0..20.0f64, -20.0..20.0f64)) {
            let p = [p.0, p.1];
            prop_assert!(close((a * b).transform_point(p), a.transform_point(b.transform_point(p)), 1e-9));
        }

        #[test]
        fn composed_angles_stay_normalised(a in pose(), b in pose()) {
            let c = a * b;
            prop_assert!(c.theta > -PI && c.theta <= PI);
            prop_assert!(a.inverse().theta > -PI && a.inverse().theta <= PI);
        }

        #[test]
        fn transforms_preserve_distances(t in pose(), p in (-20.0..20.0f64, -20.0..20.0f64), q in (-20.0..20.0f64, -20.0..20.0f64)) {
            let (p, q) = ([p.0, p.1], [q.0, q.1]);
            let (tp, tq) = (t.transform_point(p), t.transform_point(q));
            let d0 = (p[0] - q[0]).hypot(p[1] - q[1]);
            let d1 = (tp[0] - tq[0]).hypot(tp[1] - tq[1]);
            prop_assert!((d0 - d1).abs() < 1e-9);
        }

        #[test]
        fn interpolation_stays_between(a in pose(), b in pose(), t in 0.0..1.0f64) {
            let m = a.interpolate(&b, t);
            let full = angle_diff(b.theta, a.theta).abs();
            prop_assert!(angle_diff(m.theta, a.theta).abs() <= full + 1e-9);
            prop_assert!(angle_diff(b.theta, m.theta).abs() <= full + 1e-9);
            prop_assert!(m.theta > -PI && m.theta <= PI);
        }
    }
}
