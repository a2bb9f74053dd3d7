//! The server's wiring: ports that outlive its actors, and the latency log.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use amr_core::config::Configuration;
use amr_core::se2::Se2;
use ractor::OutputPort;
use tokio::sync::watch;

use crate::clock::FleetClock;
use crate::messages::{Downlink, Uplink};

/// Times of one fused update's stages, seconds (the paper's Table 4 rows).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// From the oldest scan's stamp to passing the sync gate.
    pub acquisition_sync_s: f64,
    pub preprocess_s: f64,
    pub tracking_s: f64,
    pub heading_s: f64,
    pub virtual_scan_s: f64,
    /// AMCL's update; `None` when the filter skipped it (moved less than `update_min_d`/`update_min_a`).
    pub amcl_s: Option<f64>,
    /// From the oldest scan's stamp to the published estimate.
    pub end_to_end_s: f64,
}

/// A fused frame, from the fusion actor to the AMCL actor.
#[derive(Debug, Clone)]
pub struct FusedFrame {
    pub seq: u64,
    pub configuration: Configuration,
    /// The reference robot's scan stamp.
    pub stamp_s: f64,
    /// The oldest stamp of the set (latency is counted from it).
    pub oldest_stamp_s: f64,
    /// V's pose in the reference robot's odometry frame at `stamp_s`.
    pub v_odom: Se2,
    /// The virtual scan's points in V's frame (T2–T4); `None` for T1.
    pub points: Option<Arc<Vec<[f64; 2]>>>,
    /// Per robot: its base in V, and its odometry pose at its scan.
    pub robots: Vec<(Se2, Se2)>,
    pub times: StageTimes,
}

/// Where one estimate came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EstimateSource {
    /// AMCL on the virtual scan (T2–T4), or the per-robot midpoint (T1).
    Fused(Configuration),
    /// One robot's own AMCL (the per-robot filters; the fallback when fusion is impossible).
    Robot(usize),
}

/// A robot's pose in the map with the odometry pose it corresponds to, so it can be carried
/// forward with odometry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Anchored {
    pub map: Se2,
    pub odom: Se2,
    pub stamp_s: f64,
}

/// A localisation result.
#[derive(Debug, Clone, PartialEq)]
pub struct Estimate {
    pub source: EstimateSource,
    pub stamp_s: f64,
    /// V in the map (fused estimates only).
    pub v: Option<Se2>,
    /// Per robot (formation order), where this estimate places it.
    pub robots: Vec<Option<Anchored>>,
}

/// The fusion server's state as seen from outside.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FusionStatus {
    Fusing,
    /// Robot `i`'s scans stopped; the others are localised on their own.
    RobotLost(usize),
}

/// A filter's particles after an update that ran (for recording and the live view).
#[derive(Debug, Clone)]
pub struct ParticleCloud {
    pub source: EstimateSource,
    pub stamp_s: f64,
    pub poses: Arc<Vec<Se2>>,
}

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
    /// Heading searches over the full circle (first acquisition and every re-acquisition).
    pub full_searches: AtomicU64,
    /// Robots declared lost, and back.
    pub robots_lost: AtomicU64,
    pub robots_back: AtomicU64,
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
    /// Everything the robots sent.
    pub uplink: OutputPort<Uplink>,
    pub fused: OutputPort<FusedFrame>,
    pub estimates: OutputPort<Estimate>,
    pub status: OutputPort<FusionStatus>,
    /// Every filter update's particles (for recording and the live view).
    pub particles: OutputPort<ParticleCloud>,
    /// Every message the formation sent down the link, with the robot's formation index.
    pub commands: OutputPort<(usize, Downlink)>,
    /// Per robot: `T_odom^map` of its own AMCL (map pose = this · odometry pose).
    pub corrections: watch::Sender<Vec<Option<Se2>>>,
    pub latency: LatencyLog,
    pub stats: ServerStats,
}

impl ServerPorts {
    #[must_use]
    pub fn new(robots: Vec<String>, clock: FleetClock) -> Arc<Self> {
        let n = robots.len();
        Arc::new(ServerPorts {
            clock,
            robots,
            uplink: OutputPort::default(),
            fused: OutputPort::default(),
            estimates: OutputPort::default(),
            status: OutputPort::default(),
            particles: OutputPort::default(),
            commands: OutputPort::default(),
            corrections: watch::Sender::new(vec![None; n]),
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
