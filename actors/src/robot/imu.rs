//! ImuActor: owns the LPBUS serial connection to the LPMS-B2 (the shell reopens the port with
//! backoff on its own), publishes the yaw rate on the fleet clock and reports health. Samples that
//! are not finite or beyond the sensor's range are rejected and counted.

use std::sync::Arc;

use amr_drivers::lpms::serial::{Health as LinkHealth, ImuMessage, LpmsConfig, run, spawn_serial};
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::{AbortOnDrop, ImuReading, RobotPorts, StreamConnector};
use super::status::{Counters, HealthCell};
use amr_msgs::{Device, Health};

/// The LPMS-B2 gyro's largest range, ±2000 °/s (LP-Research data sheet); beyond it a value is junk.
pub(crate) const MAX_YAW_RATE_RADPS: f64 = 2000.0 * std::f64::consts::PI / 180.0;

/// Messages of the IMU actor.
#[derive(Debug)]
pub(crate) enum ImuMsg {
    Driver(ImuMessage),
    DriverEnded,
}

/// The IMU actor.
#[derive(Debug, Clone)]
pub(crate) struct ImuActor {
    pub ports: Arc<RobotPorts>,
    pub config: LpmsConfig,
    pub counters: Counters,
    /// Reach the device through this instead of its serial port (virtual-time simulation).
    pub stream: Option<StreamConnector>,
}

#[derive(Debug)]
pub(crate) struct ImuState {
    _driver: AbortOnDrop<()>,
    _pump: AbortOnDrop<()>,
    health: HealthCell,
}

impl Actor for ImuActor {
    type Msg = ImuMsg;
    type State = ImuState;
    type Arguments = ();

    async fn pre_start(&self, myself: ActorRef<ImuMsg>, (): ()) -> Result<ImuState, ActorProcessingErr> {
        // An invalid configuration is a start failure (the supervisor retries and escalates); it
        // cannot happen with a validated robot file.
        let (mut rx, driver) = match &self.stream {
            Some(c) => {
                self.config.validate("devices.imu")?;
                let (tx, rx) = tokio::sync::mpsc::channel(64);
                let c = c.clone();
                (rx, tokio::spawn(run(self.config.session_config(), move || c.connect(), tx)))
            }
            None => spawn_serial(self.config.clone(), 64)?,
        };
        let pump = tokio::spawn(async move {
            while let Some(m) = rx.recv().await {
                if myself.cast(ImuMsg::Driver(m)).is_err() {
                    return;
                }
            }
            let _ = myself.cast(ImuMsg::DriverEnded);
        });
        let mut health = HealthCell::new(Device::Imu);
        health.set(&self.ports, Health::Starting, format!("opening {}", self.config.path));
        Ok(ImuState { _driver: AbortOnDrop(driver), _pump: AbortOnDrop(pump), health })
    }

    async fn handle(
        &self,
        _myself: ActorRef<ImuMsg>,
        msg: ImuMsg,
        state: &mut ImuState,
    ) -> Result<(), ActorProcessingErr> {
        let ports = &self.ports;
        match msg {
            ImuMsg::Driver(ImuMessage::Sample(s)) => {
                let rate = s.data.angular_velocity_radps.or(s.data.gyro_radps).map(|w| f64::from(w[2]));
                match rate {
                    Some(r) if r.is_finite() && r.abs() <= MAX_YAW_RATE_RADPS => {
                        self.counters.count("imu.samples");
                        let stamp_s = ports.clock.seconds_std(s.received_at);
                        ports.imu.send(ImuReading { stamp_s, yaw_rate_radps: r });
                        state.health.set(ports, Health::Ok, "streaming");
                    }
                    Some(_) => self.counters.rejected("imu: yaw rate not finite or out of range"),
                    None => self.counters.rejected("imu: sample without angular velocity"),
                }
            }
            ImuMsg::Driver(ImuMessage::Ready(info)) => {
                let what = format!("{info:?}");
                state.health.set(ports, Health::Starting, what);
            }
            ImuMsg::Driver(ImuMessage::Health(h)) => match h {
                LinkHealth::Connecting | LinkHealth::Configuring => {
                    state.health.set(ports, Health::Starting, format!("{h:?}"));
                }
                LinkHealth::Streaming => state.health.set(ports, Health::Ok, "streaming"),
                LinkHealth::Lost => {
                    self.counters.count("imu.link_lost");
                    state.health.set(ports, Health::Lost, "port closed, reopening");
                }
            },
            ImuMsg::Driver(ImuMessage::Error(e)) => {
                tracing::debug!(robot = %ports.robot, error = %e, "imu error");
                self.counters.rejected("imu: protocol or device error");
            }
            ImuMsg::DriverEnded => return Err("the LPBUS driver task ended".into()),
        }
        Ok(())
    }
}
