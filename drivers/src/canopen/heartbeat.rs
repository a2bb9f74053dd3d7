//! Heartbeat producer and consumer timers (CiA 301 0x1017 / 0x1016), sans-IO with `now` passed in.
//! The consumer starts watching after the first heartbeat (CiA 301; CANopenNode PR #363).

use std::time::{Duration, Instant};

/// Sends a heartbeat every `period` (0 = off).
#[derive(Debug, Clone)]
pub struct HeartbeatProducer {
    period: Duration,
    next: Option<Instant>,
}

impl HeartbeatProducer {
    /// A producer whose first heartbeat is due at `now`.
    pub fn new(period: Duration, now: Instant) -> Self {
        Self { period, next: (!period.is_zero()).then_some(now) }
    }

    /// Change the period (an SDO write of 0x1017); the next heartbeat is due at `now`.
    pub fn set_period(&mut self, period: Duration, now: Instant) {
        *self = Self::new(period, now);
    }

    /// When the next heartbeat is due.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.next
    }

    /// Whether a heartbeat is due at `now`; if so, schedules the next one.
    pub fn due(&mut self, now: Instant) -> bool {
        match self.next {
            Some(t) if t <= now => {
                // Keep the cadence, but do not burst after a long stall.
                let next = t + self.period;
                self.next = Some(if next <= now { now + self.period } else { next });
                true
            }
            _ => false,
        }
    }
}

/// What the consumer saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConsumerState {
    /// No heartbeat yet: not monitored.
    Waiting,
    /// Heartbeats arriving in time.
    Alive,
    /// The last heartbeat is older than the consumer time.
    Lost,
}

/// Watches one producer: lost when no heartbeat came within `timeout` of the previous one.
#[derive(Debug, Clone)]
pub struct HeartbeatConsumer {
    timeout: Duration,
    last: Option<Instant>,
    state: ConsumerState,
}

impl HeartbeatConsumer {
    /// A consumer with the given consumer time (0 = off).
    pub fn new(timeout: Duration) -> Self {
        Self { timeout, last: None, state: ConsumerState::Waiting }
    }

    /// The consumer time.
    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    /// A heartbeat arrived at `now`.
    pub fn received(&mut self, now: Instant) {
        self.last = Some(now);
        self.state = ConsumerState::Alive;
    }

    /// Forget the producer (after a reconfiguration or a consumer-time change).
    pub fn reset(&mut self, timeout: Duration) {
        *self = Self::new(timeout);
    }

    /// The state.
    pub fn state(&self) -> ConsumerState {
        self.state
    }

    /// When the consumer times out if nothing arrives.
    pub fn poll_timeout(&self) -> Option<Instant> {
        match (self.state, self.last) {
            (ConsumerState::Alive, Some(t)) if !self.timeout.is_zero() => Some(t + self.timeout),
            _ => None,
        }
    }

    /// Check at `now`; returns true exactly once when the producer is found lost.
    pub fn check(&mut self, now: Instant) -> bool {
        match self.poll_timeout() {
            Some(deadline) if now >= deadline => {
                self.state = ConsumerState::Lost;
                true
            }
            _ => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canopen_heartbeat_consumer_starts_after_first_and_times_out_once() {
        let t0 = Instant::now();
        let mut c = HeartbeatConsumer::new(Duration::from_millis(300));
        assert!(!c.check(t0 + Duration::from_secs(10)), "not monitored before the first heartbeat");
        c.received(t0);
        assert!(!c.check(t0 + Duration::from_millis(299)));
        assert!(c.check(t0 + Duration::from_millis(300)));
        assert!(!c.check(t0 + Duration::from_millis(400)), "reported once");
        assert_eq!(c.state(), ConsumerState::Lost);
        c.received(t0 + Duration::from_millis(500));
        assert_eq!(c.state(), ConsumerState::Alive);
    }

    #[test]
    fn canopen_heartbeat_producer_period() {
        let t0 = Instant::now();
        let mut p = HeartbeatProducer::new(Duration::from_millis(100), t0);
        assert!(p.due(t0));
        assert!(!p.due(t0 + Duration::from_millis(99)));
        assert!(p.due(t0 + Duration::from_millis(100)));
        assert_eq!(p.poll_timeout(), Some(t0 + Duration::from_millis(200)));
        let mut off = HeartbeatProducer::new(Duration::ZERO, t0);
        assert!(!off.due(t0 + Duration::from_secs(1)));
    }
}
