//! Replay: the server's fusion and AMCL re-run on a recording's exact uplink (`/amr/uplink`),
//! deterministically, with the recorded configuration or another T1–T4 and other parameters; the
//! result is a new recording and a comparison with the recorded estimates.
//!
//! The engine does what `FusionActor` and `AmclActor` (amr-actors `server::fusion`,
//! `server::amcl`) do, message by message, in one thread:
//! - each uplink scan goes first to that robot's own AMCL (its `T_odom^map` correction), then to
//!   the fusion (scan buffers of 3, pairing by stamp, the Virtual-AMR pipeline with the recorded
//!   receive time as `t_rx` of the sync gate), and a fused frame at once to AMCL on the virtual scan;
//! - a recorded `RobotLost` status marks the robot lost at its place in the stream (the fusion's
//!   100 ms tick is not replayed), and its next scan re-acquires it as the live fusion does;
//! - the filters are seeded as the live AMCL actor seeds them (`seed + k`: V 0, robot i 1 + i).
//!
//! Exactness. Every AMCL filter owns its generator and sees only its own inputs (robot i's
//! scans; the fused frames), in uplink order, so its estimates do not depend on how the live
//! actors interleaved. Two inputs of the live fusion are not on any port:
//! - the robots' AMCL corrections it reads where the configuration takes a relative pose from
//!   AMCL (T1–T3; and V itself in T1 from robot 0's correction): the live value depends on
//!   whether the fusion actor read it before or after the AMCL actor took the same scan. The
//!   replay takes "after" (what a virtual-time run does: the AMCL actor subscribes first);
//! - the sync gate's `t_rx`: the fusion actor's clock reading when it took the scan. The replay
//!   has the recorder's reading of the same moment. Equal in virtual time; in real time they
//!   differ by the scheduling delay, which matters only if the fusion actor fell so far behind
//!   that its age test (`max_age_ms`, 100 ms) decided otherwise.
//!
//! The tests check: in virtual time, every estimate and fused frame bit for bit in T1, T2, T3
//! and T4; in real time on two worker threads, T4 bit for bit (with the age test out of the way).
//! The report counts whatever differs. Both gaps close if the server stamps each uplink message
//! once (e.g. the uplink pump in `start_server` publishing `(t_rx, Uplink)`, which the fusion uses)
//! and the fusion publishes the corrections it used with each fused frame; the recorder would then
//! record those. A server tree restarted mid-run (a drill) starts its filters and tracks again:
//! the replay does not model restarts.
//! The live actors consume every message (unbounded mailboxes). A port subscription that lagged
//! (ractor's output ports skip the oldest of more than 10 messages queued for one subscriber)
//! would leave the recorder without messages the server had; nothing in the uplink's sequence
//! numbers shows it (the robots number every link message, decimated odometry too), but the
//! comparison does: estimates missing or extra.

use std::collections::{BTreeMap, VecDeque};
use std::path::Path;
use std::sync::Arc;

use amr_actors::mapping::TIM551_RANGE_M;
use amr_actors::messages::{ScanMsg, Uplink};
use amr_actors::server::amcl::{INITIAL_STD_XY_M, INITIAL_STD_YAW_RAD};
use amr_actors::server::fusion::FusionCore;
use amr_actors::server::ports::{Anchored, Estimate, EstimateSource, FusionStatus};
use amr_actors::server::{ServerSetup, fusion_setup};
use amr_core::amcl::{Amcl, LikelihoodField, scan_points};
use amr_core::config::{AmclParams, Configuration};
use amr_core::formation::slots;
use amr_core::se2::Se2;

use crate::encode::Event;
use crate::read::{ReadError, metadata, read_bytes};
use crate::recorder::{FileRecorder, RecordError};
use crate::wire::{self, FusedRecord, WireError};

/// Scans kept per robot for pairing (as the fusion actor).
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

/// The server's fusion and AMCL as one deterministic state machine: the fusion actor's own core
/// ([`FusionCore`]) and the AMCL actor's filters, fed in the recorded order.
pub struct Engine {
    robots: Vec<String>,
    fusion: FusionCore,
    configuration: Configuration,
    params: AmclParams,
    robot_filters: Vec<Amcl>,
    virtual_filter: Amcl,
    corrections: Vec<Option<Se2>>,
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Engine").field("robots", &self.robots).finish_non_exhaustive()
    }
}

/// What one input produced.
#[derive(Debug, Default)]
pub struct Step {
    pub fused: Option<FusedRecord>,
    pub estimates: Vec<Estimate>,
}

