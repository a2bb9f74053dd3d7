//! Drills of the robot's stops: e-stops (over the link, on a drive's input, during a restart, across
//! a restart), the safety actor killed while moving, a burst of stale commands, a frozen robot.

#[allow(clippy::wildcard_imports, reason = "the drills share their parent's imports and helpers")]
use super::*;

/// An e-stop comes over the link while the safety actor is down: the robot's latch keeps it, the
/// master's target hold zeroes the drives meanwhile, and the restarted safety actor comes back in
/// `EStop`, quick-stopping; an arm does not clear it; a reset and then an arm newer than the reset
/// do.
pub(crate) async fn estop_during_restart(config: &Config, seed: u64, c: &mut Check) {
    let Some((rig, feed, n0)) = safety_killed_while_driving(config, seed, c).await else { return };
    let id = rig.tree.id.clone();
    c.that(rig.server.down.send(&id, Downlink::EStop), "the e-stop queued on the link");
    // The dead actor sends no targets: the master's hold (the 200 ms command timeout) zeroes them.
    c.safe_state = c
        .within("every target zero without a safety actor", Duration::from_millis(400), || targets_zero(&rig))
        .await;
    c.detection = c
        .within("the safety actor back, in EStop", Duration::from_secs(2), || {
            started(&rig, &id, "safety", n0)
                && *rig.tree.ports.safety_now.borrow() == Some(SafetyState::EStop)
        })
        .await;
    c.within("the drives quick-stopping", Duration::from_millis(200), || {
        rig.mocks
            .drives
            .iter()
            .all(|d| matches!(d.now().state, State402::QuickStopActive | State402::SwitchOnDisabled))
    })
    .await;
    drop(feed);
    let _feed = drive_from(&rig, 0.2, 50_000);
    c.throughout(
        "an arm does not clear the latch: still EStop, wheels still",
        Duration::from_secs(1),
        || *rig.tree.ports.safety_now.borrow() == Some(SafetyState::EStop) && targets_zero(&rig),
    )
    .await;
    c.that(rig.server.down.send(&id, Downlink::ResetEStop), "the reset queued on the link");
    c.within("reset over the link: disarmed", Duration::from_millis(500), || {
        *rig.tree.ports.safety_now.borrow() == Some(SafetyState::Disarmed(DisarmReason::EStopReset))
    })
    .await;
    let _feed = drive_from(&rig, 0.2, 100_000);
    c.recovery = c
        .within("turning again after a new arm", Duration::from_secs(10), || wheels_turning(&rig, 1000.0))
        .await;
    wrap_up(rig, c, n0).await;
}

/// The safety actor dies while the robot drives: nothing sends targets, so the master's hold zeroes
/// them; the restarted safety actor starts disarmed at zero; the commands that go on are refused;
/// only a new arm moves the robot again.
pub(crate) async fn safety_crash_moving(config: &Config, seed: u64, c: &mut Check) {
    let Some((rig, feed, n0)) = safety_killed_while_driving(config, seed, c).await else { return };
    let id = rig.tree.id.clone();
    c.detection = c
        .within("the safety actor back, disarmed", Duration::from_secs(2), || {
            started(&rig, &id, "safety", n0)
                && *rig.tree.ports.safety_now.borrow() == Some(SafetyState::Disarmed(DisarmReason::Startup))
        })
        .await;
    // The master's hold (200 ms) or the new actor's zero output, whichever comes first.
    c.safe_state = c.within("every target zero", Duration::from_millis(400), || targets_zero(&rig)).await;
    refused_until_rearmed(&rig, c, feed, Duration::from_secs(1), 0.2).await;
    wrap_up(rig, c, n0).await;
}

/// A robot driving at 0.2 m/s whose safety actor is killed (the injection): the robot, the feed of
/// commands (still running) and the supervision-event index before the kill.
async fn safety_killed_while_driving(
    config: &Config,
    seed: u64,
    c: &mut Check,
) -> Option<(RobotRig, crate::AbortOnDrop<()>, usize)> {
    let rig = rig(config, seed, SimCan::InProcess, c).await?;
    let feed = drive_until_turning(&rig, 0.2, c).await?;
    let n0 = rig.tree.events.len();
    let Some(safety) = child(&rig.tree.supervisor, "safety").await else {
        c.fail("no safety actor");
        return None;
    };
    c.inject();
    safety.kill();
    Some((rig, feed, n0))
}

