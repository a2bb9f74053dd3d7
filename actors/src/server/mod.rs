//! The fusion server's actor tree (docs/architecture.md, "The server's actor tree"):
//!
//! ```text
//! server          one-for-one
//! ├── localizer   LocalizerActor  (the sans-IO ServerCore: sync gate, Virtual-AMR pipeline in
//! │                                T1–T4, per-robot AMCL, AMCL on the virtual scan)
//! └── formation   FormationActor  (reference → per-robot (v, ω), Eq. 20; arming, hold/stop)
//! ```
//!
//! Everything the robots send arrives on [`ServerPorts::uplink`], stamped once with the time it
//! came off the link; commands leave through the link's [`DownlinkSender`].

pub mod core;
pub mod formation;
pub mod localizer;
pub mod ports;
pub mod progress;

use std::sync::Arc;
use std::time::Duration;

use crate::config::RobotConfig;
use amr_core::amcl::LikelihoodField;
use amr_core::config::{AmclParams, Configuration, ScenarioConfig, ServerConfig, VamrParams};
use amr_core::formation::{FormationGains, slots};
use amr_core::map::OccupancyGrid;
use amr_core::plan::reference;
use ractor::{Actor, ActorRef, OutputPort};

use self::core::{CoreSetup, Member};
use crate::clock::FleetClock;
use crate::link::{DownlinkSender, ServerEnd};
use crate::robot::TIM551_RANGE_M;
use crate::robot::ports::AbortOnDrop;
use crate::supervisor::{
    ChildSpec, EventLog, RestartPolicy, Strategy, Supervisor, SupervisorMsg, SupervisorSpec,
};
use amr_msgs::Downlink;
use formation::{FormationActor, FormationMsg, FormationParams, FormationStatus};
use localizer::{LocalizerActor, LocalizerMsg};
use ports::ServerPorts;

/// Control period of the formation, s.
pub(crate) const FORMATION_PERIOD_S: f64 = 0.05;
/// A robot whose scans stop for this long is lost, s (about 7 scan periods at 15 Hz).
pub(crate) const LOST_AFTER_S: f64 = 0.5;

/// Run CPU-heavy work (a pipeline update, an AMCL update) without stalling the runtime's other
/// tasks — in a simulation the robots' safety loops share it: on a multi-thread runtime the worker
/// hands its queued tasks to the others first.
pub(crate) fn compute<R>(f: impl FnOnce() -> R) -> R {
    match tokio::runtime::Handle::try_current().map(|h| h.runtime_flavor()) {
        Ok(tokio::runtime::RuntimeFlavor::MultiThread) => tokio::task::block_in_place(f),
        _ => f(),
    }
}

/// Whether the formation arms by itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AutoArm {
    /// Only on the operator's `rearm`.
    Off,
    /// Once per server run, as soon as ready, if every robot reports mock devices (a simulation).
    Mock,
    /// Once per server run, as soon as ready, whatever the robots drive (the operator said so).
    Hardware,
}

/// Everything the server needs.
#[derive(Debug, Clone)]
pub struct ServerSetup {
    pub server: ServerConfig,
    pub vamr: VamrParams,
    pub amcl: AmclParams,
    pub map: OccupancyGrid,
    /// The formation's robots, in the server's order.
    pub robots: Vec<RobotConfig>,
    /// V's plan and where the formation starts.
    pub scenario: ScenarioConfig,
    pub seed: u64,
    /// Arm by itself once as soon as ready, or wait for the operator.
    pub auto_arm: AutoArm,
    pub policy: RestartPolicy,
    /// Where the formation keeps its progress in the plan (shared by the servers that follow
    /// this one: a restarted server resumes there, never later).
    pub progress: Arc<progress::PlanProgress>,
}

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("server.toml lists robot `{0}` but no robot file has that id")]
    UnknownRobot(String),
    #[error("the server supervisor did not start: {0}")]
    Spawn(#[from] ractor::SpawnErr),
}

/// A running server.
#[derive(Debug)]
pub struct ServerTree {
    pub supervisor: ActorRef<SupervisorMsg>,
    pub ports: Arc<ServerPorts>,
    pub events: EventLog,
    pub formation: Arc<OutputPort<FormationStatus>>,
    /// The link to the robots, for the operator's e-stop (which does not go through the actors).
    down: DownlinkSender,
    join: tokio::task::JoinHandle<()>,
    _pump: AbortOnDrop<()>,
}

