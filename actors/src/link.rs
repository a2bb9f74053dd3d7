//! The link between the robots and the server, behind one interface: channel ends. A robot gets a
//! [`RobotEnd`] (send [`Uplink`], receive [`Downlink`]); the server gets a [`ServerEnd`] (receive
//! every robot's uplink, send to any robot). The in-process link here joins them through a router
//! that a drill can cut; the network link (Zenoh) hands out the same ends from its bridge actors.
//!
//! Sensor data is lossy by design: when a queue is full the newest message is dropped and counted,
//! so a slow consumer never blocks a robot. Commands are small and few; the robot's command
//! watchdog, not the link, decides what a late command means.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use tokio::sync::mpsc;

use crate::messages::{Downlink, Uplink};

/// Depth of each queue: about one second of scans at 15 Hz with odometry at 50 Hz.
const DEPTH: usize = 128;

/// A robot's end of the link.
#[derive(Debug)]
pub struct RobotEnd {
    pub robot: String,
    pub up: UplinkSender,
    pub down: mpsc::Receiver<Downlink>,
}

/// Sends up the link without ever waiting: a full queue drops the message and counts it.
#[derive(Debug, Clone)]
pub struct UplinkSender {
    tx: mpsc::Sender<Uplink>,
    dropped: Arc<AtomicU64>,
}

impl UplinkSender {
    /// Wraps a channel sender.
    #[must_use]
    pub fn new(tx: mpsc::Sender<Uplink>) -> Self {
        UplinkSender { tx, dropped: Arc::default() }
    }

    /// Queue `msg`; false if it was dropped (queue full or link closed).
    pub fn send(&self, msg: Uplink) -> bool {
        match self.tx.try_send(msg) {
            Ok(()) => true,
            Err(_) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
                false
            }
        }
    }

    /// Messages dropped so far.
    #[must_use]
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

/// The server's end of the link.
#[derive(Debug)]
pub struct ServerEnd {
    pub up: mpsc::Receiver<Uplink>,
    pub down: DownlinkSender,
}

/// Sends to any robot without waiting.
#[derive(Debug, Clone, Default)]
pub struct DownlinkSender {
    robots: BTreeMap<String, mpsc::Sender<Downlink>>,
}

impl DownlinkSender {
    /// Routes to these robots.
    #[must_use]
    pub fn new(robots: BTreeMap<String, mpsc::Sender<Downlink>>) -> Self {
        DownlinkSender { robots }
    }

    /// Queue `msg` for `robot`; false if the robot is unknown, its queue full or its link closed.
    pub fn send(&self, robot: &str, msg: Downlink) -> bool {
        self.robots.get(robot).is_some_and(|tx| tx.try_send(msg).is_ok())
    }
}

/// Drill control of the in-process link: cut and restore one robot's link, count what was lost.
#[derive(Debug, Clone, Default)]
pub struct LinkControl {
    cut: Arc<BTreeMap<String, AtomicBool>>,
    lost: Arc<AtomicU64>,
}

impl LinkControl {
    /// Cut (`true`) or restore (`false`) `robot`'s link in both directions.
    pub fn set_cut(&self, robot: &str, cut: bool) {
        if let Some(flag) = self.cut.get(robot) {
            flag.store(cut, Ordering::Relaxed);
        }
    }

    fn is_cut(&self, robot: &str) -> bool {
        self.cut.get(robot).is_some_and(|f| f.load(Ordering::Relaxed))
    }

    /// Messages that met a cut link.
    #[must_use]
    pub fn lost(&self) -> u64 {
        self.lost.load(Ordering::Relaxed)
    }
}

/// Build an in-process link for `robots`: the server's end, each robot's end (in the order given)
/// and the control. Must be called inside a tokio runtime (it spawns the router tasks, which end
/// when the ends are dropped).
#[must_use]
pub fn in_process(robots: &[String]) -> (ServerEnd, Vec<RobotEnd>, LinkControl) {
    let control = LinkControl {
        cut: Arc::new(robots.iter().map(|r| (r.clone(), AtomicBool::new(false))).collect()),
        lost: Arc::default(),
    };
    let (server_up_tx, server_up_rx) = mpsc::channel(DEPTH * robots.len().max(1));
    let mut downs = BTreeMap::new();
    let mut ends = Vec::new();
    for robot in robots {
        // Robot → router → server.
        let (up_tx, mut up_rx) = mpsc::channel::<Uplink>(DEPTH);
        let to_server = server_up_tx.clone();
        let (ctl, name) = (control.clone(), robot.clone());
        tokio::spawn(async move {
            while let Some(msg) = up_rx.recv().await {
                if ctl.is_cut(&name) || to_server.try_send(msg).is_err() {
                    ctl.lost.fetch_add(1, Ordering::Relaxed);
                }
            }
        });
        // Server → router → robot.
        let (down_tx, mut down_rx) = mpsc::channel::<Downlink>(DEPTH);
        let (to_robot, robot_rx) = mpsc::channel::<Downlink>(DEPTH);
        let (ctl, name) = (control.clone(), robot.clone());
        tokio::spawn(async move {
            while let Some(msg) = down_rx.recv().await {
                if ctl.is_cut(&name) || to_robot.try_send(msg).is_err() {
                    ctl.lost.fetch_add(1, Ordering::Relaxed);
                }
            }
        });
        downs.insert(robot.clone(), down_tx);
        ends.push(RobotEnd { robot: robot.clone(), up: UplinkSender::new(up_tx), down: robot_rx });
    }
    (ServerEnd { up: server_up_rx, down: DownlinkSender::new(downs) }, ends, control)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;
    use crate::messages::Command;

    fn cmd(seq: u64) -> Downlink {
        Downlink::Command(Command { seq, stamp_s: 0.0, v_mps: 0.1, w_radps: 0.0 })
    }

    #[tokio::test]
    async fn routes_by_robot_and_a_cut_loses_both_directions() {
        let robots = vec!["a".to_owned(), "b".to_owned()];
        let (mut server, mut ends, control) = in_process(&robots);
        assert!(server.down.send("b", cmd(1)));
        assert_eq!(ends[1].down.recv().await, Some(cmd(1)));
        assert!(!server.down.send("nobody", cmd(2)));
        ends[0].up.send(Uplink::Safety {
            robot: "a".into(),
            seq: 1,
            stamp_s: 0.0,
            state: crate::messages::SafetyState::Armed,
        });
        assert_eq!(server.up.recv().await.map(|m| m.robot().to_owned()), Some("a".to_owned()));

        control.set_cut("a", true);
        assert!(server.down.send("a", cmd(3)), "the router takes it; the cut loses it");
        ends[0].up.send(Uplink::Safety {
            robot: "a".into(),
            seq: 2,
            stamp_s: 0.0,
            state: crate::messages::SafetyState::Armed,
        });
        // Both messages reach the router and are lost there; b is unaffected.
        tokio::time::timeout(std::time::Duration::from_secs(2), async {
            while control.lost() < 2 {
                tokio::task::yield_now().await;
            }
        })
        .await
        .unwrap();
        assert!(ends[0].down.try_recv().is_err());
        assert!(server.down.send("b", cmd(4)));
        assert_eq!(ends[1].down.recv().await, Some(cmd(4)));
        control.set_cut("a", false);
        assert!(server.down.send("a", cmd(5)));
        assert_eq!(ends[0].down.recv().await, Some(cmd(5)));
    }
}
