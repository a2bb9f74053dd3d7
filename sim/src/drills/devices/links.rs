//! Drills of the device links: the LiDAR's connection reset or stalled, the IMU unplugged, the CAN
//! link broken, bad data from every device, the LiDAR absent at start-up.

#[allow(clippy::wildcard_imports, reason = "the drills share their parent's imports and helpers")]
use super::*;

/// Drill 4a: the LiDAR's TCP connection is reset and refused for a while.
pub(crate) async fn lidar_reset(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig(config, seed, SimCan::InProcess, c).await else { return };
    let n0 = rig.tree.events.len();
    let conns = rig.mocks.lidar.handle.connections();
    c.inject();
    rig.mocks.lidar.handle.inject(LidarFault::Drop { refuse_for: Duration::from_millis(1000) });
    c.detection = c
        .within("LiDAR Lost", Duration::from_secs(1), || health(&rig, Device::Lidar) == Some(Health::Lost))
        .await;
    c.recovery = c
        .within("LiDAR Ok again", Duration::from_secs(8), || health(&rig, Device::Lidar) == Some(Health::Ok))
        .await;
    // Backoff 100, 200, 400, 800 ms: a handful of attempts during the refusal, not a busy loop.
    let attempts = rig.mocks.lidar.handle.connections() - conns;
    c.that((1..=6).contains(&attempts), format!("{attempts} connection attempts to recover (1..=6)"));
    c.eq("supervision events (no restart)", events_from(&rig, n0), vec![]);
    c.that(all_ok(&rig), "every device Ok after");
    c.events = events_from(&rig, n0);
    keep_counters(&rig, c);
    c.that(c.counters.get("lidar.link_lost").copied().unwrap_or(0) >= 1, "the link loss counted");
    rig.tree.shutdown().await;
}

/// Drill 4b: the LiDAR stays connected but sends nothing (half-open).
pub(crate) async fn lidar_stall(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig(config, seed, SimCan::InProcess, c).await else { return };
    let n0 = rig.tree.events.len();
    c.inject();
    rig.mocks.lidar.handle.inject(LidarFault::Stall);
    // The scan watchdog is 500 ms.
    c.detection = c
        .within("LiDAR Lost (scan watchdog)", Duration::from_millis(900), || {
            health(&rig, Device::Lidar) == Some(Health::Lost)
        })
        .await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    rig.mocks.lidar.handle.inject(LidarFault::Resume);
    c.recovery = c
        .within("LiDAR Ok again", Duration::from_secs(8), || health(&rig, Device::Lidar) == Some(Health::Ok))
        .await;
    end_without_restarts(rig, c, n0).await;
}

/// Drill 4c: the IMU's tty disappears and comes back.
pub(crate) async fn imu_unplug(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig(config, seed, SimCan::InProcess, c).await else { return };
    let n0 = rig.tree.events.len();
    c.inject();
    if let Err(e) = rig.mocks.imu.unplug().await {
        return c.fail(format!("unplug: {e}"));
    }
    // No data for 250 ms reopens the port.
    c.detection = c
        .within("IMU Lost", Duration::from_millis(800), || health(&rig, Device::Imu) == Some(Health::Lost))
        .await;
    c.within("odometry on the wheels alone", Duration::from_millis(500), || {
        health(&rig, Device::Odometry) == Some(Health::Degraded)
    })
    .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    if let Err(e) = rig.mocks.imu.replug().await {
        return c.fail(format!("replug: {e}"));
    }
    c.recovery = c
        .within("IMU and odometry Ok again", Duration::from_secs(8), || {
            health(&rig, Device::Imu) == Some(Health::Ok)
                && health(&rig, Device::Odometry) == Some(Health::Ok)
        })
        .await;
    end_without_restarts(rig, c, n0).await;
}