/// Drill 11: e-stop while moving: zero within 100 ms, latched until reset, orderly shutdown.
pub(crate) async fn estop(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig(config, seed, SimCan::InProcess, c).await else { return };
    let Some(_feed) = drive_until_turning(&rig, 0.2, c).await else { return };
    c.inject();
    rig.tree.estop();
    c.safe_state = c
        .within("both drives commanded to zero and quick-stopping", Duration::from_millis(100), || {
            targets_zero(&rig)
                && rig
                    .mocks
                    .drives
                    .iter()
                    .all(|d| matches!(d.now().state, State402::QuickStopActive | State402::SwitchOnDisabled))
        })
        .await;
    c.detection = c.safe_state;
    // 0.2 m/s at the 0.5 m/s² quick-stop deceleration: 0.4 s.
    c.within("the wheels at rest", Duration::from_millis(800), || wheels_still(&rig)).await;
    c.eq("safety state", *rig.tree.ports.safety_now.borrow(), Some(SafetyState::EStop));
    c.throughout("latched: commands keep coming, the wheels stay still", Duration::from_secs(1), || {
        wheels_still(&rig)
    })
    .await;
    rig.tree.reset_estop();
    c.within("reset: disarmed, not moving", Duration::from_millis(500), || {
        *rig.tree.ports.safety_now.borrow() == Some(SafetyState::Disarmed(DisarmReason::EStopReset))
    })
    .await;
    c.throughout("still: a reset does not re-arm", Duration::from_millis(500), || wheels_still(&rig)).await;
    // An e-stop whose message the safety actor never got (only the latch was set, as when it comes
    // while the actor restarts or the port lags): the actor reads the latch every cycle.
    rig.tree.ports.estop_latch.set(amr_actors::robot::ports::EStopSource::Local);
    c.within("the latch alone e-stops within a few cycles", Duration::from_millis(100), || {
        *rig.tree.ports.safety_now.borrow() == Some(SafetyState::EStop)
    })
    .await;
    rig.tree.reset_estop();
    // Disarmed: by the reset, or, if the drives' report of their quick stop comes after it, by
    // the halt that report causes (both need a new arm).
    c.within("reset again: disarmed", Duration::from_millis(500), || {
        matches!(*rig.tree.ports.safety_now.borrow(), Some(SafetyState::Disarmed(_)))
    })
    .await;
    c.eq("e-stop resets refused", rig.tree.counters.get("safety.refused.reset"), 0);
    keep_counters(&rig, c);
    let n0 = rig.tree.events.len();
    let log = rig.tree.events.clone();
    let drives = rig.mocks.drives.iter().map(|d| d.snapshot.clone()).collect::<Vec<_>>();
    rig.tree.shutdown().await;
    let lines: Vec<String> =
        log.snapshot().iter().skip(n0).map(|e| format!("{}: {:?}", e.supervisor, e.kind)).collect();
    let stopped = |s: &str, ch: &str| format!("{s}: Stopped {{ child: \"{ch}\" }}");
    c.eq(
        "orderly shutdown, in reverse start order",
        lines.clone(),
        vec![
            stopped("robot-a", "uplink"),
            stopped("robot-a", "safety"),
            stopped("robot-a", "odometry"),
            stopped("robot-a/drives", "drive"),
            stopped("robot-a/drives", "can-bus"),
            stopped("robot-a", "drives"),
            stopped("robot-a", "imu"),
            stopped("robot-a", "lidar"),
        ],
    );
    c.that(
        drives.iter().all(|d| d.borrow().state != State402::OperationEnabled),
        "no drive left enabled after the shutdown",
    );
    c.events = lines;
}

