//! `amr-sim`: the whole system in one process against the mock devices: the world (hil-mocks) moves
//! the robots, the mocks serve it through the drivers' real transports, and the real robot and
//! server trees run on it, for `amr sim`, the HIL tests and the fault-recovery drills (module
//! `drills`, feature `drills`). A run is in real time (two runs of one seed are close, not
//! identical) or, with every device on in-memory pipes and tokio's clock paused, reproducible from
//! its seed ([`SimCan::VirtualTime`]); [`eval`] is the simulated-time evaluation of T1–T4
//! (`amr eval`), and [`served`] serves the world to separate robot processes.

#[cfg(feature = "drills")]
pub mod drills;
pub mod eval;
#[cfg(feature = "drills")]
pub mod kernel_can;
pub mod report;
pub mod served;
pub mod survey;
pub mod truth;

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::config::{Config, RobotConfig};
use amr_actors::link::{LinkControl, in_process};
use amr_actors::robot::canbus::CanLink;
use amr_actors::robot::ports::{AbortOnDrop, StreamConnector};
use amr_actors::robot::{DeviceOverrides, RobotOptions, RobotTree, start_robot};
use amr_actors::server::formation::{FormationStatus, Phase};
use amr_actors::server::{ServerSetup, ServerTree, formation_robots, start_server};
use amr_actors::supervisor::RestartPolicy;
use amr_core::config::{Configuration, ScenarioConfig};
use amr_core::map::OccupancyGrid;
use amr_core::metrics::ErrorStats;
use amr_core::se2::{Se2, angle_diff};
use amr_core::vamr::frame::virtual_frame;
use amr_drivers::canopen::transport::in_process::InProcessBus;
use amr_msgs::{Device, Health, HealthReport};
use amr_msgs::{Estimate, EstimateSource};
use hil_mocks::lpms::{MockImuHandle, MockImuOptions, start_mock_imu};
use hil_mocks::teco_drive::{DriveHandle, TecoDrive, TecoDriveConfig, spawn_drive};
use hil_mocks::tim551::{MockConfig, Tim551Mock};
use hil_mocks::world::{Noise, RobotSpec, SharedWorld, Site, World, WorldImu, WorldLidar};
use ractor::{Actor, ActorProcessingErr, ActorRef};
use tokio::time::{Instant, MissedTickBehavior};

pub use report::{SimReport, latency_table};
pub use truth::TruthLog;

/// World physics step, s.
pub const PHYSICS_DT_S: f64 = 0.005;

/// How the robots reach their mock drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SimCan {
    /// The in-process bus.
    InProcess,
    /// A socketcand server on loopback in front of the in-process bus.
    Socketcand,
    /// No socket and no tty at all: the LiDAR and the IMU over in-memory pipes, CAN on the
    /// in-process bus. With tokio's clock paused (a current-thread runtime) nothing but that clock
    /// orders events, so a run is reproducible from its seed (`amr sim --virtual-time`).
    VirtualTime,
}

/// Run settings.
#[derive(Debug, Clone)]
pub struct SimOptions {
    pub scenario_name: String,
    pub scenario: ScenarioConfig,
    pub seed: u64,
    pub noise: Noise,
    pub can: SimCan,
    /// T1–T4 (default: the server file's).
    pub configuration: Option<Configuration>,
    /// Stop after this much wall time even if the plan is not done.
    pub max_duration: Option<Duration>,
    /// A scenario file's own map (its YAML's path, and the grid); `None`: the configuration's
    /// map that the scenario names.
    pub map: Option<(String, OccupancyGrid)>,
    /// AMCL's map from a simulated survey of the site ([`survey`]) instead of the site's own.
    pub surveyed_map: bool,
}

