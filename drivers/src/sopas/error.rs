//! Errors, in two layers kept apart (docs/architecture.md, "Time, configuration, errors"): the
//! device answered with an error (`sFA` + code, [`DeviceError`]) versus the link or the protocol
//! broke ([`LinkError`], [`ProtocolError`]).

use serde::Serialize;
use thiserror::Error;

/// SOPAS error codes carried by `sFA` (notes §2.1; names from Wireshark `packet-cola2.c`
/// `cola2_error_vals`, meanings from `packet-cola.c`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum ErrorCode {
    SopasOk,
    MethodInAccessDenied,
    MethodInUnknownIndex,
    VariableUnknownIndex,
    LocalConditionFailed,
    InvalidData,
    UnknownError,
    BufferOverflow,
    BufferUnderflow,
    ErrorUnknownType,
    VariableWriteAccessDenied,
    UnknownCmdForNameserver,
    UnknownColaCommand,
    MethodInServerBusy,
    FlexOutOfBounds,
    EventRegUnknownIndex,
    ColaAValueOverflow,
    ColaAInvalidCharacter,
    OsaiNoMessage,
    OsaiNoAnswerMessage,
    Internal,
    HubAddressCorrupted,
    HubAddressDecoding,
    HubAddressAddressExceeded,
    HubAddressBlankExpected,
    AsyncMethodsAreSuppressed,
    ComplexArraysNotSupported,
    /// A code outside the documented table.
    Other(u16),
}

const NAMED: [(u16, ErrorCode, &str); 27] = [
    (0x00, ErrorCode::SopasOk, "Sopas_Ok"),
    (0x01, ErrorCode::MethodInAccessDenied, "METHODIN_ACCESSDENIED"),
    (0x02, ErrorCode::MethodInUnknownIndex, "METHODIN_UNKNOWNINDEX"),
    (0x03, ErrorCode::VariableUnknownIndex, "VARIABLE_UNKNOWNINDEX"),
    (0x04, ErrorCode::LocalConditionFailed, "LOCALCONDITIONFAILED"),
    (0x05, ErrorCode::InvalidData, "INVALID_DATA"),
    (0x06, ErrorCode::UnknownError, "UNKNOWN_ERROR"),
    (0x07, ErrorCode::BufferOverflow, "BUFFER_OVERFLOW"),
    (0x08, ErrorCode::BufferUnderflow, "BUFFER_UNDERFLOW"),
    (0x09, ErrorCode::ErrorUnknownType, "ERROR_UNKNOWN_TYPE"),
    (0x0A, ErrorCode::VariableWriteAccessDenied, "VARIABLE_WRITE_ACCESSDENIED"),
    (0x0B, ErrorCode::UnknownCmdForNameserver, "UNKNOWN_CMD_FOR_NAMESERVER"),
    (0x0C, ErrorCode::UnknownColaCommand, "UNKNOWN_COLA_COMMAND"),
    (0x0D, ErrorCode::MethodInServerBusy, "METHODIN_SERVER_BUSY"),
    (0x0E, ErrorCode::FlexOutOfBounds, "FLEX_OUT_OF_BOUNDS"),
    (0x0F, ErrorCode::EventRegUnknownIndex, "EVENTREG_UNKNOWNINDEX"),
    (0x10, ErrorCode::ColaAValueOverflow, "COLA_A_VALUE_OVERFLOW"),
    (0x11, ErrorCode::ColaAInvalidCharacter, "COLA_A_INVALID_CHARACTER"),
    (0x12, ErrorCode::OsaiNoMessage, "OSAI_NO_MESSAGE"),
    (0x13, ErrorCode::OsaiNoAnswerMessage, "OSAI_NO_ANSWER_MESSAGE"),
    (0x14, ErrorCode::Internal, "INTERNAL"),
    (0x15, ErrorCode::HubAddressCorrupted, "HubAddressCorrupted"),
    (0x16, ErrorCode::HubAddressDecoding, "HubAddressDecoding"),
    (0x17, ErrorCode::HubAddressAddressExceeded, "HubAddressAddressExceeded"),
    (0x18, ErrorCode::HubAddressBlankExpected, "HubAddressBlankExpected"),
    (0x19, ErrorCode::AsyncMethodsAreSuppressed, "AsyncMethodsAreSuppressed"),
    // 0x20 in WS2; WS numbers it 26 — the notes (§2.1) keep the WS2 value.
    (0x20, ErrorCode::ComplexArraysNotSupported, "ComplexArraysNotSupported"),
];

