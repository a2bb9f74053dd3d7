//! The motor behind a mock drive: velocity follows its target within acceleration limits
//! (integrated exactly over any time step), the encoder counts the motion with configurable slip
//! and seeded Gaussian read noise (amr-core's `Rng`).

use amr_core::rng::Rng;

/// Motor and encoder state, in encoder counts.
#[derive(Debug, Clone)]
pub(crate) struct Motor {
    /// Shaft speed, counts/s.
    pub(crate) velocity_cps: f64,
    /// Encoder position, counts (exact, before noise; wraps to i32 only when reported).
    pub(crate) position_counts: f64,
    /// Fraction of the motion the encoder does not see (wheel slip), 0..1.
    slip: f64,
    /// Standard deviation of the reported position, counts.
    noise_counts: f64,
    rng: Rng,
}

impl Motor {
    pub(crate) fn new(position_counts: f64, slip: f64, noise_counts: f64, seed: u64) -> Self {
        Self {
            velocity_cps: 0.0,
            position_counts,
            slip: slip.clamp(0.0, 1.0),
            noise_counts,
            rng: Rng::seed(seed),
        }
    }

    /// Advance `dt_s` towards `target_cps` with `accel_cps2` (speeding up) or `decel_cps2`
    /// (slowing down); a zero limit means an immediate step.
    pub(crate) fn advance(&mut self, dt_s: f64, target_cps: f64, accel_cps2: f64, decel_cps2: f64) {
        if dt_s <= 0.0 || !dt_s.is_finite() {
            return;
        }
        let v0 = self.velocity_cps;
        let dv = target_cps - v0;
        let speeding_up = target_cps.abs() > v0.abs() && target_cps * v0 >= 0.0;
        let a = if speeding_up { accel_cps2 } else { decel_cps2 };
        let (v1, travel) = if a <= 0.0 || dv == 0.0 {
            (target_cps, target_cps * dt_s)
        } else {
            let t_ramp = dv.abs() / a;
            if t_ramp >= dt_s {
                let v1 = v0 + dv.signum() * a * dt_s;
                (v1, (v0 + v1) / 2.0 * dt_s)
            } else {
                (target_cps, (v0 + target_cps) / 2.0 * t_ramp + target_cps * (dt_s - t_ramp))
            }
        };
        self.velocity_cps = v1;
        self.position_counts += travel * (1.0 - self.slip);
    }

    /// The position as the encoder reports it: noisy, rounded, wrapped to 32 bits like 0x6064.
    pub(crate) fn reported_position(&mut self) -> i32 {
        let noise = if self.noise_counts > 0.0 { self.rng.gaussian(self.noise_counts) } else { 0.0 };
        let p = (self.position_counts + noise).round();
        // rem_euclid keeps the value in range before the cast; the cast then wraps like a counter.
        p.rem_euclid(4_294_967_296.0) as u32 as i32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn teco_motor_ramps_exactly_and_wraps() {
        let mut m = Motor::new(0.0, 0.0, 0.0, 1);
        // 1000 counts/s² to 500 counts/s: 0.5 s ramp (125 counts), then 0.5 s at speed (250).
        m.advance(1.0, 500.0, 1000.0, 1000.0);
        assert!((m.velocity_cps - 500.0).abs() < 1e-9);
        assert!((m.position_counts - 375.0).abs() < 1e-9);
        // The same in 10 steps gives the same result.
        let mut n = Motor::new(0.0, 0.0, 0.0, 1);
        for _ in 0..10 {
            n.advance(0.1, 500.0, 1000.0, 1000.0);
        }
        assert!((n.position_counts - 375.0).abs() < 1e-9);
        let mut w = Motor::new(f64::from(i32::MAX), 0.0, 0.0, 1);
        w.advance(1.0, 10.0, 0.0, 0.0);
        assert_eq!(w.reported_position(), i32::MIN + 9);
        let mut s = Motor::new(0.0, 0.1, 0.0, 1);
        s.advance(1.0, 100.0, 0.0, 0.0);
        assert!((s.position_counts - 90.0).abs() < 1e-9, "10 % slip");
    }
}
