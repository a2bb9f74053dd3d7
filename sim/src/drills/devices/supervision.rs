//! Drills of the robot's supervision tree: an actor that panics, one that fails forever, the CAN bus
//! actor restarted with the drives after it.

#[allow(clippy::wildcard_imports, reason = "the drills share their parent's imports and helpers")]
use super::*;

/// Drill 1: the LiDAR actor panics; it alone is restarted.
pub(crate) async fn lidar_panic(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig(config, seed, SimCan::InProcess, c).await else { return };
    let sup = rig.tree.supervisor.clone();
    let others =
        (child(&sup, "imu").await.map(|c| c.get_id()), child(&sup, "drives").await.map(|c| c.get_id()));
    let enables = rig.mocks.drives[0].now().enables;
    let n0 = rig.tree.events.len();
    let Some(lidar) = child(&sup, "lidar").await else { return c.fail("no lidar actor") };
    c.inject();
    let _ = ActorRef::<LidarMsg>::from(lidar).cast(LidarMsg::InjectPanic("drill: lidar panic".into()));
    c.detection = c
        .within("the panic seen by the supervisor", Duration::from_secs(2), || {
            kinds(&rig, "robot-a", n0)
                .iter()
                .any(|k| matches!(k, EventKind::Failed { child, .. } if child == "lidar"))
        })
        .await;
    c.recovery = c
        .within("the LiDAR restarted and Ok", Duration::from_secs(5), || {
            started(&rig, "robot-a", "lidar", n0) && health(&rig, Device::Lidar) == Some(Health::Ok)
        })
        .await;
    let k = kinds(&rig, "robot-a", n0);
    c.that(
        matches!(k.first(), Some(EventKind::Failed { child, reason }) if child == "lidar" && reason.contains("drill: lidar panic")),
        format!("first event a failure of the LiDAR with the panic text: {k:?}"),
    );
    c.eq(
        "then",
        k.get(1..).map(<[EventKind]>::to_vec).unwrap_or_default(),
        vec![
            EventKind::RestartScheduled { child: "lidar".into(), attempt: 1, delay_ms: 100 },
            EventKind::Started { child: "lidar".into() },
        ],
    );
    let now = (child(&sup, "imu").await.map(|c| c.get_id()), child(&sup, "drives").await.map(|c| c.get_id()));
    c.eq("IMU and drives actors (same ids)", now, others);
    c.eq("drive enables", rig.mocks.drives[0].now().enables, enables);
    wrap_up(rig, c, n0).await;
}

/// Drill 2: a device actor that fails every time it starts: escalation, the robot stopped and
/// reporting Fault, and no restart storm.
pub(crate) async fn fail_forever(config: &Config, seed: u64, c: &mut Check) {
    let Some(mut rig) = rig(config, seed, SimCan::InProcess, c).await else { return };
    let Some(_feed) = drive_until_turning(&rig, 0.15, c).await else { return };
    let sup = rig.tree.supervisor.clone();
    let n0 = rig.tree.events.len();
    c.inject();
    // Kill the LiDAR actor every time it is started again (bounded: the intensity is 3).
    for k in 0..8 {
        if k > 0 {
            let seen = rig
                .tree
                .events
                .wait_for_nth(
                    |e| {
                        e.supervisor == "robot-a"
                            && (e.kind == EventKind::Started { child: "lidar".into() }
                                || matches!(e.kind, EventKind::Escalated { .. }))
                    },
                    1 + k,
                    Duration::from_secs(5),
                )
                .await;
            if matches!(seen.map(|e| e.kind), Some(EventKind::Escalated { .. }) | None) {
                break;
            }
        }
        match child(&sup, "lidar").await {
            Some(l) => l.kill(),
            None => break,
        }
        if k == 0 {
            c.detection = Some(c.since_injection());
        }
    }
    let escalated = rig
        .tree
        .events
        .wait_for(|e| matches!(e.kind, EventKind::Escalated { .. }), Duration::from_secs(10))
        .await;
    c.that(escalated.is_some(), "the robot supervisor escalated");
    c.safe_state = c.within("the wheels stopped", Duration::from_secs(2), || wheels_still(&rig)).await;
    let mut fault = false;
    let until = tokio::time::Instant::now() + Duration::from_secs(3);
    while !fault && tokio::time::Instant::now() < until {
        if let Ok(Some(Uplink::Safety { state, .. })) =
            tokio::time::timeout(Duration::from_millis(100), rig.server.up.recv()).await
        {
            fault = state == SafetyState::Fault;
        }
    }
    c.that(fault, "Fault reported up the link");
    c.that(!rig.tree.is_running(), "the robot tree stopped");
    let failures =
        kinds(&rig, "robot-a", n0).iter().filter(|k| matches!(k, EventKind::Failed { .. })).count();
    c.eq("failures before escalation (max_restarts + 1)", failures, 4);
    let n = rig.tree.events.len();
    c.throughout("no restart after the escalation", Duration::from_secs(2), || rig.tree.events.len() == n)
        .await;
    c.that(wheels_still(&rig), "the wheels stay still");
    c.events = events_from(&rig, n0);
    keep_counters(&rig, c);
}

/// Drill 3: the CAN bus actor fails; the drives actor is restarted after it.
pub(crate) async fn can_bus_restart(config: &Config, seed: u64, c: &mut Check) {
    let Some(rig) = rig(config, seed, SimCan::Socketcand, c).await else { return };
    let Some(drives_cell) = child(&rig.tree.supervisor, "drives").await else {
        c.fail("setup: the robot has no running `drives` supervisor");
        return rig.tree.shutdown().await;
    };
    let drives_sup: ActorRef<SupervisorMsg> = drives_cell.into();
    let Some(bus) = child(&drives_sup, "can-bus").await else {
        c.fail("setup: the drives supervisor has no running `can-bus` actor");
        return rig.tree.shutdown().await;
    };
    let (boots, enables) = (rig.mocks.drives[0].now().boots, rig.mocks.drives[0].now().enables);
    let n0 = rig.tree.events.len();
    c.inject();
    let _ = ActorRef::<CanBusMsg>::from(bus).cast(CanBusMsg::InjectFailure("drill: bus bug".into()));
    c.detection = c
        .within("the failure seen", Duration::from_secs(2), || !kinds(&rig, "robot-a/drives", n0).is_empty())
        .await;
    c.recovery = c
        .within("the drives enabled again", Duration::from_secs(10), || {
            let d = rig.mocks.drives[0].now();
            d.boots > boots && d.enables > enables && health(&rig, Device::Drives) == Some(Health::Ok)
        })
        .await;
    c.eq(
        "drives subtree events",
        kinds(&rig, "robot-a/drives", n0),
        vec![
            EventKind::Failed { child: "can-bus".into(), reason: "drill: bus bug".into() },
            EventKind::Stopped { child: "drive".into() },
            EventKind::RestartScheduled { child: "can-bus".into(), attempt: 1, delay_ms: 100 },
            EventKind::Started { child: "can-bus".into() },
            EventKind::Started { child: "drive".into() },
        ],
    );
    c.eq("top supervisor events", kinds(&rig, "robot-a", n0), vec![]);
    c.eq(
        "enables without configuration",
        rig.mocks.drives.iter().map(|d| d.now().enables_unconfigured).sum::<u32>(),
        0,
    );
    wrap_up(rig, c, n0).await;
}
