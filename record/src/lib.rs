//! Recording, replay and live view (issue 12): MCAP files and a Foxglove WebSocket server with
//! Foxglove's schemas.
//!
//! - [`Recorder`] subscribes to the server's ports ([`amr_actors::server::ports::ServerPorts`])
//!   and/or robots' ports ([`amr_actors::robot::ports::RobotPorts`]) and writes every message to an
//!   MCAP file and/or the live view; topics and schemas are listed in [`encode`].
//! - [`LogLayer`] records `tracing` log lines as `foxglove.Log`.
//! - [`replay::run`] re-runs fusion + AMCL on a recording's exact uplink channel and compares.
//! - [`live::serve`] is the Foxglove WebSocket server (`foxglove.websocket.v1`).
//! - [`read`] reads a recording back, complete or cut short by a crash.
//!
//! # Build decisions (measured 2026-12-01 on this 2-core machine, shared with two other builds)
//!
//! **JSON schemas, not the `foxglove` SDK crate.** Foxglove opens MCAP channels with schema
//! encoding `jsonschema` and message encoding `json` with no plugin, so the well-known schemas are
//! written here as JSON ([`foxglove`]) and the live server is ~200 lines over `tokio-tungstenite`.
//! `foxglove` 0.30.3 with only its `websocket` feature resolves to 152 crates (prost, serde_with,
//! flume, sha2, tungstenite 0.30, …) against 107 for everything this crate adds (mcap without
//! compression, tungstenite's bare handshake, serde_json); see the report of issue 12 for the build
//! times measured.
//!
//! **No compression.** `mcap`'s default features build the zstd and lz4 C libraries. Recordings
//! are written uncompressed (chunks whole, closed about every second): the C build costs more than
//! the disk it saves for recordings of a few minutes, and an uncompressed chunk is readable byte
//! for byte up to a crash. `zstd -3` on a 20 s simulated recording shrinks it about 6×
//! (numbers in the issue report); a long-running robot that needs that can turn the feature on
//! (`mcap/zstd`) and set [`mcap::WriteOptions::compression`].
//!
//! # Crash safety
//!
//! Chunks are written whole (`disable_seeking`: the open chunk lives in memory, nothing on disk is
//! patched later) and closed by a [`FlushPolicy`] (1 s of log time or 2000 messages, and a 250 ms
//! tick for a quiet stream). A killed process leaves the header and every closed chunk;
//! [`read::read_bytes`] reads them and stops at the first incomplete record (tested by cutting a real
//! recording at many offsets).

pub mod encode;
pub mod foxglove;
pub mod live;
pub mod log_layer;
pub mod read;
pub mod recorder;
pub mod replay;
pub mod sink;
pub mod wire;

pub use live::{Hub, LiveServer, serve};
pub use log_layer::LogLayer;
pub use recorder::{FileRecorder, LogTap, RecordError, RecordOptions, RecordSources, Recorder};
pub use replay::{ReplayReport, run as replay};
pub use sink::FlushPolicy;
