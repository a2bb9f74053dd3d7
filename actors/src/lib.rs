//! `amr-actors`: the runtime. Supervised actors that own the drivers and the algorithms, the robot
//! and server actor trees, and what the runtime needs to start: loading the configuration.
//!
//! The actor trees arrive with their issue; this crate depends on `amr-core` and `amr-drivers` and is
//! used by `host` (see `docs/architecture.md`: the crates, the actor trees, the rules between crates).

pub mod clock;
pub mod config;
pub mod link;
pub mod robot;
pub mod server;
pub mod supervisor;
