//! The robot's odometry, as pure arithmetic: wheel travel for distance, the gyro's yaw rate for
//! heading (wheels slip in turns and their radii and track are never exactly the nominal ones; the
//! gyro sees the body turn), and the wheels' heading when the gyro is silent. The gyro bias is
//! estimated whenever the wheels stand still (a zero-velocity update), so it does not integrate
//! into the heading. `amr robot`'s odometry actor runs it on its devices; `amr eval` runs it on the
//! simulated encoders and gyro, so that both dead-reckon alike.

use crate::se2::Se2;

/// A gyro reading older than this is not used for heading, s.
pub const GYRO_FRESH_S: f64 = 0.1;
/// The bias estimate is the mean of the stationary readings, over at most this many of the latest
/// (so that it follows a bias that drifts with temperature). Within one standstill the mean of n
/// readings errs by σ/√n; an exponential average of gain g, which this replaced (g = 0.02), errs by
/// σ·√(g/2) at best, the mean of 50 readings however long the robot stands.
const BIAS_WINDOW: u32 = 2000;
/// Wheel travel below this per cycle counts as standing still, m.
const STILL_M: f64 = 1e-5;

/// One cycle's wheel travel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Travel {
    pub stamp_s: f64,
    /// Time since the previous travel, s.
    pub dt_s: f64,
    pub left_m: f64,
    pub right_m: f64,
}

/// Wheels + gyro dead reckoning from the origin.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Odometer {
    pose: Se2,
    /// Sum and count of gyro rates since the last wheel travel.
    gyro_sum: f64,
    gyro_n: u32,
    last_gyro_s: Option<f64>,
    bias: Option<f64>,
    /// Stationary readings in the bias estimate (at most [`BIAS_WINDOW`]).
    bias_n: u32,
}

/// The motion along an arc of length `ds` turning by `dtheta`, in the start frame.
#[must_use]
pub fn arc(ds: f64, dtheta: f64) -> Se2 {
    if dtheta.abs() < 1e-9 {
        return Se2::new(ds * (0.5 * dtheta).cos(), ds * (0.5 * dtheta).sin(), dtheta);
    }
    let r = ds / dtheta;
    Se2::new(r * dtheta.sin(), r * (1.0 - dtheta.cos()), dtheta)
}

impl Odometer {
    /// At the origin, nothing known of the gyro.
    #[must_use]
    pub fn new() -> Self {
        Odometer::default()
    }

    /// The pose since the origin.
    #[must_use]
    pub fn pose(&self) -> Se2 {
        self.pose
    }

    /// The gyro bias learnt at standstill so far, rad/s.
    #[must_use]
    pub fn bias(&self) -> Option<f64> {
        self.bias
    }

    /// A gyro yaw rate, rad/s, taken at `stamp_s`.
    pub fn gyro(&mut self, stamp_s: f64, rate_radps: f64) {
        if !rate_radps.is_finite() {
            return;
        }
        self.gyro_sum += rate_radps;
        self.gyro_n += 1;
        self.last_gyro_s = Some(stamp_s);
    }

