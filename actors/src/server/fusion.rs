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
    core: FusionCore,
}

/// The fusion without its actor, sans-IO: scans in, fused frames out. The actor drives it with the
/// uplink port and its clock; `amr replay` drives it with a recording, so both run the same code.
#[derive(Debug)]
pub struct FusionCore {
    members: Vec<Member>,
    pipeline: Pipeline,
    configuration: Configuration,
    /// Per robot: recent scans with their arrival time.
    scans: Vec<VecDeque<(ScanMsg, f64)>>,
    /// Per robot: stamp of its last fused scan.
    fused_stamp: Vec<f64>,
    lost: Vec<bool>,
    seq: u64,
}

/// What one scan did.
#[derive(Debug, Default)]
pub struct Offered {
    /// The robot had been lost and is back (its track is re-acquired with the full heading search);
    /// the flag: no robot is lost any more.
    pub back: Option<bool>,
    /// The fusion it led to, if a set of unfused scans was complete.
    pub fused: Option<Result<FusedFrame, UpdateError>>,
    /// The fusion needed the full heading search.
    pub full_search: bool,
}

impl FusionCore {
    #[must_use]
    pub fn new(members: Vec<Member>, params: &FusionParams) -> Self {
        let mut pipeline = Pipeline::new(
            members.len(),
            params.vamr.clone(),
            params.configuration,
            params.max_spread_s,
            params.max_age_s,
        );
        let y0 = members.first().map_or(0.0, |m| m.slot_y_m);
        for (i, m) in members.iter().enumerate().skip(1) {
            pipeline.set_expected(i, [0.0, m.slot_y_m - y0], 0.5);
        }
        let n = members.len();
        FusionCore {
            members,
            pipeline,
            configuration: params.configuration,
            scans: vec![VecDeque::new(); n],
            fused_stamp: vec![f64::NEG_INFINITY; n],
            lost: vec![false; n],
            seq: 0,
        }
    }

    #[must_use]
    pub fn members(&self) -> &[Member] {
        &self.members
    }

    #[must_use]
    pub fn configuration(&self) -> Configuration {
        self.configuration
    }

    /// Switch T1–T4.
    pub fn set_configuration(&mut self, c: Configuration) {
        self.configuration = c;
        self.pipeline.set_configuration(c);
    }

    /// Robot `i`'s scan, received at `rx_s`. `corrections`: each robot's map ← odometry from its
    /// own AMCL (T1–T3); `now_s`: the clock when fusing (the acquisition time); `lap`: called at
    /// the end of each pipeline stage (for timings).
    pub fn offer(
        &mut self,
        i: usize,
        s: ScanMsg,
        rx_s: f64,
        corrections: &[Option<Se2>],
        now_s: f64,
        lap: &mut dyn FnMut(Stage),
    ) -> Offered {
        let mut out = Offered::default();
        let Some(buf) = self.scans.get_mut(i) else { return out };
        if buf.back().is_some_and(|(b, _)| b.stamp_s >= s.stamp_s) {
            // Time went backwards or a duplicate: dropped.
            return out;
        }
        buf.push_back((s, rx_s));
        while buf.len() > BUFFER {
            buf.pop_front();
        }
        if self.lost[i] {
            self.lost[i] = false;
            if i > 0 {
                self.pipeline.reset_robot(i);
            } else {
                for k in 1..self.members.len() {
                    self.pipeline.reset_robot(k);
                }
            }
            out.back = Some(!self.lost.iter().any(|l| *l));
        }
        if let Some(set) = self.pick(i) {
            let (fused, full) = self.fuse(&set, corrections, now_s, lap);
            out.fused = Some(fused);
            out.full_search = full;
        }
        out
    }

    /// Robots whose last scan arrived more than `lost_after_s` before `now_s`: the ones newly lost.
    pub fn check_lost(&mut self, now_s: f64, lost_after_s: f64) -> Vec<usize> {
        let mut newly = Vec::new();
        for i in 0..self.members.len() {
            let last = self.scans[i].back().map(|(_, rx)| *rx);
            if last.is_some_and(|t| now_s - t > lost_after_s) && !self.lost[i] {
                self.lost[i] = true;
                newly.push(i);
            }
        }
        newly
    }

    /// Robot `i` is lost (as a recording says).
    pub fn mark_lost(&mut self, i: usize) {
        if let Some(l) = self.lost.get_mut(i) {
            *l = true;
        }
    }