/// A stalled transport flushes its backlog at once: a hundred fresh commands, a disarm, then twenty
/// more arrive in one burst. Every one reaches the safety layer, in order: the disarm holds (the
/// robot brakes at the stop deceleration), the twenty after it are refused, the inbox does not
/// overflow, and a new arm drives again. Then the inbox's overflow policy: while the robot is
/// frozen (its safety actor cannot take anything), more inputs than the inbox holds arrive; the
/// robot halts, `Disarmed(QueueFull)`, every target zero.
pub(crate) async fn command_burst(config: &Config, seed: u64, c: &mut Check) {
    use amr_actors::robot::ports::{SAFETY_INBOX_CAPACITY, SafetyInput};
    let Some(rig) = rig_on(config, seed, SimCan::InProcess, true, c).await else { return };
    let Some(apart) = rig.apart.as_ref() else {
        c.fail("setup: the robot has no runtime of its own");
        return;
    };
    let Some(feed) = drive_until_turning(&rig, 0.15, c).await else { return };
    drop(feed);
    let (id, down, clock) = (rig.tree.id.clone(), rig.server.down.clone(), rig.clock);
    let n0 = rig.tree.events.len();
    let counter = |name: &str| rig.tree.counters.get(name);
    let refused0 = counter("safety.refused.not_armed");
    let cmd = |seq| Downlink::Command(Command { seq, stamp_s: clock.now_s(), v_mps: 0.15, w_radps: 0.0 });
    c.inject();
    let mut queued = 0u32;
    for seq in 50_000..50_100 {
        queued += u32::from(down.send(&id, cmd(seq)));
    }
    queued += u32::from(down.send(&id, Downlink::Disarm));
    for seq in 50_100..50_120 {
        queued += u32::from(down.send(&id, cmd(seq)));
    }
    c.eq("the burst queued on the link", queued, 121);
    c.detection = c
        .within("the burst's disarm applied: Disarmed(Requested)", Duration::from_millis(500), || {
            *rig.tree.ports.safety_now.borrow() == Some(SafetyState::Disarmed(DisarmReason::Requested))
        })
        .await;
    c.safe_state = c.within("the wheels at rest", Duration::from_secs(1), || wheels_still(&rig)).await;
    c.within("the twenty commands after the disarm refused", Duration::from_millis(500), || {
        counter("safety.refused.not_armed") >= refused0 + 20
    })
    .await;
    c.throughout("still disarmed, every target zero", Duration::from_millis(500), || {
        targets_zero(&rig) && *rig.tree.ports.safety_now.borrow() != Some(SafetyState::Armed)
    })
    .await;
    c.eq("inbox overflows during the burst", counter("safety.inbox_full"), 0);
    let feed = drive_from(&rig, 0.15, 100_000);
    c.recovery = c
        .within("turning again after a new arm", Duration::from_secs(10), || wheels_turning(&rig, 1000.0))
        .await;

    // The overflow policy. A 100 ms freeze is well inside the drives' heartbeat consumer time.
    if !apart.freeze(Duration::from_millis(100)).await {
        c.fail("the robot's runtime is gone");
    }
    let inbox = &rig.tree.ports.safety_inbox;
    let pushed = (0..SAFETY_INBOX_CAPACITY as u64 + 50)
        .filter(|k| inbox.push(SafetyInput::Link(cmd(200_000 + k))))
        .count();
    c.eq("inputs the full inbox took", pushed, SAFETY_INBOX_CAPACITY);
    c.within("halted on the overflow: Disarmed(QueueFull)", Duration::from_millis(500), || {
        *rig.tree.ports.safety_now.borrow() == Some(SafetyState::Disarmed(DisarmReason::QueueFull))
    })
    .await;
    c.within("every target zero after the overflow", Duration::from_millis(200), || targets_zero(&rig)).await;
    c.eq("overflows counted", counter("safety.inbox_full"), 1);
    drop(feed);

    // The link's queue to the robot: while the robot is frozen it fills with commands and a
    // disarm finds it full. The robot does not lose that silently: thawed, it halts.
    let feed = drive_from(&rig, 0.15, 300_000);
    c.within("turning again", Duration::from_secs(10), || wheels_turning(&rig, 1000.0)).await;
    if !apart.freeze(Duration::from_millis(100)).await {
        c.fail("the robot's runtime is gone");
    }
    // Paced so that the link's router (on the drill's runtime) moves them to the robot's queue.
    for seq in 400_000..400_200 {
        down.send(&id, cmd(seq));
        tokio::task::yield_now().await;
    }
    tokio::time::sleep(Duration::from_millis(10)).await;
    c.that(down.send(&id, Downlink::Disarm), "the disarm queued by the server");
    c.within("halted on the missed disarm: Disarmed(QueueFull)", Duration::from_millis(500), || {
        counter("safety.link_queue_full") == 1
            && *rig.tree.ports.safety_now.borrow() == Some(SafetyState::Disarmed(DisarmReason::QueueFull))
    })
    .await;
    drop(feed);
    end_without_restarts(rig, c, n0).await;
}

