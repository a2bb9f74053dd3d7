//! LocalizerActor: drives the server's [`ServerCore`] with the uplink and its clock. Each scan goes
//! through the core (the robot's own AMCL, the Virtual-AMR pipeline in the configured T1–T4, AMCL
//! on the virtual scan); the actor publishes what comes out — estimates, fused frames with their
//! stage times, particle clouds — and watches for robots whose scans stopped (lost) and came back.

use std::sync::Arc;
use std::time::{Duration, Instant};

use amr_core::vamr::pipeline::{Stage, UpdateError};
use amr_msgs::{EstimateSource, FusionStatus, ParticleCloud, StageTimes, Uplink};
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::core::{CoreSetup, Lap, ServerCore};
use super::ports::{ServerPorts, ServerStats};

/// Messages of the localizer actor.
#[derive(Debug)]
pub enum LocalizerMsg {
    /// Scans are waiting in [`ServerPorts::scans`].
    Scans,
    /// Check for lost robots.
    Tick,
    /// An operator's pose for V ([`ServerCore::set_initial_pose`]): V, and the spread, m and rad.
    InitialPose { v: amr_core::se2::Se2, std_xy_m: f64, std_yaw_rad: f64 },
    /// A drill: for `during` from now, every scan first costs the localizer `each` more (a
    /// stalled or slow localisation). A deadline rather than an "end" message, which would queue
    /// behind the backlog the stall builds.
    #[cfg(feature = "fault-injection")]
    InjectStall { each: Duration, during: Duration, how: Stall },
}

/// How a drill's stall costs the localizer its time.
#[cfg(feature = "fault-injection")]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stall {
    /// It blocks the actor's worker thread (a computation that hogs it): what the robots' safety
    /// loops must survive on the multi-thread runtime. Real time only.
    BlockThread,
    /// The actor waits before the scan, its mailbox queueing meanwhile (a localisation slower
    /// than the scans come, as on a loaded host): on virtual time as in real time.
    Wait,
}

/// The localizer actor.
#[derive(Debug, Clone)]
pub(crate) struct LocalizerActor {
    pub ports: Arc<ServerPorts>,
    pub setup: CoreSetup,
    /// A robot whose last scan is older than this is lost, s.
    pub lost_after_s: f64,
}

#[derive(Debug)]
pub(crate) struct LocalizerState {
    core: ServerCore,
    /// A [`LocalizerMsg::Scans`] is queued: the waker sends no other until it is handled, so the
    /// mailbox holds at most one however fast scans come.
    pending: Arc<std::sync::atomic::AtomicBool>,
    _waker: crate::robot::ports::AbortOnDrop<()>,
    /// The drill's stall per scan, until when, and how.
    #[cfg(feature = "fault-injection")]
    stall: Option<(Duration, tokio::time::Instant, Stall)>,
}

impl Actor for LocalizerActor {
    type Msg = LocalizerMsg;
    type State = LocalizerState;
    type Arguments = ();

    async fn pre_start(
        &self,
        myself: ActorRef<LocalizerMsg>,
        (): (),
    ) -> Result<LocalizerState, ActorProcessingErr> {
        let pending = Arc::new(std::sync::atomic::AtomicBool::new(true));
        let (slots, flag, me) = (self.ports.scans.clone(), Arc::clone(&pending), myself.clone());
        let waker = tokio::spawn(async move {
            loop {
                if !flag.swap(true, std::sync::atomic::Ordering::SeqCst)
                    && me.cast(LocalizerMsg::Scans).is_err()
                {
                    return;
                }
                slots.ready().await;
            }
        });
        // Whatever arrived while no localizer ran.
        myself.cast(LocalizerMsg::Scans)?;
        myself.send_interval(Duration::from_millis(100), || LocalizerMsg::Tick);
        Ok(LocalizerState {
            core: ServerCore::new(self.setup.clone()),
            pending,
            _waker: crate::robot::ports::AbortOnDrop(waker),
            #[cfg(feature = "fault-injection")]
            stall: None,
        })
    }

    async fn handle(
        &self,
        _myself: ActorRef<LocalizerMsg>,
        msg: LocalizerMsg,
        state: &mut LocalizerState,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            LocalizerMsg::Scans => {
                state.pending.store(false, std::sync::atomic::Ordering::SeqCst);
                for (scan, rx) in self.ports.scans.take(self.ports.clock.now_s()) {
                    #[cfg(feature = "fault-injection")]
                    if let Some((each, until, Stall::Wait)) = state.stall
                        && tokio::time::Instant::now() < until
                    {
                        tokio::time::sleep(each).await;
                    }
                    let u = Uplink::Scan(scan);
                    // For recorders and observers: the scans the localizer processed, in order.
                    self.ports.uplink.send((u.clone(), rx));
                    self.scan(state, &u, rx);
                }
            }
            LocalizerMsg::Tick => {
                let now = self.ports.clock.now_s();
                for i in state.core.check_lost(now, self.lost_after_s) {
                    tracing::warn!(robot = %self.ports.robots[i], "localizer: scans stopped, robot lost");
                    ServerStats::add(&self.ports.stats.robots_lost);
                    self.ports.status.send(FusionStatus::RobotLost(i));
                }
            }
            LocalizerMsg::InitialPose { v, std_xy_m, std_yaw_rad } => {
                if !state.core.set_initial_pose(v, std_xy_m, std_yaw_rad) {
                    tracing::warn!(
                        ?v,
                        std_xy_m,
                        std_yaw_rad,
                        "localizer: an initial pose that is not one, ignored"
                    );
                }
            }
            #[cfg(feature = "fault-injection")]
            LocalizerMsg::InjectStall { each, during, how } => {
                tracing::warn!(
                    each_ms = each.as_millis(),
                    during_ms = during.as_millis(),
                    ?how,
                    "localizer: drill stall"
                );
                state.stall = Some((each, tokio::time::Instant::now() + during, how));
            }
        }
        Ok(())
    }
}

