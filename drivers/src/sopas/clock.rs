//! Mapping the device's µs tick to host time (notes §6: sick_scan_xd's software PLL fits ticks to
//! host time by regression over recent telegrams; stamp = generation tick mapped to host time).
//!
//! Each scan gives a pair (transmission tick, host receive time). The drift is the least-squares
//! slope over a window of recent pairs, clamped to ±1000 ppm; the offset is the lower envelope
//! (minimum receive latency), which network or scheduling delays can only push up, never down.
//! The 32-bit tick is unwrapped through signed deltas, so the counter wrapping after ~71.6 min is
//! seamless; a tick that jumps back (device reboot) or a pair that disagrees with the fit by more
//! than [`RESYNC_THRESHOLD_S`] restarts the fit.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// A pair further than this from the fit means the device clock restarted.
pub const RESYNC_THRESHOLD_S: f64 = 0.5;
const MAX_DRIFT: f64 = 1e-3;

/// What one observation did to the mapping.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClockUpdate {
    /// The pair was added to the fit.
    Tracked,
    /// First pair, or the tick went back / disagreed with the fit: the fit restarted.
    Reset,
}

/// The tick → host time mapping.
#[derive(Debug, Clone)]
pub struct DeviceClock {
    capacity: usize,
    base: Option<Instant>,
    last_raw: u32,
    last_unwrapped_us: i64,
    /// (unwrapped tick µs, host seconds since `base`).
    samples: VecDeque<(i64, f64)>,
    resets: u32,
}

impl DeviceClock {
    /// A mapping fitted over the last `capacity` pairs (at least 2).
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.max(2),
            base: None,
            last_raw: 0,
            last_unwrapped_us: 0,
            samples: VecDeque::new(),
            resets: 0,
        }
    }

    /// How often the fit restarted (device reboots seen), the first pair included.
    pub fn resets(&self) -> u32 {
        self.resets
    }

    fn unwrap(&self, raw: u32) -> i64 {
        self.last_unwrapped_us + i64::from(raw.wrapping_sub(self.last_raw) as i32)
    }

    fn host_s(&self, now: Instant) -> f64 {
        self.base.map_or(0.0, |b| now.saturating_duration_since(b).as_secs_f64())
    }

    /// (offset s, slope s/µs) of the current fit, relative to the first sample's tick.
    fn fit(&self) -> Option<(f64, f64, i64)> {
        let &(x0, _) = self.samples.front()?;
        let n = self.samples.len() as f64;
        let mut slope = 1e-6;
        if self.samples.len() >= 2 {
            let mx = self.samples.iter().map(|(x, _)| (x - x0) as f64).sum::<f64>() / n;
            let my = self.samples.iter().map(|(_, y)| y).sum::<f64>() / n;
            let (mut sxy, mut sxx) = (0.0, 0.0);
            for (x, y) in &self.samples {
                let dx = (x - x0) as f64 - mx;
                sxy += dx * (y - my);
                sxx += dx * dx;
            }
            if sxx > 0.0 {
                slope = (sxy / sxx).clamp(1e-6 * (1.0 - MAX_DRIFT), 1e-6 * (1.0 + MAX_DRIFT));
            }
        }
        let offset =
            self.samples.iter().map(|(x, y)| y - slope * (x - x0) as f64).fold(f64::INFINITY, f64::min);
        Some((offset, slope, x0))
    }

    fn predict_s(&self, unwrapped_us: i64) -> Option<f64> {
        let (offset, slope, x0) = self.fit()?;
        Some(offset + slope * (unwrapped_us - x0) as f64)
    }

    fn reset(&mut self, raw: u32, now: Instant) {
        self.samples.clear();
        self.base = Some(now);
        self.last_raw = raw;
        self.last_unwrapped_us = i64::from(raw);
        self.samples.push_back((self.last_unwrapped_us, 0.0));
        self.resets += 1;
    }

    /// Feeds one pair: the telegram's transmission tick and when the host received it.
    pub fn observe(&mut self, transmission_tick_us: u32, now: Instant) -> ClockUpdate {
        if self.base.is_none() {
            self.reset(transmission_tick_us, now);
            return ClockUpdate::Reset;
        }
        let x = self.unwrap(transmission_tick_us);
        let y = self.host_s(now);
        let went_back = x < self.last_unwrapped_us;
        let off_fit = self.predict_s(x).is_none_or(|p| (y - p).abs() > RESYNC_THRESHOLD_S);
        if went_back || off_fit {
            tracing::info!(transmission_tick_us, went_back, "device clock restarted; refitting");
            self.reset(transmission_tick_us, now);
            return ClockUpdate::Reset;
        }
        self.last_raw = transmission_tick_us;
        self.last_unwrapped_us = x;
        self.samples.push_back((x, y));
        while self.samples.len() > self.capacity {
            self.samples.pop_front();
        }
        ClockUpdate::Tracked
    }

    /// Host time of a device tick near the last observed one (e.g. the scan's generation tick).
    pub fn to_host(&self, tick_us: u32) -> Option<Instant> {
        let base = self.base?;
        let s = self.predict_s(self.unwrap(tick_us))?;
        if s >= 0.0 {
            base.checked_add(Duration::from_secs_f64(s))
        } else {
            base.checked_sub(Duration::from_secs_f64(-s))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Simulates a device whose clock runs `drift` fast, sending every 66.7 ms with a latency of
    /// 1–4 ms, and checks the mapped generation time against the truth.
    fn run(clock: &mut DeviceClock, t0: Instant, start_tick: u32, from_s: f64, n: usize) -> f64 {
        let drift = 80e-6;
        let mut worst: f64 = 0.0;
        for i in 0..n {
            let true_s = from_s + i as f64 / 15.0;
            let tick = start_tick.wrapping_add(((true_s - from_s) * 1e6 * (1.0 + drift)) as u32);
            let latency = 0.001 + 0.003 * ((i * 7919) % 13) as f64 / 13.0;
            clock.observe(tick, t0 + Duration::from_secs_f64(true_s + latency));
            if i > 20 {
                let mapped = clock.to_host(tick).unwrap();
                let err = (mapped.duration_since(t0).as_secs_f64() - (true_s + 0.001)).abs();
                worst = worst.max(err);
            }
        }
        worst
    }

    #[test]
    fn tracks_drift_and_latency_jitter() {
        let t0 = Instant::now();
        let mut c = DeviceClock::new(64);
        let worst = run(&mut c, t0, 1_000_000, 0.0, 300);
        assert!(worst < 0.0015, "worst {worst}");
        assert_eq!(c.resets(), 1);
    }

    #[test]
    fn tick_wrap_is_seamless() {
        let t0 = Instant::now();
        let mut c = DeviceClock::new(64);
        let worst = run(&mut c, t0, u32::MAX - 3_000_000, 0.0, 300);
        assert!(worst < 0.0015, "worst {worst}");
        assert_eq!(c.resets(), 1, "a wrap is not a reboot");
    }

    #[test]
    fn reboot_restarts_the_fit() {
        let t0 = Instant::now();
        let mut c = DeviceClock::new(64);
        run(&mut c, t0, 500_000_000, 0.0, 100);
        // The device reboots: its tick restarts near zero 20 s later.
        let worst = run(&mut c, t0, 2_000_000, 30.0, 100);
        assert_eq!(c.resets(), 2);
        assert!(worst < 0.0015, "worst {worst}");
    }
}
