//! `amr-net`: the fleet over the network. Robots and the fusion server run as separate processes
//! and reach each other over Eclipse Zenoh: one bridge actor per process ([`bridge`], which lists
//! the keys) turns the link's channel ends ([`amr_actors::link`]) into Zenoh samples and back, so
//! the actor trees do not know which link they are on. [`network`] and [`settings`] turn
//! `network.toml` into Zenoh's configurations, and [`certs`] makes the fleet's certificates for
//! its mutual TLS (`amr fleet certs`).
//!
//! # Security
//!
//! Mutual TLS ([`settings::Security::Tls`]): every peer presents a certificate of the
//! fleet's CA ([`certs`], `amr fleet certs`) and checks the other's, and a robot checks that the
//! server's certificate is valid for the address it dialled. The server's access control, an allow
//! list keyed on the certificate's name, lets no one but the server publish commands, only the
//! server and the configured operators publish e-stops, and a robot publish only its own data,
//! on exact keys (a wildcard put is refused). A robot also checks that a command names the
//! configured server (an e-stop: the server or an operator), is for it, and is newer than the last
//! ([`wire::Freshness`]), and its safety layer refuses stale commands and stops by itself when
//! commands stop. `--insecure` ([`settings::Security::Insecure`]) runs plain TCP with Zenoh's
//! user/password instead: authenticated, not encrypted, and the server unauthenticated to a robot.
//!
//! # Logging
//!
//! Zenoh 1.10 prints its whole configuration, the password included, at debug level on the
//! `zenoh::api::session` target when a session opens. A program using these bridges must keep that
//! target at info or above (the `amr` binary forces it, whatever `RUST_LOG` says, and a test checks
//! it at trace level). This crate itself never logs a password ([`Credential`]'s `Debug` hides it).
//! With TLS the configuration holds file paths only, never key material.

pub mod bridge;
pub mod certs;
pub mod network;
pub mod settings;
pub mod wire;

pub use bridge::{
    Bridge, BridgeStats, EstopOutcome, ServerBridge, decode_status, operator_estop, start_robot_bridge,
    start_server_bridge,
};
pub use settings::{Credential, Credentials, NetError, NetSettings};