impl ServerTree {
    /// The running formation actor, if any.
    pub async fn formation_actor(&self) -> Option<ActorRef<FormationMsg>> {
        let children = ractor::call!(self.supervisor, SupervisorMsg::Children).ok()?;
        children.into_iter().find(|c| c.name == "formation").and_then(|c| c.cell).map(ActorRef::from)
    }

    /// The formation's status now.
    pub async fn formation_status(&self) -> Option<FormationStatus> {
        let f = self.formation_actor().await?;
        ractor::call!(f, FormationMsg::Status).ok()
    }

    /// The running localizer actor, if any.
    pub async fn localizer_actor(&self) -> Option<ActorRef<LocalizerMsg>> {
        let children = ractor::call!(self.supervisor, SupervisorMsg::Children).ok()?;
        children.into_iter().find(|c| c.name == "localizer").and_then(|c| c.cell).map(ActorRef::from)
    }

    /// Crash (a drill): every actor of the tree is killed at once, as if the process died — no
    /// orderly stop, nothing more is sent — and nothing more is taken from the link.
    pub fn crash(&self) {
        self.supervisor.kill();
        self._pump.0.abort();
    }

    /// Whether the tree is still running.
    #[must_use]
    pub fn is_running(&self) -> bool {
        !self.join.is_finished()
    }

    /// A handle for inputs from outside (ROS 2's `/initialpose` and `/cmd_vel`), to move into a
    /// task: it finds the running localizer and formation each time (they may have restarted).
    #[must_use]
    pub fn control(&self) -> ServerControl {
        ServerControl { supervisor: self.supervisor.clone() }
    }

    /// Allow the formation to (re)start.
    pub async fn rearm(&self) -> bool {
        self.formation_actor().await.is_some_and(|f| f.cast(FormationMsg::Rearm).is_ok())
    }

    /// The operator's e-stop: [`Downlink::EStop`] to every robot straight onto the link (not through
    /// the formation actor, which may be busy or restarting), then the formation stopped. Returns
    /// the robots whose queue refused it (full or closed): the caller must say so.
    pub async fn estop_all(&self) -> Vec<String> {
        let refused = self.to_all(Downlink::EStop);
        if let Some(f) = self.formation_actor().await {
            let _ = f.cast(FormationMsg::Stop);
        }
        refused
    }

    /// Clear every robot's e-stop latch ([`Downlink::ResetEStop`]); they stay disarmed until a
    /// re-arm. Returns the robots whose queue refused it.
    #[must_use]
    pub fn reset_estop_all(&self) -> Vec<String> {
        self.to_all(Downlink::ResetEStop)
    }

    fn to_all(&self, msg: Downlink) -> Vec<String> {
        self.down.robots().filter(|r| !self.down.send(r, msg)).map(str::to_owned).collect()
    }

    /// Orderly shutdown, bounded in time.
    pub async fn shutdown(self) {
        self.supervisor.stop(Some("shutdown".into()));
        let _ = tokio::time::timeout(Duration::from_secs(5), self.join).await;
    }
}

/// Inputs to a running server from outside ([`ServerTree::control`]).
#[derive(Debug, Clone)]
pub struct ServerControl {
    supervisor: ActorRef<SupervisorMsg>,
}

impl ServerControl {
    async fn child<M: ractor::Message>(&self, name: &str) -> Option<ActorRef<M>> {
        let children = ractor::call!(self.supervisor, SupervisorMsg::Children).ok()?;
        children.into_iter().find(|c| c.name == name).and_then(|c| c.cell).map(ActorRef::from)
    }

    /// An operator's pose for V: the localizer's filters start again around it
    /// ([`core::ServerCore::set_initial_pose`]). Whether a localizer took it.
    pub async fn initial_pose(&self, v: amr_core::se2::Se2, std_xy_m: f64, std_yaw_rad: f64) -> bool {
        self.child::<LocalizerMsg>("localizer")
            .await
            .is_some_and(|l| l.cast(LocalizerMsg::InitialPose { v, std_xy_m, std_yaw_rad }).is_ok())
    }

    /// A twist for V ([`FormationMsg::Twist`]). Whether a formation took it.
    pub async fn twist(&self, v_mps: f64, w_radps: f64) -> bool {
        self.child::<FormationMsg>("formation")
            .await
            .is_some_and(|f| f.cast(FormationMsg::Twist { v_mps, w_radps }).is_ok())
    }
}

