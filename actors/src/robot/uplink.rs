//! UplinkActor: sends the robot's data up the link — each scan with the odometry interpolated at
//! its stamp, odometry, health and safety changes — numbered and stamped. Sending never waits: a
//! full link drops the message (counted by the link).

use std::collections::VecDeque;
use std::sync::Arc;

use amr_core::se2::Se2;
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::RobotPorts;
use crate::link::UplinkSender;
use amr_msgs::{HealthReport, OdomMsg, SafetyState, ScanMsg, Uplink};

/// Odometry kept for interpolation, s.
const HISTORY_S: f64 = 1.0;

/// Messages of the uplink actor.
#[derive(Debug)]
pub(crate) enum UplinkMsg {
    Scan(ScanMsg),
    Odom(OdomMsg),
    Health(HealthReport),
    Safety(SafetyState),
    /// Re-send every device's health and the safety state (periodically, and at start).
    Resend,
}

/// Period of the full health re-send: the server learns the state even of what changed before it
/// (or this actor) was listening.
pub(crate) const RESEND_PERIOD: std::time::Duration = std::time::Duration::from_secs(1);

/// The uplink actor.
#[derive(Debug, Clone)]
pub(crate) struct UplinkActor {
    pub ports: Arc<RobotPorts>,
    pub link: UplinkSender,
    /// Send odometry every this many odometry updates (1 = all).
    pub odom_decimation: u64,
}

#[derive(Debug, Default)]
pub(crate) struct UplinkState {
    history: VecDeque<OdomMsg>,
    seq: u64,
}

/// The odometry pose at `t` from a time-ordered history: interpolated between the two updates
/// around it, or the nearest end.
#[must_use]
pub(crate) fn odom_at(history: &VecDeque<OdomMsg>, t: f64) -> Option<Se2> {
    let after = history.iter().position(|o| o.stamp_s >= t);
    match after {
        None => history.back().map(|o| o.pose),
        Some(0) => history.front().map(|o| o.pose),
        Some(i) => {
            let (a, b) = (&history[i - 1], &history[i]);
            let span = b.stamp_s - a.stamp_s;
            let f = if span > 0.0 { (t - a.stamp_s) / span } else { 1.0 };
            let d = a.pose.inverse() * b.pose;
            Some(a.pose * Se2::new(d.x * f, d.y * f, d.theta * f))
        }
    }
}

impl UplinkActor {
    /// The safety layer's stop counter now.
    fn stops(&self) -> u64 {
        self.ports.stops.load(std::sync::atomic::Ordering::SeqCst)
    }
}

impl Actor for UplinkActor {
    type Msg = UplinkMsg;
    type State = UplinkState;
    type Arguments = ();

    async fn pre_start(
        &self,
        myself: ActorRef<UplinkMsg>,
        (): (),
    ) -> Result<UplinkState, ActorProcessingErr> {
        self.ports.scans.subscribe(myself.clone(), |s| Some(UplinkMsg::Scan(s)));
        self.ports.odom.subscribe(myself.clone(), |o| Some(UplinkMsg::Odom(o)));
        self.ports.health.subscribe(myself.clone(), |h| Some(UplinkMsg::Health(h)));
        self.ports.safety.subscribe(myself.clone(), |s| Some(UplinkMsg::Safety(s)));
        let _ = myself.cast(UplinkMsg::Resend);
        myself.send_interval(RESEND_PERIOD, || UplinkMsg::Resend);
        Ok(UplinkState::default())
    }

    async fn handle(
        &self,
        _myself: ActorRef<UplinkMsg>,
        msg: UplinkMsg,
        state: &mut UplinkState,
    ) -> Result<(), ActorProcessingErr> {
        let robot = self.ports.robot.clone();
        let now = self.ports.clock.now_s();
        state.seq += 1;
        let seq = state.seq;
        let up = match msg {
            UplinkMsg::Scan(s) => {
                // Without odometry yet, the scan is of no use to the server.
                let Some(odom) = odom_at(&state.history, s.stamp_s) else { return Ok(()) };
                let odom_frame = state.history.back().map_or(0, |o| o.frame);
                Uplink::Scan(ScanMsg { robot, seq, odom: Some(odom), odom_frame, ..s })
            }
            UplinkMsg::Odom(o) => {
                // A new odometry frame (the odometry restarted at the origin): the old poses are of
                // another frame and must not be interpolated with the new ones.
                if state.history.back().is_some_and(|b| b.frame != o.frame) {
                    state.history.clear();
                }
                state.history.push_back(o);
                while state.history.front().is_some_and(|f| o.stamp_s - f.stamp_s > HISTORY_S) {
                    state.history.pop_front();
                }
                if o.seq % self.odom_decimation.max(1) != 0 {
                    return Ok(());
                }
                Uplink::Odom { robot, msg: o }
            }
            UplinkMsg::Health(report) => Uplink::Health { robot, seq, stamp_s: now, report },
            UplinkMsg::Safety(s) => Uplink::Safety {
                robot,
                seq,
                stamp_s: now,
                state: s,
                stops: self.stops(),
                mock: self.ports.mock,
            },
            UplinkMsg::Resend => {
                let board: Vec<HealthReport> = self.ports.health_board.borrow().values().cloned().collect();
                for report in board {
                    state.seq += 1;
                    self.link.send(Uplink::Health {
                        robot: robot.clone(),
                        seq: state.seq,
                        stamp_s: now,
                        report,
                    });
                }
                let Some(s) = *self.ports.safety_now.borrow() else { return Ok(()) };
                state.seq += 1;
                Uplink::Safety {
                    robot,
                    seq: state.seq,
                    stamp_s: now,
                    state: s,
                    stops: self.stops(),
                    mock: self.ports.mock,
                }
            }
        };
        self.link.send(up);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn odometry_is_interpolated_at_the_scan_stamp() {
        let o = |t: f64, x: f64, th: f64| OdomMsg {
            seq: 0,
            frame: 1,
            stamp_s: t,
            pose: Se2::new(x, 0.0, th),
            twist: (0.0, 0.0),
            gyro: true,
        };
        let h: VecDeque<OdomMsg> = [o(1.0, 0.0, 0.0), o(1.02, 0.002, 0.0), o(1.04, 0.004, 0.02)].into();
        assert!(odom_at(&h, 1.01).is_some_and(|p| p.approx_eq(&Se2::new(0.001, 0.0, 0.0), 1e-12, 1e-12)));
        assert!(odom_at(&h, 1.03).is_some_and(|p| (p.theta - 0.01).abs() < 1e-12));
        assert_eq!(odom_at(&h, 0.5).map(|p| p.x), Some(0.0));
        assert_eq!(odom_at(&h, 9.0).map(|p| p.x), Some(0.004));
        assert!(odom_at(&VecDeque::new(), 1.0).is_none());
    }
}
