//! Drills on the whole fleet: the link, the server, a slow consumer (drills 8–10 of issue 10).

use amr_core::config::Config;

use super::Check;

/// Drill 8: robot ↔ server link lost.
pub(crate) async fn link_lost(_config: &Config, _seed: u64, c: &mut Check) {
    c.that(false, "not written yet");
}

/// Drill 9: the server crashes and restarts.
pub(crate) async fn server_restart(_config: &Config, _seed: u64, c: &mut Check) {
    c.that(false, "not written yet");
}

/// Drill 10: a stalled localisation does not delay the robot's safety loop.
pub(crate) async fn slow_consumer(_config: &Config, _seed: u64, c: &mut Check) {
    c.that(false, "not written yet");
}