/// Drill 4e: the CAN link (socketcand over TCP) breaks and refuses connections for a while.
pub(crate) async fn can_link_reset(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig(config, seed, SimCan::Socketcand, c).await else { return };
    let Some(control) = rig.mocks.socketcand.as_ref().map(|s| s.control.clone()) else {
        return c.fail("no socketcand server");
    };
    let Some(_feed) = drive_until_turning(&rig, 0.15, c).await else { return };
    let n0 = rig.tree.events.len();
    let accepted = control.accepted();
    c.inject();
    control.drop_connections(Duration::from_millis(800));
    c.detection = c
        .within("CAN bus Lost", Duration::from_millis(500), || {
            health(&rig, Device::CanBus) == Some(Health::Lost)
        })
        .await;
    // Without the master's heartbeat each drive quick-stops by itself after its 300 ms consumer
    // time (0x1016/0x6007).
    c.safe_state =
        c.within("the drives stopped by themselves", Duration::from_millis(800), || drives_safe(&rig)).await;
    c.within("the robot disarmed", Duration::from_millis(500), || {
        matches!(*rig.tree.ports.safety_now.borrow(), Some(SafetyState::Disarmed(_)))
    })
    .await;
    c.recovery = c
        .within("bus and drives Ok again", Duration::from_secs(10), || {
            health(&rig, Device::CanBus) == Some(Health::Ok)
                && health(&rig, Device::Drives) == Some(Health::Ok)
        })
        .await;
    // Backoff 100, 200, 400, 800 ms during an 800 ms refusal: a few attempts, not a busy loop.
    let attempts = control.accepted() - accepted;
    c.that((1..=6).contains(&attempts), format!("{attempts} connection attempts to recover (1..=6)"));
    c.eq(
        "enables without configuration",
        rig.mocks.drives.iter().map(|d| d.now().enables_unconfigured).sum::<u32>(),
        0,
    );
    end_without_restarts(rig, c, n0).await;
}

/// Drill 6: bad data from every device and on the link: rejected and counted, nothing panics.
pub(crate) async fn bad_data(config: &Config, seed: u64, c: &mut Check) {
    use hil_mocks::lpms::Fault as ImuFault;
    let Some(rig) = rig(config, seed, SimCan::InProcess, c).await else { return };
    let n0 = rig.tree.events.len();
    let rejected = rig.tree.counters.get("rejected");
    c.inject();
    let l = &rig.mocks.lidar.handle;
    l.inject(LidarFault::Garbage(b"\x02sSN LMDscandata \xff\xfe garbage\x03\x00\x00".to_vec()));
    l.inject(LidarFault::TruncateNext);
    tokio::time::sleep(Duration::from_millis(200)).await;
    l.inject(LidarFault::CorruptNext);
    for f in [
        ImuFault::WrongLrc(5),
        ImuFault::Truncate(5),
        ImuFault::Garbage(vec![0x3a, 0x01, 0x00, 0xff, 0xff, 0x7f]),
    ] {
        if let Err(e) = rig.mocks.imu.inject(f).await {
            c.that(false, format!("imu fault: {e}"));
        }
    }
    // Once the broken frames are through (10 frames at 100 Hz), well-framed IMU samples with a NaN
    // or an impossible yaw rate.
    tokio::time::sleep(Duration::from_millis(300)).await;
    rig.mocks.imu_bad.store(6, std::sync::atomic::Ordering::Relaxed);
    // Commands that are not finite, replayed, stale or absurd.
    let id = rig.tree.id.clone();
    let down = &rig.server.down;
    let now = rig.clock.now_s();
    down.send(&id, Downlink::Arm { seq: 10, stops: rig.stops(), stamp_s: rig.clock.now_s() });
    tokio::time::sleep(Duration::from_millis(100)).await;
    let cmd = |seq, stamp_s, v_mps| Downlink::Command(Command { seq, stamp_s, v_mps, w_radps: 0.0 });
    down.send(&id, cmd(10, now, f64::NAN));
    down.send(&id, cmd(11, now - 5.0, 0.1));
    down.send(&id, cmd(9, now, 0.1));
    down.send(&id, cmd(12, rig.clock.now_s(), 50.0));
    tokio::time::sleep(Duration::from_millis(60)).await;
    down.send(&id, cmd(12, rig.clock.now_s(), 0.1));
    c.detection = c
        .within("rejections counted", Duration::from_secs(2), || {
            rig.tree.counters.get("rejected") >= rejected + 3
        })
        .await;
    // The absurd speed is clamped: the drives never get more than the robot's limit.
    let max_cps = 0.22 / (std::f64::consts::TAU * 0.065) * 20.0 * 10_000.0;
    c.throughout("the wheels within the speed limit", Duration::from_secs(1), || {
        rig.mocks.drives.iter().all(|d| d.now().velocity_cps.abs() <= max_cps * 1.001)
    })
    .await;
    keep_counters(&rig, c);
    let counters = c.counters.clone();
    let get = |k: &str| counters.get(k).copied().unwrap_or(0);
    let (nan, expired, stale) =
        (get("safety.refused.not_finite"), get("safety.refused.expired"), get("safety.refused.stale"));
    c.eq("refused (not finite, expired, stale)", (nan, expired, stale), (1, 1, 2));
    c.that(get("lidar: protocol or device error") >= 2, "LiDAR frames rejected and counted");
    c.that(get("imu: protocol or device error") >= 2, "IMU frames rejected and counted");
    c.eq(
        "IMU samples with NaN or out-of-range yaw rate rejected",
        get("imu: yaw rate not finite or out of range"),
        6,
    );
    c.eq("supervision events (nothing failed)", events_from(&rig, n0), vec![]);
    c.recovery = c.within("every device Ok", Duration::from_secs(5), || all_ok(&rig)).await;
    c.events = events_from(&rig, n0);
    rig.tree.shutdown().await;
}

