//! A robot on a kernel CAN interface: the robot tree's CAN link is the project's SocketCAN
//! transport on `iface` (e.g. `vcan0`), and the mock drives sit on the same interface through a
//! socket of their own ([`hil_mocks::teco_drive::bridge`]). Then, with `cansend` (can-utils) as a
//! third-party peer writing to the interface: malformed frames, an error-passive report and a
//! bus-off. `tests/vm/run` runs it inside a Linux VM (this machine's kernel has no CAN), and checks
//! `candump`'s capture of the same exchange.
//!
//! Each check is a line, passed or failed, with what was measured; nothing panics.

use std::path::Path;
use std::time::Duration;

use amr_actors::config::Config;
use amr_actors::robot::RobotOptions;
use amr_actors::robot::canbus::CanLink;
use amr_drivers::canopen::cia402::State402;
use amr_drivers::canopen::transport::socketcan::SocketCan;
use amr_msgs::{Device, Health, SafetyState, Uplink};
use tokio::time::Instant;

use crate::drills::{drive_from, health, wheels_still, wheels_turning};
use crate::{RobotRig, SimCan};

/// Every error class bit (`CAN_ERR_MASK`, linux/can/error.h).
const CAN_ERR_MASK: u32 = 0x1FFF_FFFF;

/// One check's outcome.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct CheckLine {
    pub name: String,
    pub passed: bool,
    pub detail: String,
}

#[derive(Debug, Default)]
struct Lines(Vec<CheckLine>);

impl Lines {
    fn check(&mut self, name: &str, passed: bool, detail: impl Into<String>) -> bool {
        self.0.push(CheckLine { name: name.into(), passed, detail: detail.into() });
        passed
    }
}

