//! The neighbour tracker (paper §4.2, Eq. 8–10; docs/method.md §4): a constant-velocity Kalman
//! filter on the neighbour's centre in the observing robot's base frame, with a dynamic ROI, a
//! Mahalanobis gate and the lost-track rule.

use nalgebra::{Matrix2, Matrix2x4, Matrix4, Vector2, Vector4};

use crate::config::TrackerParams;

/// State `(x, y, vx, vy)` with its covariance, valid at `t_s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackState {
    pub x: Vector4<f64>,
    pub p: Matrix4<f64>,
    pub t_s: f64,
}

impl TrackState {
    #[must_use]
    pub fn position(&self) -> [f64; 2] {
        [self.x[0], self.x[1]]
    }

    #[must_use]
    pub fn velocity(&self) -> [f64; 2] {
        [self.x[2], self.x[3]]
    }
}

/// Axis-aligned region of interest in the observer's base frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Roi {
    pub center: [f64; 2],
    pub half_width: [f64; 2],
}

impl Roi {
    #[must_use]
    pub fn contains(&self, p: [f64; 2]) -> bool {
        (p[0] - self.center[0]).abs() <= self.half_width[0]
            && (p[1] - self.center[1]).abs() <= self.half_width[1]
    }
}

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TrackOutcome {
    /// First measurement: the track starts at it with zero velocity (Eq. 8).
    Started,
    /// The measurement passed the gate and corrected the prediction (Eq. 9f–9h).
    Updated { mahalanobis_sq: f64 },
    /// The measurement failed the gate; the prediction was kept and counted as a miss.
    Gated { mahalanobis_sq: f64, misses: u32 },
    /// No measurement; the prediction was kept and counted as a miss.
    Missed { misses: u32 },
    /// `N_miss,max` consecutive misses: the track is dropped. Re-acquire with the full ROI and run
    /// the full heading search.
    Lost,
    /// Nothing to do: no track and no measurement.
    Idle,
    /// The update's time is before the track's: rejected, state unchanged.
    TimeWentBackwards,
}

/// The constant-velocity tracker with the paper's parameters (Table 2).
#[derive(Debug, Clone)]
pub struct Tracker {
    params: TrackerParams,
    gate_sq: f64,
    state: Option<TrackState>,
    misses: u32,
}

/// Eq. 9c: `F(Δt)`.
#[must_use]
pub fn transition(dt: f64) -> Matrix4<f64> {
    let mut f = Matrix4::identity();
    f[(0, 2)] = dt;
    f[(1, 3)] = dt;
    f
}

/// Discrete white-noise-acceleration `Q(Δt)` (docs/method.md §4): σ²Δt⁴/4 on positions,
/// σ²Δt³/2 across, σ²Δt² on velocities. At Δt = 0.1 s, σ = 0.05 m/s² this is Table 2's 6.25e-8,
/// 1.25e-6, 2.5e-5.
#[must_use]
pub fn process_noise(dt: f64, accel_sigma: f64) -> Matrix4<f64> {
    let s2 = accel_sigma * accel_sigma;
    let (pp, pv, vv) = (s2 * dt.powi(4) / 4.0, s2 * dt.powi(3) / 2.0, s2 * dt * dt);
    Matrix4::new(pp, 0.0, pv, 0.0, 0.0, pp, 0.0, pv, pv, 0.0, vv, 0.0, 0.0, pv, 0.0, vv)
}

/// Chi-square quantile with 2 degrees of freedom: `−2 ln(1 − p)` (closed form for 2 dof).
#[must_use]
pub fn chi2_2dof(probability: f64) -> f64 {
    -2.0 * (1.0 - probability).ln()
}

const H: Matrix2x4<f64> = Matrix2x4::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0);

impl Tracker {
    #[must_use]
    pub fn new(params: TrackerParams) -> Self {
        Tracker { gate_sq: chi2_2dof(params.gate_probability.get()), params, state: None, misses: 0 }
    }

    /// The current (posterior) state, if tracking.
    #[must_use]
    pub fn state(&self) -> Option<&TrackState> {
        self.state.as_ref()
    }

    #[must_use]
    pub fn misses(&self) -> u32 {
        self.misses
    }

    /// Drop the track (e.g. when the neighbour is known to have gone).
    pub fn reset(&mut self) {
        self.state = None;
        self.misses = 0;
    }

    /// Eq. 9a–9b: the prior at `t_s` (the current state if `t_s` is not later).
    #[must_use]
    pub fn predict(&self, t_s: f64) -> Option<TrackState> {
        let s = self.state?;
        let dt = t_s - s.t_s;
        if dt <= 0.0 {
            return Some(s);
        }
        let f = transition(dt);
        Some(TrackState {
            x: f * s.x,
            p: f * s.p * f.transpose() + process_noise(dt, self.params.accel_sigma_mps2.get()),
            t_s,
        })
    }

