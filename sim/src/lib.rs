//! `amr-sim`: the whole system in one process against the mock devices: the world (hil-mocks) moves
//! the robots, the mocks serve it through the drivers' real transports, and the real robot and
//! server trees run on it, for `amr sim`, the HIL tests and the fault-recovery drills (module
//! `drills`, feature `drills`). A run is in real time (two runs of one seed are close, not
//! identical) or, with every device on in-memory pipes and tokio's clock paused, reproducible from
//! its seed ([`SimCan::VirtualTime`]); [`eval`] is the simulated-time evaluation of T1–T4
//! (`amr eval`), and [`served`] serves the world to separate robot processes.

#[cfg(feature = "drills")]
pub mod drills;
pub mod eval;
#[cfg(feature = "drills")]
pub mod kernel_can;
mod mocks;
mod observer;
mod options;
pub mod report;
mod rig;
pub mod served;
mod sim;
pub mod survey;
pub mod truth;
mod watch_drive;
mod world;
mod world_loop;

// The drills name it at the crate's root.
#[cfg(feature = "drills")]
use amr_actors::robot::ports::AbortOnDrop;

pub use mocks::{DEVICES, RobotMocks, SocketcandMock, start_mocks};
pub use options::{SimCan, SimError, SimOptions};
pub use report::{SimReport, latency_table};
pub use rig::{Apart, RobotRig};
pub use sim::Sim;
pub use truth::TruthLog;
pub use world::{build_world, check_formation, robot_spec, site_for, site_of, v_of};
pub use world_loop::{PHYSICS_DT_S, spawn_world_loop};
