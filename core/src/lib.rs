//! `amr-core`: the math of the Virtual-AMR controller: SE(2) poses, scans, occupancy maps and
//! distance fields, the Virtual-AMR measurement-construction pipeline ([`vamr`]), AMCL ([`amcl`]),
//! odometry, formation control and V's reference plan, the paper's error metrics, CARMEN logs, and
//! the configuration types of the algorithms and the robot's body. Pure and deterministic: no IO,
//! no async, no clock, no threads, no global state; time and randomness ([`rng`]) come in as
//! arguments, so everything here can be tested with plain values.

pub mod amcl;
pub mod carmen;
pub mod config;
pub mod formation;
pub mod geometry;
pub mod map;
pub mod metrics;
pub mod odometry;
pub mod plan;
pub mod rng;
pub mod scan;
pub mod se2;
pub mod vamr;
