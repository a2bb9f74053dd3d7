//! Rigid formation control (paper §4.5, Eq. 20; spec §8) and differential-drive odometry.

use crate::se2::Se2;

/// Lateral slots in V's frame: two robots at ±spacing/2 (the paper); three or more in a line with
/// robot 0 — the pipeline's reference, which must see every other robot — in the middle, then
/// +spacing, −spacing, +2·spacing, …
#[must_use]
pub fn slots(robots: usize, spacing_m: f64) -> Vec<f64> {
    match robots {
        0 | 1 => vec![0.0; robots],
        2 => vec![spacing_m / 2.0, -spacing_m / 2.0],
        n => (0..n)
            .map(|i| {
                if i == 0 {
                    0.0
                } else {
                    let k = i.div_ceil(2) as f64;
                    if i % 2 == 1 { k * spacing_m } else { -k * spacing_m }
                }
            })
            .collect(),
    }
}

/// Eq. 20, generalised to any lateral offset: a robot at lateral offset `y_i` (metres, left
/// positive) from the virtual robot V, heading-aligned with it, moves with V's twist `(v_V, ω_V)` when
/// it drives `v_i = v_V − ω_V·y_i`, `ω_i = ω_V`. For the paper's pair, A at `+R` and B at `−R`:
/// `v_A = v_V − ω_V·R`, `v_B = v_V + ω_V·R`.
#[must_use]
pub fn member_twist(v_mps: f64, w_radps: f64, lateral_offset_m: f64) -> (f64, f64) {
    (v_mps - w_radps * lateral_offset_m, w_radps)
}

/// A formation correction on top of Eq. 20 (the paper's controller has none; spec §8 asks for a
/// small documented one): a member whose measured pose in V's frame drifts from its slot
/// `(0, y_i, 0)` gets `Δv = k_x·e_x` along track and `Δω = k_y·e_y + k_θ·e_θ`, with `e` the slot
/// minus the measured pose expressed in the member's frame. Gains small enough that the correction
/// stays well inside the robots' limits at the formation's speeds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FormationGains {
    pub k_x: f64,
    pub k_y: f64,
    pub k_theta: f64,
}

impl FormationGains {
    pub const DEFAULT: FormationGains = FormationGains { k_x: 0.5, k_y: 1.0, k_theta: 1.0 };
}

/// Eq. 20 plus the correction for a member whose measured pose in V's frame is `measured_in_v`.
#[must_use]
pub fn member_command(
    v_mps: f64,
    w_radps: f64,
    slot_y_m: f64,
    measured_in_v: &Se2,
    gains: &FormationGains,
) -> (f64, f64) {
    let (v, w) = member_twist(v_mps, w_radps, slot_y_m);
    let slot = Se2::new(0.0, slot_y_m, 0.0);
    let e = measured_in_v.inverse() * slot;
    // Turning moves a robot sideways only while it moves, and the other way round when it
    // reverses: the lateral term follows the sign of the member's own speed (without this, a
    // reversing formation turns away from its slots, as in Kanayama's tracking law where the
    // lateral term is scaled by the reference speed).
    let lateral = if v.abs() < 1e-3 { 0.0 } else { v.signum() };
    (v + gains.k_x * e.x, w + lateral * gains.k_y * e.y + gains.k_theta * e.theta)
}

/// Clamp a twist to the robot's limits: `|v| ≤ v_max`, `|ω| ≤ ω_max`, and the change from
/// `previous` within `a_max·dt` (wheel-surface acceleration, shared by v and ω·b/2).
#[must_use]
pub fn limit_twist(
    cmd: (f64, f64),
    previous: (f64, f64),
    dt_s: f64,
    v_max: f64,
    w_max: f64,
    a_max: f64,
) -> (f64, f64) {
    let v = cmd.0.clamp(-v_max, v_max);
    let w = cmd.1.clamp(-w_max, w_max);
    let dv = a_max * dt_s;
    (previous.0 + (v - previous.0).clamp(-dv, dv), w)
}

