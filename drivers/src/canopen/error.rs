//! Two-layer errors (as in tokio-modbus): the drive answered with an error ([`DeviceError`]: SDO
//! abort, EMCY, Fault state) is kept apart from the link or the protocol breaking ([`LinkError`]).

use thiserror::Error;

use super::frame::NodeId;
use super::sdo::{AbortCode, ObjectAddr};

/// A drive is reachable and reported an error.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum DeviceError {
    /// The drive's SDO server aborted a transfer.
    #[error("node {node}: SDO abort on {addr}: {code}")]
    SdoAbort {
        /// The node.
        node: NodeId,
        /// The object.
        addr: ObjectAddr,
        /// The abort code (with its CiA 301 name in the message).
        code: AbortCode,
    },
    /// The drive sent an EMCY with a non-zero error code.
    #[error("node {node}: EMCY {code:#06x} ({class}), error register {register:#04x}")]
    Emcy {
        /// The node.
        node: NodeId,
        /// Error code.
        code: u16,
        /// Error class name.
        class: &'static str,
        /// Error register 0x1001.
        register: u8,
    },
    /// The drive entered the Fault state.
    #[error("node {node}: drive in Fault (last EMCY code {error_code:#06x})")]
    Fault {
        /// The node.
        node: NodeId,
        /// The last EMCY error code seen (0 if none).
        error_code: u16,
    },
    /// The fault reset was sent on a rising edge but the drive did not leave Fault in time.
    #[error("node {node}: fault reset not confirmed")]
    FaultResetFailed {
        /// The node.
        node: NodeId,
    },
    /// 0x6061 did not report the requested mode.
    #[error("node {node}: mode {requested} not confirmed on 0x6061 (reads {displayed})")]
    ModeNotConfirmed {
        /// The node.
        node: NodeId,
        /// The mode written to 0x6060.
        requested: i8,
        /// The last mode read from 0x6061.
        displayed: i8,
    },
    /// The drive did not reach Operation enabled in time.
    #[error("node {node}: not enabled within the enable timeout")]
    EnableTimeout {
        /// The node.
        node: NodeId,
    },
}

/// The bus, or a node's communication, is broken.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum LinkError {
    /// No SDO response within the request timeout.
    #[error("node {node}: SDO timeout on {addr}")]
    SdoTimeout {
        /// The node.
        node: NodeId,
        /// The object.
        addr: ObjectAddr,
    },
    /// The SDO exchange broke (bad command specifier, toggle); the client aborted.
    #[error("node {node}: SDO protocol error on {addr}: {code}")]
    SdoProtocol {
        /// The node.
        node: NodeId,
        /// The object.
        addr: ObjectAddr,
        /// The abort code the client sent.
        code: AbortCode,
    },
    /// No heartbeat within the consumer time.
    #[error("node {node}: heartbeat lost")]
    HeartbeatLost {
        /// The node.
        node: NodeId,
    },
    /// No boot-up after a reset within the boot timeout.
    #[error("node {node}: no boot-up within the boot timeout")]
    BootTimeout {
        /// The node.
        node: NodeId,
    },
    /// The transport failed.
    #[error(transparent)]
    Transport(#[from] TransportError),
}

/// A frame transport failed.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum TransportError {
    /// An I/O error of the socket.
    #[error("CAN transport I/O: {kind:?}: {message}")]
    Io {
        /// The error kind.
        kind: std::io::ErrorKind,
        /// The error text.
        message: String,
    },
    /// The controller went bus-off (an error frame of class `CAN_ERR_BUSOFF`): it sends nothing
    /// until it is restarted. The connection ends; the caller reopens it (with the interface's
    /// `restart-ms` set, the kernel restarts the controller by itself).
    #[error("CAN controller bus-off")]
    BusOff,
    /// The controller reported an error frame that does not end the connection (error warning or
    /// passive, back to error active, a protocol or acknowledgement error, …).
    #[error("CAN error frame, class {class:#x}, state {state:?}")]
    ErrorFrame {
        /// The SocketCAN error class bits (`linux/can/error.h`).
        class: u32,
        /// The controller's fault-confinement state, when the frame says.
        state: Option<BusState>,
    },
    /// The peer closed the connection, or the bus was dropped.
    #[error("CAN transport closed")]
    Closed,
    /// The socketcand server said something that breaks the protocol.
    #[error("socketcand: {0}")]
    Socketcand(String),
}

/// A CAN controller's fault-confinement state (ISO 11898-1: error active, warning at 96 errors,
/// passive at 128; bus-off is [`TransportError::BusOff`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BusState {
    ErrorActive,
    ErrorWarning,
    ErrorPassive,
}

impl TransportError {
    /// Whether the connection ends with this error (everything but a non-fatal error frame).
    #[must_use]
    pub fn is_fatal(&self) -> bool {
        !matches!(self, TransportError::ErrorFrame { .. })
    }

    /// From an I/O error.
    pub fn io(err: &std::io::Error) -> Self {
        Self::Io { kind: err.kind(), message: err.to_string() }
    }
}

/// Any CANopen error, as published by the master.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum CanopenError {
    /// A drive reported an error.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The link broke.
    #[error(transparent)]
    Link(#[from] LinkError),
}
