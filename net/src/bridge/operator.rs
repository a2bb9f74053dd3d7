//! An operator's e-stop: published on each robot's own e-stop key as that operator, confirmed by
//! the robots' reports of their safety state.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_msgs::{Downlink, Uplink};
use zenoh::qos::{CongestionControl, Priority};

use super::{Stamper, estop_key, new_session, zerr};
use crate::settings::{NetError, NetSettings, PREFIX};
use crate::wire::{Envelope, from_downlink, to_uplink};

/// How often an e-stop is sent again to a robot that has not confirmed it.
const ESTOP_RESEND: Duration = Duration::from_millis(250);

/// What an operator's e-stop (or reset) found: per robot, the safety state it reported after the
/// message was sent, if it confirmed within the time allowed.
pub type EstopOutcome = BTreeMap<String, Option<amr_msgs::SafetyState>>;

/// E-stop `robots` (or, with `reset`, clear their e-stop) as operator `user`: publish on each
/// robot's `fleet/<robot>/estop/<user>` at the highest priority, then wait up to `timeout` for each
/// robot's own report (its safety state comes up `fleet/<robot>/health` on every change and
/// periodically): `EStop`, or after a reset any other state. An e-stop is sent again every 250 ms
/// to the robots that have not confirmed it; a reset once, when the robot is first heard from (its
/// reports come at least once a second). The server's access control lets only `user` publish on
/// its own key.
pub async fn operator_estop(
    settings: &NetSettings,
    user: &str,
    robots: &[String],
    reset: bool,
    clock: FleetClock,
    timeout: Duration,
) -> Result<EstopOutcome, NetError> {
    use amr_msgs::SafetyState;
    let session = tokio::time::timeout(timeout, zenoh::open(settings.client_config(user)?))
        .await
        .map_err(|_| NetError::Zenoh(format!("no server reached within {timeout:?}")))?
        .map_err(zerr)?;
    let seen: Arc<Mutex<EstopOutcome>> =
        Arc::new(Mutex::new(robots.iter().map(|r| (r.clone(), None)).collect()));
    // The robots heard from since the session opened: their links are up.
    let heard: Arc<Mutex<BTreeSet<String>>> = Arc::default();
    let sent_at = clock.now_s();
    let mut subscribers = Vec::new();
    for robot in robots {
        let (seen, heard, me) = (Arc::clone(&seen), Arc::clone(&heard), robot.clone());
        let sub = session
            .declare_subscriber(format!("{PREFIX}/{robot}/health"))
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                let Ok(u) = Envelope::decode(&bytes).and_then(|env| to_uplink(env, &me, "health")) else {
                    return;
                };
                heard.lock().unwrap_or_else(PoisonError::into_inner).insert(me.clone());
                if let Uplink::Safety { stamp_s, state, .. } = u
                    && stamp_s >= sent_at
                {
                    let ok = if reset { state != SafetyState::EStop } else { state == SafetyState::EStop };
                    if ok {
                        seen.lock().unwrap_or_else(PoisonError::into_inner).insert(me.clone(), Some(state));
                    }
                }
            })
            .await
            .map_err(zerr)?;
        subscribers.push(sub);
    }
    let msg = if reset { Downlink::ResetEStop } else { Downlink::EStop };
    let sid = new_session();
    let mut stampers: BTreeMap<&str, Stamper> =
        robots.iter().map(|r| (r.as_str(), Stamper::new(sid, user, r))).collect();
    let until = tokio::time::Instant::now() + timeout;
    let mut next_send = tokio::time::Instant::now();
    let mut reset_sent = BTreeSet::new();
    // Bounded by `timeout`.
    while tokio::time::Instant::now() < until {
        let pending: Vec<String> = seen
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .iter()
            .filter(|(_, s)| s.is_none())
            .map(|(r, _)| r.clone())
            .collect();
        if pending.is_empty() {
            break;
        }
        // An e-stop is sent again to each robot that has not confirmed it: a stop is taken
        // whatever its sequence, and one put can be lost (a robot whose link is coming up, a
        // router that has not yet seen its subscription). A reset is sent once (sent again, it
        // could clear an e-stop another operator gave after it), when the robot is first heard
        // from: sent before its link is up, it would be lost.
        let to_send: Vec<&String> = if reset {
            let heard = heard.lock().unwrap_or_else(PoisonError::into_inner);
            pending.iter().filter(|r| heard.contains(*r) && !reset_sent.contains(*r)).collect()
        } else if tokio::time::Instant::now() >= next_send {
            next_send += ESTOP_RESEND;
            pending.iter().collect()
        } else {
            Vec::new()
        };
        for robot in to_send {
            reset_sent.insert(robot.clone());
            let Some(stamper) = stampers.get_mut(robot.as_str()) else { continue };
            let now = clock.now_s();
            let (stamp, body) = from_downlink(&msg, now);
            let Some(bytes) = stamper.encode(stamp, now, body) else { continue };
            session
                .put(estop_key(robot, user), bytes)
                .priority(Priority::RealTime)
                .congestion_control(CongestionControl::Block)
                .express(true)
                .await
                .map_err(zerr)?;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    drop(subscribers);
    let _ = session.close().await;
    let outcome = seen.lock().unwrap_or_else(PoisonError::into_inner).clone();
    Ok(outcome)
}
