//! Supervision of a real robot tree (docs/architecture.md, "Supervision"): one robot with its mock
//! devices behind their real transports, real time, bounded waits. Exact ordered event logs; the
//! safe stop on escalation is checked on the mock drives themselves.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::time::Duration;

use amr_actors::config::{ConfigSource, load};
use amr_actors::robot::RobotOptions;
use amr_actors::robot::canbus::CanBusMsg;
use amr_actors::robot::lidar::LidarMsg;
use amr_actors::supervisor::{ChildInfo, EventKind, SupervisorMsg};
use amr_drivers::canopen::cia402::State402;
use amr_msgs::{Command, Device, Downlink, Health, SafetyState, Uplink};
use amr_sim::{RobotRig, SimCan};
use ractor::{ActorCell, ActorRef};

async fn rig() -> RobotRig {
    let config = load(&ConfigSource::Embedded).unwrap();
    let scenario = config.scenarios["straight"].clone();
    let rig =
        RobotRig::start(&config, &scenario, 3, SimCan::InProcess, RobotOptions::default()).await.unwrap();
    wait_until("every device Ok", Duration::from_secs(15), || {
        let b = rig.tree.ports.health_board.borrow();
        [Device::Lidar, Device::Imu, Device::CanBus, Device::Drives]
            .iter()
            .all(|d| b.get(d).is_some_and(|r| r.health == Health::Ok))
    })
    .await;
    rig
}

