//! `amr-actors`: the runtime. The robot's and the fusion server's actor trees ([`robot`],
//! [`server`]) own the drivers and the algorithms under an OTP-style [`supervisor`], talk through
//! the [`link`] (in process here, over Zenoh in `amr-net`) on the fleet [`clock`], and start from a
//! loaded configuration ([`config`]); the server's localisation is one sans-IO core
//! ([`server::core`]) that `amr replay` and `amr eval` drive too. The trees, the data flow and
//! supervision are described in `docs/architecture.md`.

pub mod clock;
pub mod config;
pub mod link;
pub mod robot;
pub mod server;
pub mod supervisor;
