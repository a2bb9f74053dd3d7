//! The tokio shell: runs a [`Master`] over any [`CanTransport`], taking commands from a channel and
//! publishing events. Time is tokio's (`Instant::now().into_std()`), so tests can pause it.

use tokio::sync::mpsc;
use tokio::time::Instant;

use super::error::{CanopenError, LinkError, TransportError};
use super::frame::NodeId;
use super::master::{Master, MasterEvent};
use super::sdo::SdoRequest;
use super::transport::CanTransport;

/// A command to the running master.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MasterCommand {
    /// Walk every drive to Operation enabled.
    Enable,
    /// Disable voltage on every drive.
    Disable,
    /// Quick stop every drive.
    QuickStop,
    /// Set or clear the halt bit.
    Halt(bool),
    /// Target velocities (drive units) applied together at the next SYNC.
    SetTargets(Vec<(NodeId, i32)>),
    /// Verified fault reset of one drive.
    Recover(NodeId),
    /// An SDO request; the result comes as an event with the id the master assigns (counting from 0).
    Sdo(NodeId, SdoRequest),
    /// Stop the master's heartbeat and SYNC (for drills: the drives must stop by themselves) and
    /// end the task.
    Shutdown,
}

fn now() -> std::time::Instant {
    Instant::now().into_std()
}

/// Run until [`MasterCommand::Shutdown`], the command channel closing, or the transport failing
/// (reported as an event before returning it).
pub async fn run_master<T: CanTransport>(
    mut master: Master,
    mut transport: T,
    mut commands: mpsc::Receiver<MasterCommand>,
    events: mpsc::Sender<MasterEvent>,
) -> Result<(), CanopenError> {
    // Events dropped since the user last heard of a loss.
    let mut lost: u64 = 0;
    // Bounded by the inputs: each pass handles one frame, command or timeout.
    loop {
        while let Some(frame) = master.poll_transmit() {
            if let Err(e) = transport.send(frame).await {
                let err: CanopenError = LinkError::from(e).into();
                let _ = events.send(MasterEvent::Error(err.clone())).await;
                return Err(err);
            }
        }
        // Never block the master (its heartbeat keeps the drives alive): drop on a full channel,
        // and say so as soon as there is room, before any newer event.
        if lost > 0 && events.try_send(MasterEvent::EventsLost { count: lost }).is_ok() {
            lost = 0;
        }
        while let Some(ev) = master.poll_event() {
            match events.try_send(ev) {
                Ok(()) => {}
                Err(mpsc::error::TrySendError::Full(ev)) => {
                    tracing::warn!(?ev, "master event dropped: the drives will count as degraded");
                    lost += 1;
                }
                Err(mpsc::error::TrySendError::Closed(_)) => return Ok(()),
            }
        }
        let deadline = master.poll_timeout().map(Instant::from_std);
        // In a fixed order, so that a run on a paused clock is the same every time: a command
        // (a quick stop, a shutdown) first, then a frame, then a timer that is due. The timers are
        // also run after every frame, so a bus that never falls quiet cannot starve the master's
        // heartbeat or its consumers of the drives'.
        tokio::select! {
            biased;
            cmd = commands.recv() => match cmd {
                None | Some(MasterCommand::Shutdown) => return Ok(()),
                Some(cmd) => apply(&mut master, cmd),
            },
            frame = transport.recv() => match frame {
                Ok(frame) => {
                    master.handle_frame(now(), &frame);
                    master.handle_timeout(now());
                }
                // An error frame that does not end the connection: reported, never blocking.
                Err(TransportError::ErrorFrame { class, state }) => {
                    let _ = events.try_send(MasterEvent::BusError { class, state });
                }
                Err(e) => {
                    let err: CanopenError = LinkError::from(e).into();
                    let _ = events.send(MasterEvent::Error(err.clone())).await;
                    return Err(err);
                }
            },
            () = sleep_until(deadline) => master.handle_timeout(now()),
        }
    }
}

async fn sleep_until(deadline: Option<Instant>) {
    match deadline {
        Some(t) => tokio::time::sleep_until(t).await,
        None => std::future::pending().await,
    }
}

fn apply(master: &mut Master, cmd: MasterCommand) {
    match cmd {
        MasterCommand::Enable => master.enable(now()),
        MasterCommand::Disable => master.disable(),
        MasterCommand::QuickStop => master.quick_stop(),
        MasterCommand::Halt(h) => master.set_halt(h),
        MasterCommand::SetTargets(t) => master.set_targets(now(), &t),
        MasterCommand::Recover(n) => master.recover(n),
        MasterCommand::Sdo(n, req) => {
            let _ = master.sdo(now(), n, req);
        }
        MasterCommand::Shutdown => {}
    }
}

/// A running master: its command sender, its events and the task.
#[derive(Debug)]
pub struct MasterHandle {
    /// Commands to the master.
    pub commands: mpsc::Sender<MasterCommand>,
    /// Events from the master.
    pub events: mpsc::Receiver<MasterEvent>,
    /// The task; ends with the master.
    pub task: tokio::task::JoinHandle<Result<(), CanopenError>>,
}

/// Spawn [`run_master`] on the current runtime.
pub fn spawn_master<T: CanTransport + 'static>(master: Master, transport: T) -> MasterHandle {
    let (ctx, crx) = mpsc::channel(64);
    let (etx, erx) = mpsc::channel(1024);
    let task = tokio::spawn(run_master(master, transport, crx, etx));
    MasterHandle { commands: ctx, events: erx, task }
}