    /// Eq. 10: the ROI at `t_s`, `h = h0 + |v|·Δt + γ·sqrt(P)` per axis around the predicted centre
    /// (γ on the standard deviation, docs/method.md §4). `None` without a track: search everywhere.
    #[must_use]
    pub fn roi(&self, t_s: f64) -> Option<Roi> {
        let s = self.state?;
        let prior = self.predict(t_s)?;
        let dt = (t_s - s.t_s).max(0.0);
        let g = self.params.roi_gamma.get();
        let h0 = self.params.roi_half_width_m;
        Some(Roi {
            center: prior.position(),
            half_width: [
                h0[0].get() + prior.x[2].abs() * dt + g * prior.p[(0, 0)].sqrt(),
                h0[1].get() + prior.x[3].abs() * dt + g * prior.p[(1, 1)].sqrt(),
            ],
        })
    }

    /// A packet without a usable measurement: keep the prediction, or drop the track after
    /// `N_miss,max` in a row.
    fn miss(&mut self, prior: TrackState, outcome: impl FnOnce(u32) -> TrackOutcome) -> TrackOutcome {
        self.misses += 1;
        if self.misses >= self.params.max_missed_packets.get() {
            self.reset();
            TrackOutcome::Lost
        } else {
            self.state = Some(prior);
            outcome(self.misses)
        }
    }

