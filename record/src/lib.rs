//! `amr-record`: recording, replay and live view of a running fleet. The [`Recorder`] writes every
//! message on the server's and/or the robots' ports ([`amr_actors::server::ports::ServerPorts`],
//! [`amr_actors::robot::ports::RobotPorts`]), and through [`LogLayer`] the log lines, to an MCAP
//! file with Foxglove's schemas (topics in [`encode`]) or a ROS 2 bag ([`ros2`]), and/or to a
//! Foxglove WebSocket live view ([`live::serve`]). [`read`] reads a recording back, complete or cut
//! short by a crash, [`replay::run`] re-runs the server's localisation on its exact uplink and
//! compares, and [`ros2::bag`] reads a bag's scans and odometry for `amr localize --bag`.
//!
//! # Build decisions (measured 2026-12-01 on a 2-core machine, shared with two other builds)
//!
//! **JSON schemas, not the `foxglove` SDK crate.** Foxglove opens MCAP channels with schema
//! encoding `jsonschema` and message encoding `json` with no plugin, so the well-known schemas are
//! written here as JSON ([`foxglove`]) and the live server is ~200 lines over `tokio-tungstenite`.
//! Clean release builds of a probe binary, each in its own target directory:
//!
//! | dependencies | crates (`cargo tree`) | build, elapsed |
//! |---|---|---|
//! | `foxglove` 0.30.3, only its `websocket` feature | 152 | 1840 s |
//! | ours: `mcap` (no default features), `tokio-tungstenite` (`handshake`), `serde_json`, `tokio` | 107 | 576 s |
//! | `mcap` alone, no compression | 35 | 86 s (57 s CPU) |
//! | `mcap` with `zstd` | 43 | 225 s (152 s CPU) |
//!
//! (The first two ran while the machine's load was about 7, so their times are inflated; their
//! ratio, about 3×, is the point.) In the workspace this crate adds 47 crates to what amr-actors
//! already pulls in, of which `tracing-subscriber` and `serde_json` are in the `amr` binary anyway.
//!
//! **LZ4 chunks.** Chunks are LZ4-compressed by default ([`sink::FlushPolicy::lz4`]; `amr …
//! --record-uncompressed` turns it off). `mcap`'s `lz4` feature builds liblz4 (`lz4-sys`, C):
//! about 12 s more per clean build here, against about 95 s of CPU for `zstd-sys`. Measured on
//! 2026-12-02 (`amr sim --virtual-time --duration 60 --seed 3 --record F [--record-uncompressed]`,
//! debug build, so liblz4 unoptimised): one recorded minute of two robots is 21.4 MB uncompressed
//! and 9.1 MB with LZ4 (2.35×), for 0.21 s more CPU (medians of three runs: 6.79 s against
//! 6.58 s). zstd -3 would make such a file about 4.4× smaller (measured on an earlier 16 s run:
//! 6.2 MB → 1.42 MB, lz4 2.69 MB) for that build cost. [`read`] checks a compressed chunk's records
//! with liblz4 before mcap's reader sees them (lz4_flex 0.10, which Zenoh builds, panics on some
//! damaged frames: the damaged-file test found it); `amr replay` and the Python `mcap` package read
//! the files (tests in `tests/record_replay.rs`).
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
pub mod ros2;
pub mod sink;
pub mod wire;

pub use live::{Hub, LiveOptions, LiveServer, serve, serve_with};
pub use log_layer::LogLayer;
pub use recorder::{FileRecorder, LogTap, RecordError, RecordOptions, RecordSources, Recorder};
pub use replay::{ReplayReport, run as replay};
pub use sink::FlushPolicy;
