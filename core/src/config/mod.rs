//! The configuration types of the pure math: the algorithm parameters and the robot's body.
//!
//! | file | type | what |
//! |---|---|---|
//! | `server.toml` | [`ServerConfig`] | the formation, fusion weights and gates, the T1–T4 switch |
//! | `vamr.toml` | [`VamrParams`] | the Virtual-AMR pipeline parameters (paper Table 2) |
//! | `amcl.toml` | [`AmclParams`] | AMCL parameters (nav2_amcl names; `odom_slip_share` and `odom_slip_probability` are ours) |
//! | `scenarios/<name>.toml` | [`ScenarioConfig`] | an experiment: start, spacing, V's path, on a map |
//! | `robot-<id>.toml` | [`ChassisConfig`], [`KinematicsConfig`], [`MountConfig`], [`MotionLimits`], [`SafetyConfig`] | a robot's body; its `[devices.*]` are the drivers' |
//!
//! Each crate owns the types of its own part of the configuration: the drivers their device
//! sections, the network link `network.toml`; `amr_actors::config` reads a whole set of files.
//! Every struct rejects unknown keys. Rules on a single value are checked while the file is
//! deserialised ([`value`], from amr-settings); rules that relate several values afterwards. Either
//! way the first broken rule comes back as a [`ConfigError`] naming the file, the key and the rule.
//! This module does no IO: callers read the files and hand over their text.

mod amcl;
pub mod nav2;
mod robot;
mod scenario;
mod server;
mod vamr;

pub use amr_settings::{ConfigError, ConfigFileType, Violation, join, key_line, parse_file, rule, value};

pub use amcl::{AmclParams, InitialPose, LaserModel};
pub use robot::{ChassisConfig, KinematicsConfig, MotionLimits, MountConfig, RobotId, SafetyConfig};
pub use scenario::{ScenarioConfig, ScenarioLimits, Segment, StartPose};
pub use server::{
    Configuration, FormationMember, HeadingFrom, IntegrityChecks, OnRobotLost, PositionFrom, ServerConfig,
    SyncGates,
};
pub use vamr::{
    AmclMotion, ContourParams, FusionParams, HeadingParams, PreprocessParams, TrackerParams, VamrParams,
};