/// Why a simulation could not start.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("no map `{0}` in the configuration")]
    NoMap(String),
    #[error("the world's site: {0}")]
    Site(String),
    #[error(transparent)]
    Server(#[from] amr_actors::server::ServerError),
    #[error(transparent)]
    Robot(#[from] amr_actors::robot::RobotError),
    #[error("mock {0}: {1}")]
    Mock(&'static str, String),
}

/// The socketcand server in front of a robot's mock bus.
#[derive(Debug)]
pub struct SocketcandMock {
    pub address: std::net::SocketAddr,
    pub control: hil_mocks::teco_drive::socketcand::SocketcandControl,
    _task: AbortOnDrop<()>,
}

/// One robot's mock devices.
#[derive(Debug)]
pub struct RobotMocks {
    pub lidar: Tim551Mock,
    pub imu: MockImuHandle,
    /// Set to n: the IMU's next n samples carry a NaN or an out-of-range yaw rate (drills).
    pub imu_bad: Arc<std::sync::atomic::AtomicU32>,
    pub bus: InProcessBus,
    /// Left, right.
    pub drives: Vec<DriveHandle>,
    pub socketcand: Option<SocketcandMock>,
    /// Virtual time: the in-memory ways to the LiDAR and the IMU.
    pub lidar_pipe: Option<hil_mocks::tim551::MemoryConnector>,
    pub imu_pipe: Option<hil_mocks::lpms::ImuConnector>,
}

/// What the observer collected.
#[derive(Debug, Default)]
struct Observed {
    samples: Vec<report::ErrorSample>,
    /// Fused estimates of V waiting for the truth to pass their stamp (the world is sampled every
    /// physics step, so the latest estimate is usually a little ahead of it).
    pending: std::collections::VecDeque<(f64, Se2, bool)>,
    /// The integrity of the latest fused estimate.
    integrity: Option<amr_msgs::EstimateIntegrity>,
    health: BTreeMap<String, BTreeMap<String, (Health, Health)>>,
    formation: Option<FormationStatus>,
    /// Every formation phase seen, in order (a repeated phase once).
    phases: Vec<Phase>,
    /// The latest fused estimate: V, and each robot's pose with its odometry pose at the stamp.
    last_fused: Option<(Se2, Vec<Option<amr_msgs::Anchored>>)>,
    /// Each robot's latest odometry pose.
    odom: BTreeMap<String, Se2>,
}

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

fn drive_config(robot: &RobotConfig, node: u8, noise: &Noise, seed: u64) -> TecoDriveConfig {
    let d = &robot.devices.drives;
    TecoDriveConfig {
        encoder_counts_per_rev: d.encoder_counts_per_rev,
        velocity_units_per_rps: d.velocity_units_per_rps,
        encoder_noise_counts: noise.encoder_sigma_counts,
        seed: seed.wrapping_mul(1000).wrapping_add(u64::from(node)),
        ..TecoDriveConfig::new(node)
    }
}

/// The world's model of robot `c`'s body: chassis, wheels, LiDAR mount and acceleration limit.
#[must_use]
pub fn robot_spec(c: &RobotConfig) -> RobotSpec {
    RobotSpec {
        chassis: c.chassis.outline_m.clone(),
        wheel_radius_m: c.kinematics.wheel_radius_m.get(),
        track_width_m: c.kinematics.track_width_m.get(),
        lidar_mount: c.lidar_mount.to_se2(),
        max_accel_mps2: c.limits.max_accel_mps2.get(),
    }
}

/// V in the map from the robots' poses, Eq. 16 with equal weights.
#[must_use]
pub fn v_of(poses: &[Se2]) -> Option<Se2> {
    let first = poses.first()?;
    let rel: Vec<(Se2, f64)> = poses.iter().map(|p| (first.inverse() * *p, 1.0)).collect();
    Some(*first * virtual_frame(&rel))
}

impl Sim {
    /// Start the world, the mocks, the server and every robot of the server's formation.
    pub async fn start(config: &Config, options: SimOptions) -> Result<Sim, SimError> {
        let sc = &options.scenario;
        let (map_name, map) = match &options.map {
            Some(m) => m.clone(),
            None => (
                sc.map.clone(),
                config.maps.get(&sc.map).ok_or_else(|| SimError::NoMap(sc.map.clone()))?.clone(),
            ),
        };
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
        let mut server_cfg = config.server.clone();
        if let Some(c) = options.configuration {
            server_cfg.configuration = c;
        }
        let configuration = server_cfg.configuration;
        let setup = ServerSetup {
            server: server_cfg,
            vamr: config.vamr.clone(),
            amcl: config.amcl.clone(),
            map,
            robots: robots.clone(),
            scenario: sc.clone(),
            seed: options.seed,
            auto_arm: amr_actors::server::AutoArm::Mock,
            policy: RestartPolicy::default(),
            progress: std::sync::Arc::new(amr_actors::server::progress::PlanProgress::in_memory()),
        };
        let server = start_server(setup.clone(), server_end, clock).await?;
        let mut trees = Vec::new();
        for ((r, end), m) in robots.iter().zip(robot_ends).zip(&mocks) {
            trees.push(
                start_robot(
                    r,
                    m.overrides(),
                    end,
                    clock,
                    RobotOptions { mock: true, ..RobotOptions::default() },
                )
                .await?,
            );
        }

        // The observer scores estimates and records health.
        let observed = Arc::new(std::sync::Mutex::new(Observed::default()));
        let (observer, _) = Observer::spawn(
            None,
            Observer { observed: Arc::clone(&observed), truth: truth.clone(), weights_equal: true },
            (),
        )
        .await
        .map_err(|e| SimError::Mock("observer", e.to_string()))?;
        observe_server(&server, &observer);
        for t in &trees {
            let id = t.id.clone();
            t.ports.odom.subscribe(observer.clone(), move |m| Some(ObserverMsg::Odom(id.clone(), m.pose)));
        }
        // Health: the boards hold every device's state; sampling them misses nothing that lasts.
        let boards: Vec<(String, Arc<amr_actors::robot::ports::RobotPorts>)> =
            trees.iter().map(|t| (t.id.clone(), Arc::clone(&t.ports))).collect();
        let obs = observer.clone();
        let health_task = tokio::spawn(async move {
            let mut every = tokio::time::interval(Duration::from_millis(50));
            loop {
                every.tick().await;
                for (id, ports) in &boards {
                    let board: Vec<HealthReport> = ports.health_board.borrow().values().cloned().collect();
                    for report in board {
                        if obs.cast(ObserverMsg::Health(id.clone(), report)).is_err() {
                            return;
                        }
                    }
                }
            }
        });

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

/// The observer follows `server`'s estimates and formation.
fn observe_server(server: &ServerTree, observer: &ActorRef<ObserverMsg>) {
    server.ports.estimates.subscribe(observer.clone(), |e| Some(ObserverMsg::Estimate(Box::new(e))));
    server.formation.subscribe(observer.clone(), |s| Some(ObserverMsg::Formation(s)));
}

/// What the world ray-casts for a scenario on map `map_name`: a shipped site as its polygons (its
/// map is their rendering, `hil_mocks::world::shipped_site`), any other map (a site of one's own)
/// as its occupied cells.
///
/// A rendering marks both cells that touch a face, so its occupied cells reach a cell in front of
/// every face. Ray-cast as a grid, each face stood a cell nearer the robots than on the map AMCL
/// uses with `--map true`, whose likelihood field puts a two-cell band's surface between its
/// layers: on `short-racks` (2 robots 0.5 m apart, 10 trials, seed 7) every configuration was
/// placed 5.0 cm towards the racks, and T4 erred by 6.3 cm on the site's own map against 2.9 on a
/// survey. As polygons: 0.9 cm. A map given by path has no polygons; there `--map true` keeps
/// that offset (README). A configuration's own map that only shares a name with one of ours (a
/// `maps/corridor.yaml` of another building) is not our rendering, and is ray-cast as its cells.
pub fn site_for(map_name: &str, map: &OccupancyGrid) -> Result<Site, SimError> {
    let Some(polygons) = hil_mocks::world::shipped_site(map_name) else { return Ok(map.clone().into()) };
    let polygons = polygons.map_err(|e| SimError::Site(format!("{e:?}")))?;
    let Some(room) = polygons.first() else { return Ok(map.clone().into()) };
    let rendering = amr_core::map::rasterize_outlines(
        &polygons,
        room,
        map.resolution_m,
        map.origin,
        map.width,
        map.height,
    );
    let same = (0..map.height).all(|j| {
        (0..map.width).all(|i| {
            rendering.is_occupied(i, j) == map.is_occupied(i, j)
                && rendering.is_free(i, j) == map.is_free(i, j)
        })
    });
    Ok(if same { polygons.into() } else { map.clone().into() })
}

/// The site of the configuration's map named by `sc`.
pub fn site_of(config: &Config, sc: &ScenarioConfig) -> Result<Site, SimError> {
    site_for(&sc.map, config.maps.get(&sc.map).ok_or_else(|| SimError::NoMap(sc.map.clone()))?)
}

/// The world does not model collisions: refuse a scenario that drives a robot of the formation
/// into a wall (its chassis' reach from its centre must stay clear, every 10 cm of V's path).
pub fn check_formation(site: &Site, sc: &ScenarioConfig, robots: &[RobotConfig]) -> Result<(), SimError> {
    let Some(first) = robots.first() else { return Ok(()) };
    let (x0, y0, x1, y1) = robot_spec(first).chassis.bounds();
    let reach = x0.abs().max(x1.abs()).hypot(y0.abs().max(y1.abs()));
    let slots = amr_core::formation::slots(robots.len(), sc.spacing_m.get());
    for r in eval::reference(sc, robots.len(), 0.1) {
        for y in &slots {
            let c = (r.pose * Se2::new(0.0, *y, 0.0)).transform_point([0.0, 0.0]);
            if !site.is_clear(c, reach) {
                return Err(SimError::Site(format!(
                    "with {} robots {} m apart the scenario drives a robot into a wall (or off the map) near ({:.2}, {:.2})",
                    robots.len(),
                    sc.spacing_m.get(),
                    c[0],
                    c[1]
                )));
            }
        }
    }
    Ok(())
}

/// The world with the formation's robots at their slots around the scenario's start.
pub fn build_world(
    robots: &[RobotConfig],
    sc: &ScenarioConfig,
    site: Site,
    noise: &Noise,
    seed: u64,
) -> Result<SharedWorld, SimError> {
    let mut world = World::new(site, *noise, seed);
    let slots = amr_core::formation::slots(robots.len(), sc.spacing_m.get());
    let start_v = sc.start_pose();
    for (r, y) in robots.iter().zip(&slots) {
        let mut spec = robot_spec(r);
        // The drives ramp (and quick-stop) the wheels; the world only must not be slower.
        spec.max_accel_mps2 = spec.max_accel_mps2.max(r.devices.drives.quick_stop_decel_mps2);
        world.add_robot(spec, start_v * Se2::new(0.0, *y, 0.0));
    }
    Ok(Arc::new(std::sync::Mutex::new(world)))
}

/// Robot `i`'s mock devices, backed by `world`.
pub async fn start_mocks(
    world: &SharedWorld,
    i: usize,
    r: &RobotConfig,
    noise: &Noise,
    seed: u64,
    can: SimCan,
) -> Result<RobotMocks, SimError> {
    let lidar_config = MockConfig {
        serial: 0x0100_0000 + i as u32,
        initial_tick_us: 1_000_000 * i as u32,
        ..MockConfig::default()
    };
    let lidar_source = Arc::new(WorldLidar { world: Arc::clone(world), robot: i });
    let (lidar, lidar_pipe) = if can == SimCan::VirtualTime {
        let (mock, connector) = Tim551Mock::spawn_in_memory(lidar_config, lidar_source);
        (mock, Some(connector))
    } else {
        let mock = Tim551Mock::spawn("127.0.0.1:0", lidar_config, lidar_source)
            .await
            .map_err(|e| SimError::Mock("lidar", e.to_string()))?;
        (mock, None)
    };
    let mut imu_opts = MockImuOptions::default();
    imu_opts.device.stream_hz = r.devices.imu.stream_hz;
    imu_opts.device.imu_id = r.devices.imu.imu_id;
    let imu_bad = Arc::new(std::sync::atomic::AtomicU32::new(0));
    let source =
        BadValues { inner: WorldImu { world: Arc::clone(world), robot: i }, left: Arc::clone(&imu_bad) };
    let (imu, imu_pipe) = if can == SimCan::VirtualTime {
        let (mock, connector) = hil_mocks::lpms::start_mock_imu_in_memory(imu_opts, Box::new(source));
        (mock, Some(connector))
    } else {
        let mock = start_mock_imu(imu_opts, Box::new(source))
            .await
            .map_err(|e| SimError::Mock("imu", e.to_string()))?;
        (mock, None)
    };
    let bus = InProcessBus::default();
    let now = Instant::now().into_std();
    let drives = [r.devices.drives.left.node_id, r.devices.drives.right.node_id]
        .iter()
        .map(|n| spawn_drive(TecoDrive::new(drive_config(r, *n, noise, seed), now), bus.port()))
        .collect();
    let socketcand = match can {
        SimCan::InProcess | SimCan::VirtualTime => None,
        SimCan::Socketcand => {
            let control = hil_mocks::teco_drive::socketcand::SocketcandControl::default();
            let (addr, task) =
                hil_mocks::teco_drive::socketcand::bind_with("127.0.0.1:0", bus.clone(), control.clone())
                    .await
                    .map_err(|e| SimError::Mock("socketcand", e.to_string()))?;
            Some(SocketcandMock { address: addr, control, _task: AbortOnDrop(task) })
        }
    };
    Ok(RobotMocks { lidar, imu, imu_bad, bus, drives, socketcand, lidar_pipe, imu_pipe })
}

impl RobotMocks {
    /// Where the robot finds these mocks.
    #[must_use]
    pub fn overrides(&self) -> DeviceOverrides {
        DeviceOverrides {
            lidar: Some(("127.0.0.1".to_owned(), self.lidar.port())),
            imu_path: Some(self.imu.tty_path().display().to_string()),
            can: Some(match &self.socketcand {
                Some(s) => CanLink::Socketcand { address: s.address.to_string(), channel: "can0".into() },
                None => CanLink::InProcess(self.bus.clone()),
            }),
            lidar_stream: self.lidar_pipe.clone().map(|c| {
                StreamConnector(Arc::new(move || {
                    let c = c.clone();
                    Box::pin(async move { c.connect().await })
                }))
            }),
            imu_stream: self.imu_pipe.clone().map(|c| {
                StreamConnector(Arc::new(move || {
                    let c = c.clone();
                    Box::pin(async move { c.connect().await })
                }))
            }),
        }
    }
}

/// The world loop: the mock drives' shaft speeds in, physics, the truth out; every physics step.
pub fn spawn_world_loop(
    world: &SharedWorld,
    truth: &TruthLog,
    clock: FleetClock,
    robots: &[RobotConfig],
    mocks: &[RobotMocks],
) -> AbortOnDrop<()> {
    let wheels: Vec<(RobotConfig, Vec<watch_drive::Snapshot>)> = robots
        .iter()
        .zip(mocks)
        .map(|(r, m)| (r.clone(), m.drives.iter().map(watch_drive::Snapshot::of).collect()))
        .collect();
    let (w, t) = (Arc::clone(world), truth.clone());
    AbortOnDrop(tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_secs_f64(PHYSICS_DT_S));
        tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
        let mut last = Instant::now();
        // Runs until aborted with the simulation.
        loop {
            tick.tick().await;
            let now = Instant::now();
            let dt = now.duration_since(last).as_secs_f64();
            last = now;
            let mut world = w.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            for (i, (robot, drives)) in wheels.iter().enumerate() {
                let (l, r) = watch_drive::wheel_speeds(robot, drives);
                let b = robot.kinematics.track_width_m.get();
                world.command(i, 0.5 * (l + r), (r - l) / b);
            }
            world.step(dt);
            let poses: Vec<Se2> = (0..world.robot_count()).filter_map(|i| world.pose(i)).collect();
            drop(world);
            t.push(clock.now_s(), poses);
        }
    }))
}

/// One robot with its mock devices and the world, its link's far end in the test's hands: for
/// supervision tests and drills.
#[derive(Debug)]
pub struct RobotRig {
    pub clock: FleetClock,
    pub world: SharedWorld,
    pub truth: TruthLog,
    /// The robot's configuration.
    pub robot: RobotConfig,
    pub tree: RobotTree,
    pub mocks: RobotMocks,
    /// The server's end of the link: read what the robot sends, send it commands.
    pub server: amr_actors::link::ServerEnd,
    pub link: LinkControl,
    _world: AbortOnDrop<()>,
    /// The robot tree's own runtime, when it has one ([`RobotRig::start_apart`]).
    pub apart: Option<Apart>,
}

/// A runtime of its own, on its own thread, for a robot tree: blocking it freezes the whole
/// robot as a stopped process would (`kill -STOP`: no task runs, nothing is sent, sockets stay
/// open), while the mock devices, the world and the drill go on in theirs.
#[derive(Debug)]
pub struct Apart {
    handle: tokio::runtime::Handle,
    /// Dropping it ends the runtime's thread.
    _stop: tokio::sync::oneshot::Sender<()>,
}

impl Apart {
    fn start() -> std::io::Result<Apart> {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let handle = rt.handle().clone();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        std::thread::Builder::new().name("robot-apart".into()).spawn(move || {
            rt.block_on(async move {
                let _ = stopped.await;
            });
        })?;
        Ok(Apart { handle, _stop: stop })
    }

    /// Freeze everything on this runtime for `d` (its one thread blocked); returns once the
    /// freeze has begun (false if the runtime is gone).
    pub async fn freeze(&self, d: Duration) -> bool {
        let (frozen, began) = tokio::sync::oneshot::channel();
        self.handle.spawn(async move {
            let _ = frozen.send(());
            std::thread::sleep(d);
        });
        began.await.is_ok()
    }
}

impl RobotRig {
    /// The robot's stop counter as it reports it (an arm must carry it).
    #[must_use]
    pub fn stops(&self) -> u64 {
        self.tree.ports.stops.load(std::sync::atomic::Ordering::SeqCst)
    }

    /// Kill the robot as `kill -9` kills its process (its runtime ends where every task is: nothing
    /// runs on the way out, no quick stop is sent) and start it again on the same devices with
    /// `options` (e.g. the same latch file), on a new link. Only for a rig started apart.
    pub async fn kill_and_restart(&mut self, options: RobotOptions) -> Result<(), SimError> {
        let Some(old) = self.apart.take() else {
            return Err(SimError::Site("only a robot on a runtime of its own can be killed".into()));
        };
        drop(old);
        // The killed runtime's thread winds down; a real restart takes far longer than this.
        tokio::time::sleep(Duration::from_millis(200)).await;
        let id = self.robot.id.as_str().to_owned();
        let (server, mut ends, link) = in_process(std::slice::from_ref(&id));
        let end = ends.pop().ok_or(SimError::Site("no link end".into()))?;
        let apart = Apart::start().map_err(|e| SimError::Site(format!("the robot's runtime: {e}")))?;
        let (robot, overrides, clock) = (self.robot.clone(), self.mocks.overrides(), self.clock);
        let options = RobotOptions { mock: true, ..options };
        let tree = apart
            .handle
            .spawn(async move { start_robot(&robot, overrides, end, clock, options).await })
            .await
            .map_err(|e| SimError::Site(format!("starting the robot: {e}")))??;
        self.tree = tree;
        self.server = server;
        self.link = link;
        self.apart = Some(apart);
        Ok(())
    }

    /// Robot `config.server.robots[0]` alone in the scenario's world (its formation partner absent).
    pub async fn start(
        config: &Config,
        scenario: &ScenarioConfig,
        seed: u64,
        can: SimCan,
        options: RobotOptions,
    ) -> Result<RobotRig, SimError> {
        Self::start_with(config, scenario, seed, can, options, |_| {}).await
    }

    /// As [`RobotRig::start`], with the device addresses changed by `tweak` (a device absent, …).
    pub async fn start_with(
        config: &Config,
        scenario: &ScenarioConfig,
        seed: u64,
        can: SimCan,
        options: RobotOptions,
        tweak: impl FnOnce(&mut DeviceOverrides),
    ) -> Result<RobotRig, SimError> {
        Self::start_on(config, scenario, seed, can, options, tweak, false).await
    }

    /// As [`RobotRig::start`], with the robot tree on a runtime of its own ([`Apart`]), so that a
    /// drill can freeze the robot while its devices go on.
    pub async fn start_apart(
        config: &Config,
        scenario: &ScenarioConfig,
        seed: u64,
        can: SimCan,
        options: RobotOptions,
    ) -> Result<RobotRig, SimError> {
        Self::start_on(config, scenario, seed, can, options, |_| {}, true).await
    }

    async fn start_on(
        config: &Config,
        scenario: &ScenarioConfig,
        seed: u64,
        can: SimCan,
        options: RobotOptions,
        tweak: impl FnOnce(&mut DeviceOverrides),
        apart: bool,
    ) -> Result<RobotRig, SimError> {
        let robots = formation_robots(&config.server, &config.robots)?;
        let robot = robots.into_iter().next().ok_or(SimError::Site("the formation is empty".into()))?;
        let clock = FleetClock::start();
        let world = build_world(
            std::slice::from_ref(&robot),
            scenario,
            site_of(config, scenario)?,
            &Noise::TYPICAL,
            seed,
        )?;
        let truth = TruthLog::default();
        let mocks = start_mocks(&world, 0, &robot, &Noise::TYPICAL, seed, can).await?;
        let world_task = spawn_world_loop(
            &world,
            &truth,
            clock,
            std::slice::from_ref(&robot),
            std::slice::from_ref(&mocks),
        );
        let (server, mut ends, link) = in_process(&[robot.id.as_str().to_owned()]);
        let end = ends.pop().ok_or(SimError::Site("no link end".into()))?;
        let mut overrides = mocks.overrides();
        tweak(&mut overrides);
        let config = robot.clone();
        let options = RobotOptions { mock: true, ..options };
        let (tree, apart) = if apart {
            let apart = Apart::start().map_err(|e| SimError::Site(format!("the robot's runtime: {e}")))?;
            let tree = apart
                .handle
                .spawn(async move { start_robot(&robot, overrides, end, clock, options).await })
                .await
                .map_err(|e| SimError::Site(format!("starting the robot: {e}")))??;
            (tree, Some(apart))
        } else {
            (start_robot(&robot, overrides, end, clock, options).await?, None)
        };
        Ok(RobotRig {
            clock,
            world,
            truth,
            robot: config,
            tree,
            mocks,
            server,
            link,
            _world: world_task,
            apart,
        })
    }
}

/// The world's IMU motion, with bad values on demand: well-framed packets whose yaw rate is NaN
/// or beyond the gyro's range, alternately.
#[derive(Debug)]
struct BadValues {
    inner: WorldImu,
    left: Arc<std::sync::atomic::AtomicU32>,
}

impl hil_mocks::lpms::MotionSource for BadValues {
    fn motion_at(&mut self, t_s: f64) -> hil_mocks::lpms::Motion {
        let mut m = self.inner.motion_at(t_s);
        let n = self.left.load(std::sync::atomic::Ordering::Relaxed);
        if n > 0 {
            self.left.store(n - 1, std::sync::atomic::Ordering::Relaxed);
            m.angular_velocity_radps[2] = if n.is_multiple_of(2) { f64::NAN } else { 1.0e3 };
        }
        m
    }
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

mod watch_drive {
    //! The drives' shaft speeds, read from their snapshots without holding the handles.
    use amr_actors::config::RobotConfig;
    use hil_mocks::teco_drive::{DriveHandle, DriveSnapshot};
    use tokio::sync::watch;

    #[derive(Debug, Clone)]
    pub(crate) struct Snapshot {
        pub(crate) node: u8,
        pub(crate) rx: watch::Receiver<DriveSnapshot>,
    }

    impl Snapshot {
        pub(crate) fn of(h: &DriveHandle) -> Self {
            Snapshot { node: h.node_id, rx: h.snapshot.clone() }
        }
    }

    /// Wheel surface speeds (left, right), m/s.
    pub(crate) fn wheel_speeds(robot: &RobotConfig, drives: &[Snapshot]) -> (f64, f64) {
        let d = &robot.devices.drives;
        let r = robot.kinematics.wheel_radius_m.get();
        let speed = |node: u8, inverted: bool| {
            let cps = drives.iter().find(|h| h.node == node).map_or(0.0, |h| h.rx.borrow().velocity_cps);
            let sign = if inverted { -1.0 } else { 1.0 };
            sign * cps / f64::from(d.encoder_counts_per_rev) / d.gear_ratio * std::f64::consts::TAU * r
        };
        (speed(d.left.node_id, d.left.inverted), speed(d.right.node_id, d.right.inverted))
    }
}

/// Messages of the observer.
#[derive(Debug)]
enum ObserverMsg {
    Estimate(Box<Estimate>),
    Formation(FormationStatus),
    Health(String, HealthReport),
    /// A robot's odometry pose.
    Odom(String, Se2),
}

#[derive(Debug)]
struct Observer {
    observed: Arc<std::sync::Mutex<Observed>>,
    truth: TruthLog,
    weights_equal: bool,
}

impl Observer {
    /// Score every pending estimate the truth has caught up with.
    fn score(&self, o: &mut Observed) {
        let Some((latest, _)) = self.truth.latest() else { return };
        while let Some((t, v, verified)) = o.pending.front().copied() {
            if t > latest {
                return;
            }
            o.pending.pop_front();
            if let Some(truth) = self.truth.at(t).and_then(|p| v_of(&p)) {
                o.samples.push(report::ErrorSample {
                    t_s: t,
                    e_x_m: v.x - truth.x,
                    e_y_m: v.y - truth.y,
                    e_theta_rad: angle_diff(v.theta, truth.theta),
                    verified,
                });
            }
        }
    }
}

impl Actor for Observer {
    type Msg = ObserverMsg;
    type State = ();
    type Arguments = ();

    async fn pre_start(&self, _myself: ActorRef<ObserverMsg>, (): ()) -> Result<(), ActorProcessingErr> {
        Ok(())
    }

    async fn handle(
        &self,
        _myself: ActorRef<ObserverMsg>,
        msg: ObserverMsg,
        (): &mut (),
    ) -> Result<(), ActorProcessingErr> {
        let mut o = self.observed.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        match msg {
            ObserverMsg::Estimate(e) => {
                if let (EstimateSource::Fused(_), Some(v)) = (e.source, e.v) {
                    o.last_fused = Some((v, e.robots.clone()));
                    o.integrity = Some(e.integrity);
                    if self.weights_equal {
                        o.pending.push_back((e.stamp_s, v, e.integrity.verified()));
                    }
                }
                self.score(&mut o);
            }
            ObserverMsg::Odom(robot, pose) => {
                o.odom.insert(robot, pose);
            }
            ObserverMsg::Formation(s) => {
                if o.phases
                    .last()
                    .is_none_or(|p| std::mem::discriminant(p) != std::mem::discriminant(&s.phase))
                {
                    o.phases.push(s.phase.clone());
                }
                o.formation = Some(s);
            }
            ObserverMsg::Health(robot, h) => {
                let entry = o
                    .health
                    .entry(robot)
                    .or_default()
                    .entry(format!("{:?}", h.device))
                    .or_insert((h.health, h.health));
                if report::rank(h.health) < report::rank(entry.0) {
                    entry.0 = h.health;
                }
                entry.1 = h.health;
            }
        }
        Ok(())
    }
}

/// The devices every robot has.
pub const DEVICES: [Device; 6] =
    [Device::Lidar, Device::Imu, Device::CanBus, Device::Drives, Device::Odometry, Device::Safety];