/// Differential-drive odometry from wheel rotation increments (left, right, radians): the exact arc.
#[must_use]
pub fn wheel_odometry_increment(
    d_left_rad: f64,
    d_right_rad: f64,
    wheel_radius_m: f64,
    track_width_m: f64,
) -> Se2 {
    let (sl, sr) = (d_left_rad * wheel_radius_m, d_right_rad * wheel_radius_m);
    crate::odometry::arc(0.5 * (sl + sr), (sr - sl) / track_width_m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eq_20_by_hand() {
        // R = 0.45 m, V turning left at 0.2 rad/s while moving at 0.1 m/s: the inner robot A (left)
        // slows by ω·R = 0.09 m/s, the outer B speeds up by as much; both turn at ω_V.
        let close = |a: (f64, f64), b: (f64, f64)| (a.0 - b.0).abs() < 1e-12 && (a.1 - b.1).abs() < 1e-12;
        assert!(close(member_twist(0.1, 0.2, 0.45), (0.01, 0.2)));
        assert!(close(member_twist(0.1, 0.2, -0.45), (0.19, 0.2)));
        // Straight: both at v_V, no turn.
        assert_eq!(member_twist(0.22, 0.0, 0.45), (0.22, 0.0));
    }

    #[test]
    fn rigid_motion_keeps_the_slots() {
        // Integrating Eq. 20 for both members keeps them at their slots relative to V.
        let (v, w, r, dt) = (0.15, 0.2, 0.45, 0.001);
        let mut vpose = Se2::IDENTITY;
        let mut a = Se2::new(0.0, r, 0.0);
        let mut b = Se2::new(0.0, -r, 0.0);
        for _ in 0..5000 {
            let step = |p: &mut Se2, (vi, wi): (f64, f64)| *p = *p * arc(vi * dt, wi * dt);
            step(&mut a, member_twist(v, w, r));
            step(&mut b, member_twist(v, w, -r));
            vpose = vpose * arc(v * dt, w * dt);
        }
        assert!((vpose.inverse() * a).approx_eq(&Se2::new(0.0, r, 0.0), 1e-9, 1e-9));
        assert!((vpose.inverse() * b).approx_eq(&Se2::new(0.0, -r, 0.0), 1e-9, 1e-9));
    }

    fn arc(ds: f64, dth: f64) -> Se2 {
        if dth.abs() < 1e-12 {
            Se2::new(ds, 0.0, 0.0)
        } else {
            Se2::new(ds / dth * dth.sin(), ds / dth * (1.0 - dth.cos()), dth)
        }
    }

    #[test]
    fn correction_pulls_a_member_back_to_its_slot() {
        // A member 5 cm behind its slot speeds up; one 5 cm right of it turns left.
        let (v, _) = member_command(0.1, 0.0, 0.45, &Se2::new(-0.05, 0.45, 0.0), &FormationGains::DEFAULT);
        assert!(v > 0.1);
        let (_, w) = member_command(0.1, 0.0, 0.45, &Se2::new(0.0, 0.40, 0.0), &FormationGains::DEFAULT);
        assert!(w > 0.0);
        // At its slot nothing changes.
        assert_eq!(
            member_command(0.1, 0.05, 0.45, &Se2::new(0.0, 0.45, 0.0), &FormationGains::DEFAULT),
            member_twist(0.1, 0.05, 0.45)
        );
    }

    #[test]
    fn correction_converges_driving_forwards_and_reversing() {
        // A member starts 5 cm right of its slot and 3° off; V drives straight at ±0.2 m/s.
        for v_ref in [0.2, -0.2] {
            let dt = 0.02;
            let mut vpose = Se2::IDENTITY;
            let mut m = Se2::new(0.0, 0.40, 3f64.to_radians());
            for _ in 0..1500 {
                let c = member_command(v_ref, 0.0, 0.45, &(vpose.inverse() * m), &FormationGains::DEFAULT);
                m = m * arc(c.0 * dt, c.1 * dt);
                vpose = vpose * arc(v_ref * dt, 0.0);
            }
            let e = vpose.inverse() * m;
            assert!(
                (e.y - 0.45).abs() < 0.005 && e.x.abs() < 0.005 && e.theta.abs() < 0.01,
                "v = {v_ref}: ends at {e:?}"
            );
        }
    }

    #[test]
    fn wheel_odometry_by_hand() {
        // Both wheels 1 rad at r = 0.1: 0.1 m straight.
        assert_eq!(wheel_odometry_increment(1.0, 1.0, 0.1, 0.3), Se2::new(0.1, 0.0, 0.0));
        // Opposite wheels: a turn on the spot by 2·0.1/0.3 rad.
        let t = wheel_odometry_increment(-1.0, 1.0, 0.1, 0.3);
        assert!(t.x.abs() < 1e-12 && t.y.abs() < 1e-12 && (t.theta - 0.2 / 0.3).abs() < 1e-12);
        // A quarter circle of radius 1 m: left wheel on r = 0.85, right on 1.15 (b = 0.3).
        let q = std::f64::consts::FRAC_PI_2;
        let t = wheel_odometry_increment(0.85 * q / 0.1, 1.15 * q / 0.1, 0.1, 0.3);
        assert!(t.approx_eq(&Se2::new(1.0, 1.0, q), 1e-12, 1e-12), "{t:?}");
    }

    #[test]
    fn limits() {
        let (v, w) = limit_twist((0.5, 0.5), (0.0, 0.0), 0.1, 0.22, 0.2, 0.05);
        assert!((v - 0.005).abs() < 1e-12 && (w - 0.2).abs() < 1e-12);
        assert_eq!(limit_twist((-0.5, -0.5), (-0.22, 0.0), 1.0, 0.22, 0.2, 0.05), (-0.22, -0.2));
    }
}
