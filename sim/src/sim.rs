//! A running simulation: the world, the mock devices, the server and every robot of the server's
//! formation in one process, with its live status line and its report.

use std::sync::Arc;
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::config::{Config, RobotConfig};
use amr_actors::link::{LinkControl, RobotEnd, in_process};
use amr_actors::robot::ports::AbortOnDrop;
use amr_actors::robot::{RobotOptions, RobotTree, start_robot};
use amr_actors::server::formation::{FormationStatus, Phase};
use amr_actors::server::{ServerSetup, ServerTree, formation_robots, start_server};
use amr_actors::supervisor::RestartPolicy;
use amr_core::config::Configuration;
use amr_core::map::OccupancyGrid;
use amr_core::metrics::ErrorStats;
use amr_core::se2::Se2;
use amr_msgs::Health;
use hil_mocks::world::SharedWorld;
use ractor::ActorRef;
use tokio::time::{Instant, MissedTickBehavior};

use crate::mocks::{RobotMocks, start_mocks};
use crate::observer::{self, Observed, ObserverMsg, observe_server};
use crate::options::{SimCan, SimError, SimOptions};
use crate::report::{SimReport, latency_table};
use crate::survey;
use crate::truth::TruthLog;
use crate::world::{build_world, check_formation, site_for, v_of};
use crate::world_loop::spawn_world_loop;

/// A running simulation.
#[derive(Debug)]
pub struct Sim {
    pub clock: FleetClock,
    pub world: SharedWorld,
    pub truth: TruthLog,
    pub robots: Vec<RobotTree>,
    pub server: ServerTree,
    pub mocks: Vec<RobotMocks>,
    pub link: LinkControl,
    pub options: SimOptions,
    configuration: Configuration,
    /// How the server was started (a restarted one starts the same way).
    /// What the server was started with.
    pub setup: ServerSetup,
    observed: Arc<std::sync::Mutex<Observed>>,
    observer: ActorRef<ObserverMsg>,
    started: Instant,
    _tasks: Vec<AbortOnDrop<()>>,
}

impl Sim {
    /// Start the world, the mocks, the server and every robot of the server's formation.
    pub async fn start(config: &Config, options: SimOptions) -> Result<Sim, SimError> {
        let sc = &options.scenario;
        let (map_name, map) = scenario_map(config, &options)?;
        let robots = formation_robots(&config.server, &config.robots)?;
        let site = site_for(&map_name, &map)?;
        check_formation(&site, sc, &robots)?;
        let map = if options.surveyed_map {
            survey::surveyed_map(&site, &map, &survey::SurveyOptions::TYPICAL, options.seed)
        } else {
            map
        };
        let clock = FleetClock::start();
        let world = build_world(&robots, sc, site, &options.noise, options.seed)?;
        let truth = TruthLog::default();

        let mut mocks = Vec::new();
        for (i, r) in robots.iter().enumerate() {
            mocks.push(start_mocks(&world, i, r, &options.noise, options.seed, options.can).await?);
        }
        let world_task = spawn_world_loop(&world, &truth, clock, &robots, &mocks);

        // The link, the server, the robots.
        let ids: Vec<String> = robots.iter().map(|r| r.id.as_str().to_owned()).collect();
        let (server_end, robot_ends, link) = in_process(&ids);
        let setup = server_setup(config, &options, map, &robots);
        let configuration = setup.server.configuration;
        let server = start_server(setup.clone(), server_end, clock).await?;
        let trees = start_robots(&robots, robot_ends, &mocks, clock).await?;

        // The observer scores estimates and records health.
        let (observed, observer, health_task) = observer::start(&truth, &server, &trees).await?;

        Ok(Sim {
            clock,
            world,
            truth,
            robots: trees,
            server,
            mocks,
            link,
            configuration,
            setup,
            options,
            observed,
            observer,
            started: Instant::now(),
            _tasks: vec![world_task, AbortOnDrop(health_task)],
        })
    }

    /// The formation's latest status.
    #[must_use]
    pub fn formation(&self) -> Option<FormationStatus> {
        self.observed.lock().unwrap_or_else(std::sync::PoisonError::into_inner).formation.clone()
    }

    /// Every formation phase seen so far, in order (a phase repeated in a row once), across server
    /// restarts.
    #[must_use]
    pub fn phases(&self) -> Vec<Phase> {
        self.observed.lock().unwrap_or_else(std::sync::PoisonError::into_inner).phases.clone()
    }

    /// The latest fused estimate of V.
    #[must_use]
    pub fn last_v(&self) -> Option<Se2> {
        self.observed
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .last_fused
            .as_ref()
            .map(|f| f.0)
    }

