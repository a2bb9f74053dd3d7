//! Rigid formation control (paper §4.5, Eq. 20; docs/method.md §8) and differential-drive odometry.

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

/// A formation correction on top of Eq. 20 (the paper's controller has none; docs/method.md §8
/// documents this one): a member whose measured pose in V's frame drifts from its slot
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

/// A re-forming robot this close to its slot, m, is in the near zone: it no longer steers towards
/// the slot's point (whose bearing is ill-defined so close, and estimates jitter by centimetres),
/// only along its own heading and onto V's heading.
pub const REFORM_NEAR_M: f64 = 0.10;
/// In the near zone, a robot within this distance along its heading, m, and this heading of V's,
/// rad, stands.
pub const REFORM_TOLERANCE: (f64, f64) = (0.03, 0.035);

/// A robot at `measured_in_v` (V's frame) driven to its slot `(0, slot_y_m, 0)` with V at rest.
/// Away from the slot, the unicycle's go-to-pose law in polar coordinates (distance ρ to the slot,
/// bearing α of the slot from the robot's heading, β the slot's heading seen along that bearing):
/// `v = k_ρ·ρ`, `ω = k_α·α + k_β·β`, which converges for `k_ρ > 0`, `k_β < 0`, `k_α > k_ρ`
/// (Siegwart, Nourbakhsh and Scaramuzza, *Introduction to Autonomous Mobile Robots*, 2nd ed.,
/// §3.6.2.4); a slot behind the robot is reached in reverse (the bearing taken from the robot's
/// rear), so a robot never turns round to back into its slot. Within [`REFORM_NEAR_M`] it only
/// moves along its heading and turns onto V's: the polar law's bearing turns a robot through
/// large angles towards a point a few centimetres away. [`member_command`] cannot re-form: with
/// V at rest its lateral term is off (a differential drive moves sideways only while it moves),
/// so a robot beside its slot would stand there for good.
#[must_use]
pub fn reform_command(slot_y_m: f64, measured_in_v: &Se2) -> (f64, f64) {
    const K_RHO: f64 = 0.5;
    const K_ALPHA: f64 = 1.5;
    const K_BETA: f64 = -0.4;
    let (dx, dy) = (0.0 - measured_in_v.x, slot_y_m - measured_in_v.y);
    let rho = dx.hypot(dy);
    let heading_error = crate::se2::normalize_angle(-measured_in_v.theta);
    if rho <= REFORM_NEAR_M {
        let (s, c) = measured_in_v.theta.sin_cos();
        let along = c * dx + s * dy;
        let (v, w) = (K_RHO * along, K_ALPHA * heading_error);
        let at_rest = along.abs() <= REFORM_TOLERANCE.0 && heading_error.abs() <= REFORM_TOLERANCE.1;
        return if at_rest { (0.0, 0.0) } else { (v, w) };
    }
    let bearing = dy.atan2(dx);
    let mut alpha = crate::se2::normalize_angle(bearing - measured_in_v.theta);
    let mut direction = 1.0;
    if alpha.abs() > std::f64::consts::FRAC_PI_2 {
        // Behind: drive backwards, the bearing taken from the robot's rear.
        alpha = crate::se2::normalize_angle(alpha + std::f64::consts::PI);
        direction = -1.0;
    }
    let beta = crate::se2::normalize_angle(-measured_in_v.theta - alpha);
    // Mostly facing the slot's direction first: little forward speed while the bearing is large.
    let v = direction * K_RHO * rho * alpha.cos().max(0.0);
    (v, K_ALPHA * alpha + K_BETA * beta)
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

    /// A robot beside, ahead of or behind its slot, at any heading within ±60° of V's, re-forms with
    /// V at rest under the formation's limits (0.22 m/s, 0.2 rad/s, 0.05 m/s²): within the near
    /// zone and on V's heading in 90 s, standing there, and never more than 0.5 m farther from
    /// the slot than it started; estimates that jitter by 2 cm and 1° near the slot turn it by
    /// no more than 10°. [`member_command`] leaves a robot beside its slot where it is.
    #[test]
    fn a_robot_beside_its_slot_reforms_with_v_at_rest() {
        let (slot_y, dt) = (-0.45, 0.05);
        let mut starts = Vec::new();
        for dy in [-0.7, -0.3, 0.3, 0.65] {
            for dx in [-0.5, 0.0, 0.4] {
                for th in [-60f64, 0.0, 45.0] {
                    starts.push(Se2::new(dx, slot_y + dy, th.to_radians()));
                }
            }
        }
        for start in starts {
            let rho0 = start.x.hypot(start.y - slot_y);
            let (mut p, mut last, mut worst) = (start, (0.0, 0.0), 0.0f64);
            let mut at_rest = None;
            for k in 0..(90.0 / dt) as usize {
                let cmd = limit_twist(reform_command(slot_y, &p), last, dt, 0.22, 0.2, 0.05);
                last = cmd;
                p = p * arc(cmd.0 * dt, cmd.1 * dt);
                worst = worst.max(p.x.hypot(p.y - slot_y));
                if cmd == (0.0, 0.0) && at_rest.is_none() {
                    at_rest = Some(k);
                }
            }
            let rho = p.x.hypot(p.y - slot_y);
            assert!(
                rho <= REFORM_NEAR_M && p.theta.abs() <= REFORM_TOLERANCE.1 + 0.01,
                "from {start:?}: ended at {p:?}"
            );
            assert_eq!(reform_command(slot_y, &p), (0.0, 0.0), "from {start:?}: at {p:?}");
            assert!(worst <= rho0 + 0.5, "from {start:?}: went {worst:.2} m from the slot");
            assert!(at_rest.is_some(), "from {start:?}");
        }
        // At its slot, on estimates that jitter: it stays there, on V's heading.
        let mut rng = crate::rng::Rng::seed(3);
        for start in [Se2::new(0.0, slot_y, 0.0), Se2::new(0.06, slot_y - 0.05, 0.03)] {
            let (mut p, mut last) = (start, (0.0, 0.0));
            for _ in 0..(60.0 / dt) as usize {
                let seen = Se2::new(
                    p.x + rng.range(-0.02, 0.02),
                    p.y + rng.range(-0.02, 0.02),
                    p.theta + rng.range(-1f64, 1.0).to_radians(),
                );
                let cmd = limit_twist(reform_command(slot_y, &seen), last, dt, 0.22, 0.2, 0.05);
                last = cmd;
                p = p * arc(cmd.0 * dt, cmd.1 * dt);
                assert!(p.theta.abs() <= 10f64.to_radians(), "from {start:?}: turned to {p:?}");
                assert!(p.x.hypot(p.y - slot_y) <= REFORM_NEAR_M + 0.02, "from {start:?}: left for {p:?}");
            }
        }
        // The tracking law's correction does not move it sideways with V at rest.
        let beside = Se2::new(0.0, slot_y + 0.5, 0.0);
        assert_eq!(member_command(0.0, 0.0, slot_y, &beside, &FormationGains::DEFAULT), (0.0, 0.0));
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