/// The whole robot process freezes: none of its tasks runs (no SYNC, no heartbeat, no target),
/// while its drives run on. Each drive's consumer of the master's heartbeat (0x1016, written at
/// start-up) expires and its communication-loss reaction (0x6007 = quick stop) stops it: quick stop
/// engaged within 2 × the consumer time, the wheels at rest within the consumer time plus the
/// quick-stop ramp. Thawed, the robot finds its drives stopped and halts; it moves again only after
/// a new arm.
pub(crate) async fn robot_freeze(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig_on(config, seed, SimCan::InProcess, true, c).await else { return };
    let Some(apart) = rig.apart.as_ref() else {
        c.fail("setup: the robot has no runtime of its own");
        return;
    };
    let v = 0.2;
    let Some(feed) = drive_until_turning(&rig, v, c).await else { return };
    let snapshots: Vec<_> = rig.mocks.drives.iter().map(crate::watch_drive::Snapshot::of).collect();
    let speed = || {
        let (l, r) = crate::watch_drive::wheel_speeds(&rig.robot, &snapshots);
        l.abs().max(r.abs())
    };
    c.within("at speed", Duration::from_secs(10), || speed() > 0.95 * v).await;
    let d = &rig.robot.devices.drives;
    let consumer = Duration::from_millis(u64::from(d.master_consumer_ms));
    let ramp = Duration::from_secs_f64(v / d.quick_stop_decel_mps2);
    let frozen_for = 2 * consumer + ramp + Duration::from_secs(1);
    let n0 = rig.tree.events.len();
    c.inject();
    if !apart.freeze(frozen_for).await {
        c.fail("the robot's runtime is gone");
        return;
    }
    let quick_stopped = || {
        rig.mocks.drives.iter().all(|h| {
            let s = h.now();
            s.state == State402::QuickStopActive && s.master_losses >= 1
        })
    };
    let left = |c: &Check, deadline: Duration| deadline.saturating_sub(c.since_injection());
    let deadline = left(c, 2 * consumer);
    c.detection =
        c.within("every drive in quick stop on the master's lost heartbeat", deadline, quick_stopped).await;
    let deadline = left(c, consumer + ramp + Duration::from_millis(100));
    c.safe_state = c.within("the wheels at rest", deadline, || wheels_still(&rig)).await;
    c.that(c.since_injection() < frozen_for, "the drives stopped while the robot was still frozen");
    tokio::time::sleep(frozen_for.saturating_sub(c.since_injection())).await;
    c.within("thawed, the robot halted: Disarmed(DeviceLost)", Duration::from_secs(2), || {
        *rig.tree.ports.safety_now.borrow() == Some(SafetyState::Disarmed(DisarmReason::DeviceLost))
    })
    .await;
    c.within("the drives enabled again", Duration::from_secs(10), || {
        rig.mocks.drives.iter().all(|h| h.now().state == State402::OperationEnabled)
            && health(&rig, Device::Drives) == Some(Health::Ok)
    })
    .await;
    refused_until_rearmed(&rig, c, feed, Duration::from_secs(2), 0.15).await;
    wrap_up(rig, c, n0).await;
}