async fn wait_until(what: &str, timeout: Duration, mut cond: impl FnMut() -> bool) {
    let start = tokio::time::Instant::now();
    while !cond() {
        assert!(start.elapsed() < timeout, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

async fn children(sup: &ActorRef<SupervisorMsg>) -> Vec<ChildInfo> {
    ractor::call!(sup, SupervisorMsg::Children).unwrap()
}

async fn child(sup: &ActorRef<SupervisorMsg>, name: &str) -> ActorCell {
    children(sup).await.into_iter().find(|c| c.name == name).and_then(|c| c.cell).unwrap()
}

fn kinds_after(rig: &RobotRig, supervisor: &str, from: usize) -> Vec<EventKind> {
    rig.tree.events.snapshot()[from..]
        .iter()
        .filter(|e| e.supervisor == supervisor)
        .map(|e| e.kind.clone())
        .collect()
}

fn started(child: &str) -> EventKind {
    EventKind::Started { child: child.into() }
}

fn stopped(child: &str) -> EventKind {
    EventKind::Stopped { child: child.into() }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_lidar_actor_is_restarted_alone() {
    let rig = rig().await;
    let sup = rig.tree.supervisor.clone();
    let (imu, drives) = (child(&sup, "imu").await.get_id(), child(&sup, "drives").await.get_id());
    let enables = rig.mocks.drives[0].now().enables;
    let n0 = rig.tree.events.len();
    let lidar: ActorRef<LidarMsg> = child(&sup, "lidar").await.into();
    lidar.cast(LidarMsg::InjectFailure("drill: lidar bug".into())).unwrap();
    // The second start of the LiDAR (the log keeps the first).
    rig.tree
        .events
        .wait_for_nth(|e| e.supervisor == "robot-a" && e.kind == started("lidar"), 2, Duration::from_secs(5))
        .await
        .unwrap();
    let kinds = kinds_after(&rig, "robot-a", n0);
    assert_eq!(
        kinds,
        [
            EventKind::Failed { child: "lidar".into(), reason: "drill: lidar bug".into() },
            EventKind::RestartScheduled { child: "lidar".into(), attempt: 1, delay_ms: 100 },
            started("lidar"),
        ]
    );
    // The others were not touched: same actors, drives still enabled once.
    assert_eq!(child(&sup, "imu").await.get_id(), imu);
    assert_eq!(child(&sup, "drives").await.get_id(), drives);
    assert_eq!(rig.mocks.drives[0].now().enables, enables);
    assert_eq!(rig.mocks.drives[0].now().state, State402::OperationEnabled);
    // The new LiDAR actor connects and scans again.
    wait_until("the LiDAR back to Ok", Duration::from_secs(5), || {
        rig.tree.ports.health_board.borrow().get(&Device::Lidar).is_some_and(|r| r.health == Health::Ok)
    })
    .await;
    rig.tree.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_can_bus_actor_restarts_the_drives_after_it() {
    let rig = rig().await;
    let top = rig.tree.supervisor.clone();
    let drives_sup: ActorRef<SupervisorMsg> = child(&top, "drives").await.into();
    let (boots, enables) = (rig.mocks.drives[0].now().boots, rig.mocks.drives[0].now().enables);
    let n0 = rig.tree.events.len();
    let bus: ActorRef<CanBusMsg> = child(&drives_sup, "can-bus").await.into();
    bus.cast(CanBusMsg::InjectFailure("drill: bus bug".into())).unwrap();
    rig.tree
        .events
        .wait_for_nth(
            |e| e.supervisor == "robot-a/drives" && e.kind == started("drive"),
            2,
            Duration::from_secs(5),
        )
        .await
        .unwrap();
    assert_eq!(
        kinds_after(&rig, "robot-a/drives", n0),
        [
            EventKind::Failed { child: "can-bus".into(), reason: "drill: bus bug".into() },
            stopped("drive"),
            EventKind::RestartScheduled { child: "can-bus".into(), attempt: 1, delay_ms: 100 },
            started("can-bus"),
            started("drive"),
        ]
    );
    // The top supervisor saw nothing: the subtree handled it.
    assert_eq!(kinds_after(&rig, "robot-a", n0), []);
    // The new master resets the drives, configures them on their boot-up and enables them again.
    wait_until("the drives enabled again", Duration::from_secs(10), || {
        let d = rig.mocks.drives[0].now();
        d.boots > boots && d.enables > enables && d.state == State402::OperationEnabled
    })
    .await;
    assert_eq!(rig.mocks.drives[0].now().enables_unconfigured, 0);
    wait_until("drives health Ok", Duration::from_secs(5), || {
        rig.tree.ports.health_board.borrow().get(&Device::Drives).is_some_and(|r| r.health == Health::Ok)
    })
    .await;
    rig.tree.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn restart_intensity_exceeded_escalates_and_stops_the_moving_robot() {
    let mut rig = rig().await;
    let id = rig.tree.id.clone();
    // Arm and drive at 0.15 m/s.
    assert!(
        rig.server.down.send(&id, Downlink::Arm { seq: 1, stops: rig.stops(), stamp_s: rig.clock.now_s() })
    );
    let down = rig.server.down.clone();
    let clock = rig.clock;
    let r = id.clone();
    let feeder = tokio::spawn(async move {
        for seq in 1..=2000u64 {
            let c = Command { seq, stamp_s: clock.now_s(), v_mps: 0.15, w_radps: 0.0 };
            down.send(&r, Downlink::Command(c));
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    });
    wait_until("the wheels turning", Duration::from_secs(10), || {
        rig.mocks.drives[0].now().velocity_cps.abs() > 1000.0
    })
    .await;

    let sup = rig.tree.supervisor.clone();
    let n0 = rig.tree.events.len();
    // Four failures within the 10 s window: the fourth exceeds max_restarts = 3.
    for k in 1..=4 {
        let lidar: ActorRef<LidarMsg> = child(&sup, "lidar").await.into();
        lidar.cast(LidarMsg::InjectFailure(format!("drill: failure {k}"))).unwrap();
        if k < 4 {
            rig.tree
                .events
                .wait_for_nth(
                    |e| e.supervisor == "robot-a" && e.kind == started("lidar"),
                    1 + k,
                    Duration::from_secs(5),
                )
                .await
                .unwrap();
        }
    }
    rig.tree
        .events
        .wait_for(|e| matches!(e.kind, EventKind::Escalated { .. }), Duration::from_secs(10))
        .await
        .unwrap();
    let kinds = kinds_after(&rig, "robot-a", n0);
    let mut expected = Vec::new();
    for (k, delay) in [(1, 100), (2, 200), (3, 400)] {
        expected.push(EventKind::Failed { child: "lidar".into(), reason: format!("drill: failure {k}") });
        expected.push(EventKind::RestartScheduled { child: "lidar".into(), attempt: k, delay_ms: delay });
        expected.push(started("lidar"));
    }
    expected.push(EventKind::Failed { child: "lidar".into(), reason: "drill: failure 4".into() });
    expected.extend(["uplink", "safety", "odometry", "drives", "imu"].map(stopped));
    assert_eq!(kinds[..expected.len()], expected[..], "{kinds:#?}");
    assert!(
        matches!(&kinds[expected.len()], EventKind::Escalated { reason } if reason.contains("lidar")),
        "{kinds:#?}"
    );
    assert_eq!(kinds.len(), expected.len() + 1);

    // Safe stop: both wheels at rest within the quick-stop time (0.15 m/s at 0.5 m/s²: 0.3 s),
    // and not enabled to follow anything.
    wait_until("the wheels stopped", Duration::from_secs(2), || {
        rig.mocks
            .drives
            .iter()
            .all(|d| d.now().velocity_cps.abs() < 1.0 && d.now().state != State402::OperationEnabled)
    })
    .await;
    // The robot reports Fault up the link.
    let mut fault = false;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(3);
    while !fault && tokio::time::Instant::now() < deadline {
        if let Ok(Some(Uplink::Safety { state, .. })) =
            tokio::time::timeout(Duration::from_millis(100), rig.server.up.recv()).await
        {
            fault = state == SafetyState::Fault;
        }
    }
    assert!(fault, "no Fault reported");
    assert!(!rig.tree.is_running());
    // No restart storm: nothing more happens.
    let n = rig.tree.events.len();
    tokio::time::sleep(Duration::from_secs(2)).await;
    assert_eq!(rig.tree.events.len(), n);
    assert!(rig.mocks.drives.iter().all(|d| d.now().velocity_cps.abs() < 1.0));
    feeder.abort();
}