/// Order `all` as the server's formation lists them.
pub fn formation_robots(server: &ServerConfig, all: &[RobotConfig]) -> Result<Vec<RobotConfig>, ServerError> {
    server
        .robots
        .iter()
        .map(|m| {
            all.iter()
                .find(|r| r.id == m.id)
                .cloned()
                .ok_or_else(|| ServerError::UnknownRobot(m.id.as_str().to_owned()))
        })
        .collect()
}

/// The server core of `setup`, running `configurations` side by side (the server runs its
/// configured one): what the localizer actor runs, and what a replay of its input must run.
#[must_use]
pub fn core_setup(setup: &ServerSetup, configurations: &[Configuration]) -> CoreSetup {
    let slot_y = slots(setup.robots.len(), setup.scenario.spacing_m.get());
    let members = setup
        .robots
        .iter()
        .zip(&slot_y)
        .zip(&setup.server.robots)
        .map(|((r, y), m)| Member {
            id: r.id.as_str().to_owned(),
            lidar_to_base: r.lidar_mount.to_se2(),
            chassis: r.chassis.outline_m.clone(),
            weight: m.weight.get(),
            slot_y_m: *y,
        })
        .collect();
    let s = &setup.server.sync;
    CoreSetup {
        members,
        configurations: configurations.to_vec(),
        vamr: setup.vamr.clone(),
        max_spread_s: f64::from(s.max_stamp_spread_ms.ms()) / 1000.0,
        max_age_s: f64::from(s.max_age_ms.ms()) / 1000.0,
        amcl: setup.amcl.clone(),
        field: Arc::new(LikelihoodField::new(&setup.map, &setup.amcl, TIM551_RANGE_M.1)),
        initial_v: setup.amcl.initial_pose.map_or(setup.scenario.start_pose(), |p| p.pose()),
        seed: setup.seed,
        oracle: amr_core::vamr::pipeline::Oracle::default(),
        checks: setup.server.integrity,
    }
}

/// Start the server tree on `link`.
pub async fn start_server(
    setup: ServerSetup,
    link: ServerEnd,
    clock: FleetClock,
) -> Result<ServerTree, ServerError> {
    let ids: Vec<String> = setup.robots.iter().map(|r| r.id.as_str().to_owned()).collect();
    let ports = ServerPorts::with_scans(ids, clock, link.scans.clone());
    let events = EventLog::default();
    let formation_status = Arc::new(OutputPort::<FormationStatus>::default());
    let sc = &setup.scenario;
    let slot_y = slots(setup.robots.len(), sc.spacing_m.get());
    let localizer = LocalizerActor {
        ports: Arc::clone(&ports),
        setup: core_setup(&setup, &[setup.server.configuration]),
        lost_after_s: LOST_AFTER_S,
    };
    let plan = reference(sc, setup.robots.len(), FORMATION_PERIOD_S);
    // Once per server run: a restarted formation actor does not arm by itself again.
    let auto_armed = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let formation = FormationActor {
        ports: Arc::clone(&ports),
        params: FormationParams {
            plan_id: progress::plan_id(&plan),
            progress: Arc::clone(&setup.progress),
            plan: Arc::new(plan),
            period_s: FORMATION_PERIOD_S,
            slots: slot_y,
            gains: FormationGains::DEFAULT,
            limits: sc.limits,
            on_robot_lost: setup.server.on_robot_lost,
            auto_arm: setup.auto_arm,
            auto_armed: Arc::clone(&auto_armed),
        },
        link: link.down.clone(),
        status: Arc::clone(&formation_status),
    };
    let spec = SupervisorSpec {
        name: "server".into(),
        strategy: Strategy::OneForOne,
        policy: setup.policy,
        children: vec![
            ChildSpec::new("localizer", move || (localizer.clone(), ())),
            ChildSpec::new("formation", move || (formation.clone(), ())),
        ],
        events: events.clone(),
    };
    let (supervisor, join) = Supervisor::spawn(None, Supervisor, spec).await?;
    let mut up = link.up;
    let p = Arc::clone(&ports);
    let pump = tokio::spawn(async move {
        while let Some(msg) = up.recv().await {
            p.uplink.send((msg, p.clock.now_s()));
        }
    });
    let join = tokio::spawn(async move {
        let _ = join.await;
    });
    Ok(ServerTree {
        supervisor,
        ports,
        events,
        formation: formation_status,
        down: link.down.clone(),
        join,
        _pump: AbortOnDrop(pump),
    })
}
