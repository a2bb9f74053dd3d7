//! Where the mock IMU's numbers come from: a [`MotionSource`] gives the motion at a time; the world
//! simulator will implement it for each robot body. [`ConstantYawRate`] is the simple one for tests.

/// The motion an IMU would measure at one instant, in the sensor frame, SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// Angular rate as the gyro reports it (true rate plus any bias and noise), rad/s.
    pub angular_velocity_radps: [f64; 3],
    /// Orientation quaternion w, x, y, z.
    pub orientation_wxyz: [f64; 4],
    /// Acceleration without gravity, m/s².
    pub linear_acc_mps2: [f64; 3],
}

/// A source of motion for the mock IMU.
pub trait MotionSource: Send {
    /// The motion at `t_s` seconds since the mock started. Calls come with non-decreasing `t_s`.
    fn motion_at(&mut self, t_s: f64) -> Motion;
}

/// A body turning at a constant yaw rate on flat ground; the gyro adds a constant bias and
/// Gaussian noise from a seeded generator, so two runs with the same seed give the same numbers.
#[derive(Debug, Clone)]
pub struct ConstantYawRate {
    /// True yaw rate, rad/s.
    pub yaw_rate_radps: f64,
    /// Gyro bias added to the measured rate, rad/s.
    pub bias_radps: f64,
    /// Standard deviation of the gyro noise, rad/s.
    pub noise_std_radps: f64,
    rng: amr_core::rng::Rng,
}

impl ConstantYawRate {
    /// Turning at `yaw_rate_radps` with the given gyro bias, noise and seed.
    pub fn new(yaw_rate_radps: f64, bias_radps: f64, noise_std_radps: f64, seed: u64) -> Self {
        Self { yaw_rate_radps, bias_radps, noise_std_radps, rng: amr_core::rng::Rng::seed(seed) }
    }
}

impl MotionSource for ConstantYawRate {
    fn motion_at(&mut self, t_s: f64) -> Motion {
        let yaw_rad = self.yaw_rate_radps * t_s;
        let noise = self.noise_std_radps * self.rng.normal();
        Motion {
            angular_velocity_radps: [0.0, 0.0, self.yaw_rate_radps + self.bias_radps + noise],
            orientation_wxyz: [(yaw_rad / 2.0).cos(), 0.0, 0.0, (yaw_rad / 2.0).sin()],
            linear_acc_mps2: [0.0, 0.0, 0.0],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_numbers_and_noise_has_the_asked_spread() {
        let mut a = ConstantYawRate::new(0.5, 0.01, 0.02, 42);
        let mut b = ConstantYawRate::new(0.5, 0.01, 0.02, 42);
        let n = 20_000;
        let mut sum = 0.0;
        let mut sum_sq = 0.0;
        for i in 0..n {
            let t = f64::from(i) * 0.01;
            let (ma, mb) = (a.motion_at(t), b.motion_at(t));
            assert_eq!(ma, mb);
            let e = ma.angular_velocity_radps[2] - 0.51;
            sum += e;
            sum_sq += e * e;
        }
        let mean = sum / f64::from(n);
        let std = (sum_sq / f64::from(n) - mean * mean).sqrt();
        assert!(mean.abs() < 0.001, "mean {mean}");
        assert!((std - 0.02).abs() < 0.001, "std {std}");
        let mut c = ConstantYawRate::new(0.5, 0.01, 0.02, 43);
        assert_ne!(c.motion_at(0.0), ConstantYawRate::new(0.5, 0.01, 0.02, 42).motion_at(0.0));
    }

    #[test]
    fn orientation_integrates_the_true_rate() {
        let mut m = ConstantYawRate::new(0.5, 0.1, 0.0, 1);
        let q = m.motion_at(2.0).orientation_wxyz;
        let yaw = 2.0 * q[3].atan2(q[0]);
        assert!((yaw - 1.0).abs() < 1e-12);
    }
}
