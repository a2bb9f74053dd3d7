//! The fleet clock: seconds since one epoch, read from tokio's clock so tests can pause time.

use tokio::time::Instant;

/// Seconds since an epoch shared by everything in the process.
#[derive(Debug, Clone, Copy)]
pub struct FleetClock {
    epoch: Instant,
}

impl FleetClock {
    /// A clock whose zero is now.
    #[must_use]
    pub fn start() -> Self {
        FleetClock { epoch: Instant::now() }
    }

    /// Seconds since the epoch.
    #[must_use]
    pub fn now_s(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64()
    }

    /// A tokio instant on this clock.
    #[must_use]
    pub fn seconds(&self, at: Instant) -> f64 {
        at.saturating_duration_since(self.epoch).as_secs_f64()
    }

    /// A std instant (the drivers' stamps) on this clock.
    #[must_use]
    pub fn seconds_std(&self, at: std::time::Instant) -> f64 {
        at.saturating_duration_since(self.epoch.into_std()).as_secs_f64()
    }
}
