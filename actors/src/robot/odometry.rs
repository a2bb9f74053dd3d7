//! OdometryActor: wheel travel for distance, the gyro's yaw rate for heading (wheels slip in
//! turns; the gyro does not), and the wheels' heading when the gyro is silent. The gyro bias is
//! estimated whenever the wheels stand still (a zero-velocity update), so it does not integrate
//! into the heading.

use std::sync::Arc;

use amr_core::se2::Se2;
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::{ImuReading, RobotPorts, WheelTravel};
use super::status::HealthCell;
use amr_msgs::{Device, Health, OdomMsg};

/// A gyro reading older than this is not used for heading.
pub(crate) const GYRO_FRESH_S: f64 = 0.1;
/// Weight of each stationary reading in the bias estimate.
const BIAS_GAIN: f64 = 0.02;
/// Wheel travel below this per cycle counts as standing still, m.
const STILL_M: f64 = 1e-5;

/// Messages of the odometry actor.
#[derive(Debug)]
pub(crate) enum OdomMsgIn {
    Wheels(WheelTravel),
    Gyro(ImuReading),
}

/// The odometry actor.
#[derive(Debug, Clone)]
pub(crate) struct OdometryActor {
    pub ports: Arc<RobotPorts>,
    pub track_width_m: f64,
}

#[derive(Debug)]
pub(crate) struct OdometryState {
    pose: Se2,
    /// This frame's number (`OdomMsg::frame`): the fleet-clock microsecond it started at, so a
    /// restarted actor (back at the origin) is told apart from the one before.
    frame: u64,
    seq: u64,
    /// Sum and count of gyro rates since the last wheel travel.
    gyro_sum: f64,
    gyro_n: u32,
    last_gyro_s: Option<f64>,
    bias: Option<f64>,
    health: HealthCell,
}

/// The motion along an arc of length `ds` turning by `dtheta`, in the start frame.
#[must_use]
pub(crate) fn arc(ds: f64, dtheta: f64) -> Se2 {
    if dtheta.abs() < 1e-9 {
        return Se2::new(ds * (0.5 * dtheta).cos(), ds * (0.5 * dtheta).sin(), dtheta);
    }
    let r = ds / dtheta;
    Se2::new(r * dtheta.sin(), r * (1.0 - dtheta.cos()), dtheta)
}

impl OdometryState {
    /// At the origin of odometry frame `frame`, nothing known of the gyro.
    fn new(health: HealthCell, frame: u64) -> Self {
        OdometryState {
            pose: Se2::IDENTITY,
            frame,
            seq: 0,
            gyro_sum: 0.0,
            gyro_n: 0,
            last_gyro_s: None,
            bias: None,
            health,
        }
    }

