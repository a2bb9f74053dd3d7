//! AmclActor: one AMCL per robot on its own scan (T1, the T2/T3 relative poses, and the fallback
//! when fusion is impossible) and one on the virtual scan (T2–T4). It publishes each robot's
//! `T_odom^map` correction for the fusion actor and every estimate for the formation actor.

use std::sync::Arc;

use amr_core::amcl::{Amcl, LikelihoodField, scan_points};
use amr_core::config::{AmclParams, Configuration};
use amr_core::se2::Se2;
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::{Anchored, Estimate, EstimateSource, FusedFrame, ParticleCloud, ServerPorts, ServerStats};
use crate::messages::{ScanMsg, Uplink};

/// Spread of the initial particle clouds (a pose given by the operator or the scenario).
pub const INITIAL_STD_XY_M: f64 = 0.1;
pub const INITIAL_STD_YAW_RAD: f64 = 0.05;

/// Messages of the AMCL actor.
#[derive(Debug)]
pub enum AmclMsg {
    Scan(Box<ScanMsg>),
    Fused(Box<FusedFrame>),
    /// A drill: for `during` from now, every update first blocks the actor's worker thread for
    /// `each` (a stalled localisation). A deadline rather than an "end" message, which would queue
    /// behind the backlog the stall builds.
    InjectStall {
        each: std::time::Duration,
        during: std::time::Duration,
    },
}

/// The AMCL actor.
#[derive(Debug, Clone)]
pub struct AmclActor {
    pub ports: Arc<ServerPorts>,
    pub params: AmclParams,
    pub field: Arc<LikelihoodField>,
    /// Per robot: its LiDAR in its base frame.
    pub mounts: Vec<Se2>,
    /// Initial poses in the map: per robot, and V.
    pub initial_robots: Vec<Se2>,
    pub initial_v: Se2,
    pub seed: u64,
}

#[derive(Debug)]
pub struct AmclState {
    robots: Vec<Amcl>,
    virtual_filter: Amcl,
    /// The drill's stall per update, and until when.
    stall: Option<(std::time::Duration, std::time::Instant)>,
}

impl Actor for AmclActor {
    type Msg = AmclMsg;
    type State = AmclState;
    type Arguments = ();

    async fn pre_start(&self, myself: ActorRef<AmclMsg>, (): ()) -> Result<AmclState, ActorProcessingErr> {
        self.ports.uplink.subscribe(myself.clone(), |u| match u {
            Uplink::Scan(s) => Some(AmclMsg::Scan(Box::new(s))),
            _ => None,
        });
        self.ports.fused.subscribe(myself, |f| Some(AmclMsg::Fused(Box::new(f))));
        let filter = |k: u64, at: Se2| {
            let mut f = Amcl::new(self.params.clone(), Arc::clone(&self.field), self.seed.wrapping_add(k));
            f.init_pose(at, INITIAL_STD_XY_M, INITIAL_STD_YAW_RAD);
            f
        };
        let robots = self.initial_robots.iter().enumerate().map(|(i, p)| filter(1 + i as u64, *p)).collect();
        self.ports.corrections.send_replace(vec![None; self.initial_robots.len()]);
        Ok(AmclState { robots, virtual_filter: filter(0, self.initial_v), stall: None })
    }

    async fn handle(
        &self,
        _myself: ActorRef<AmclMsg>,
        msg: AmclMsg,
        state: &mut AmclState,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            AmclMsg::Scan(s) => {
                let Some(i) = self.ports.index(&s.robot) else { return Ok(()) };
                let (Some(filter), Some(mount)) = (state.robots.get_mut(i), self.mounts.get(i)) else {
                    return Ok(());
                };
                let points = scan_points(&s.scan, mount, &self.params);
                let stall = state.stall;
                let outcome = super::compute(|| {
                    stalled(stall);
                    filter.update(s.odom, &points, false)
                });
                if matches!(outcome, amr_core::amcl::UpdateOutcome::Updated { .. }) {
                    self.publish_particles(EstimateSource::Robot(i), s.stamp_s, filter);
                }
                if let Some(map) = filter.pose_at(&s.odom) {
                    self.ports.corrections.send_modify(|c| {
                        if let Some(slot) = c.get_mut(i) {
                            *slot = Some(map * s.odom.inverse());
                        }
                    });
                    if let Some(c) = self.ports.stats.own_estimates.get(i) {
                        ServerStats::add(c);
                    }
                    let mut robots = vec![None; self.mounts.len()];
                    robots[i] = Some(Anchored { map, odom: s.odom, stamp_s: s.stamp_s });
                    self.ports.estimates.send(Estimate {
                        source: EstimateSource::Robot(i),
                        stamp_s: s.stamp_s,
                        v: None,
                        robots,
                    });
                }
            }
            AmclMsg::Fused(f) => {
                let started = std::time::Instant::now();
                let mut ran = false;
                let v = match (&f.points, f.configuration) {
                    (Some(points), _) => {
                        let (filter, stall) = (&mut state.virtual_filter, state.stall);
                        let outcome = super::compute(|| {
                            stalled(stall);
                            filter.update(f.v_odom, points, false)
                        });
                        ran = matches!(outcome, amr_core::amcl::UpdateOutcome::Updated { .. });
                        if ran {
                            self.publish_particles(EstimateSource::Fused(f.configuration), f.stamp_s, filter);
                        }
                        state.virtual_filter.pose_at(&f.v_odom)
                    }
                    // T1: V from the reference robot's own AMCL (the relative poses came from AMCL).
                    (None, Configuration::T1) | (None, _) => {
                        let c = self.ports.corrections.borrow().first().copied().flatten();
                        c.map(|c| c * f.v_odom)
                    }
                };
                let mut times = f.times;
                times.amcl_s = ran.then(|| started.elapsed().as_secs_f64());
                if let Some(v) = v {
                    let robots = f
                        .robots
                        .iter()
                        .map(|(base_in_v, odom)| {
                            Some(Anchored { map: v * *base_in_v, odom: *odom, stamp_s: f.stamp_s })
                        })
                        .collect();
                    self.ports.estimates.send(Estimate {
                        source: EstimateSource::Fused(f.configuration),
                        stamp_s: f.stamp_s,
                        v: Some(v),
                        robots,
                    });
                    times.end_to_end_s = self.ports.clock.now_s() - f.oldest_stamp_s;
                    self.ports.latency.push(times);
                }
            }
            AmclMsg::InjectStall { each, during } => {
                tracing::warn!(
                    each_ms = each.as_millis(),
                    during_ms = during.as_millis(),
                    "amcl: drill stall"
                );
                state.stall = Some((each, std::time::Instant::now() + during));
            }
        }
        Ok(())
    }
}

impl AmclActor {
    fn publish_particles(&self, source: EstimateSource, stamp_s: f64, filter: &Amcl) {
        let poses = Arc::new(filter.particles().iter().map(|p| p.pose).collect());
        self.ports.particles.send(ParticleCloud { source, stamp_s, poses });
    }
}

/// Block the calling thread for a drill's stall (inside [`super::compute`], so on a multi-thread
/// runtime the worker hands its other tasks on first).
fn stalled(stall: Option<(std::time::Duration, std::time::Instant)>) {
    if let Some((each, until)) = stall
        && std::time::Instant::now() < until
    {
        std::thread::sleep(each);
    }
}