/// Drill 7: the LiDAR is absent when the robot starts.
pub(crate) async fn absent_at_start(config: &Config, seed: u64, c: &mut Check) {
    let Some(scenario) = config.scenarios.get("straight").cloned() else {
        return c.fail("setup: the configuration has no `straight` scenario");
    };
    // A port nobody listens on (yet).
    let port = match std::net::TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()) {
        Ok(a) => a.port(),
        Err(e) => return c.fail(format!("no free port: {e}")),
    };
    c.inject();
    let rig = match crate::RobotRig::start_with(
        config,
        &scenario,
        seed,
        SimCan::InProcess,
        Default::default(),
        |o| {
            o.lidar = Some(("127.0.0.1".into(), port));
        },
    )
    .await
    {
        Ok(r) => r,
        Err(e) => return c.fail(format!("setup: {e}")),
    };
    c.within("IMU and drives Ok without the LiDAR", Duration::from_secs(15), || {
        [Device::Imu, Device::CanBus, Device::Drives].iter().all(|d| health(&rig, *d) == Some(Health::Ok))
    })
    .await;
    c.detection = c
        .within("LiDAR Lost", Duration::from_secs(2), || health(&rig, Device::Lidar) == Some(Health::Lost))
        .await;
    let lost0 = rig.tree.counters.get("lidar.link_lost");
    tokio::time::sleep(Duration::from_secs(3)).await;
    let attempts = rig.tree.counters.get("lidar.link_lost") - lost0;
    c.that((1..=6).contains(&attempts), format!("{attempts} retries in 3 s: retrying, with backoff"));
    c.that(rig.tree.is_running(), "the robot runs without its LiDAR");
    c.eq(
        "supervision failures",
        rig.tree
            .events
            .snapshot()
            .iter()
            .filter(|e| matches!(e.kind, EventKind::Failed { .. } | EventKind::StartFailed { .. }))
            .count(),
        0,
    );
    // The LiDAR appears.
    let mock = hil_mocks::tim551::Tim551Mock::spawn(
        &format!("127.0.0.1:{port}"),
        hil_mocks::tim551::MockConfig::default(),
        std::sync::Arc::new(hil_mocks::world::WorldLidar { world: rig.world.clone(), robot: 0 }),
    )
    .await;
    if let Err(e) = &mock {
        return c.fail(format!("mock on port {port}: {e}"));
    }
    let appeared = c.since_injection();
    c.recovery = c
        .within("LiDAR Ok once it appears", Duration::from_secs(8), || {
            health(&rig, Device::Lidar) == Some(Health::Ok)
        })
        .await
        .map(|t| t.saturating_sub(appeared));
    keep_counters(&rig, c);
    rig.tree.shutdown().await;
}
