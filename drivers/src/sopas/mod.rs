//! SICK TiM551 / TiM5xx over SOPAS (CoLa-A and CoLa-B): codec, scan decoder, session, tokio shell.
//!
//! - [`framing`]: cutting a byte stream into CoLa-A / CoLa-B frames, with resync and a length cap.
//! - `cola_a`, `cola_b`, `args`: argument encodings of the two dialects behind one reader/writer.
//! - [`command`]: the requests and replies of devices.md §1, both directions (the mock uses them).
//! - [`scan`]: the full LMDscandata telegram and the robot-unit [`Scan`].
//! - [`session`]: start-up profiles, dialect detection, watchdog, reconnect backoff (sans-IO).
//! - [`clock`]: device µs tick → host time.
//! - [`tcp`]: the tokio shell over `TcpStream`.
//! - [`capture`]: decoding a captured telegram file.
//!
//! Protocol facts, with their public sources: `docs/devices.md` §1.

mod args;
pub mod capture;
pub mod clock;
mod cola_a;
mod cola_b;
pub mod command;
pub mod error;
pub mod framing;
pub mod scan;
pub mod session;
pub mod tcp;

pub use capture::decode_capture;
pub use clock::{ClockUpdate, DeviceClock};
pub use command::{Command, OutputRange, Reply, ScanDataConfig, Sector, Variable};
pub use error::{DecodeError, DeviceError, ErrorCode, FrameError, LinkError, ProtocolError, SopasError};
pub use framing::{Dialect, Frame, Framer, encode_frame};
pub use scan::{Channel, Scan, ScanTelegram};
pub use session::{
    DeviceInfo, DialectChoice, Event, Mode, Profile, ReconnectReason, Session, SessionConfig, StampedScan,
};
pub use tcp::{Health, LidarConfig, LidarMessage, run_tcp, spawn_tcp};
