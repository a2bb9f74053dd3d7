//! CANopen (CiA 301) and CiA 402 for the TECO wheel drives: frames, transports (SocketCAN,
//! socketcand, in-process bus), the master, the drive state machine, the differential-drive layer.
//!
//! - [`frame`]: the CAN frame and the predefined connection set ([`Cob`]).
//! - [`nmt`], [`sdo`], [`pdo`], [`emcy`], [`heartbeat`]: the CiA 301 services, sans-IO.
//! - [`cia402`]: statusword states, controlword commands, the transition table.
//! - [`master`]: the sans-IO master (NMT, SYNC, heartbeats, SDO, PDO remap, 402 enable/recover).
//! - [`config`]: `[devices.can]` ([`config::BusConfig`]) and `[devices.drives]`
//!   ([`config::DrivesConfig`]).
//! - [`diff_drive`]: (v, ω) → wheel targets in drive units, wheel odometry by arc integration.
//! - [`transport`]: the frame transport trait and its three implementations.
//! - [`shell`]: the tokio task running the master over a transport.
//!
//! Protocol facts, with their public sources: `docs/devices.md` §2.

pub mod cia402;
pub mod config;
pub mod diff_drive;
pub mod emcy;
pub mod error;
pub mod frame;
pub mod heartbeat;
pub mod master;
pub mod nmt;
pub mod pdo;
pub mod sdo;
pub mod shell;
pub mod transport;

pub use error::{CanopenError, DeviceError, LinkError, TransportError};
pub use frame::{CanFrame, Cob, NodeId};