/// The robot's e-stop chain opens: it is wired to a digital input of a drive (0x60FD bit 16,
/// normally closed), which the master reads in TPDO2 every cycle. The drive actor latches the
/// e-stop and quick-stops the drives at once. A local reset is refused while the chain is open; the
/// latch holds when it closes again and refuses an arm; the server's reset over the network is
/// refused (the stop was not initiated there); a local reset and a new arm drive again.
pub(crate) async fn estop_input(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig(config, seed, SimCan::InProcess, c).await else { return };
    let Some(feed) = drive_until_turning(&rig, 0.15, c).await else { return };
    let n0 = rig.tree.events.len();
    let estop = || *rig.tree.ports.safety_now.borrow() == Some(SafetyState::EStop);
    c.inject();
    rig.mocks.drives[0].inject(DriveFault::Inputs(hil_mocks::teco_drive::DEFAULT_INPUTS & !(1 << 16)));
    c.detection =
        c.within("the e-stop latched from the drive's input", Duration::from_millis(200), estop).await;
    c.safe_state = c
        .within("every drive quick-stopped", Duration::from_millis(200), || {
            rig.mocks.drives.iter().all(|h| h.now().state == State402::QuickStopActive)
        })
        .await;
    c.within("the wheels at rest", Duration::from_secs(1), || wheels_still(&rig)).await;
    let refused_resets = || rig.tree.counters.get("safety.refused.reset");
    rig.tree.reset_estop();
    c.within("a local reset refused while the chain is open", Duration::from_millis(300), || {
        refused_resets() == 1 && estop()
    })
    .await;
    rig.mocks.drives[0].inject(DriveFault::Inputs(hil_mocks::teco_drive::DEFAULT_INPUTS));
    drop(feed);
    let refused = rig.tree.counters.get("safety.refused.arm.latched");
    let _feed = drive_from(&rig, 0.15, 100_000);
    c.throughout("latched after the input closed again, an arm refused", Duration::from_millis(500), || {
        estop() && wheels_still(&rig)
    })
    .await;
    c.that(rig.tree.counters.get("safety.refused.arm.latched") > refused, "the arm was refused (latched)");
    c.eq("e-stop inputs seen", rig.tree.counters.get("drives.estop_input"), 1);
    drop(_feed);
    c.that(rig.server.down.send(&rig.tree.id, Downlink::ResetEStop), "the server's reset queued");
    c.within("the server's reset refused: the stop was local", Duration::from_millis(300), || {
        refused_resets() == 2 && estop()
    })
    .await;
    rig.tree.reset_estop();
    c.within("reset: Disarmed(EStopReset)", Duration::from_millis(500), || {
        *rig.tree.ports.safety_now.borrow() == Some(SafetyState::Disarmed(DisarmReason::EStopReset))
    })
    .await;
    let _feed = drive_from(&rig, 0.15, 200_000);
    c.recovery = c
        .within("turning again after the reset and a new arm", Duration::from_secs(10), || {
            wheels_turning(&rig, 1000.0)
        })
        .await;
    end_without_restarts(rig, c, n0).await;
}

