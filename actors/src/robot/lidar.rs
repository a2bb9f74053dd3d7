//! LidarActor: owns the SOPAS connection to the TiM551 (the TCP shell reconnects with backoff on
//! its own), turns telegrams into scans on the fleet clock, and reports health.

use std::sync::Arc;

use amr_drivers::sopas::tcp::{Health as LinkHealth, LidarConfig, LidarMessage, spawn_stream, spawn_tcp};
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::{AbortOnDrop, RobotPorts, StreamConnector};
use super::status::{Counters, HealthCell};
use amr_core::scan::Scan;
use amr_msgs::{Device, Health, ScanMsg};

/// The TiM551's measuring range (devices.md §1: 0.05–10 m).
pub(crate) const TIM551_RANGE_M: (f64, f64) = (0.05, 10.0);

/// A decoded TiM551 scan in the robot's units: ranges of 0 (no return) or outside the measuring
/// range become NaN (invalid beam).
fn robot_scan(s: &amr_drivers::sopas::scan::Scan) -> Scan {
    let (lo, hi) = TIM551_RANGE_M;
    let ranges = s
        .ranges_m
        .iter()
        .map(|r| {
            let r = f64::from(*r);
            if r.is_finite() && (lo..=hi).contains(&r) { r } else { f64::NAN }
        })
        .collect();
    Scan::new(s.angle_min_rad, s.angle_increment_rad, lo, hi, ranges)
}

/// Messages of the LiDAR actor.
#[derive(Debug)]
pub enum LidarMsg {
    /// From the driver task.
    Driver(LidarMessage),
    /// The driver task ended (it only ends when its channel closes: a bug).
    DriverEnded,
    /// Fail now, as a bug would (drills).
    #[cfg(feature = "fault-injection")]
    InjectFailure(String),
    /// Panic now, as a bug would (drills).
    #[cfg(feature = "fault-injection")]
    InjectPanic(String),
}

/// The LiDAR actor.
#[derive(Debug, Clone)]
pub(crate) struct LidarActor {
    pub ports: Arc<RobotPorts>,
    pub config: LidarConfig,
    pub counters: Counters,
    /// Reach the device through this instead of TCP (virtual-time simulation).
    pub stream: Option<StreamConnector>,
}

/// Its state.
#[derive(Debug)]
pub(crate) struct LidarState {
    _driver: AbortOnDrop<()>,
    _pump: AbortOnDrop<()>,
    health: HealthCell,
    seq: u64,
}

impl Actor for LidarActor {
    type Msg = LidarMsg;
    type State = LidarState;
    type Arguments = ();

    async fn pre_start(&self, myself: ActorRef<LidarMsg>, (): ()) -> Result<LidarState, ActorProcessingErr> {
        let (driver, mut rx) = match &self.stream {
            Some(c) => {
                let c = c.clone();
                spawn_stream(self.config.clone(), move |_addr| c.connect(), 16)
            }
            None => spawn_tcp(self.config.clone(), 16),
        };
        let pump = tokio::spawn(async move {
            while let Some(m) = rx.recv().await {
                if myself.cast(LidarMsg::Driver(m)).is_err() {
                    return;
                }
            }
            let _ = myself.cast(LidarMsg::DriverEnded);
        });
        let mut health = HealthCell::new(Device::Lidar);
        health.set(
            &self.ports,
            Health::Starting,
            format!("connecting to {}:{}", self.config.host, self.config.port),
        );
        Ok(LidarState { _driver: AbortOnDrop(driver), _pump: AbortOnDrop(pump), health, seq: 0 })
    }

    async fn handle(
        &self,
        _myself: ActorRef<LidarMsg>,
        msg: LidarMsg,
        state: &mut LidarState,
    ) -> Result<(), ActorProcessingErr> {
        let ports = &self.ports;
        match msg {
            LidarMsg::Driver(LidarMessage::Scan(s)) => {
                let received_s = ports.clock.seconds_std(s.received);
                let stamp_s = s.stamp.map_or(received_s, |t| ports.clock.seconds_std(t));
                let scan = robot_scan(&s.scan);
                if scan.valid_count() == 0 {
                    self.counters.rejected("lidar: scan without a valid beam");
                    return Ok(());
                }
                state.seq += 1;
                self.counters.count("lidar.scans");
                ports.scans.send(ScanMsg {
                    robot: ports.robot.clone(),
                    seq: state.seq,
                    stamp_s,
                    received_s,
                    scan: Arc::new(scan),
                    odom: None,
                    odom_frame: 0,
                });
                state.health.set(ports, Health::Ok, "scanning");
            }
            LidarMsg::Driver(LidarMessage::Health(h)) => match h {
                LinkHealth::Starting => state.health.set(ports, Health::Starting, "start-up sequence"),
                LinkHealth::Ok(info) => {
                    let what = format!("{info:?}");
                    state.health.set(ports, Health::Ok, what);
                }
                LinkHealth::Lost { retry_in } => {
                    self.counters.count("lidar.link_lost");
                    state.health.set(ports, Health::Lost, format!("reconnecting in {retry_in:?}"));
                }
            },
            LidarMsg::Driver(LidarMessage::Error(e)) => {
                tracing::debug!(robot = %ports.robot, error = %e, "lidar error");
                self.counters.rejected("lidar: protocol or device error");
            }
            LidarMsg::DriverEnded => return Err("the SOPAS driver task ended".into()),
            #[cfg(feature = "fault-injection")]
            LidarMsg::InjectFailure(why) => return Err(why.into()),
            #[cfg(feature = "fault-injection")]
            #[allow(clippy::panic, reason = "the drill hook: a panicking actor, on purpose")]
            LidarMsg::InjectPanic(why) => panic!("{why}"),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_and_out_of_range_beams_become_invalid() {
        let s = amr_drivers::sopas::scan::Scan {
            serial: 0,
            device_status: [0; 2],
            telegram_counter: 0,
            scan_counter: 0,
            generation_tick_us: 0,
            transmission_tick_us: 0,
            scan_frequency_hz: 15.0,
            measurement_frequency_hz: 0.0,
            angle_min_rad: -1.0,
            angle_increment_rad: 0.5,
            angles_rad: vec![-1.0, -0.5, 0.0, 0.5],
            ranges_m: vec![0.0, 2.0, 12.0, f32::NAN],
            rssi: None,
        };
        let out = robot_scan(&s);
        assert_eq!(out.len(), 4);
        let r = out.ranges_m();
        assert!(r[0].is_nan() && r[2].is_nan() && r[3].is_nan());
        assert_eq!(r[1], 2.0);
        assert_eq!((out.angle_min_rad, out.angle_increment_rad), (-1.0, 0.5));
    }
}
