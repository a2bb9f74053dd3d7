//! V's reference motion: the scenario's segments executed one after the other with trapezoidal
//! speed profiles inside the limits, sampled at the physics step.

use crate::config::ScenarioConfig;
use crate::se2::Se2;

/// V's planned pose and twist at one physics step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reference {
    pub pose: Se2,
    pub v_mps: f64,
    pub w_radps: f64,
}

/// Speeds over time for covering `distance` (either sign) with `|speed| ≤ max`, `|accel| ≤ accel`,
/// from rest to rest, sampled every `dt`.
fn trapezoid(distance: f64, max: f64, accel: f64, dt: f64) -> Vec<f64> {
    let d = distance.abs();
    if d == 0.0 || max <= 0.0 || accel <= 0.0 {
        return Vec::new();
    }
    let peak = max.min((d * accel).sqrt());
    let t_acc = peak / accel;
    let d_cruise = (d - peak * t_acc).max(0.0);
    let total = 2.0 * t_acc + d_cruise / peak;
    let n = (total / dt).ceil() as usize;
    let sign = distance.signum();
    (0..n)
        .map(|k| {
            let t = (k as f64 + 0.5) * dt;
            sign * peak.min(accel * t).min(accel * (total - t)).max(0.0)
        })
        .collect()
}

/// The whole reference of a scenario for a formation of `robots`, sampled every `dt_s`, with 1 s at
/// rest at the start (so the filters settle) and at the end.
#[must_use]
pub fn reference(sc: &ScenarioConfig, robots: usize, dt_s: f64) -> Vec<Reference> {
    let lim = &sc.limits;
    // Turning on the spot: the robot furthest from V, and its outer wheel (0.2 m further), sets the
    // yaw rate and angular acceleration. With three or more robots that is not spacing/2: a plan
    // built for two swung the outer robots of three 1 m apart up to 1.3 m off their slots (out of
    // the reference robot's view) in hall-turning.
    let furthest = crate::formation::slots(robots.max(2), sc.spacing_m.get())
        .into_iter()
        .fold(0.0_f64, |m, y| m.max(y.abs()));
    let half = furthest + 0.2;
    let mut twists: Vec<(f64, f64)> = vec![(0.0, 0.0); (1.0 / dt_s).round() as usize];
    for _ in 0..sc.laps.get() {
        for seg in &sc.segments {
            if let Some(d) = seg.straight_m {
                twists.extend(
                    trapezoid(d.get(), lim.max_speed_mps.get(), lim.max_accel_mps2.get(), dt_s)
                        .into_iter()
                        .map(|v| (v, 0.0)),
                );
            }
            if let Some(a) = seg.turn_deg {
                let w_max = lim.max_yaw_rate_radps.get().min(lim.max_speed_mps.get() / half);
                let alpha = lim.max_accel_mps2.get() / half;
                twists.extend(
                    trapezoid(a.get().to_radians(), w_max, alpha, dt_s).into_iter().map(|w| (0.0, w)),
                );
            }
        }
    }
    twists.extend(std::iter::repeat_n((0.0, 0.0), (1.0 / dt_s).round() as usize));
    let mut pose = sc.start_pose();
    twists
        .into_iter()
        .map(|(v, w)| {
            let r = Reference { pose, v_mps: v, w_radps: w };
            let dth = w * dt_s;
            let inc = if dth.abs() < 1e-12 {
                Se2::new(v * dt_s, 0.0, 0.0)
            } else {
                Se2::new(v / w * dth.sin(), v / w * (1.0 - dth.cos()), dth)
            };
            pose = pose * inc;
            r
        })
        .collect()
}