impl LocalizerActor {
    /// One scan through the core, and what came out published.
    fn scan(&self, state: &mut LocalizerState, u: &Uplink, rx: f64) {
        #[cfg(feature = "fault-injection")]
        let stall = state.stall;
        let core = &mut state.core;
        let mut times = StageTimes::default();
        let mut amcl_s = 0.0;
        let mut last = Instant::now();
        let step = super::compute(|| {
            #[cfg(feature = "fault-injection")]
            if let Some((each, until, Stall::BlockThread)) = stall
                && tokio::time::Instant::now() < until
            {
                std::thread::sleep(each);
            }
            core.offer(u, rx, &mut |lap| {
                let now = Instant::now();
                let d = now.duration_since(last).as_secs_f64();
                last = now;
                match lap {
                    Lap::RobotAmcl => {}
                    Lap::Pipeline(_, Stage::Preprocess) => times.preprocess_s += d,
                    Lap::Pipeline(_, Stage::Tracking) => times.tracking_s += d,
                    Lap::Pipeline(_, Stage::Heading) => times.heading_s += d,
                    Lap::Pipeline(_, Stage::VirtualScan) => times.virtual_scan_s += d,
                    Lap::VirtualAmcl(_) => amcl_s += d,
                }
            })
        });
        if step.odometry_restarted {
            ServerStats::add(&self.ports.stats.odometry_restarts);
        }
        if let Some(why) = &step.refused {
            let n = self.ports.stats.refused.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            // The first few, then every 1000th: a robot sending garbage cannot flood the log.
            if n < 10 || n.is_multiple_of(1000) {
                tracing::warn!(robot = %u.robot(), kind = why.kind(), %why, refused = n + 1, "localizer: scan refused");
            }
        }
        self.publish(&state.core, step, times, amcl_s);
    }

    fn publish(&self, core: &ServerCore, step: super::core::Step, times: StageTimes, amcl_s: f64) {
        let ports = &self.ports;
        if let Some(all_back) = step.back {
            tracing::info!(robot = ?step.robot, "localizer: robot back, re-acquiring");
            ServerStats::add(&ports.stats.robots_back);
            if all_back {
                ports.status.send(FusionStatus::Fusing);
            }
        }
        for source in &step.updated {
            if let Some(f) = core.filter(*source) {
                // The stamp of the estimate the update gave.
                let stamp_s = step.estimates.iter().find(|e| e.source == *source).map_or(0.0, |e| e.stamp_s);
                let poses = Arc::new(f.particles().iter().map(|p| p.pose).collect());
                ports.particles.send(ParticleCloud { source: *source, stamp_s, poses });
            }
        }
        let mut fused_at = Vec::new();
        for fusion in step.fusions {
            match fusion.result {
                Ok(mut frame) => {
                    ServerStats::add(&ports.stats.fused);
                    if fusion.full_search {
                        ServerStats::add(&ports.stats.full_searches);
                    }
                    let ran = step.updated.contains(&EstimateSource::Fused(frame.configuration));
                    frame.times = StageTimes {
                        acquisition_sync_s: frame.times.acquisition_sync_s,
                        amcl_s: ran.then_some(amcl_s),
                        ..times
                    };
                    fused_at.push((frame.configuration, frame.oldest_stamp_s, frame.times));
                    ports.fused.send(frame);
                }
                Err(UpdateError::Sync(f)) => {
                    ServerStats::add(&ports.stats.gate_failures);
                    tracing::debug!(failure = ?f, "localizer: sync gate");
                }
                Err(e) => tracing::debug!(error = %e, "localizer: no fused measurement"),
            }
        }
        for e in step.estimates {
            match e.source {
                EstimateSource::Robot(i) => {
                    if let Some(c) = ports.stats.own_estimates.get(i) {
                        ServerStats::add(c);
                    }
                }
                EstimateSource::Fused(c) => {
                    if let Some((_, oldest, mut t)) = fused_at.iter().copied().find(|(k, _, _)| *k == c) {
                        t.end_to_end_s = ports.clock.now_s() - oldest;
                        ports.latency.push(t);
                    }
                }
            }
            ports.estimates.send(e);
        }
    }
}
