//! An operator's e-stop: published on each robot's own e-stop key as that operator, confirmed by
//! the robots' reports of their safety state.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_msgs::{Downlink, Uplink};
use zenoh::qos::{CongestionControl, Priority};

use super::{Stamper, estop_key, new_session, zerr};
use crate::settings::{NetError, NetSettings, PREFIX};
use crate::wire::{Envelope, from_downlink, to_uplink};

/// What an operator's e-stop (or reset) found: per robot, the safety state it reported after the
/// message was sent, if it confirmed within the time allowed.
pub type EstopOutcome = BTreeMap<String, Option<amr_msgs::SafetyState>>;

/// E-stop `robots` (or, with `reset`, clear their e-stop) as operator `user`: publish on each
/// robot's `fleet/<robot>/estop/<user>` at the highest priority, then wait up to `timeout` for each
/// robot's own report (its safety state comes up `fleet/<robot>/health` on every change and
/// periodically): `EStop`, or after a reset any other state. The server's access control lets only
/// `user` publish on its own key.
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
    let sent_at = clock.now_s();
    let mut subscribers = Vec::new();
    for robot in robots {
        let (seen, me) = (Arc::clone(&seen), robot.clone());
        let sub = session
            .declare_subscriber(format!("{PREFIX}/{robot}/health"))
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                let Ok(u) = Envelope::decode(&bytes).and_then(|env| to_uplink(env, &me, "health")) else {
                    return;
                };
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
    for robot in robots {
        let mut stamper = Stamper::new(sid, user, robot);
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
    let until = tokio::time::Instant::now() + timeout;
    // Bounded by `timeout`.
    while tokio::time::Instant::now() < until {
        if seen.lock().unwrap_or_else(PoisonError::into_inner).values().all(Option::is_some) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    drop(subscribers);
    let _ = session.close().await;
    let outcome = seen.lock().unwrap_or_else(PoisonError::into_inner).clone();
    Ok(outcome)
}
