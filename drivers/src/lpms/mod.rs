//! LP-Research LPMS-B2 over LPBUS: codec, session, tokio-serial shell.
//!
//! - [`frame`]: LPBUS framing with LRC and resynchronisation (sans-IO).
//! - [`command`]: the B2 command set, requests and replies.
//! - [`data`]: config register and sensor-data payloads in float and 16-bit modes.
//! - [`session`]: the start-up sequence, watchdog and reopen backoff as a pure state machine.
//! - [`serial`]: the tokio shell over tokio-serial (or any `AsyncRead + AsyncWrite`).
//!
//! Protocol facts, with their public sources: `docs/devices.md` §3.
//!
//! ```no_run
//! # async fn imu() -> Result<(), amr_settings::Violation> {
//! use amr_drivers::lpms::{ImuMessage, LpmsConfig, spawn_serial};
//! let config = LpmsConfig { path: "/dev/rfcomm0".into(), stream_hz: 100, ..LpmsConfig::default() };
//! let (mut rx, _task) = spawn_serial(config, 256)?;
//! while let Some(msg) = rx.recv().await {
//!     match msg {
//!         ImuMessage::Sample(s) => tracing::trace!(yaw_rate = ?s.data.gyro_radps, "imu"),
//!         ImuMessage::Error(e) => tracing::warn!(%e, "imu"),
//!         ImuMessage::Ready(_) | ImuMessage::Health(_) => {}
//!     }
//! }
//! # Ok(())
//! # }
//! ```

pub mod command;
pub mod data;
pub mod error;
pub mod frame;
pub mod serial;
pub mod session;

pub use command::{Command, CommandId, FirmwareVersion, Reply};
pub use data::{ConfigRegister, DataMode, OutputMask, SensorData};
pub use error::{DeviceError, LinkError, LpmsError, ProtocolError};
pub use frame::{Frame, FrameDecoder, FrameError};
pub use serial::{
    B2_STREAM_RATES_HZ, BAUD_RATES, Health, ImuMessage, ImuSample, LpmsConfig, open_serial, run, run_serial,
    spawn_serial,
};
pub use session::{DeviceInfo, Event, Session, SessionConfig};
