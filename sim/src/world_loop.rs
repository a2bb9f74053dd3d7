//! The world loop, which moves the world's robots at their mock drives' shaft speeds every physics
//! step and logs their true poses.

use std::sync::Arc;
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::config::RobotConfig;
use amr_actors::robot::ports::AbortOnDrop;
use amr_core::se2::Se2;
use hil_mocks::world::SharedWorld;
use tokio::time::{Instant, MissedTickBehavior};

use crate::mocks::RobotMocks;
use crate::truth::TruthLog;
use crate::watch_drive;

/// World physics step, s.
pub const PHYSICS_DT_S: f64 = 0.005;

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
