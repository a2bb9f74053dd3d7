//! Frame transports: an async trait and three implementations — an in-process bus for tests and
//! mocks ([`in_process`]), a socketcand TCP client ([`socketcand`]) and Linux SocketCAN
//! ([`socketcan`]) for the robot (devices.md §2).

pub mod in_process;
pub mod socketcan;
pub mod socketcand;

use std::future::Future;

use super::error::TransportError;
use super::frame::CanFrame;

/// Sends and receives whole CAN frames.
///
/// `recv` must be cancel-safe (the master's shell selects on it together with its timers): a
/// frame is either returned or stays queued.
pub trait CanTransport: Send {
    /// Send one frame.
    fn send(&mut self, frame: CanFrame) -> impl Future<Output = Result<(), TransportError>> + Send;
    /// Receive the next frame from the other nodes.
    fn recv(&mut self) -> impl Future<Output = Result<CanFrame, TransportError>> + Send;
}