impl ErrorCode {
    /// The code for a wire value.
    pub fn from_code(code: u16) -> Self {
        NAMED.iter().find(|(c, _, _)| *c == code).map_or(Self::Other(code), |(_, e, _)| *e)
    }

    /// The wire value.
    pub fn code(self) -> u16 {
        match self {
            Self::Other(code) => code,
            known => NAMED.iter().find(|(_, e, _)| *e == known).map_or(0xFFFF, |(c, _, _)| *c),
        }
    }

    /// The SOPAS name, e.g. `VARIABLE_WRITE_ACCESSDENIED`.
    pub fn name(self) -> &'static str {
        NAMED.iter().find(|(_, e, _)| *e == self).map_or("UNKNOWN_SOPAS_ERROR", |(_, _, n)| *n)
    }
}

impl std::fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} (0x{:X})", self.name(), self.code())
    }
}

/// The device answered a command with `sFA`.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("device refused `{command}`: sFA {code}")]
pub struct DeviceError {
    /// The command the device refused, e.g. `sWN LMPoutputRange`.
    pub command: String,
    pub code: ErrorCode,
}

/// The byte stream could not be cut into frames (the bytes concerned are dropped; see `framing`).
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum FrameError {
    #[error("CoLa-B checksum mismatch: frame says {expected:#04x}, payload XOR is {actual:#04x}")]
    Checksum { expected: u8, actual: u8 },
    #[error("frame length {len} exceeds the cap of {max}")]
    TooLong { len: usize, max: usize },
    #[error("CoLa-B frame with an empty payload")]
    Empty,
    #[error("CoLa-A frame cut off by a new STX after {len} bytes")]
    Truncated { len: usize },
}

/// A frame's payload did not decode.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum DecodeError {
    #[error("payload ended while reading {what}")]
    UnexpectedEnd { what: &'static str },
    #[error("bad value for {what}")]
    BadValue { what: &'static str },
    #[error("{what} = {value} is out of range")]
    OutOfRange { what: &'static str, value: i64 },
    #[error("bad command header")]
    BadHeader,
    #[error("unknown command `{kind} {name}`")]
    UnknownCommand { kind: String, name: String },
    #[error("{n} bytes left after the last field")]
    TrailingData { n: usize },
    #[error("channel counts disagree: {what}")]
    CountMismatch { what: String },
    #[error("telegram has no distance channel")]
    NoDistanceChannel,
}

/// The link or the protocol broke (as opposed to the device answering with an error).
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum ProtocolError {
    #[error(transparent)]
    Frame(#[from] FrameError),
    #[error(transparent)]
    Decode(#[from] DecodeError),
    #[error("no reply to `{command}` within {timeout_ms} ms")]
    ReplyTimeout { command: String, timeout_ms: u64 },
    #[error("no scan for {timeout_ms} ms")]
    ScanTimeout { timeout_ms: u64 },
    #[error("unexpected reply `{got}` to `{command}`")]
    UnexpectedReply { command: String, got: String },
}

/// The transport failed.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum LinkError {
    #[error("connect to {addr} failed: {msg}")]
    Connect { addr: String, msg: String },
    #[error("connection closed by the device")]
    Closed,
    #[error("i/o error: {0}")]
    Io(String),
}

/// Every error of the SOPAS driver, with the device-answered layer apart from the broken-link layer.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum SopasError {
    #[error(transparent)]
    Device(#[from] DeviceError),
    #[error(transparent)]
    Protocol(#[from] ProtocolError),
    #[error(transparent)]
    Link(#[from] LinkError),
}

impl From<DecodeError> for SopasError {
    fn from(e: DecodeError) -> Self {
        Self::Protocol(ProtocolError::Decode(e))
    }
}

impl From<FrameError> for SopasError {
    fn from(e: FrameError) -> Self {
        Self::Protocol(ProtocolError::Frame(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_round_trip_and_have_names() {
        for code in 0u16..0x30 {
            let e = ErrorCode::from_code(code);
            assert_eq!(e.code(), code);
        }
        assert_eq!(ErrorCode::from_code(0x0A).name(), "VARIABLE_WRITE_ACCESSDENIED");
        assert_eq!(ErrorCode::from_code(8), ErrorCode::BufferUnderflow);
        assert_eq!(ErrorCode::from_code(0x1A), ErrorCode::Other(0x1A));
    }
}
