//! OdometryActor: the robot's wheels and gyro into its odometry ([`amr_core::odometry::Odometer`]:
//! wheel travel for distance, the gyro's yaw rate for heading, the gyro bias learnt at standstill),
//! published with the frame it counts from.

use std::sync::Arc;

use amr_core::odometry::Odometer;
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::{ImuReading, RobotPorts, WheelTravel};
use super::status::HealthCell;
use amr_msgs::{Device, Health, OdomMsg};

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
    odometer: Odometer,
    /// This frame's number (`OdomMsg::frame`): the fleet-clock microsecond it started at, so a
    /// restarted actor (back at the origin) is told apart from the one before.
    frame: u64,
    seq: u64,
    health: HealthCell,
}

impl OdometryState {
    /// At the origin of odometry frame `frame`, nothing known of the gyro.
    fn new(health: HealthCell, frame: u64) -> Self {
        OdometryState { odometer: Odometer::new(), frame, seq: 0, health }
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
            OdomMsgIn::Gyro(g) => state.odometer.gyro(g.stamp_s, g.yaw_rate_radps),
            OdomMsgIn::Wheels(w) => {
                if !(w.left_m.is_finite() && w.right_m.is_finite()) {
                    return Ok(());
                }
                let gyro = state.odometer.step(&w, self.track_width_m);
                state.seq += 1;
                let dt = if w.dt_s > 0.0 { w.dt_s } else { f64::INFINITY };
                let twist =
                    (0.5 * (w.left_m + w.right_m) / dt, (w.right_m - w.left_m) / self.track_width_m / dt);
                self.ports.odom.send(OdomMsg {
                    seq: state.seq,
                    frame: state.frame,
                    stamp_s: w.stamp_s,
                    pose: state.odometer.pose(),
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
