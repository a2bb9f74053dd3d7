//! FusionActor: pairs the robots' scans (sync gate, Eq. 15), runs the Virtual-AMR pipeline in the
//! configured T1–T4 mode and hands the fused frame to the AMCL actor. It watches each robot's
//! scans: when one stops, it reports the robot lost (the others are localised on their own); when
//! it returns, its track is re-acquired with the full heading search.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use amr_core::config::{Configuration, VamrParams};
use amr_core::geometry::Polygon;
use amr_core::se2::Se2;
use amr_core::vamr::frame::PacketTimes;
use amr_core::vamr::pipeline::{Pipeline, RobotPacket, Source, Stage, UpdateError};
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::{FusedFrame, FusionStatus, ServerPorts, ServerStats, StageTimes};
use crate::messages::{ScanMsg, Uplink};

/// Scans kept per robot for pairing.
const BUFFER: usize = 3;

/// One formation member as the fusion sees it.
#[derive(Debug, Clone)]
pub struct Member {
    pub lidar_to_base: Se2,
    pub chassis: Polygon,
    pub weight: f64,
    /// Its slot: lateral offset in V (for the expected search area).
    pub slot_y_m: f64,
}

/// Fusion settings.
#[derive(Debug, Clone)]
pub struct FusionParams {
    pub configuration: Configuration,
    pub vamr: VamrParams,
    pub max_spread_s: f64,
    pub max_age_s: f64,
    /// A robot whose last scan is older than this is lost.
    pub lost_after_s: f64,
}

/// Messages of the fusion actor.
#[derive(Debug)]
pub enum FusionMsg {
    Scan(Box<ScanMsg>),
    /// Check for lost robots.
    Tick,
    /// Switch T1–T4.
    SetConfiguration(Configuration),
}

/// The fusion actor.
#[derive(Debug, Clone)]
pub struct FusionActor {
    pub ports: Arc<ServerPorts>,
    pub members: Vec<Member>,
    pub params: FusionParams,
}

#[derive(Debug)]
pub struct FusionState {
    pipeline: Pipeline,
    configuration: Configuration,
    /// Per robot: recent scans with their arrival time.
    scans: Vec<VecDeque<(ScanMsg, f64)>>,
    /// Per robot: stamp of its last fused scan.
    fused_stamp: Vec<f64>,
    lost: Vec<bool>,
    seq: u64,
    gate_failures: u64,
}

impl FusionActor {
    /// Choose one unfused scan per robot, closest in time to robot `from`'s newest.
    fn pick(&self, state: &FusionState, from: usize) -> Option<Vec<(ScanMsg, f64)>> {
        let newest = state.scans[from].back()?;
        let t = newest.0.stamp_s;
        let mut set = Vec::with_capacity(self.members.len());
        for (i, buf) in state.scans.iter().enumerate() {
            let best = buf
                .iter()
                .filter(|(s, _)| s.stamp_s > state.fused_stamp[i])
                .min_by(|a, b| (a.0.stamp_s - t).abs().total_cmp(&(b.0.stamp_s - t).abs()))?;
            set.push(best.clone());
        }
        Some(set)
    }

    fn fuse(&self, state: &mut FusionState, set: &[(ScanMsg, f64)]) {
        let clock = &self.ports.clock;
        let oldest = set.iter().map(|(s, _)| s.stamp_s).fold(f64::INFINITY, f64::min);
        let corrections = self.ports.corrections.borrow().clone();
        let packets: Vec<RobotPacket<'_>> = set
            .iter()
            .zip(&self.members)
            .enumerate()
            .map(|(i, ((s, rx), m))| RobotPacket {
                scan: &s.scan,
                times: PacketTimes { stamp_s: s.stamp_s, received_s: *rx },
                lidar_to_base: m.lidar_to_base,
                chassis: &m.chassis,
                weight: m.weight,
                amcl_pose: corrections.get(i).copied().flatten().map(|c| c * s.odom),
            })
            .collect();
        let mut times = StageTimes { acquisition_sync_s: clock.now_s() - oldest, ..StageTimes::default() };
        let mut last = std::time::Instant::now();
        let pipeline = &mut state.pipeline;
        let result = super::compute(|| {
            pipeline.update_with_laps(&packets, &mut |stage| {
                let now = std::time::Instant::now();
                let d = now.duration_since(last).as_secs_f64();
                last = now;
                match stage {
                    Stage::Preprocess => times.preprocess_s += d,
                    Stage::Tracking => times.tracking_s += d,
                    Stage::Heading => times.heading_s += d,
                    Stage::VirtualScan => times.virtual_scan_s += d,
                }
            })
        });
        for (i, (s, _)) in set.iter().enumerate() {
            state.fused_stamp[i] = s.stamp_s;
        }
        match result {
            Ok(u) => {
                state.seq += 1;
                ServerStats::add(&self.ports.stats.fused);
                if u.pairs.iter().any(|p| p.heading_source == Source::FullSearch) {
                    ServerStats::add(&self.ports.stats.full_searches);
                }
                let points = u
                    .virtual_scan
                    .as_ref()
                    .map(|v| Arc::new(v.points.iter().map(|(p, _)| *p).collect::<Vec<[f64; 2]>>()));
                self.ports.fused.send(FusedFrame {
                    seq: state.seq,
                    configuration: state.configuration,
                    stamp_s: set[0].0.stamp_s,
                    oldest_stamp_s: oldest,
                    v_odom: set[0].0.odom * u.v_in_reference,
                    points,
                    robots: u.bases_in_v.iter().zip(set).map(|(b, (s, _))| (*b, s.odom)).collect(),
                    times,
                });
            }
            Err(UpdateError::Sync(f)) => {
                state.gate_failures += 1;
                ServerStats::add(&self.ports.stats.gate_failures);
                tracing::debug!(failure = ?f, "fusion: sync gate");
            }
            Err(e) => tracing::debug!(error = %e, "fusion: no fused measurement"),
        }
    }
}