    /// Fold one wheel travel (and the gyro readings since the previous one) into the pose;
    /// returns whether the gyro gave the heading.
    fn step(&mut self, w: &WheelTravel, track_width_m: f64) -> bool {
        let ds = 0.5 * (w.left_m + w.right_m);
        let wheel_dtheta = (w.right_m - w.left_m) / track_width_m;
        let fresh = self.last_gyro_s.is_some_and(|t| w.stamp_s - t <= GYRO_FRESH_S) && self.gyro_n > 0;
        let still = w.left_m.abs() < STILL_M && w.right_m.abs() < STILL_M;
        let mean = if self.gyro_n > 0 { self.gyro_sum / f64::from(self.gyro_n) } else { 0.0 };
        if fresh && still {
            self.bias = Some(match self.bias {
                None => mean,
                Some(b) => b + BIAS_GAIN * (mean - b),
            });
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

impl Actor for OdometryActor {
    type Msg = OdomMsgIn;
    type State = OdometryState;
    type Arguments = ();

    async fn pre_start(
        &self,
        myself: ActorRef<OdomMsgIn>,
        (): (),
    ) -> Result<OdometryState, ActorProcessingErr> {
        self.ports.wheels.subscribe(myself.clone(), |w| Some(OdomMsgIn::Wheels(w)));
        self.ports.imu.subscribe(myself, |g| Some(OdomMsgIn::Gyro(g)));
        let mut health = HealthCell::new(Device::Odometry);
        health.set(&self.ports, Health::Starting, "waiting for wheel travel");
        // Microseconds of the fleet clock: distinct for every start, never 0 (the "no frame" value).
        let frame = ((self.ports.clock.now_s().max(0.0) * 1e6) as u64).max(1);
        tracing::info!(robot = %self.ports.robot, frame, "odometry starts a new frame at the origin");
        Ok(OdometryState::new(health, frame))
    }

    async fn handle(
        &self,
        _myself: ActorRef<OdomMsgIn>,
        msg: OdomMsgIn,
        state: &mut OdometryState,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            OdomMsgIn::Gyro(g) => {
                state.gyro_sum += g.yaw_rate_radps;
                state.gyro_n += 1;
                state.last_gyro_s = Some(g.stamp_s);
            }
            OdomMsgIn::Wheels(w) => {
                if !(w.left_m.is_finite() && w.right_m.is_finite()) {
                    return Ok(());
                }
                let gyro = state.step(&w, self.track_width_m);
                state.seq += 1;
                let dt = if w.dt_s > 0.0 { w.dt_s } else { f64::INFINITY };
                let twist =
                    (0.5 * (w.left_m + w.right_m) / dt, (w.right_m - w.left_m) / self.track_width_m / dt);
                self.ports.odom.send(OdomMsg {
                    seq: state.seq,
                    frame: state.frame,
                    stamp_s: w.stamp_s,
                    pose: state.pose,
                    twist,
                    gyro,
                });
                if gyro {
                    state.health.set(&self.ports, Health::Ok, "wheels + gyro");
                } else {
                    state.health.set(&self.ports, Health::Degraded, "wheels only (no fresh gyro)");
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state() -> OdometryState {
        OdometryState::new(HealthCell::new(Device::Odometry), 1)
    }

    fn gyro(s: &mut OdometryState, t: f64, rate: f64) {
        s.gyro_sum += rate;
        s.gyro_n += 1;
        s.last_gyro_s = Some(t);
    }

    #[test]
    fn heading_from_the_gyro_minus_the_bias_learnt_at_standstill() {
        let mut s = state();
        let bias = 0.002;
        // Two seconds still at 50 Hz: the bias is learnt, the pose does not move.
        for k in 0..100 {
            let t = f64::from(k) * 0.02;
            gyro(&mut s, t, bias);
            assert!(s.step(&WheelTravel { stamp_s: t, dt_s: 0.02, left_m: 0.0, right_m: 0.0 }, 0.33));
        }
        assert_eq!(s.pose, Se2::IDENTITY);
        assert!((s.bias.unwrap_or(0.0) - bias).abs() < 1e-9);
        // Then 1 s turning at 0.2 rad/s while the wheels (slipping) claim 0.3 rad/s.
        for k in 0..50 {
            let t = 2.0 + f64::from(k) * 0.02;
            gyro(&mut s, t, 0.2 + bias);
            let d = 0.3 * 0.02 * 0.33 / 2.0;
            assert!(s.step(&WheelTravel { stamp_s: t, dt_s: 0.02, left_m: -d, right_m: d }, 0.33));
        }
        assert!((s.pose.theta - 0.2).abs() < 1e-9, "{}", s.pose.theta);
    }

    #[test]
    fn without_a_fresh_gyro_the_wheels_give_the_heading() {
        let mut s = state();
        gyro(&mut s, 0.0, 5.0);
        // The last reading is 1 s old.
        let d = 0.01;
        assert!(!s.step(&WheelTravel { stamp_s: 1.0, dt_s: 0.02, left_m: -d, right_m: d }, 0.2));
        assert!((s.pose.theta - 0.1).abs() < 1e-12);
        // Straight travel moves along x.
        let mut s = state();
        assert!(!s.step(&WheelTravel { stamp_s: 0.0, dt_s: 0.02, left_m: 0.5, right_m: 0.5 }, 0.2));
        assert!(s.pose.approx_eq(&Se2::new(0.5, 0.0, 0.0), 1e-12, 1e-12));
    }
}
