//! Linux SocketCAN through the `socketcan` crate's tokio socket: what the robot uses. CI has no
//! AF_CAN, so the conversions and the error mapping are unit-tested and the socket only opened
//! (and expected to fail cleanly) there. ENOBUFS (errno 105, the TX queue is full: python-canopen
//! #202) is back-pressure and retried a bounded number of times; error frames become
//! [`TransportError::ErrorFrame`] (bus-off: bring the interface back with
//! `ip link set can0 type can restart-ms 100`).

use std::time::Duration;

use ::socketcan::{EmbeddedFrame, ExtendedId, Frame as _, Id, StandardId};

use super::CanTransport;
use crate::canopen::error::TransportError;
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
        ::socketcan::CanFrame::Error(e) => Err(TransportError::ErrorFrame { class: e.raw_id() }),
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
    /// Open the interface (needs a tokio runtime with IO enabled).
    pub fn open(interface: &str) -> Result<Self, TransportError> {
        let socket = ::socketcan::tokio::CanSocket::open(interface).map_err(|e| TransportError::io(&e))?;
        Ok(Self { socket })
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

    #[tokio::test]
    async fn canopen_socketcan_open_fails_cleanly_without_the_interface() {
        // No such interface here (and no AF_CAN on CI): an error value, never a panic.
        let err = SocketCan::open("amrnocan9").unwrap_err();
        assert!(matches!(err, TransportError::Io { .. }), "{err:?}");
    }
}
