//! A simulation's run settings, how its robots reach their mock drives, and why a simulation could
//! not start.

use std::time::Duration;

use amr_core::config::{Configuration, ScenarioConfig};
use amr_core::map::OccupancyGrid;
use hil_mocks::world::Noise;

/// How the robots reach their mock drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SimCan {
    /// The in-process bus.
    InProcess,
    /// A socketcand server on loopback in front of the in-process bus.
    Socketcand,
    /// No socket and no tty at all: the LiDAR and the IMU over in-memory pipes, CAN on the
    /// in-process bus. With tokio's clock paused (a current-thread runtime) nothing but that clock
    /// orders events, so a run is reproducible from its seed (`amr sim --virtual-time`).
    VirtualTime,
}

/// Run settings.
#[derive(Debug, Clone)]
pub struct SimOptions {
    pub scenario_name: String,
    pub scenario: ScenarioConfig,
    pub seed: u64,
    pub noise: Noise,
    pub can: SimCan,
    /// T1–T4 (default: the server file's).
    pub configuration: Option<Configuration>,
    /// Stop after this much wall time even if the plan is not done.
    pub max_duration: Option<Duration>,
    /// A scenario file's own map (its YAML's path, and the grid); `None`: the configuration's
    /// map that the scenario names.
    pub map: Option<(String, OccupancyGrid)>,
    /// AMCL's map from a simulated survey of the site ([`survey`](crate::survey)) instead of the
    /// site's own.
    pub surveyed_map: bool,
}

/// Why a simulation could not start.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("no map `{0}` in the configuration")]
    NoMap(String),
    #[error("the world's site: {0}")]
    Site(String),
    #[error(transparent)]
    Server(#[from] amr_actors::server::ServerError),
    #[error(transparent)]
    Robot(#[from] amr_actors::robot::RobotError),
    #[error("mock {0}: {1}")]
    Mock(&'static str, String),
}
