//! Test rigs: one robot with its mock devices and the world, the server's end of its link in the
//! test's hands, for supervision tests and drills; and a runtime of its own on which a robot tree
//! can be frozen or killed as a process can.

use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::config::{Config, RobotConfig};
use amr_actors::link::{LinkControl, in_process};
use amr_actors::robot::ports::AbortOnDrop;
use amr_actors::robot::{DeviceOverrides, RobotOptions, RobotTree, start_robot};
use amr_actors::server::formation_robots;
use amr_core::config::ScenarioConfig;
use hil_mocks::world::{Noise, SharedWorld};

use crate::mocks::{RobotMocks, start_mocks};
use crate::options::{SimCan, SimError};
use crate::truth::TruthLog;
use crate::world::{build_world, site_of};
use crate::world_loop::spawn_world_loop;

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
