//! The fleet clock: seconds since one epoch, read from tokio's clock so tests can pause time.
//!
//! In one process every actor shares one epoch ([`FleetClock::start`]). Robots and the server in
//! separate processes compare stamps (the robot refuses a command stamped too long ago; the server
//! gates scans by age), so there the epoch is the Unix epoch ([`FleetClock::wall`]) and the hosts'
//! clocks must be synchronised (NTP or PTP), as for any distributed robot system.

use tokio::time::Instant;

/// Seconds since an epoch shared by everything in the process (or, from [`FleetClock::wall`], by
/// every process whose host clock is synchronised).
#[derive(Debug, Clone, Copy)]
pub struct FleetClock {
    epoch: Instant,
    /// Seconds of the epoch instant on the fleet's time scale (0 for a process-local clock).
    offset_s: f64,
}

impl FleetClock {
    /// A clock whose zero is now.
    #[must_use]
    pub fn start() -> Self {
        FleetClock { epoch: Instant::now(), offset_s: 0.0 }
    }

    /// A clock reading seconds since the Unix epoch (the host's wall clock at start, then tokio's
    /// monotonic clock: a step of the wall clock later does not move it). An f64 holds today's
    /// Unix time to about half a microsecond.
    #[must_use]
    pub fn wall() -> Self {
        let unix = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs_f64())
            .unwrap_or(0.0);
        FleetClock { epoch: Instant::now(), offset_s: unix }
    }

    /// Seconds since the epoch.
    #[must_use]
    pub fn now_s(&self) -> f64 {
        self.offset_s + self.epoch.elapsed().as_secs_f64()
    }

    /// A tokio instant on this clock.
    #[must_use]
    pub fn seconds(&self, at: Instant) -> f64 {
        self.offset_s + at.saturating_duration_since(self.epoch).as_secs_f64()
    }

    /// A std instant (the drivers' stamps) on this clock.
    #[must_use]
    pub(crate) fn seconds_std(&self, at: std::time::Instant) -> f64 {
        self.offset_s + at.saturating_duration_since(self.epoch.into_std()).as_secs_f64()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_wall_clock_reads_unix_time_and_advances_with_tokio() {
        let unix = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs_f64();
        let c = FleetClock::wall();
        let t0 = c.now_s();
        assert!((t0 - unix).abs() < 1.0, "{t0} vs {unix}");
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        let dt = c.now_s() - t0;
        assert!((0.015..1.0).contains(&dt), "{dt}");
        assert!((c.seconds(Instant::now()) - c.now_s()).abs() < 0.01);
        assert_eq!(FleetClock::start().seconds(Instant::now() - std::time::Duration::from_secs(5)), 0.0);
    }
}