    /// One synchronised packet at `t_s` with the contour measurement `z` (or none).
    pub fn update(&mut self, t_s: f64, z: Option<[f64; 2]>) -> TrackOutcome {
        let Some(current) = self.state else {
            return match z {
                Some(z) => {
                    let p0 = Matrix4::from_diagonal(&Vector4::new(
                        self.params.initial_position_var_m2.get(),
                        self.params.initial_position_var_m2.get(),
                        self.params.initial_velocity_var_m2ps2.get(),
                        self.params.initial_velocity_var_m2ps2.get(),
                    ));
                    self.state = Some(TrackState { x: Vector4::new(z[0], z[1], 0.0, 0.0), p: p0, t_s });
                    self.misses = 0;
                    TrackOutcome::Started
                }
                None => TrackOutcome::Idle,
            };
        };
        if t_s < current.t_s {
            return TrackOutcome::TimeWentBackwards;
        }
        let Some(prior) = self.predict(t_s) else { return TrackOutcome::Idle };
        let Some(z) = z else {
            return self.miss(prior, |misses| TrackOutcome::Missed { misses });
        };
        let r = Matrix2::from_diagonal_element(self.params.measurement_var_m2.get());
        let innovation = Vector2::new(z[0], z[1]) - H * prior.x;
        let s = H * prior.p * H.transpose() + r;
        let Some(s_inv) = s.try_inverse() else {
            return self.miss(prior, |misses| TrackOutcome::Missed { misses });
        };
        let d2 = (innovation.transpose() * s_inv * innovation)[(0, 0)];
        if d2 > self.gate_sq {
            return self.miss(prior, |misses| TrackOutcome::Gated { mahalanobis_sq: d2, misses });
        }
        let k = prior.p * H.transpose() * s_inv;
        let x = prior.x + k * innovation;
        let p = (Matrix4::identity() - k * H) * prior.p;
        // Keep P symmetric against rounding.
        let p = 0.5 * (p + p.transpose());
        self.state = Some(TrackState { x, p, t_s });
        self.misses = 0;
        TrackOutcome::Updated { mahalanobis_sq: d2 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{ConfigFileType, VamrParams, parse_file};

    fn params() -> TrackerParams {
        let text =
            std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/vamr.toml")).unwrap();
        let v: VamrParams = parse_file("vamr.toml", &text).unwrap();
        assert!(v.validate().is_ok());
        v.tracker
    }

    #[test]
    fn q_reproduces_table_2_at_a_tenth_of_a_second() {
        let q = process_noise(0.1, 0.05);
        let close = |a: f64, b: f64| (a - b).abs() < 1e-15;
        assert!(close(q[(0, 0)], 6.25e-8) && close(q[(1, 1)], 6.25e-8));
        assert!(close(q[(0, 2)], 1.25e-6) && close(q[(2, 0)], 1.25e-6) && close(q[(1, 3)], 1.25e-6));
        assert!(close(q[(2, 2)], 2.5e-5) && close(q[(3, 3)], 2.5e-5));
        assert_eq!(q[(0, 1)], 0.0);
        assert_eq!(q[(0, 3)], 0.0);
    }

    #[test]
    fn chi_square_two_dof() {
        assert!((chi2_2dof(0.99) - 9.210_340_371_976_18).abs() < 1e-9);
        assert!((chi2_2dof(0.95) - 5.991_464_547_107_98).abs() < 1e-9);
    }

    #[test]
    fn first_update_by_hand() {
        let mut t = Tracker::new(params());
        assert_eq!(t.update(0.0, Some([1.0, -0.5])), TrackOutcome::Started);
        // Eq. 8: x0 = (z, 0), P0 = diag(2.5e-3, 2.5e-3, 1e-2, 1e-2).
        let s = *t.state().unwrap();
        assert_eq!(s.x, Vector4::new(1.0, -0.5, 0.0, 0.0));
        // One step of 0.1 s with a measurement 1 cm further in x.
        let out = t.update(0.1, Some([1.01, -0.5]));
        assert!(matches!(out, TrackOutcome::Updated { .. }), "{out:?}");
        // By hand for the x axis: P⁻ = F P0 Fᵀ + Q.
        let (dt, s2) = (0.1f64, 0.05f64 * 0.05);
        let ppx = 2.5e-3 + dt * dt * 1e-2 + s2 * dt.powi(4) / 4.0;
        let pvx = dt * 1e-2 + s2 * dt.powi(3) / 2.0;
        let k_pos = ppx / (ppx + 4.0e-4);
        let k_vel = pvx / (ppx + 4.0e-4);
        let s = t.state().unwrap();
        assert!((s.x[0] - (1.0 + k_pos * 0.01)).abs() < 1e-12);
        assert!((s.x[2] - k_vel * 0.01).abs() < 1e-12);
        assert!((s.p[(0, 0)] - (1.0 - k_pos) * ppx).abs() < 1e-15);
    }

    #[test]
    fn roi_grows_with_uncertainty_and_speed() {
        let p = params();
        let mut t = Tracker::new(p);
        assert_eq!(t.roi(0.0), None, "no track: full ROI");
        t.update(0.0, Some([1.0, 0.0]));
        let roi0 = t.roi(0.0).unwrap();
        // h = h0 + 0 + γ·sqrt(P0) = 0.25 + 2·0.05.
        assert!((roi0.half_width[0] - 0.35).abs() < 1e-12, "{roi0:?}");
        let roi1 = t.roi(1.0).unwrap();
        assert!(roi1.half_width[0] > roi0.half_width[0]);
        assert!(roi0.contains([1.3, 0.3]) && !roi0.contains([1.4, 0.0]));
    }

    #[test]
    fn follows_a_moving_target() {
        let mut t = Tracker::new(params());
        for k in 0..=50 {
            let ts = f64::from(k) * 0.1;
            let out = t.update(ts, Some([1.0 + 0.1 * ts, 0.5]));
            assert!(!matches!(out, TrackOutcome::Gated { .. } | TrackOutcome::Lost), "{k}: {out:?}");
        }
        let s = t.state().unwrap();
        assert!((s.x[2] - 0.1).abs() < 0.01, "vx {}", s.x[2]);
        assert!((s.x[0] - 1.5).abs() < 0.005);
    }

    #[test]
    fn gate_rejects_a_jump_and_three_misses_lose_the_track() {
        let mut t = Tracker::new(params());
        t.update(0.0, Some([1.0, 0.0]));
        t.update(0.1, Some([1.0, 0.0]));
        // A wall corner 1 m away is far outside the gate.
        let out = t.update(0.2, Some([2.0, 0.0]));
        assert!(matches!(out, TrackOutcome::Gated { misses: 1, .. }), "{out:?}");
        assert!((t.state().unwrap().x[0] - 1.0).abs() < 1e-3, "the prediction was kept");
        assert_eq!(t.update(0.3, None), TrackOutcome::Missed { misses: 2 });
        assert_eq!(t.update(0.4, None), TrackOutcome::Lost);
        assert!(t.state().is_none());
        assert_eq!(t.roi(0.5), None);
        // A good measurement in between resets the count.
        let mut t = Tracker::new(params());
        t.update(0.0, Some([1.0, 0.0]));
        t.update(0.1, None);
        t.update(0.2, None);
        assert!(matches!(t.update(0.3, Some([1.0, 0.0])), TrackOutcome::Updated { .. }));
        assert_eq!(t.misses(), 0);
    }

    #[test]
    fn time_going_backwards_is_rejected() {
        let mut t = Tracker::new(params());
        t.update(1.0, Some([1.0, 0.0]));
        let before = *t.state().unwrap();
        assert_eq!(t.update(0.5, Some([1.0, 0.0])), TrackOutcome::TimeWentBackwards);
        assert_eq!(*t.state().unwrap(), before);
    }
}
