//! Tests of the in-process link: routing, cuts, delays, a new server, lossy queues.
#![allow(clippy::unwrap_used, reason = "tests")]

use super::*;
use amr_msgs::Command;

fn cmd(seq: u64) -> Downlink {
    Downlink::Command(Command { seq, stamp_s: 0.0, v_mps: 0.1, w_radps: 0.0 })
}

#[test]
fn a_full_robot_queue_drops_commands_and_remembers_safety_messages() {
    let (tx, mut rx, missed) = DownlinkTx::queue();
    for k in 0..DEPTH as u64 {
        assert!(tx.send(cmd(k)));
    }
    assert!(!tx.send(cmd(999)));
    assert!(!missed.any.load(Ordering::SeqCst), "a dropped command is not a missed safety message");
    assert!(!tx.send(Downlink::Disarm));
    assert!(missed.any.load(Ordering::SeqCst) && !missed.estop.load(Ordering::SeqCst));
    assert!(!tx.send(Downlink::EStop));
    assert!(missed.estop.load(Ordering::SeqCst));
    assert_eq!(rx.try_recv().ok(), Some(cmd(0)), "what was queued stays, in order");
}

#[tokio::test]
async fn routes_by_robot_and_a_cut_loses_both_directions() {
    let robots = vec!["a".to_owned(), "b".to_owned()];
    let (mut server, mut ends, control) = in_process(&robots);
    assert!(server.down.send("b", cmd(1)));
    assert_eq!(ends[1].down.recv().await, Some(cmd(1)));
    assert!(!server.down.send("nobody", cmd(2)));
    ends[0].up.send(Uplink::Safety {
        robot: "a".into(),
        seq: 1,
        stamp_s: 0.0,
        state: amr_msgs::SafetyState::Armed,
        stops: 1,
        mock: false,
    });
    assert_eq!(server.up.recv().await.map(|m| m.robot().to_owned()), Some("a".to_owned()));

    control.set_cut("a", true);
    assert!(server.down.send("a", cmd(3)), "the router takes it; the cut loses it");
    ends[0].up.send(Uplink::Safety {
        robot: "a".into(),
        seq: 2,
        stamp_s: 0.0,
        state: amr_msgs::SafetyState::Armed,
        stops: 1,
        mock: false,
    });
    // Both messages reach the router and are lost there; b is unaffected.
    tokio::time::timeout(std::time::Duration::from_secs(2), async {
        while control.lost() < 2 {
            tokio::task::yield_now().await;
        }
    })
    .await
    .unwrap();
    assert!(ends[0].down.try_recv().is_err());
    assert!(server.down.send("b", cmd(4)));
    assert_eq!(ends[1].down.recv().await, Some(cmd(4)));
    control.set_cut("a", false);
    assert!(server.down.send("a", cmd(5)));
    assert_eq!(ends[0].down.recv().await, Some(cmd(5)));
}

#[tokio::test]
async fn a_held_link_delivers_its_backlog_late() {
    let robots = vec!["a".to_owned()];
    let (server, mut ends, control) = in_process(&robots);
    control.set_held("a", true);
    assert!(server.down.send("a", cmd(1)));
    assert!(server.down.send("a", cmd(2)));
    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    assert!(ends[0].down.try_recv().is_err(), "nothing passes while held");
    control.set_held("a", false);
    assert_eq!(ends[0].down.recv().await, Some(cmd(1)));
    assert_eq!(ends[0].down.recv().await, Some(cmd(2)));
    assert_eq!(control.late(), 2, "the message the router was holding and the queued one");
    assert_eq!(control.lost(), 0);
}

#[tokio::test]
async fn a_new_server_end_replaces_the_old_one() {
    let robots = vec!["a".to_owned(), "b".to_owned()];
    let (old, mut ends, control) = in_process(&robots);
    let mut new = control.new_server_end().unwrap();
    drop(old);
    // The router may still hold the old queue for a moment: bounded retries.
    let mut got = None;
    for k in 0..100 {
        assert!(new.down.send("b", cmd(k + 1)));
        if let Ok(Some(m)) =
            tokio::time::timeout(std::time::Duration::from_millis(10), ends[1].down.recv()).await
        {
            got = Some(m);
            break;
        }
    }
    assert!(matches!(got, Some(Downlink::Command(_))));
    ends[0].up.send(Uplink::Safety {
        robot: "a".into(),
        seq: 1,
        stamp_s: 0.0,
        state: amr_msgs::SafetyState::Armed,
        stops: 1,
        mock: false,
    });
    assert_eq!(new.up.recv().await.map(|m| m.robot().to_owned()), Some("a".to_owned()));
}
