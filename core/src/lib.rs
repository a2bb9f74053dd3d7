//! `amr-core`: the math of the Virtual-AMR controller.
//!
//! Pure and deterministic: no IO, no async, no clock, no threads, no global state. Time and
//! randomness come in as arguments. Everything here can be tested with plain values.
//!
//! - [`se2`]: the one rigid-transform type of the project.
//! - [`geometry`]: planar polygons (chassis outlines).
//! - [`config`]: the configuration schema, parsed from TOML text and validated into domain types.
//! - [`scan`]: range scans with per-beam validity.
//! - [`map`]: occupancy grids in the ROS map_server format, distance transforms.
//! - [`rng`]: the seedable generator behind every random draw.
//! - [`vamr`]: the Virtual-AMR measurement-construction pipeline (paper §4).
//! - [`amcl`]: adaptive Monte Carlo localisation on a likelihood field.
//! - [`carmen`]: CARMEN robot logs, for replaying public 2D LiDAR datasets.

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