/// A restart is not a reset (ISO 13850): the robot is e-stopped while driving, its process killed
/// (`kill -9`: nothing runs on the way out) and started again on the same devices and state file,
/// and the server re-arms it and commands on. It comes back in EStop, refuses the arm, and no wheel
/// moves until the e-stop is reset and a new arm comes. Then the same for a fault (the supervisor
/// escalates), which a reset over the network does not clear; only a reset on the robot does.
pub(crate) async fn estop_restart(config: &Config, seed: u64, c: &mut Check) {
    let dir = std::env::temp_dir().join(format!("amr-drill-estop-restart-{}-{seed}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let options = RobotOptions { latch_file: Some(dir.join("robot.safety")), ..RobotOptions::default() };
    let Some(mut rig) = rig_with(config, seed, SimCan::InProcess, true, options.clone(), c).await else {
        return;
    };
    let Some(feed) = drive_until_turning(&rig, 0.15, c).await else { return };
    let state = |rig: &RobotRig| *rig.tree.ports.safety_now.borrow();
    let id = rig.tree.id.clone();
    c.inject();
    c.that(rig.server.down.send(&id, Downlink::EStop), "the e-stop queued on the link");
    c.detection =
        c.within("EStop", Duration::from_millis(300), || state(&rig) == Some(SafetyState::EStop)).await;
    c.safe_state = c.within("the wheels at rest", Duration::from_secs(2), || wheels_still(&rig)).await;
    drop(feed);

    if let Err(e) = rig.kill_and_restart(options.clone()).await {
        return c.fail(format!("restarting the robot: {e}"));
    }
    c.within("the restarted robot in EStop, from its state file", Duration::from_secs(5), || {
        state(&rig) == Some(SafetyState::EStop)
    })
    .await;
    // Latched, the drives are not enabled (they stay Starting); the others come up.
    let sensors_ok = |rig: &RobotRig| {
        [Device::Lidar, Device::Imu, Device::CanBus].iter().all(|d| health(rig, *d) == Some(Health::Ok))
    };
    c.within("the restarted robot's sensors and bus Ok", Duration::from_secs(15), || sensors_ok(&rig)).await;
    // The server re-arms, as `rearm` or `--auto-arm` would, and commands on.
    let feed = drive_from(&rig, 0.15, 100_000);
    c.throughout(
        "re-armed after the restart: still EStop, every wheel still",
        Duration::from_secs(2),
        || state(&rig) == Some(SafetyState::EStop) && wheels_still(&rig),
    )
    .await;
    c.that(rig.tree.counters.get("safety.refused.arm.latched") >= 1, "the arm was refused (latched)");
    drop(feed);
    c.that(rig.server.down.send(&id, Downlink::ResetEStop), "the reset queued on the link");
    c.within("reset: Disarmed(EStopReset)", Duration::from_millis(500), || {
        state(&rig) == Some(SafetyState::Disarmed(DisarmReason::EStopReset))
    })
    .await;
    c.throughout("reset, not armed: every wheel still", Duration::from_millis(500), || wheels_still(&rig))
        .await;
    let feed = drive_from(&rig, 0.15, 200_000);
    c.recovery = c
        .within("turning again after the reset and a new arm", Duration::from_secs(10), || {
            wheels_turning(&rig, 1000.0)
        })
        .await;

    // A fault: the LiDAR fails four times within the restart window; the supervisor escalates.
    let sup = rig.tree.supervisor.clone();
    for k in 1..=4 {
        let Some(lidar) = child(&sup, "lidar").await else { break };
        let lidar: ActorRef<LidarMsg> = lidar.into();
        let _ = lidar.cast(LidarMsg::InjectFailure(format!("drill: failure {k}")));
        tokio::time::sleep(Duration::from_millis(900)).await;
    }
    c.within("the escalation reported: Fault", Duration::from_secs(5), || {
        state(&rig) == Some(SafetyState::Fault)
    })
    .await;
    c.within("the wheels at rest after the fault", Duration::from_secs(3), || wheels_still(&rig)).await;
    drop(feed);
    if let Err(e) = rig.kill_and_restart(options.clone()).await {
        return c.fail(format!("restarting the robot after the fault: {e}"));
    }
    c.within("the restarted robot in Fault, from its state file", Duration::from_secs(5), || {
        state(&rig) == Some(SafetyState::Fault)
    })
    .await;
    c.within("the restarted robot's sensors and bus Ok", Duration::from_secs(15), || sensors_ok(&rig)).await;
    let feed = drive_from(&rig, 0.15, 300_000);
    let refused = rig.tree.counters.get("safety.refused.reset");
    c.that(rig.server.down.send(&id, Downlink::ResetEStop), "a network reset queued");
    c.throughout(
        "re-armed and reset over the network: still Fault, every wheel still",
        Duration::from_secs(2),
        || state(&rig) == Some(SafetyState::Fault) && wheels_still(&rig),
    )
    .await;
    c.that(rig.tree.counters.get("safety.refused.reset") > refused, "the network reset was refused");
    drop(feed);
    rig.tree.reset_estop();
    c.within("reset on the robot: Disarmed(FaultReset)", Duration::from_millis(500), || {
        state(&rig) == Some(SafetyState::Disarmed(DisarmReason::FaultReset))
    })
    .await;
    let _feed = drive_from(&rig, 0.15, 400_000);
    c.within("turning again after the fault's reset and a new arm", Duration::from_secs(10), || {
        wheels_turning(&rig, 1000.0)
    })
    .await;
    keep_counters(&rig, c);
    rig.tree.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}
