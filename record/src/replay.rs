//! Replay: the server's localisation re-run on a recording's exact uplink (`/amr/uplink`),
//! deterministically, with the recorded configuration or another T1–T4 and other parameters; the
//! result is a new recording and a comparison with the recorded estimates.
//!
//! The engine is the server's own [`ServerCore`] (amr-actors `server::core`), the one the
//! localizer actor drives, fed the recorded messages with the receive time the server stamped on
//! each (`rx_s`, the time its sync gate used). A recorded `RobotLost` status marks the robot lost
//! at its place in the stream (the localizer's 100 ms tick is not replayed), and its next scan
//! re-acquires it as the live server does. So a replay reproduces every estimate and fused frame
//! bit for bit, in virtual and in real time. What it does not model: a server tree restarted
//! mid-run (a drill) starts its filters and tracks again.
//!
//! The live actors consume every message (unbounded mailboxes). A port subscription that lagged
//! (ractor's output ports skip the oldest of more than 10 messages queued for one subscriber)
//! would leave the recorder without messages the server had; nothing in the uplink's sequence
//! numbers shows it (the robots number every link message, decimated odometry too), but the
//! comparison does: estimates missing or extra.

use std::collections::{BTreeMap, VecDeque};
use std::path::Path;

use amr_actors::server::core::ServerCore;
use amr_actors::server::{ServerSetup, core_setup};
use amr_core::config::Configuration;
use amr_msgs::{Estimate, FusedFrame, FusionStatus, Uplink};

use crate::encode::Event;
use crate::read::{ReadError, metadata, read_bytes};
use crate::recorder::{FileRecorder, RecordError};
use crate::wire::{self, FusedRecord, WireError};

/// Why a replay failed.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Read(#[from] ReadError),
    #[error("a recorded message: {0}")]
    Wire(#[from] WireError),
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error("the recording has no `/amr/uplink` channel: nothing to replay")]
    NoUplink,
}

/// What a replay did and how it compares.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReplayReport {
    pub configuration: Option<Configuration>,
    /// Uplink messages replayed, and scans among them.
    pub uplink: usize,
    pub scans: usize,
    /// Fused frames produced, and recorded.
    pub fused: usize,
    pub recorded_fused: usize,
    /// Estimates produced, and recorded.
    pub estimates: usize,
    pub recorded_estimates: usize,
    /// Estimates present in both (same source and stamp), and how many of them are bit-identical.
    pub compared: usize,
    pub identical: usize,
    /// Recorded estimates the replay did not produce, and the reverse.
    pub missing: usize,
    pub extra: usize,
    /// Fused frames equal to the recorded ones (by sequence number).
    pub fused_identical: usize,
    /// The input file was cut short (a crash): replayed up to its last whole chunk.
    pub truncated: bool,
    /// The first estimate that differs, for people.
    pub first_difference: Option<String>,
}

impl ReplayReport {
    /// Every recorded estimate reproduced bit for bit, and nothing more.
    #[must_use]
    pub fn exact(&self) -> bool {
        self.recorded_estimates > 0
            && self.compared == self.recorded_estimates
            && self.identical == self.compared
            && self.missing == 0
            && self.extra == 0
    }
}

/// The server's localisation as one deterministic state machine, fed in the recorded order.
pub struct Engine {
    core: ServerCore,
    robots: Vec<String>,
    configuration: Configuration,
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Engine").field("robots", &self.robots).finish_non_exhaustive()
    }
}

/// What one input produced.
#[derive(Debug, Default)]
pub struct Step {
    pub fused: Option<FusedFrame>,
    pub estimates: Vec<Estimate>,
}

impl Engine {
    /// The server of `setup` (as `amr_actors::server::start_server` builds it), in `configuration`
    /// if given, else the setup's.
    #[must_use]
    pub fn new(setup: &ServerSetup, configuration: Option<Configuration>) -> Self {
        let configuration = configuration.unwrap_or(setup.server.configuration);
        let core = ServerCore::new(core_setup(setup, &[configuration]));
        let robots = core.members().iter().map(|m| m.id.clone()).collect();
        Engine { core, robots, configuration }
    }

    /// Robot ids in formation order.
    #[must_use]
    pub fn robots(&self) -> &[String] {
        &self.robots
    }

    /// A fusion status change seen in the recording.
    pub fn status(&mut self, s: FusionStatus) {
        if let FusionStatus::RobotLost(i) = s {
            self.core.mark_lost(i);
        }
    }

    /// One uplink message received at `rx_s`.
    pub fn uplink(&mut self, rx_s: f64, msg: &Uplink) -> Step {
        let step = self.core.offer(msg, rx_s, &mut |_| {});
        let fused = step.fusions.into_iter().find_map(|f| f.result.ok());
        Step { fused, estimates: step.estimates }
    }
}

fn key(e: &Estimate) -> (String, u64) {
    (e.source.to_string(), e.stamp_s.to_bits())
}

