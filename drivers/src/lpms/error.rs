//! Two-layer errors (as in tokio-modbus): the sensor answered "no" ([`DeviceError`]) is kept apart
//! from the link or the byte stream breaking ([`LinkError`], [`ProtocolError`]).

use std::time::Duration;

use thiserror::Error;

use super::command::{CommandError, CommandId};
use super::data::DataLengthError;
use super::frame::FrameError;

/// The sensor is reachable and refused something.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum DeviceError {
    /// The sensor answered NACK (OpenZen treats this as `ZenError_FW_FunctionFailed`; notes A2).
    #[error("LPMS sensor refused {command} (NACK)")]
    Nack {
        /// The command that was refused.
        command: CommandId,
    },
    /// The config register read back after start-up differs from the settings sent (outputs, data
    /// mode or rate); the data is decoded with the reported register.
    #[error("LPMS config register is {reported:#010x}, settings sent describe {requested:#010x}")]
    ConfigNotApplied {
        /// Register value the settings describe (0 if the rate is not a B2 rate).
        requested: u32,
        /// Register value the sensor reported.
        reported: u32,
    },
}

/// The link to the sensor is unusable; the session asks the shell to close and reopen it.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum LinkError {
    /// No reply to a command after every attempt.
    #[error("no reply to {command} after {attempts} attempts")]
    ReplyTimeout {
        /// The command.
        command: CommandId,
        /// Attempts made.
        attempts: u32,
    },
    /// No data packet within the data timeout while streaming.
    #[error("no sensor data for {after:?}")]
    DataTimeout {
        /// The configured data timeout.
        after: Duration,
    },
    /// The port could not be opened, or reading/writing it failed or hit end of file.
    #[error("serial port: {kind:?}: {message}")]
    Io {
        /// The I/O error kind.
        kind: std::io::ErrorKind,
        /// The error text.
        message: String,
    },
}

impl LinkError {
    /// From an I/O error of the port.
    pub fn io(err: &std::io::Error) -> Self {
        Self::Io { kind: err.kind(), message: err.to_string() }
    }

    /// A data timeout of `after`.
    pub(crate) fn data_timeout(after: Duration) -> Self {
        Self::DataTimeout { after }
    }
}

/// A bad frame or payload; the session drops it and carries on.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum ProtocolError {
    /// A candidate frame was discarded (bad LRC, end or length).
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// A frame that is not a valid reply.
    #[error(transparent)]
    Reply(#[from] CommandError),
    /// A data packet that does not match the configured layout.
    #[error(transparent)]
    Data(#[from] DataLengthError),
}

/// Any LPMS error, as published by the shell.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum LpmsError {
    /// The sensor refused a command.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The link broke.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// A frame or payload was bad.
    #[error(transparent)]
    Protocol(#[from] ProtocolError),
}