    /// Choose one unfused scan per robot, closest in time to robot `from`'s newest.
    fn pick(&self, from: usize) -> Option<Vec<(ScanMsg, f64)>> {
        let t = self.scans.get(from)?.back()?.0.stamp_s;
        let mut set = Vec::with_capacity(self.members.len());
        for (i, buf) in self.scans.iter().enumerate() {
            let best = buf
                .iter()
                .filter(|(s, _)| s.stamp_s > self.fused_stamp[i])
                .min_by(|a, b| (a.0.stamp_s - t).abs().total_cmp(&(b.0.stamp_s - t).abs()))?;
            set.push(best.clone());
        }
        Some(set)
    }

    fn fuse(
        &mut self,
        set: &[(ScanMsg, f64)],
        corrections: &[Option<Se2>],
        now_s: f64,
        lap: &mut dyn FnMut(Stage),
    ) -> (Result<FusedFrame, UpdateError>, bool) {
        let oldest = set.iter().map(|(s, _)| s.stamp_s).fold(f64::INFINITY, f64::min);
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
        let result = self.pipeline.update_with_laps(&packets, lap);
        for (i, (s, _)) in set.iter().enumerate() {
            self.fused_stamp[i] = s.stamp_s;
        }
        let u = match result {
            Ok(u) => u,
            Err(e) => return (Err(e), false),
        };
        self.seq += 1;
        let full = u.pairs.iter().any(|p| p.heading_source == Source::FullSearch);
        let points = u
            .virtual_scan
            .as_ref()
            .map(|v| Arc::new(v.points.iter().map(|(p, _)| *p).collect::<Vec<[f64; 2]>>()));
        let (first, first_odom) = set.first().map_or((oldest, Se2::IDENTITY), |(s, _)| (s.stamp_s, s.odom));
        let frame = FusedFrame {
            seq: self.seq,
            configuration: self.configuration,
            stamp_s: first,
            oldest_stamp_s: oldest,
            v_odom: first_odom * u.v_in_reference,
            points,
            robots: u.bases_in_v.iter().zip(set).map(|(b, (s, _))| (*b, s.odom)).collect(),
            times: StageTimes { acquisition_sync_s: now_s - oldest, ..StageTimes::default() },
        };
        (Ok(frame), full)
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
        Ok(FusionState { core: FusionCore::new(self.members.clone(), &self.params) })
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
                let clock = &self.ports.clock;
                let rx = clock.now_s();
                let corrections = self.ports.corrections.borrow().clone();
                let mut times = StageTimes::default();
                let mut last = std::time::Instant::now();
                let core = &mut state.core;
                let offered = super::compute(|| {
                    core.offer(i, *s, rx, &corrections, clock.now_s(), &mut |stage| {
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
                if let Some(all_back) = offered.back {
                    tracing::info!(robot = i, "fusion: robot back, re-acquiring");
                    ServerStats::add(&self.ports.stats.robots_back);
                    if all_back {
                        self.ports.status.send(FusionStatus::Fusing);
                    }
                }
                match offered.fused {
                    Some(Ok(mut frame)) => {
                        ServerStats::add(&self.ports.stats.fused);
                        if offered.full_search {
                            ServerStats::add(&self.ports.stats.full_searches);
                        }
                        frame.times =
                            StageTimes { acquisition_sync_s: frame.times.acquisition_sync_s, ..times };
                        self.ports.fused.send(frame);
                    }
                    Some(Err(UpdateError::Sync(f))) => {
                        ServerStats::add(&self.ports.stats.gate_failures);
                        tracing::debug!(failure = ?f, "fusion: sync gate");
                    }
                    Some(Err(e)) => tracing::debug!(error = %e, "fusion: no fused measurement"),
                    None => {}
                }
            }
            FusionMsg::Tick => {
                let now = self.ports.clock.now_s();
                for i in state.core.check_lost(now, self.params.lost_after_s) {
                    tracing::warn!(robot = %self.ports.robots[i], "fusion: scans stopped, robot lost");
                    ServerStats::add(&self.ports.stats.robots_lost);
                    self.ports.status.send(FusionStatus::RobotLost(i));
                }
            }
            FusionMsg::SetConfiguration(c) => state.core.set_configuration(c),
        }
        Ok(())
    }
}