/// Wait until `cond` holds, at most `limit`; how long it took.
async fn until(limit: Duration, mut cond: impl FnMut() -> bool) -> Option<Duration> {
    let t0 = Instant::now();
    // Bounded by `limit`.
    while t0.elapsed() <= limit {
        if cond() {
            return Some(t0.elapsed());
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    None
}

fn ms(d: Option<Duration>) -> String {
    d.map_or_else(|| "not seen".to_owned(), |d| format!("{:.0} ms", d.as_secs_f64() * 1e3))
}

/// `cansend IFACE FRAME` (can-utils' frame syntax); why it failed, if it did.
fn cansend(cansend: &Path, iface: &str, frame: &str) -> Result<(), String> {
    let out = std::process::Command::new(cansend)
        .args([iface, frame])
        .output()
        .map_err(|e| format!("{}: {e}", cansend.display()))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "cansend {iface} {frame}: {} {}",
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

type Latest = std::sync::Arc<std::sync::Mutex<Option<amr_core::se2::Se2>>>;

/// Read everything the robot sends, keeping the latest odometry pose (from its odometry messages
/// and the poses its scans carry).
fn watch_odometry(rig: &mut RobotRig) -> (Latest, crate::AbortOnDrop<()>) {
    let (_, empty) = tokio::sync::mpsc::channel(1);
    let mut up = std::mem::replace(&mut rig.server.up, empty);
    let latest = Latest::default();
    let keep = std::sync::Arc::clone(&latest);
    let task = tokio::spawn(async move {
        // Ends with the robot's link.
        while let Some(u) = up.recv().await {
            let pose = match u {
                Uplink::Odom { msg, .. } => Some(msg.pose),
                Uplink::Scan(s) => s.odom,
                _ => None,
            };
            if let Some(p) = pose {
                *keep.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = Some(p);
            }
        }
    });
    (latest, crate::AbortOnDrop(task))
}

fn now_of(latest: &Latest) -> Option<amr_core::se2::Se2> {
    *latest.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn distance(rig: &RobotRig, from: Option<(f64, f64)>) -> f64 {
    let now = rig.truth.latest().and_then(|(_, p)| p.first().map(|p| (p.x, p.y)));
    match (from, now) {
        (Some(a), Some(b)) => (b.0 - a.0).hypot(b.1 - a.1),
        _ => f64::NAN,
    }
}

/// Run the checks on `iface` with the configuration's first robot in the `straight` scenario.
pub async fn run(config: &Config, seed: u64, iface: &str, cansend_bin: &Path) -> Vec<CheckLine> {
    let mut out = Lines::default();
    if !check_transport(iface, &mut out) {
        return out.0;
    }
    let mut rig = match start_rig(config, seed, iface).await {
        Ok(r) => r,
        Err(e) => {
            out.check("setup", false, e);
            return out.0;
        }
    };
    let n0 = rig.tree.events.len();
    if !bring_up(&rig, &mut out).await {
        rig.tree.shutdown().await;
        return out.0;
    }
    velocity_move_and_quick_stop(&mut rig, &mut out).await;
    malformed_frames(&rig, &mut out, cansend_bin, iface, n0).await;
    error_passive(&rig, &mut out, cansend_bin, iface).await;
    bus_off(&rig, &mut out, cansend_bin, iface).await;
    rig.tree.shutdown().await;
    out.0
}

/// The transport asks the kernel for every error frame (its default mask is 0).
fn check_transport(iface: &str, out: &mut Lines) -> bool {
    match SocketCan::open(iface) {
        Ok(s) => {
            let mask = s.error_mask();
            out.check(
                "transport: error frames enabled",
                mask == Ok(CAN_ERR_MASK),
                format!("CAN_RAW_ERR_FILTER read back: {mask:x?}"),
            );
        }
        Err(e) => {
            out.check("transport: open", false, format!("{iface}: {e}"));
            return false;
        }
    }
    true
}

/// The robot with its CAN link on the interface, the mock drives on it through a socket of
/// their own.
async fn start_rig(config: &Config, seed: u64, iface: &str) -> Result<RobotRig, String> {
    let Some(scenario) = config.scenarios.get("straight").cloned() else {
        return Err("the configuration has no `straight` scenario".to_owned());
    };
    let mut bridge_err = None;
    let started =
        RobotRig::start_with(config, &scenario, seed, SimCan::InProcess, RobotOptions::default(), |o| {
            // The drives' bus goes onto the interface through a socket of its own; the robot's CAN
            // link becomes the interface.
            if let Some(CanLink::InProcess(bus)) = o.can.take() {
                match SocketCan::open(iface) {
                    Ok(t) => {
                        let port = bus.port();
                        tokio::spawn(async move {
                            let why = hil_mocks::teco_drive::bridge::bridge(port, t).await;
                            tracing::error!(error = %why, "the mock drives' bridge ended");
                        });
                    }
                    Err(e) => bridge_err = Some(e.to_string()),
                }
            }
            o.can = Some(CanLink::SocketCan { interface: iface.to_owned() });
        })
        .await;
    match (started, bridge_err) {
        (Ok(r), None) => Ok(r),
        (Err(e), _) => Err(e.to_string()),
        (_, Some(e)) => Err(format!("the drives' socket: {e}")),
    }
}

/// NMT, SDO configuration, heartbeats, the CiA 402 enable: the drives report Ok only when both
/// are enabled.
async fn bring_up(rig: &RobotRig, out: &mut Lines) -> bool {
    let up = until(Duration::from_secs(30), || {
        [Device::CanBus, Device::Drives].iter().all(|d| health(rig, *d) == Some(Health::Ok))
    })
    .await;
    let consumer = rig.robot.devices.drives.master_consumer_ms;
    let snaps: Vec<_> = rig.mocks.drives.iter().map(|d| d.now()).collect();
    let configured = snaps.iter().all(|s| {
        s.state == State402::OperationEnabled
            && s.mode_display == 3
            && s.master_consumer & 0xFFFF == consumer
            && s.enables_unconfigured == 0
    });
    out.check(
        "bring-up: NMT, SDO configuration, heartbeats, enable",
        up.is_some() && configured,
        format!(
            "CAN bus and drives Ok after {}; drives {:?}",
            ms(up),
            snaps.iter().map(|s| (s.state, s.mode_display, s.master_consumer)).collect::<Vec<_>>()
        ),
    )
}

/// A velocity move: RPDO targets applied at each SYNC, TPDO positions back as the robot's
/// odometry, which must agree with the world's truth (the comfort ramp, 0.05 m/s², takes 2 s to
/// reach 0.1 m/s); then a quick stop by the robot's e-stop, and the reset.
async fn velocity_move_and_quick_stop(rig: &mut RobotRig, out: &mut Lines) {
    let from = rig.truth.latest().and_then(|(_, p)| p.first().map(|p| (p.x, p.y)));
    let (odometry, _reader) = watch_odometry(rig);
    until(Duration::from_secs(2), || now_of(&odometry).is_some()).await;
    let odo0 = now_of(&odometry);
    let feed = drive_from(rig, 0.1, 1);
    let turning = until(Duration::from_secs(10), || wheels_turning(rig, 1000.0)).await;
    tokio::time::sleep(Duration::from_secs(3)).await;

    // Quick stop by the robot's e-stop.
    rig.tree.estop();
    let stopping = until(Duration::from_millis(500), || {
        rig.mocks.drives.iter().all(|d| {
            let s = d.now();
            s.target_velocity == 0
                && matches!(s.state, State402::QuickStopActive | State402::SwitchOnDisabled)
        })
    })
    .await;
    let still = until(Duration::from_secs(2), || wheels_still(rig)).await;
    // At rest: the odometry has caught up with the wheels.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let moved = distance(rig, from);
    let odo_moved = match (odo0, now_of(&odometry)) {
        (Some(a), Some(b)) => (b.x - a.x).hypot(b.y - a.y),
        _ => f64::NAN,
    };
    out.check(
        "velocity move: PDO targets at SYNC, positions back as odometry",
        turning.is_some() && moved > 0.1 && (odo_moved - moved).abs() < 0.01,
        format!(
            "wheels turning after {}; at 0.1 m/s for 3 s and a quick stop the robot moved {moved:.3} m, \
             its odometry says {odo_moved:.3} m",
            ms(turning)
        ),
    );
    out.check(
        "quick stop",
        stopping.is_some() && still.is_some(),
        format!("both drives quick-stopping after {}, at rest after {}", ms(stopping), ms(still)),
    );
    drop(feed);
    rig.tree.reset_estop();
    until(Duration::from_secs(2), || {
        matches!(*rig.tree.ports.safety_now.borrow(), Some(SafetyState::Disarmed(_)))
    })
    .await;
    until(Duration::from_secs(10), || health(rig, Device::Drives) == Some(Health::Ok)).await;
}

/// Malformed frames from a third party: a one-byte SDO response, a remote frame, an empty
/// heartbeat, a heartbeat of an unknown state. Nothing restarts; the bus and drives stay Ok.
async fn malformed_frames(rig: &RobotRig, out: &mut Lines, cansend_bin: &Path, iface: &str, n0: usize) {
    let mut sent = Vec::new();
    for f in ["581#FF", "123#R", "701#", "702#7E", "181#0102"] {
        sent.push(cansend(cansend_bin, iface, f));
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let errors: Vec<&String> = sent.iter().filter_map(|r| r.as_ref().err()).collect();
    out.check(
        "malformed frames survived",
        errors.is_empty()
            && health(rig, Device::CanBus) == Some(Health::Ok)
            && health(rig, Device::Drives) == Some(Health::Ok)
            && rig.tree.events.len() == n0,
        format!(
            "cansend errors {errors:?}; CAN bus {:?}, drives {:?}; supervision events {}",
            health(rig, Device::CanBus),
            health(rig, Device::Drives),
            rig.tree.events.len() - n0
        ),
    );
}

/// Error passive (CAN_ERR_CRTL, TX passive), then error active again (CAN_ERR_CRTL_ACTIVE).
async fn error_passive(rig: &RobotRig, out: &mut Lines, cansend_bin: &Path, iface: &str) {
    let passive = cansend(cansend_bin, iface, "20000004#0020000000000000");
    let degraded =
        until(Duration::from_secs(1), || health(rig, Device::CanBus) == Some(Health::Degraded)).await;
    let active = cansend(cansend_bin, iface, "20000004#0040000000000000");
    let back = until(Duration::from_secs(1), || health(rig, Device::CanBus) == Some(Health::Ok)).await;
    out.check(
        "error frame: error passive reported, and back",
        passive.is_ok() && active.is_ok() && degraded.is_some() && back.is_some(),
        format!(
            "cansend {passive:?} {active:?}; CAN bus Degraded after {}, Ok again after {}; counters passive {} active {}",
            ms(degraded),
            ms(back),
            rig.tree.counters.get("can.error_passive"),
            rig.tree.counters.get("can.error_active")
        ),
    );
}

/// Bus-off while driving: the connection ends, the robot halts, the link comes back, the drives
/// are reconfigured and a new arm drives again.
async fn bus_off(rig: &RobotRig, out: &mut Lines, cansend_bin: &Path, iface: &str) {
    let feed = drive_from(rig, 0.1, 1000);
    let turning = until(Duration::from_secs(10), || wheels_turning(rig, 1000.0)).await;
    let t0 = Instant::now();
    let sent = cansend(cansend_bin, iface, "20000040#0000000000000000");
    // Each measured from the bus-off frame.
    let since = |d: Option<Duration>| d.map(|_| t0.elapsed());
    let lost =
        since(until(Duration::from_millis(1000), || health(rig, Device::CanBus) == Some(Health::Lost)).await);
    let halted = since(
        until(Duration::from_millis(1000), || {
            matches!(*rig.tree.ports.safety_now.borrow(), Some(SafetyState::Disarmed(_)))
        })
        .await,
    );
    let safe = since(
        until(Duration::from_secs(2), || {
            rig.mocks.drives.iter().all(|d| {
                let s = d.now();
                s.target_velocity == 0 || s.state != State402::OperationEnabled
            })
        })
        .await,
    );
    drop(feed);
    let recovered = until(Duration::from_secs(20), || {
        [Device::CanBus, Device::Drives].iter().all(|d| health(rig, *d) == Some(Health::Ok))
    })
    .await;
    let recovery = t0.elapsed();
    let feed = drive_from(rig, 0.1, 2000);
    let again = until(Duration::from_secs(10), || wheels_turning(rig, 1000.0)).await;
    drop(feed);
    out.check(
        "bus-off: halted, reconnected, driving again",
        sent.is_ok()
            && turning.is_some()
            && lost.is_some()
            && halted.is_some()
            && safe.is_some()
            && again.is_some()
            && recovered.is_some(),
        format!(
            "cansend {sent:?}; CAN bus Lost after {}, robot disarmed after {}, drives safe after {}; \
             bus and drives Ok again after {:.1} s; turning again after a new arm in {}; bus-offs counted {}",
            ms(lost),
            ms(halted),
            ms(safe),
            recovery.as_secs_f64(),
            ms(again),
            rig.tree.counters.get("can.bus_off")
        ),
    );
}