impl Engine {
    /// The server of `setup` (as `amr_actors::server::start_server` builds it), in `configuration`
    /// if given, else the setup's.
    #[must_use]
    pub fn new(setup: &ServerSetup, configuration: Option<Configuration>) -> Self {
        let (members, params) = fusion_setup(setup, configuration);
        let configuration = params.configuration;
        let sc = &setup.scenario;
        let slot_y = slots(setup.robots.len(), sc.spacing_m.get());
        let field = Arc::new(LikelihoodField::new(&setup.map, &setup.amcl, TIM551_RANGE_M.1));
        let initial_v = setup.amcl.initial_pose.map_or(sc.start_pose(), |p| p.pose());
        let filter = |k: u64, at: Se2| {
            let mut f = Amcl::new(setup.amcl.clone(), Arc::clone(&field), setup.seed.wrapping_add(k));
            f.init_pose(at, INITIAL_STD_XY_M, INITIAL_STD_YAW_RAD);
            f
        };
        let robot_filters = slot_y
            .iter()
            .enumerate()
            .map(|(i, y)| filter(1 + i as u64, initial_v * Se2::new(0.0, *y, 0.0)))
            .collect();
        let n = members.len();
        Engine {
            robots: setup.robots.iter().map(|r| r.id.as_str().to_owned()).collect(),
            fusion: FusionCore::new(members, &params),
            configuration,
            params: setup.amcl.clone(),
            robot_filters,
            virtual_filter: filter(0, initial_v),
            corrections: vec![None; n],
        }
    }

    /// Robot ids in formation order.
    #[must_use]
    pub fn robots(&self) -> &[String] {
        &self.robots
    }

    /// A fusion status change seen in the recording.
    pub fn status(&mut self, s: FusionStatus) {
        if let FusionStatus::RobotLost(i) = s {
            self.fusion.mark_lost(i);
        }
    }

    /// One uplink message received at `rx_s`.
    pub fn uplink(&mut self, rx_s: f64, msg: &Uplink) -> Step {
        let mut step = Step::default();
        let Uplink::Scan(s) = msg else { return step };
        let Some(i) = self.robots.iter().position(|r| *r == s.robot) else { return step };
        if let Some(e) = self.robot_amcl(i, s) {
            step.estimates.push(e);
        }
        if let Some(f) = self.fusion(i, s, rx_s) {
            if let Some(e) = self.virtual_amcl(&f) {
                step.estimates.push(e);
            }
            step.fused = Some(f);
        }
        step
    }

    /// `AmclActor`, `AmclMsg::Scan`.
    fn robot_amcl(&mut self, i: usize, s: &ScanMsg) -> Option<Estimate> {
        let (filter, mount) = (self.robot_filters.get_mut(i)?, self.fusion.members().get(i)?.lidar_to_base);
        let points = scan_points(&s.scan, &mount, &self.params);
        filter.update(s.odom, &points, false);
        let map = filter.pose_at(&s.odom)?;
        if let Some(c) = self.corrections.get_mut(i) {
            *c = Some(map * s.odom.inverse());
        }
        let mut robots = vec![None; self.robots.len()];
        robots[i] = Some(Anchored { map, odom: s.odom, stamp_s: s.stamp_s });
        Some(Estimate { source: EstimateSource::Robot(i), stamp_s: s.stamp_s, v: None, robots })
    }

    /// `AmclActor`, `AmclMsg::Fused`.
    fn virtual_amcl(&mut self, f: &FusedRecord) -> Option<Estimate> {
        let v = match &f.points {
            Some(points) => {
                self.virtual_filter.update(f.v_odom, points, false);
                self.virtual_filter.pose_at(&f.v_odom)
            }
            None => self.corrections.first().copied().flatten().map(|c| c * f.v_odom),
        }?;
        let robots = f
            .robots
            .iter()
            .map(|(base_in_v, odom)| Some(Anchored { map: v * *base_in_v, odom: *odom, stamp_s: f.stamp_s }))
            .collect();
        Some(Estimate {
            source: EstimateSource::Fused(f.configuration),
            stamp_s: f.stamp_s,
            v: Some(v),
            robots,
        })
    }

    /// `FusionActor`, `FusionMsg::Scan`: the same core, with the recorded receive time (which is
    /// also the acquisition time's clock reading: only timings, not estimates, depend on it).
    fn fusion(&mut self, i: usize, s: &ScanMsg, rx_s: f64) -> Option<FusedRecord> {
        let offered = self.fusion.offer(i, s.clone(), rx_s, &self.corrections, rx_s, &mut |_| {});
        offered.fused?.ok().map(|f| FusedRecord::of(&f))
    }
}

fn key(e: &Estimate) -> (String, u64) {
    (wire::source_name(e.source), e.stamp_s.to_bits())
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
            meta.insert("configuration".into(), wire::configuration_name(engine.configuration).to_owned());
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
                write(r.rx_s, Event::Uplink(r.msg), &mut out)?;
                if let Some(f) = step.fused {
                    write(r.rx_s, Event::Fused(f.clone()), &mut out)?;
                    produced_fused.push(f);
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
    report.fused = produced_fused.len();
    report.fused_identical = produced_fused
        .iter()
        .filter(|f| recorded_fused.get(&f.seq).is_some_and(|r| wire::encode_fused(f).is_ok_and(|b| b == *r)))
        .count();
    report.estimates = produced.len();
    for e in &produced {
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
    if let Some(f) = out {
        f.finish()?;
    }
    Ok(report)
}