    /// V now as the server last knew it: each robot's pose in the latest fused estimate carried
    /// forward by its odometry since (what a server that saved its last estimate can know).
    #[must_use]
    pub fn last_v_carried(&self) -> Option<Se2> {
        let o = self.observed.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let (_, anchored) = o.last_fused.as_ref()?;
        let poses: Option<Vec<Se2>> = self
            .robots
            .iter()
            .zip(anchored)
            .map(|(r, a)| {
                let a = (*a)?;
                let odom = o.odom.get(&r.id)?;
                Some(a.map * (a.odom.inverse() * *odom))
            })
            .collect();
        v_of(&poses?)
    }

    /// Crash the server (a drill): its whole tree is killed at once, nothing more is sent to the
    /// robots, nothing more is read from them. [`Sim::restart_server`] brings up a new one.
    pub fn crash_server(&self) {
        self.server.crash();
    }

    /// Start a new server on the same link, replacing the current one (crashed first if it still
    /// runs). It starts as the first did, except that it does not arm by itself (the operator
    /// re-arms, [`ServerTree::rearm`]) and its AMCL starts from the last fused estimate of V carried
    /// forward by the robots' odometry ([`Sim::last_v_carried`]), with the robots at their slots
    /// around it (the scenario's start pose when there is none): the robots are where the old
    /// server left them — and then coasted to a stop — not at the start. Its formation plan starts where
    /// V is (see the formation actor).
    pub async fn restart_server(&mut self) -> Result<(), SimError> {
        if self.server.is_running() {
            self.server.crash();
        }
        let end =
            self.link.new_server_end().ok_or(SimError::Site("the link cannot take a new server".into()))?;
        let mut setup = self.setup.clone();
        setup.auto_arm = amr_actors::server::AutoArm::Off;
        if let Some(v) = self.last_v_carried().or_else(|| self.last_v()) {
            let prior = setup.amcl.initial_pose;
            let num = |x: f64| amr_core::config::value::Finite::new(x).map_err(SimError::Site);
            let spread = |x: f64| amr_core::config::value::NonNegative::new(x).map_err(SimError::Site);
            setup.amcl.initial_pose = Some(amr_core::config::InitialPose {
                x: num(v.x)?,
                y: num(v.y)?,
                yaw: num(v.theta)?,
                std_xy_m: prior.map_or(spread(0.1), |p| Ok(p.std_xy_m))?,
                std_yaw_rad: prior.map_or(spread(0.05), |p| Ok(p.std_yaw_rad))?,
            });
        }
        let server = start_server(setup, end, self.clock).await?;
        observe_server(&server, &self.observer);
        let old = std::mem::replace(&mut self.server, server);
        // Dead already; this only waits (bounded) for its supervisor's task.
        old.shutdown().await;
        Ok(())
    }

    /// A one-line live status.
    #[must_use]
    pub fn status_line(&self) -> String {
        let o = self.observed.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let phase = o.formation.as_ref().map_or("starting".to_owned(), |f| format!("{:?}", f.phase));
        let plan = o.formation.as_ref().map_or(0.0, |f| f.plan_s);
        let err =
            o.samples.last().map_or("-".to_owned(), |s| format!("{:.1} cm", s.e_x_m.hypot(s.e_y_m) * 100.0));
        let integrity = o.integrity.map_or("none".to_owned(), |i| match i.disagrees {
            Some(j) => format!("{} (robot {j} disagrees)", i.state),
            None => i.state.to_string(),
        });
        let health: Vec<String> = o
            .health
            .iter()
            .map(|(robot, d)| {
                let bad: Vec<String> = d
                    .iter()
                    .filter(|(_, (_, last))| *last != Health::Ok)
                    .map(|(k, (_, l))| format!("{k}:{l:?}"))
                    .collect();
                if bad.is_empty() { format!("{robot} ok") } else { format!("{robot} {}", bad.join(" ")) }
            })
            .collect();
        format!(
            "t={:5.1}s plan={plan:5.1}s {phase} | V {integrity}, error {err} | {}",
            self.started.elapsed().as_secs_f64(),
            health.join(" | ")
        )
    }

    /// Run until the plan is done, the formation stops, or `max_duration` passes; `status` is
    /// called about once a second.
    pub async fn run(&self, mut status: impl FnMut(&Sim)) {
        let limit = self.options.max_duration.unwrap_or(Duration::MAX);
        let mut every = tokio::time::interval(Duration::from_secs(1));
        every.set_missed_tick_behavior(MissedTickBehavior::Delay);
        // Bounded by `limit` and by the plan's end.
        loop {
            every.tick().await;
            status(self);
            if self.started.elapsed() >= limit {
                return;
            }
            if matches!(self.formation().map(|f| f.phase), Some(Phase::Finished | Phase::Stopped { .. })) {
                return;
            }
        }
    }

