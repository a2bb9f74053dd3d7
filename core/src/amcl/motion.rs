//! The odometry motion model for a differential drive (Probabilistic Robotics, Table 5.6,
//! `sample_motion_model_odometry`), with nav2_amcl's two refinements: no first rotation for
//! in-place turns (translation < 1 cm), and rotation noise from `min(|δ|, |π − δ|)` so that driving
//! backwards is not mistaken for two half-turns.

use crate::config::AmclParams;
use crate::rng::Rng;
use crate::se2::{Se2, angle_diff};

/// The odometry increment as (rot1, trans, rot2) with the standard deviations of each.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometryDelta {
    pub rot1: f64,
    pub trans: f64,
    pub rot2: f64,
    pub sigma_rot1: f64,
    pub sigma_trans: f64,
    pub sigma_rot2: f64,
    /// The share of samples that do not trust the increment (see `AmclParams::odom_slip_share`):
    /// translation uniform in ±[`SLIP_REACH`] × `trans`, heading with [`SLIP_HEADING_SIGMA`] more
    /// noise. 0 from [`delta`].
    pub slip_share: f64,
}

/// Decompose the odometry change `old → new` (both in the odometry frame).
#[must_use]
pub fn delta(old: &Se2, new: &Se2, alpha: [f64; 4]) -> OdometryDelta {
    let (dx, dy) = (new.x - old.x, new.y - old.y);
    let trans = dx.hypot(dy);
    let rot1 = if trans < 0.01 { 0.0 } else { angle_diff(dy.atan2(dx), old.theta) };
    let rot2 = angle_diff(angle_diff(new.theta, old.theta), rot1);
    let noise = |r: f64| angle_diff(r, 0.0).abs().min(angle_diff(r, std::f64::consts::PI).abs());
    let (n1, n2) = (noise(rot1), noise(rot2));
    let [a1, a2, a3, a4] = alpha;
    OdometryDelta {
        rot1,
        trans,
        rot2,
        sigma_rot1: (a1 * n1 * n1 + a2 * trans * trans).sqrt(),
        sigma_trans: (a3 * trans * trans + a4 * n1 * n1 + a4 * n2 * n2).sqrt(),
        sigma_rot2: (a1 * n2 * n2 + a2 * trans * trans).sqrt(),
        slip_share: 0.0,
    }
}

/// The four α of the model from the parameters.
#[must_use]
pub fn alphas(params: &AmclParams) -> [f64; 4] {
    [params.alpha1.get(), params.alpha2.get(), params.alpha3.get(), params.alpha4.get()]
}

/// How far a slipped translation may reach, as a multiple of the odometry's, either way.
pub const SLIP_REACH: f64 = 1.5;
/// The heading noise (rad, σ) a slipped sample gets on top of the model's, whatever the increment:
/// a robot can be turned without its odometry seeing it (freiburg-079: the scans themselves show turns
/// of +16° and −25° within three scans where the odometry says +1° and −4°).
pub const SLIP_HEADING_SIGMA: f64 = 0.2;

/// Move one pose by a noisy sample of the increment; true if the sample took the slip tail.
pub fn sample(pose: &mut Se2, d: &OdometryDelta, rng: &mut Rng) -> bool {
    let rot1 = angle_diff(d.rot1, rng.gaussian(d.sigma_rot1));
    let slip = d.slip_share > 0.0 && rng.uniform() < d.slip_share;
    let trans = if slip {
        d.trans * rng.range(-SLIP_REACH, SLIP_REACH)
    } else {
        d.trans - rng.gaussian(d.sigma_trans)
    };
    let rot2 = angle_diff(
        d.rot2,
        rng.gaussian(d.sigma_rot2) + if slip { rng.gaussian(SLIP_HEADING_SIGMA) } else { 0.0 },
    );
    let (sin, cos) = (pose.theta + rot1).sin_cos();
    *pose = Se2::new(pose.x + trans * cos, pose.y + trans * sin, pose.theta + rot1 + rot2);
    slip
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALPHA: [f64; 4] = [0.2, 0.2, 0.2, 0.2];

    #[test]
    fn decomposition_by_hand() {
        // 1 m straight ahead, then a 90° turn on the spot at the end.
        let d = delta(&Se2::IDENTITY, &Se2::from_degrees(1.0, 0.0, 90.0), ALPHA);
        assert!(d.rot1.abs() < 1e-12 && (d.trans - 1.0).abs() < 1e-12);
        assert!((d.rot2 - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        let half_pi = std::f64::consts::FRAC_PI_2;
        assert!((d.sigma_trans - (0.2f64 + 0.2 * half_pi * half_pi).sqrt()).abs() < 1e-12);
        // In place: no rot1, all rotation in rot2.
        let d = delta(&Se2::IDENTITY, &Se2::from_degrees(0.005, 0.0, 30.0), ALPHA);
        assert_eq!(d.rot1, 0.0);
        assert!((d.rot2 - 30f64.to_radians()).abs() < 1e-12);
        // Reversing 1 m: rot1 = π, but its noise term is min(π, 0) = 0.
        let d = delta(&Se2::IDENTITY, &Se2::new(-1.0, 0.0, 0.0), ALPHA);
        assert!((d.rot1.abs() - std::f64::consts::PI).abs() < 1e-12);
        assert!((d.sigma_rot1 - (0.2f64).sqrt()).abs() < 1e-12, "only the α2·trans² term");
        assert!((d.sigma_trans - (0.2f64).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn mean_and_spread_match_the_formulas() {
        let (old, new) = (Se2::from_degrees(1.0, 2.0, 30.0), Se2::from_degrees(1.5, 2.3, 50.0));
        let d = delta(&old, &new, [0.05, 0.02, 0.1, 0.01]);
        let mut rng = Rng::seed(3);
        let n = 40_000;
        let samples: Vec<Se2> = (0..n)
            .map(|_| {
                let mut p = old;
                sample(&mut p, &d, &mut rng);
                p
            })
            .collect();
        // The heading after the move is old + rot1 + rot2 + noise with variance σ1² + σ2².
        let mean_dtheta = samples.iter().map(|p| angle_diff(p.theta, new.theta)).sum::<f64>() / n as f64;
        let var_theta =
            samples.iter().map(|p| angle_diff(p.theta, new.theta).powi(2)).sum::<f64>() / n as f64;
        assert!(mean_dtheta.abs() < 0.002, "{mean_dtheta}");
        let expect = d.sigma_rot1.powi(2) + d.sigma_rot2.powi(2);
        assert!((var_theta / expect - 1.0).abs() < 0.05, "{var_theta} vs {expect}");
        // The distance travelled has mean trans and spread σ_trans (to first order).
        let dist: Vec<f64> = samples.iter().map(|p| (p.x - old.x).hypot(p.y - old.y)).collect();
        let m = dist.iter().sum::<f64>() / n as f64;
        let v = dist.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n as f64;
        assert!((m - d.trans).abs() < 0.003, "{m} vs {}", d.trans);
        assert!((v.sqrt() / d.sigma_trans - 1.0).abs() < 0.05, "{} vs {}", v.sqrt(), d.sigma_trans);
        // The mean end point is the odometry's end point.
        let (mx, my) = (
            samples.iter().map(|p| p.x).sum::<f64>() / n as f64,
            samples.iter().map(|p| p.y).sum::<f64>() / n as f64,
        );
        assert!((mx - new.x).abs() < 0.005 && (my - new.y).abs() < 0.005, "({mx}, {my})");
    }
}
