//! Linux SocketCAN through the `socketcan` crate's tokio socket: what the robot uses. The host
//! that runs the unit tests has no AF_CAN, so the conversions and the error mapping are
//! unit-tested here and the socket only opened (and expected to fail cleanly); `tests/vm/run`
//! boots a Linux kernel under qemu and runs the transport on a real `vcan0` (README).
//!
//! ENOBUFS (errno 105, the TX queue is full: python-canopen #202) is back-pressure and retried a
//! bounded number of times. The socket asks for every error frame (the kernel's default error
//! mask is 0: no error frame would ever arrive). A bus-off ends the connection
//! ([`TransportError::BusOff`]; the interface comes back by itself with
//! `ip link set can0 type can restart-ms 100`); other error frames are reported
//! ([`TransportError::ErrorFrame`], with the controller's error state when the frame gives it)
//! and the connection goes on.

use std::time::Duration;

use ::socketcan::{EmbeddedFrame, ExtendedId, Frame as _, Id, SocketOptions as _, StandardId};

use super::CanTransport;
use crate::canopen::error::{BusState, TransportError};
use crate::canopen::frame::CanFrame;

/// ENOBUFS on Linux.
const ENOBUFS: i32 = 105;
/// Attempts for one frame while the TX queue is full.
const ENOBUFS_ATTEMPTS: u32 = 20;
/// Back-off between those attempts.
const ENOBUFS_BACKOFF: Duration = Duration::from_millis(1);

/// Our frame as a SocketCAN frame.
pub(crate) fn to_socketcan(frame: &CanFrame) -> Option<::socketcan::CanFrame> {
    let id: Id = if frame.is_extended() {
        ExtendedId::new(frame.id())?.into()
    } else {
        StandardId::new(u16::try_from(frame.id()).ok()?)?.into()
    };
    ::socketcan::CanFrame::new(id, frame.data())
}

// Error frame classes and controller-problem details, linux/can/error.h.
const CAN_ERR_CRTL: u32 = 0x0004;
const CAN_ERR_BUSOFF: u32 = 0x0040;
const CAN_ERR_RESTARTED: u32 = 0x0100;
const CAN_ERR_CRTL_RX_WARNING: u8 = 0x04;
const CAN_ERR_CRTL_TX_WARNING: u8 = 0x08;
const CAN_ERR_CRTL_RX_PASSIVE: u8 = 0x10;
const CAN_ERR_CRTL_TX_PASSIVE: u8 = 0x20;
const CAN_ERR_CRTL_ACTIVE: u8 = 0x40;

/// An error frame's class bits and data as our error (see [`TransportError::is_fatal`]).
pub(crate) fn classify_error(class: u32, data: &[u8]) -> TransportError {
    if class & CAN_ERR_BUSOFF != 0 {
        return TransportError::BusOff;
    }
    let crtl = if class & CAN_ERR_CRTL != 0 { data.get(1).copied().unwrap_or(0) } else { 0 };
    let state = if crtl & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE) != 0 {
        Some(BusState::ErrorPassive)
    } else if crtl & (CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING) != 0 {
        Some(BusState::ErrorWarning)
    } else if crtl & CAN_ERR_CRTL_ACTIVE != 0 || class & CAN_ERR_RESTARTED != 0 {
        Some(BusState::ErrorActive)
    } else {
        None
    };
    TransportError::ErrorFrame { class, state }
}

/// A received SocketCAN frame as ours: data frames convert, error frames are errors, remote
/// frames (unused by this CANopen master) are skipped (`Ok(None)`).
pub(crate) fn from_socketcan(frame: &::socketcan::CanFrame) -> Result<Option<CanFrame>, TransportError> {
    match frame {
        ::socketcan::CanFrame::Data(d) => {
            let f = CanFrame::with_id(d.raw_id(), d.is_extended(), d.data())
                .map_err(|e| TransportError::Socketcand(e.to_string()))?;
            Ok(Some(f))
        }
        ::socketcan::CanFrame::Remote(_) => Ok(None),
        ::socketcan::CanFrame::Error(e) => Err(classify_error(e.error_bits(), e.data())),
    }
}

/// A SocketCAN interface (e.g. `can0`).
#[allow(missing_debug_implementations, reason = "the socket type has no Debug")]
pub struct SocketCan {
    socket: ::socketcan::tokio::CanSocket,
}

impl std::fmt::Debug for SocketCan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SocketCan")
    }
}

impl SocketCan {
    /// Open the interface (needs a tokio runtime with IO enabled), with every error frame
    /// delivered.
    pub fn open(interface: &str) -> Result<Self, TransportError> {
        let socket = ::socketcan::tokio::CanSocket::open(interface).map_err(|e| TransportError::io(&e))?;
        socket.set_error_filter_accept_all().map_err(|e| TransportError::io(&e))?;
        Ok(Self { socket })
    }