/// Replay `input` with `setup` (the server's configuration, parameters, map, robots and seed, as
/// for `amr server`) in `configuration` (default: the setup's), write the result to `output` (if
/// given: the replayed uplink, fused frames, estimates and their Foxglove views), and compare
/// with the recorded estimates.
pub fn run(
    input: &Path,
    output: Option<&Path>,
    setup: &ServerSetup,
    configuration: Option<Configuration>,
) -> Result<ReplayReport, ReplayError> {
    let bytes =
        std::fs::read(input).map_err(|source| ReadError::Io { path: input.display().to_string(), source })?;
    let recording = read_bytes(&bytes)?;
    let recorded_meta = metadata(&bytes).remove("amr").unwrap_or_default();
    let mut engine = Engine::new(setup, configuration);
    let mut report = ReplayReport {
        configuration: Some(engine.configuration),
        truncated: recording.stopped.is_some(),
        ..Default::default()
    };
    let mut out = match output {
        Some(p) => {
            let mut meta = recorded_meta.clone();
            meta.insert("replay_of".into(), input.display().to_string());
            meta.insert("configuration".into(), format!("{:?}", engine.configuration));
            Some(FileRecorder::create(p, engine.robots().to_vec(), meta)?)
        }
        None => None,
    };
    let mut recorded: BTreeMap<(String, u64), VecDeque<Vec<u8>>> = BTreeMap::new();
    let mut recorded_fused: BTreeMap<u64, Vec<u8>> = BTreeMap::new();
    let mut produced: Vec<Estimate> = Vec::new();
    let mut produced_fused: Vec<FusedRecord> = Vec::new();
    let write = |now_s: f64, ev: Event, out: &mut Option<FileRecorder>| -> Result<(), ReplayError> {
        if let Some(f) = out {
            f.put(now_s, &ev)?;
        }
        Ok(())
    };
    let mut saw_uplink = false;
    for m in &recording.messages {
        match m.topic.as_str() {
            "/amr/uplink" => {
                saw_uplink = true;
                let r = wire::decode_uplink(&m.data)?;
                report.uplink += 1;
                if matches!(r.msg, Uplink::Scan(_)) {
                    report.scans += 1;
                }
                let step = engine.uplink(r.rx_s, &r.msg);
                write(r.rx_s, Event::Uplink(r.msg, r.rx_s), &mut out)?;
                if let Some(f) = step.fused {
                    produced_fused.push(FusedRecord::of(&f));
                    write(r.rx_s, Event::Fused(f), &mut out)?;
                }
                for e in step.estimates {
                    write(r.rx_s, Event::Estimate(e.clone()), &mut out)?;
                    produced.push(e);
                }
            }
            "/amr/status" => {
                let s = wire::decode_status(&m.data)?;
                engine.status(s);
                write(m.log_time_ns as f64 * 1e-9, Event::Status(s), &mut out)?;
            }
            "/amr/estimates" => {
                let e = wire::decode_estimate(&m.data)?;
                recorded.entry(key(&e)).or_default().push_back(wire::encode_estimate(&e)?);
                report.recorded_estimates += 1;
            }
            "/amr/fused" => {
                let f = wire::decode_fused(&m.data)?;
                report.recorded_fused += 1;
                recorded_fused.insert(f.seq, m.data.clone());
            }
            _ => {}
        }
    }
    if !saw_uplink {
        return Err(ReplayError::NoUplink);
    }
    compare(&mut report, &produced, recorded, &produced_fused, &recorded_fused)?;
    if let Some(f) = out {
        f.finish()?;
    }
    Ok(report)
}

/// The replayed estimates and fused frames against the recorded ones, byte for byte.
fn compare(
    report: &mut ReplayReport,
    produced: &[Estimate],
    mut recorded: BTreeMap<(String, u64), VecDeque<Vec<u8>>>,
    produced_fused: &[FusedRecord],
    recorded_fused: &BTreeMap<u64, Vec<u8>>,
) -> Result<(), ReplayError> {
    report.fused = produced_fused.len();
    report.fused_identical = produced_fused
        .iter()
        .filter(|f| recorded_fused.get(&f.seq).is_some_and(|r| wire::encode_fused(f).is_ok_and(|b| b == *r)))
        .count();
    report.estimates = produced.len();
    for e in produced {
        let bytes = wire::encode_estimate(e)?;
        match recorded.get_mut(&key(e)).and_then(VecDeque::pop_front) {
            Some(r) => {
                report.compared += 1;
                if r == bytes {
                    report.identical += 1;
                } else if report.first_difference.is_none() {
                    report.first_difference = Some(format!(
                        "recorded {} / replayed {}",
                        String::from_utf8_lossy(&r),
                        String::from_utf8_lossy(&bytes)
                    ));
                }
            }
            None => report.extra += 1,
        }
    }
    report.missing = recorded.values().map(VecDeque::len).sum();
    Ok(())
}