impl Actor for FusionActor {
    type Msg = FusionMsg;
    type State = FusionState;
    type Arguments = ();

    async fn pre_start(
        &self,
        myself: ActorRef<FusionMsg>,
        (): (),
    ) -> Result<FusionState, ActorProcessingErr> {
        self.ports.uplink.subscribe(myself.clone(), |u| match u {
            Uplink::Scan(s) => Some(FusionMsg::Scan(Box::new(s))),
            _ => None,
        });
        myself.send_interval(Duration::from_millis(100), || FusionMsg::Tick);
        let p = &self.params;
        let mut pipeline =
            Pipeline::new(self.members.len(), p.vamr.clone(), p.configuration, p.max_spread_s, p.max_age_s);
        let y0 = self.members.first().map_or(0.0, |m| m.slot_y_m);
        for (i, m) in self.members.iter().enumerate().skip(1) {
            pipeline.set_expected(i, [0.0, m.slot_y_m - y0], 0.5);
        }
        let n = self.members.len();
        Ok(FusionState {
            pipeline,
            configuration: p.configuration,
            scans: vec![VecDeque::new(); n],
            fused_stamp: vec![f64::NEG_INFINITY; n],
            lost: vec![false; n],
            seq: 0,
            gate_failures: 0,
        })
    }

    async fn handle(
        &self,
        _myself: ActorRef<FusionMsg>,
        msg: FusionMsg,
        state: &mut FusionState,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            FusionMsg::Scan(s) => {
                let Some(i) = self.ports.index(&s.robot) else {
                    tracing::debug!(robot = %s.robot, "fusion: scan from a robot not in the formation");
                    return Ok(());
                };
                let rx = self.ports.clock.now_s();
                let buf = &mut state.scans[i];
                if buf.back().is_some_and(|(b, _)| b.stamp_s >= s.stamp_s) {
                    // Time went backwards or a duplicate: dropped.
                    return Ok(());
                }
                buf.push_back((*s, rx));
                while buf.len() > BUFFER {
                    buf.pop_front();
                }
                if state.lost[i] {
                    state.lost[i] = false;
                    if i > 0 {
                        state.pipeline.reset_robot(i);
                    } else {
                        for k in 1..self.members.len() {
                            state.pipeline.reset_robot(k);
                        }
                    }
                    tracing::info!(robot = i, "fusion: robot back, re-acquiring");
                    ServerStats::add(&self.ports.stats.robots_back);
                    if !state.lost.iter().any(|l| *l) {
                        self.ports.status.send(FusionStatus::Fusing);
                    }
                }
                if let Some(set) = self.pick(state, i) {
                    self.fuse(state, &set);
                }
            }
            FusionMsg::Tick => {
                let now = self.ports.clock.now_s();
                for i in 0..self.members.len() {
                    let last = state.scans[i].back().map(|(_, rx)| *rx);
                    let silent = last.is_some_and(|t| now - t > self.params.lost_after_s);
                    if silent && !state.lost[i] {
                        state.lost[i] = true;
                        tracing::warn!(robot = %self.ports.robots[i], "fusion: scans stopped, robot lost");
                        ServerStats::add(&self.ports.stats.robots_lost);
                        self.ports.status.send(FusionStatus::RobotLost(i));
                    }
                }
            }
            FusionMsg::SetConfiguration(c) => {
                state.configuration = c;
                state.pipeline.set_configuration(c);
            }
        }
        Ok(())
    }
}