    /// The socket's error mask (`CAN_RAW_ERR_FILTER`), as the kernel reports it.
    pub fn error_mask(&self) -> Result<u32, TransportError> {
        self.socket.error_filter().map_err(|e| TransportError::io(&e))
    }
}

impl CanTransport for SocketCan {
    async fn send(&mut self, frame: CanFrame) -> Result<(), TransportError> {
        let f =
            to_socketcan(&frame).ok_or_else(|| TransportError::Socketcand(format!("bad frame {frame:?}")))?;
        let mut attempt = 0;
        loop {
            match self.socket.write_frame(f).await {
                Ok(()) => return Ok(()),
                Err(e) if e.raw_os_error() == Some(ENOBUFS) && attempt + 1 < ENOBUFS_ATTEMPTS => {
                    attempt += 1;
                    tracing::debug!(attempt, "SocketCAN TX queue full (ENOBUFS), retrying");
                    tokio::time::sleep(ENOBUFS_BACKOFF).await;
                }
                Err(e) => return Err(TransportError::io(&e)),
            }
        }
    }

    async fn recv(&mut self) -> Result<CanFrame, TransportError> {
        // Bounded by the socket: each iteration consumes one frame.
        loop {
            let f = self.socket.read_frame().await.map_err(|e| TransportError::io(&e))?;
            if let Some(frame) = from_socketcan(&f)? {
                return Ok(frame);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canopen_socketcan_frames_convert_both_ways() {
        for frame in [
            CanFrame::new(0x601, &[0x40, 0x18, 0x10, 1, 0, 0, 0, 0]).unwrap(),
            CanFrame::new(0x080, &[]).unwrap(),
            CanFrame::with_id(0x1ABC_DEF0, true, &[1, 2, 3]).unwrap(),
        ] {
            let s = to_socketcan(&frame).unwrap();
            assert_eq!(from_socketcan(&s), Ok(Some(frame)));
        }
        let remote =
            <::socketcan::CanFrame as EmbeddedFrame>::new_remote(StandardId::new(0x701).unwrap(), 1).unwrap();
        assert_eq!(from_socketcan(&remote), Ok(None));
    }

    #[test]
    fn error_frames_are_classified_and_only_bus_off_ends_the_connection() {
        let cases: [(u32, [u8; 8], TransportError); 6] = [
            (CAN_ERR_BUSOFF, [0; 8], TransportError::BusOff),
            (
                CAN_ERR_BUSOFF | CAN_ERR_CRTL,
                [0, CAN_ERR_CRTL_TX_PASSIVE, 0, 0, 0, 0, 0, 0],
                TransportError::BusOff,
            ),
            (
                CAN_ERR_CRTL,
                [0, CAN_ERR_CRTL_TX_PASSIVE, 0, 0, 0, 0, 0, 0],
                TransportError::ErrorFrame { class: CAN_ERR_CRTL, state: Some(BusState::ErrorPassive) },
            ),
            (
                CAN_ERR_CRTL,
                [0, CAN_ERR_CRTL_RX_WARNING, 0, 0, 0, 0, 0, 0],
                TransportError::ErrorFrame { class: CAN_ERR_CRTL, state: Some(BusState::ErrorWarning) },
            ),
            (
                CAN_ERR_RESTARTED,
                [0; 8],
                TransportError::ErrorFrame { class: CAN_ERR_RESTARTED, state: Some(BusState::ErrorActive) },
            ),
            // An acknowledgement error (nobody else on the bus): reported, no state.
            (0x20, [0; 8], TransportError::ErrorFrame { class: 0x20, state: None }),
        ];
        for (class, data, want) in cases {
            let got = classify_error(class, &data);
            assert_eq!(got.is_fatal(), want == TransportError::BusOff, "{class:#x}");
            assert_eq!(got, want, "{class:#x}");
        }
        // Through the socketcan crate's frame type, as the socket delivers it.
        let frame =
            ::socketcan::CanErrorFrame::new_error(CAN_ERR_CRTL, &[0, CAN_ERR_CRTL_RX_PASSIVE]).unwrap();
        assert_eq!(
            from_socketcan(&::socketcan::CanFrame::Error(frame)),
            Err(TransportError::ErrorFrame { class: CAN_ERR_CRTL, state: Some(BusState::ErrorPassive) })
        );
    }

    #[tokio::test]
    async fn canopen_socketcan_open_fails_cleanly_without_the_interface() {
        // No such interface here (and no AF_CAN on CI): an error value, never a panic.
        let err = SocketCan::open("amrnocan9").unwrap_err();
        assert!(matches!(err, TransportError::Io { .. }), "{err:?}");
    }
}
