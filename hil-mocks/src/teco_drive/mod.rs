//! Mock TECO drives: CiA 402 nodes on any CAN transport, and a socketcand server in front of the
//! in-process bus, with a fault plan (devices.md §2, §4).
//!
//! - `motor`: velocity with acceleration limits, encoder with slip and seeded noise.
//! - [`device`]: the drive as a pure CiA 402 node ([`TecoDrive`]) and its [`Fault`]s.
//! - [`task`]: the tokio task serving a drive on a bus port ([`spawn_drive`]).
//! - [`socketcand`]: the socketcand server in front of an [`InProcessBus`].
//! - [`bridge`]: an in-process bus served on another transport (a SocketCAN interface).
//!
//! `amr mock drives --socketcand 127.0.0.1:29536 [--nodes 1,2]` needs [`start_mock_drives`].

pub mod bridge;
pub mod device;
mod motor;
pub mod socketcand;
pub mod task;

use std::net::SocketAddr;

use amr_drivers::canopen::transport::in_process::InProcessBus;

pub use device::{DEFAULT_INPUTS, DEVICE_TYPE_402_SERVO, DriveSnapshot, Fault, TecoDrive, TecoDriveConfig};
pub use task::{DriveHandle, spawn_drive};

/// Mock drives on an in-process bus behind a socketcand server.
#[derive(Debug)]
pub struct MockDrives {
    /// The address the socketcand server listens on.
    pub address: SocketAddr,
    /// The bus (more in-process nodes can join).
    pub bus: InProcessBus,
    /// One handle per drive, in the order of the node ids given.
    pub drives: Vec<DriveHandle>,
    /// The socketcand server task.
    pub server: tokio::task::JoinHandle<()>,
}

/// Start one mock drive per node id (configured by `config(node)`) on a new in-process bus and a
/// socketcand server on `address` (e.g. `127.0.0.1:29536`, or port 0 for any).
pub async fn start_mock_drives(
    address: &str,
    nodes: &[u8],
    config: impl Fn(u8) -> TecoDriveConfig,
) -> std::io::Result<MockDrives> {
    let bus = InProcessBus::default();
    let now = tokio::time::Instant::now().into_std();
    let drives = nodes.iter().map(|&n| spawn_drive(TecoDrive::new(config(n), now), bus.port())).collect();
    let (address, server) = socketcand::bind(address, bus.clone()).await?;
    tracing::info!(%address, ?nodes, "mock TECO drives behind socketcand");
    Ok(MockDrives { address, bus, drives, server })
}