    /// Fold one wheel travel (and the gyro readings since the previous one) into the pose;
    /// returns whether the gyro gave the heading. A travel that is not finite is ignored.
    pub fn step(&mut self, w: &Travel, track_width_m: f64) -> bool {
        if !(w.left_m.is_finite() && w.right_m.is_finite()) {
            return false;
        }
        let ds = 0.5 * (w.left_m + w.right_m);
        let wheel_dtheta = (w.right_m - w.left_m) / track_width_m;
        let fresh = self.last_gyro_s.is_some_and(|t| w.stamp_s - t <= GYRO_FRESH_S) && self.gyro_n > 0;
        let still = w.left_m.abs() < STILL_M && w.right_m.abs() < STILL_M;
        let mean = if self.gyro_n > 0 { self.gyro_sum / f64::from(self.gyro_n) } else { 0.0 };
        if fresh && still {
            // Each cycle's mean counts as its readings.
            let n = self.bias_n.saturating_add(self.gyro_n).min(BIAS_WINDOW);
            let gain = f64::from(self.gyro_n.min(n)) / f64::from(n.max(1));
            let b = self.bias.unwrap_or(mean);
            self.bias = Some(b + gain * (mean - b));
            self.bias_n = n;
        }
        let dtheta = if fresh && w.dt_s.is_finite() && w.dt_s > 0.0 {
            if still { 0.0 } else { (mean - self.bias.unwrap_or(0.0)) * w.dt_s }
        } else {
            wheel_dtheta
        };
        self.pose = self.pose * arc(ds, dtheta);
        self.gyro_sum = 0.0;
        self.gyro_n = 0;
        fresh
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn travel(stamp_s: f64, left_m: f64, right_m: f64) -> Travel {
        Travel { stamp_s, dt_s: 0.02, left_m, right_m }
    }

    #[test]
    fn heading_from_the_gyro_minus_the_bias_learnt_at_standstill() {
        let mut s = Odometer::new();
        let bias = 0.002;
        // Two seconds still at 50 Hz: the bias is learnt, the pose does not move.
        for k in 0..100 {
            let t = f64::from(k) * 0.02;
            s.gyro(t, bias);
            assert!(s.step(&travel(t, 0.0, 0.0), 0.33));
        }
        assert_eq!(s.pose(), Se2::IDENTITY);
        assert!((s.bias().unwrap_or(0.0) - bias).abs() < 1e-9);
        // Then 1 s turning at 0.2 rad/s while the wheels (slipping) claim 0.3 rad/s.
        for k in 0..50 {
            let t = 2.0 + f64::from(k) * 0.02;
            s.gyro(t, 0.2 + bias);
            let d = 0.3 * 0.02 * 0.33 / 2.0;
            assert!(s.step(&travel(t, -d, d), 0.33));
        }
        assert!((s.pose().theta - 0.2).abs() < 1e-9, "{}", s.pose().theta);
    }

    #[test]
    fn the_bias_is_the_mean_of_the_readings_at_standstill() {
        let mut rng = crate::rng::Rng::seed(3);
        let (bias, sigma) = (0.0015, 0.005);
        let mut s = Odometer::new();
        let mut sum = 0.0;
        for k in 0..600 {
            let t = f64::from(k) / 150.0;
            let r = bias + rng.gaussian(sigma);
            sum += r;
            s.gyro(t, r);
            s.step(&Travel { stamp_s: t, dt_s: 1.0 / 150.0, left_m: 0.0, right_m: 0.0 }, 0.33);
        }
        // 4 s at 150 Hz: the mean of all 600 readings (σ/√600 = 0.0002 rad/s from the truth), not an
        // average of the last 50 (σ/√50 = 0.0007).
        assert!((s.bias().unwrap() - sum / 600.0).abs() < 1e-12, "{:?} vs {}", s.bias(), sum / 600.0);
        // Beyond the window, older readings fade: a new bias is followed.
        for k in 600..(600 + 3 * BIAS_WINDOW) {
            let t = f64::from(k) / 150.0;
            s.gyro(t, 0.003);
            s.step(&Travel { stamp_s: t, dt_s: 1.0 / 150.0, left_m: 0.0, right_m: 0.0 }, 0.33);
        }
        assert!((s.bias().unwrap() - 0.003).abs() < 0.0001, "{:?}", s.bias());
    }

    #[test]
    fn without_a_fresh_gyro_the_wheels_give_the_heading() {
        let mut s = Odometer::new();
        s.gyro(0.0, 5.0);
        // The last reading is 1 s old.
        let d = 0.01;
        assert!(!s.step(&travel(1.0, -d, d), 0.2));
        assert!((s.pose().theta - 0.1).abs() < 1e-12);
        // Straight travel moves along x; a travel that is not finite changes nothing.
        let mut s = Odometer::new();
        assert!(!s.step(&travel(0.0, 0.5, 0.5), 0.2));
        assert!(!s.step(&travel(0.02, f64::NAN, 0.5), 0.2));
        s.gyro(0.04, f64::INFINITY);
        assert!(s.pose().approx_eq(&Se2::new(0.5, 0.0, 0.0), 1e-12, 1e-12));
    }
}
