//! An in-process CAN bus: every port sees every frame the other ports send, like nodes on a wire,
//! with optional latency and seeded loss. Time is tokio's, so tests can pause it.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::mpsc;
use tokio::time::Instant;

use super::CanTransport;
use crate::canopen::error::TransportError;
use crate::canopen::frame::CanFrame;

/// Bus options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BusOptions {
    /// Delivery delay of every frame.
    pub latency: Duration,
    /// Probability in [0, 1] that a frame is lost for a given receiver.
    pub loss: f64,
    /// Seed of the loss generator.
    pub seed: u64,
}

impl Default for BusOptions {
    fn default() -> Self {
        Self { latency: Duration::ZERO, loss: 0.0, seed: 1 }
    }
}

#[derive(Debug)]
struct Inner {
    ports: Vec<(u64, mpsc::UnboundedSender<(Instant, CanFrame)>)>,
    next_id: u64,
    options: BusOptions,
    rng: u64,
}

impl Inner {
    /// xorshift64*: a tiny seeded generator (this crate must not depend on amr-core's).
    fn uniform(&mut self) -> f64 {
        self.rng ^= self.rng >> 12;
        self.rng ^= self.rng << 25;
        self.rng ^= self.rng >> 27;
        (self.rng.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// The bus; clone it to hand it around, call [`InProcessBus::port`] for each node.
#[derive(Debug, Clone)]
pub struct InProcessBus {
    inner: Arc<Mutex<Inner>>,
}

impl Default for InProcessBus {
    fn default() -> Self {
        Self::new(BusOptions::default())
    }
}

impl InProcessBus {
    /// A bus with these options.
    pub fn new(options: BusOptions) -> Self {
        let inner = Inner { ports: Vec::new(), next_id: 0, options, rng: options.seed.max(1) };
        Self { inner: Arc::new(Mutex::new(inner)) }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // A panic while holding the lock leaves the port list consistent: use it.
        self.inner.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// A new node on the bus.
    pub fn port(&self) -> BusPort {
        let (tx, rx) = mpsc::unbounded_channel();
        let mut inner = self.lock();
        let id = inner.next_id;
        inner.next_id += 1;
        inner.ports.push((id, tx));
        BusPort { id, bus: self.clone(), rx, pending: None }
    }

    /// Number of ports still open.
    pub fn port_count(&self) -> usize {
        let mut inner = self.lock();
        inner.ports.retain(|(_, tx)| !tx.is_closed());
        inner.ports.len()
    }

    fn broadcast(&self, from: u64, frame: CanFrame) {
        let mut inner = self.lock();
        let at = Instant::now() + inner.options.latency;
        let loss = inner.options.loss;
        inner.ports.retain(|(_, tx)| !tx.is_closed());
        let targets: Vec<_> =
            inner.ports.iter().filter(|(id, _)| *id != from).map(|(_, tx)| tx.clone()).collect();
        for tx in targets {
            if loss > 0.0 && inner.uniform() < loss {
                continue;
            }
            // A closed receiver just left the bus.
            let _ = tx.send((at, frame));
        }
    }
}

/// One node's connection to an [`InProcessBus`].
#[derive(Debug)]
pub struct BusPort {
    id: u64,
    bus: InProcessBus,
    rx: mpsc::UnboundedReceiver<(Instant, CanFrame)>,
    pending: Option<(Instant, CanFrame)>,
}

impl BusPort {
    /// Send without awaiting (the bus never blocks).
    pub fn send_now(&self, frame: CanFrame) {
        self.bus.broadcast(self.id, frame);
    }

    /// A frame already delivered, if any, without waiting.
    pub fn try_recv(&mut self) -> Option<CanFrame> {
        if self.pending.is_none() {
            self.pending = self.rx.try_recv().ok();
        }
        match self.pending {
            Some((at, frame)) if at <= Instant::now() => {
                self.pending = None;
                Some(frame)
            }
            _ => None,
        }
    }
}

impl CanTransport for BusPort {
    async fn send(&mut self, frame: CanFrame) -> Result<(), TransportError> {
        self.send_now(frame);
        Ok(())
    }

    async fn recv(&mut self) -> Result<CanFrame, TransportError> {
        if self.pending.is_none() {
            // Cancel-safe: mpsc::recv is, and a taken frame is parked in `pending` first.
            self.pending = Some(self.rx.recv().await.ok_or(TransportError::Closed)?);
        }
        if let Some((at, _)) = self.pending {
            tokio::time::sleep_until(at).await;
        }
        self.pending.take().map(|(_, f)| f).ok_or(TransportError::Closed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn canopen_bus_delivers_to_others_with_latency() {
        let bus =
            InProcessBus::new(BusOptions { latency: Duration::from_millis(5), ..BusOptions::default() });
        let mut a = bus.port();
        let mut b = bus.port();
        let mut c = bus.port();
        let f = CanFrame::new(0x181, &[1, 2]).unwrap();
        let t0 = Instant::now();
        a.send(f).await.unwrap();
        assert_eq!(b.recv().await.unwrap(), f);
        assert_eq!(Instant::now() - t0, Duration::from_millis(5));
        assert_eq!(c.recv().await.unwrap(), f);
        assert!(a.try_recv().is_none(), "a sender does not hear itself");
        drop(c);
        assert_eq!(bus.port_count(), 2);
    }

    #[tokio::test(start_paused = true)]
    async fn canopen_bus_loss_is_seeded_and_partial() {
        let bus = InProcessBus::new(BusOptions { loss: 0.5, seed: 7, ..BusOptions::default() });
        let a = bus.port();
        let mut b = bus.port();
        for i in 0..1000u16 {
            a.send_now(CanFrame::new(i & 0x7FF, &[]).unwrap());
        }
        let mut got = 0;
        while b.try_recv().is_some() {
            got += 1;
        }
        assert!((350..650).contains(&got), "{got} of 1000 delivered at 50 % loss");
    }
}
