//! The tokio task serving a [`TecoDrive`] on a bus port, with its fault plan and an observable
//! snapshot. Time is tokio's, so tests can pause it.

use amr_drivers::canopen::transport::CanTransport;
use amr_drivers::canopen::transport::in_process::BusPort;
use tokio::sync::{mpsc, watch};
use tokio::time::Instant;

use super::device::{DriveSnapshot, Fault, TecoDrive};

/// A running mock drive.
#[derive(Debug)]
pub struct DriveHandle {
    /// The node id.
    pub node_id: u8,
    /// Inject faults.
    pub faults: mpsc::UnboundedSender<Fault>,
    /// The drive's state after each step.
    pub snapshot: watch::Receiver<DriveSnapshot>,
    /// The task (ends when the fault sender is dropped).
    pub task: tokio::task::JoinHandle<()>,
}

impl DriveHandle {
    /// Inject a fault (ignored if the drive task has ended).
    pub fn inject(&self, fault: Fault) {
        let _ = self.faults.send(fault);
    }

    /// The latest snapshot.
    pub fn now(&self) -> DriveSnapshot {
        *self.snapshot.borrow()
    }
}

fn now() -> std::time::Instant {
    Instant::now().into_std()
}

/// Spawn `drive` on `port` (an in-process bus port: the mock never blocks the bus).
pub fn spawn_drive(mut drive: TecoDrive, mut port: BusPort) -> DriveHandle {
    let (ftx, mut frx) = mpsc::unbounded_channel();
    let (stx, srx) = watch::channel(drive.snapshot());
    let node_id = drive.node_id();
    let task = tokio::spawn(async move {
        // Bounded by its inputs: each pass handles a frame, a fault or a timer.
        loop {
            while let Some(f) = drive.poll_transmit(now()) {
                port.send_now(f);
            }
            stx.send_replace(drive.snapshot());
            let deadline = drive.poll_timeout().map(Instant::from_std);
            // In this order (a frame, an injected fault, a timer that is due): the same order every
            // time, so a virtual-time run is the same from the same seed.
            tokio::select! {
                biased;
                frame = port.recv() => match frame {
                    Ok(f) => drive.handle_frame(now(), &f),
                    Err(_) => return,
                },
                fault = frx.recv() => match fault {
                    Some(f) => drive.inject(now(), f),
                    None => return,
                },
                () = async {
                    match deadline {
                        Some(t) => tokio::time::sleep_until(t).await,
                        None => std::future::pending().await,
                    }
                } => drive.handle_timeout(now()),
            }
        }
    });
    DriveHandle { node_id, faults: ftx, snapshot: srx, task }
}
