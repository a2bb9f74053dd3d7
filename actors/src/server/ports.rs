//! The server's wiring: ports that outlive its actors, and the latency log.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use ractor::OutputPort;

use crate::clock::FleetClock;
use amr_msgs::{Downlink, Estimate, FusedFrame, FusionStatus, ParticleCloud, StageTimes, Uplink};

/// Per-stage latencies of every fused update that produced an estimate.
#[derive(Debug, Clone, Default)]
pub struct LatencyLog(Arc<Mutex<Vec<StageTimes>>>);

impl LatencyLog {
    pub fn push(&self, t: StageTimes) {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).push(t);
    }

    #[must_use]
    pub fn snapshot(&self) -> Vec<StageTimes> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).clone()
    }
}

/// Counters of the server's work, for reports and tests.
#[derive(Debug, Default)]
pub struct ServerStats {
    /// Fused frames handed to AMCL.
    pub fused: AtomicU64,
    /// Sets refused by the sync gate.
    pub gate_failures: AtomicU64,
    /// Scans the core refused (a robot not in the formation, impossible geometry or stamps).
    pub refused: AtomicU64,
    /// Heading searches over the full circle (first acquisition and every re-acquisition).
    pub full_searches: AtomicU64,
    /// Robots declared lost, and back.
    pub robots_lost: AtomicU64,
    pub robots_back: AtomicU64,
    /// Robots whose odometry started a new frame (they restarted): their filters re-anchored.
    pub odometry_restarts: AtomicU64,
    /// Estimates from each robot's own AMCL, per robot.
    pub own_estimates: Vec<AtomicU64>,
}

impl ServerStats {
    /// Read a counter.
    #[must_use]
    pub fn get(c: &AtomicU64) -> u64 {
        c.load(Ordering::Relaxed)
    }

    pub(crate) fn add(c: &AtomicU64) {
        c.fetch_add(1, Ordering::Relaxed);
    }
}

/// Every port of the server.
#[derive(Debug)]
pub struct ServerPorts {
    pub clock: FleetClock,
    /// Robot ids in formation order.
    pub robots: Vec<String>,
    /// Everything the robots sent, with the fleet clock when it came off the link (stamped once,
    /// here: the localizer's sync gate, the recorder and a replay all see the same time).
    pub uplink: OutputPort<(Uplink, f64)>,
    /// The scans, apart from the rest of the uplink (bounded per robot): the localizer takes them
    /// from here and publishes on `uplink` those it processes.
    pub scans: crate::link::ScanSlots,
    pub fused: OutputPort<FusedFrame>,
    pub estimates: OutputPort<Estimate>,
    pub status: OutputPort<FusionStatus>,
    /// Every filter update's particles (for recording and the live view).
    pub particles: OutputPort<ParticleCloud>,
    /// Every message the formation sent down the link, with the robot's formation index.
    pub commands: OutputPort<(usize, Downlink)>,
    pub latency: LatencyLog,
    pub stats: ServerStats,
}

impl ServerPorts {
    #[must_use]
    pub fn new(robots: Vec<String>, clock: FleetClock) -> Arc<Self> {
        Self::with_scans(robots, clock, crate::link::ScanSlots::default())
    }

    /// Ports whose scans come through `scans`.
    #[must_use]
    pub fn with_scans(robots: Vec<String>, clock: FleetClock, scans: crate::link::ScanSlots) -> Arc<Self> {
        let n = robots.len();
        scans.stamp_with(clock);
        Arc::new(ServerPorts {
            clock,
            robots,
            uplink: OutputPort::default(),
            scans,
            fused: OutputPort::default(),
            estimates: OutputPort::default(),
            status: OutputPort::default(),
            particles: OutputPort::default(),
            commands: OutputPort::default(),
            latency: LatencyLog::default(),
            stats: ServerStats {
                own_estimates: (0..n).map(|_| AtomicU64::new(0)).collect(),
                ..ServerStats::default()
            },
        })
    }

    /// The formation index of robot `id`.
    #[must_use]
    pub fn index(&self, id: &str) -> Option<usize> {
        self.robots.iter().position(|r| r == id)
    }
}