    /// The report so far.
    #[must_use]
    pub fn report(&self) -> SimReport {
        let o = self.observed.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let e2d: Vec<f64> = o.samples.iter().map(|s| s.e_x_m.hypot(s.e_y_m)).collect();
        let eth: Vec<f64> = o.samples.iter().map(|s| s.e_theta_rad).collect();
        let slots = amr_core::formation::slots(self.robots.len(), self.options.scenario.spacing_m.get());
        let final_formation_error_m = match self.truth.latest().and_then(|(_, p)| v_of(&p).map(|v| (v, p))) {
            Some((v, poses)) => poses
                .iter()
                .zip(&slots)
                .map(|(p, y)| (v * Se2::new(0.0, *y, 0.0)).inverse().compose_xy(p))
                .collect(),
            None => Vec::new(),
        };
        SimReport {
            scenario: self.options.scenario_name.clone(),
            seed: self.options.seed,
            configuration: format!("{:?}", self.configuration),
            duration_s: self.started.elapsed().as_secs_f64(),
            clock: if self.options.can == SimCan::VirtualTime { "virtual" } else { "wall" }.to_owned(),
            plan_s: o.formation.as_ref().map_or(0.0, |f| f.plan_s),
            plan_len_s: o.formation.as_ref().map_or(0.0, |f| f.plan_len_s),
            final_phase: o.formation.as_ref().map_or("none".to_owned(), |f| format!("{:?}", f.phase)),
            error_2d: ErrorStats::of(&e2d),
            error_heading: ErrorStats::of(&eth),
            samples: o.samples.clone(),
            latency: latency_table(&self.server.ports.latency.snapshot()),
            health: o
                .health
                .iter()
                .map(|(r, d)| {
                    (
                        r.clone(),
                        d.iter()
                            .map(|(k, (b, l))| (k.clone(), (format!("{b:?}"), format!("{l:?}"))))
                            .collect(),
                    )
                })
                .collect(),
            counters: self.robots.iter().map(|t| (t.id.clone(), t.counters.snapshot())).collect(),
            final_formation_error_m,
            final_truth: self
                .truth
                .latest()
                .map(|(_, p)| p.iter().map(|q| [q.x, q.y, q.theta]).collect())
                .unwrap_or_default(),
        }
    }

    /// Stop everything in order: the robots (their drives quick-stop), the server, the mocks.
    pub async fn shutdown(self) {
        for r in self.robots {
            r.shutdown().await;
        }
        self.server.shutdown().await;
        self.observer.stop(None);
        for m in self.mocks {
            m.imu.shutdown();
        }
    }
}

/// The scenario's map, its name and its grid: the scenario file's own, else the configuration's
/// map that the scenario names.
fn scenario_map(config: &Config, options: &SimOptions) -> Result<(String, OccupancyGrid), SimError> {
    let sc = &options.scenario;
    Ok(match &options.map {
        Some(m) => m.clone(),
        None => {
            (sc.map.clone(), config.maps.get(&sc.map).ok_or_else(|| SimError::NoMap(sc.map.clone()))?.clone())
        }
    })
}

/// What the server starts with: the configuration's server (with the run's T1–T4 when it names
/// them), AMCL on `map`, the formation's `robots`, the scenario and the seed; it arms by itself.
fn server_setup(
    config: &Config,
    options: &SimOptions,
    map: OccupancyGrid,
    robots: &[RobotConfig],
) -> ServerSetup {
    let mut server_cfg = config.server.clone();
    if let Some(c) = options.configuration {
        server_cfg.configuration = c;
    }
    ServerSetup {
        server: server_cfg,
        vamr: config.vamr.clone(),
        amcl: config.amcl.clone(),
        map,
        robots: robots.to_vec(),
        scenario: options.scenario.clone(),
        seed: options.seed,
        auto_arm: amr_actors::server::AutoArm::Mock,
        policy: RestartPolicy::default(),
        progress: std::sync::Arc::new(amr_actors::server::progress::PlanProgress::in_memory()),
    }
}

/// Every robot of the formation, each on its end of the link and its own mocks.
async fn start_robots(
    robots: &[RobotConfig],
    ends: Vec<RobotEnd>,
    mocks: &[RobotMocks],
    clock: FleetClock,
) -> Result<Vec<RobotTree>, SimError> {
    let mut trees = Vec::new();
    for ((r, end), m) in robots.iter().zip(ends).zip(mocks) {
        trees.push(
            start_robot(r, m.overrides(), end, clock, RobotOptions { mock: true, ..RobotOptions::default() })
                .await?,
        );
    }
    Ok(trees)
}

/// Distance helper for the final formation check.
trait ComposeXy {
    fn compose_xy(&self, p: &Se2) -> f64;
}

impl ComposeXy for Se2 {
    /// The distance of `p` from this pose's origin, m.
    fn compose_xy(&self, p: &Se2) -> f64 {
        let d = *self * *p;
        d.x.hypot(d.y)
    }
}
