//! FormationActor: drives the pair (or N robots) as one rigid body. It follows V's reference plan
//! (the scenario's segments, trapezoidal profiles inside the limits) and sends each robot its Eq. 20
//! twist plus a correction towards its slot, closed on the latest localisation carried forward
//! with odometry.
//!
//! It arms the robots only when every one is healthy and localised; when a robot is lost it holds
//! (zero twist, robots stay armed, the plan pauses) or stops (robots disarmed), as configured. A
//! robot that stopped on its own — watchdog, e-stop, fault — stops the formation, and only an
//! explicit re-arm resumes it.
//!
//! It is one file because it is one state machine: each phase (waiting, arming, running, holding,
//! stopped) is a step of the same tick over the same `FormationState`, and the phases share the
//! helpers that send, stop, steer and re-form; `FormationHarness` drives that same actor's handler.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use amr_core::config::{OnRobotLost, ScenarioLimits};
use amr_core::formation::{FormationGains, limit_twist, member_command, reform_command};
use amr_core::plan::Reference;
use amr_core::se2::Se2;
use amr_core::vamr::frame::virtual_frame;
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::ServerPorts;
use crate::link::DownlinkSender;
use amr_msgs::{Anchored, Estimate, EstimateIntegrity, EstimateSource, FusionStatus};
use amr_msgs::{Command, Device, Downlink, Health, OdomMsg, SafetyState, Uplink};

/// An estimate older than this is not used for control, s.
pub(crate) const ESTIMATE_FRESH_S: f64 = 0.5;
/// Robots that do not confirm an arm within this long are asked again, s.
const ARM_TIMEOUT_S: f64 = 2.0;

/// A twist for V older than this is silence: the formation stops (holds, armed) until the next.
pub const TELEOP_TIMEOUT_S: f64 = 0.5;
/// A robot this far from its slot, as the first robot sees it (m, rad), stops the plan: the formation re-forms
/// before it goes on. Its tracking law corrects small errors while V moves; from far off it can
/// steer a robot the wrong way (in the chaos soak, one drove through the site's wall).
const OUT_OF_SHAPE: (f64, f64) = (0.25, 0.26);
/// A robot farther than this from its slot around the plan's point, m, is not re-formed: the
/// formation holds at rest (an operator brings it back).
const REFORM_MAX_M: f64 = 2.0;
/// Re-formed: the shape this close to the slots (m, rad), or every robot standing in its slot by
/// the go-to-pose law (which lets a robot stand up to `REFORM_NEAR_M` beside it), and the plan
/// goes on.
const BACK_IN_SHAPE: (f64, f64) = (0.06, 0.07);
/// A formation that is first armed with V farther than this from the plan's start (a restarted
/// server: the robots are where the last one left them) resumes the plan where V is, m and rad.
const AWAY_FROM_START_M: f64 = 0.25;
const AWAY_FROM_START_RAD: f64 = 0.25;
/// Heading weight of the whole-plan search for where V is, m per rad.
const HEADING_WEIGHT_M_PER_RAD: f64 = 0.5;
/// How close V must be to a plan point after the recorded progress, in position and heading, for a
/// fresh formation to resume there.
const RESUME_MATCH_M: f64 = 0.5;
const RESUME_MATCH_RAD: f64 = 0.35;
/// Around the recorded progress (this much plan time before and after it), the best match to V is
/// taken if it is this close: the formation lags its plan in turns (here by up to 0.4 m and 0.5 rad
/// measured) and coasts when its server dies.
const RESUME_BACK_S: f64 = 10.0;
const RESUME_AHEAD_S: f64 = 10.0;
const RESUME_NEAR_M: f64 = 0.75;
const RESUME_NEAR_RAD: f64 = 0.8;

/// Where the formation is.
#[derive(Debug, Clone, PartialEq)]
pub enum Phase {
    /// Waiting for every robot to be healthy and localised.
    Waiting,
    /// Arm sent; waiting for every robot to confirm.
    Arming {
        since_s: f64,
    },
    Running,
    /// A robot is lost: zero twist, the plan paused, resuming by itself when it returns.
    Holding {
        reason: String,
    },
    /// Stopped: robots disarmed, waiting for an explicit re-arm.
    Stopped {
        reason: String,
    },
    /// The plan is done; robots disarmed.
    Finished,
}

/// What the formation actor reports.
#[derive(Debug, Clone, PartialEq)]
pub struct FormationStatus {
    pub phase: Phase,
    /// Time into the plan, s.
    pub plan_s: f64,
    pub plan_len_s: f64,
    /// The integrity of the latest fresh estimate of V (`None`: none fresh).
    pub v_integrity: Option<EstimateIntegrity>,
}

/// Settings of the formation actor.
#[derive(Debug, Clone)]
pub(crate) struct FormationParams {
    /// V's reference, sampled every `period_s`.
    pub plan: Arc<Vec<Reference>>,
    /// The plan's identity in `progress`.
    pub plan_id: String,
    /// How far the formation got, across restarts of the server.
    pub progress: Arc<super::progress::PlanProgress>,
    pub period_s: f64,
    /// Per robot: lateral slot in V.
    pub slots: Vec<f64>,
    pub gains: FormationGains,
    pub limits: ScenarioLimits,
    pub on_robot_lost: OnRobotLost,
    /// Arm by itself, once per server run, as soon as everything is ready; otherwise wait for
    /// [`FormationMsg::Rearm`].
    pub auto_arm: super::AutoArm,
    /// A formation of this server run has run (after that only the operator arms).
    pub auto_armed: Arc<std::sync::atomic::AtomicBool>,
}

/// Messages of the formation actor.
#[derive(Debug)]
pub enum FormationMsg {
    Tick,
    Uplink(Box<Uplink>),
    Estimate(Box<Estimate>),
    Fusion(FusionStatus),
    /// The operator allows the formation to (re)start.
    Rearm,
    /// The operator stops the formation.
    Stop,
    /// A twist for V from outside (a teleop, or nav2's controller, on ROS 2's `/cmd_vel`), m/s and
    /// rad/s: from the first one on the formation follows these instead of its plan (the plan
    /// paused), through the same checks, the formation law and every robot's limits; each holds for
    /// [`TELEOP_TIMEOUT_S`], then V stops.
    Twist {
        v_mps: f64,
        w_radps: f64,
    },
    Status(ractor::RpcReplyPort<FormationStatus>),
}

/// The formation actor.
#[derive(Debug, Clone)]
pub(crate) struct FormationActor {
    pub ports: Arc<ServerPorts>,
    pub params: FormationParams,
    pub link: DownlinkSender,
    pub status: Arc<ractor::OutputPort<FormationStatus>>,
}

#[derive(Debug, Default, Clone)]
struct RobotView {
    health: BTreeMap<Device, Health>,
    safety: Option<SafetyState>,
    /// The robot's stop counter, as last reported: an arm carries it.
    stops: u64,
    /// It reports mock devices.
    mock: bool,
    odom: Option<OdomMsg>,
    /// When the robot's current odometry frame began (its first pose's stamp): an estimate
    /// anchored on a scan from before belongs to the old frame.
    frame_start_s: f64,
    fused: Option<Anchored>,
    /// The integrity of the estimate `fused` came from.
    fused_integrity: EstimateIntegrity,
    own: Option<Anchored>,
    /// The integrity of the estimate `own` came from.
    own_integrity: EstimateIntegrity,
    seq: u64,
    last_cmd: (f64, f64),
}

#[derive(Debug)]
pub(crate) struct FormationState {
    phase: Phase,
    robots: Vec<RobotView>,
    plan_s: f64,
    lost: Option<usize>,
    arm_allowed: bool,
    /// The operator allowed the arm (`rearm`), not `auto_arm`.
    by_operator: bool,
    /// Auto-arm was refused for robots on real hardware (said once).
    auto_refused: bool,
    /// How far an earlier formation on this plan got (this one resumes there or after, never
    /// before), s.
    record_s: Option<f64>,
    published: Option<FormationStatus>,
    /// When it was published, fleet-clock seconds.
    published_at_s: f64,
    /// Re-forming: a robot was out of shape, and not every one is back in it yet.
    reforming: bool,
    /// Teleoperated: the last twist for V and when it came (fleet clock, s).
    teleop: Option<(f64, f64, f64)>,
}

impl RobotView {
    /// Whether the robot's pose may be driven on: a fresh fused estimate whose V is tracking and
    /// agrees with the robots' own estimates; the reason if not.
    fn verified(&self, now_s: f64, names: &[String]) -> Result<(), String> {
        if self.fused.is_none_or(|a| now_s - a.stamp_s > ESTIMATE_FRESH_S) {
            return Err("no fresh estimate of V".to_owned());
        }
        let i = &self.fused_integrity;
        if i.state != amr_msgs::IntegrityState::Tracking && i.ambiguous {
            return Err(format!(
                "V is {}: another place explains its scans as well (the map explains {:.0} % of its scan there, {:.0} % where tracked)",
                i.state,
                i.explained * 100.0,
                i.level * 100.0
            ));
        }
        if i.state != amr_msgs::IntegrityState::Tracking {
            return Err(format!(
                "V is {} (the map explains {:.0} % of its scan, {:.0} % where tracked)",
                i.state,
                i.explained * 100.0,
                i.level * 100.0
            ));
        }
        if let Some(j) = i.disagrees {
            let who = names.get(j as usize).map_or("a robot", String::as_str);
            return Err(format!("{who}'s own estimate disagrees with V's"));
        }
        Ok(())
    }

    /// The robot's pose now by its own estimate alone, when that is fresh and verified.
    fn own_verified_now(&self, now_s: f64) -> Option<Se2> {
        let odom = self.odom?;
        let a = self.own.filter(|a| now_s - a.stamp_s <= ESTIMATE_FRESH_S)?;
        self.own_integrity.verified().then(|| a.map * (a.odom.inverse() * odom.pose)).filter(finite)
    }

    fn devices_ok(&self) -> bool {
        [Device::Lidar, Device::CanBus, Device::Drives]
            .iter()
            .all(|d| self.health.get(d).is_some_and(|h| *h == Health::Ok))
    }

    /// The robot's pose in the map now: the freshest usable estimate carried forward by odometry.
    fn pose_now(&self, now_s: f64) -> Option<amr_core::se2::Se2> {
        let odom = self.odom?;
        let fresh = |a: &Option<Anchored>| a.filter(|a| now_s - a.stamp_s <= ESTIMATE_FRESH_S);
        let a = fresh(&self.fused).or(fresh(&self.own))?;
        Some(a.map * (a.odom.inverse() * odom.pose)).filter(finite)
    }
}

/// A pose that is not finite (from odometry or an estimate that is not) is no pose.
fn finite(p: &Se2) -> bool {
    p.x.is_finite() && p.y.is_finite() && p.theta.is_finite()
}

/// What one tick checks before the phase decides.
#[derive(Debug)]
struct Checks {
    now: f64,
    /// Every robot's devices are Ok.
    healthy: bool,
    /// Every robot localised and healthy, none lost.
    ready: bool,
    /// The first robot whose pose is not verified, and why.
    unverified: Option<String>,
    /// The first robot that stopped by itself (e-stop, fault, disarmed), and how.
    stopped_by_robot: Option<(usize, SafetyState)>,
}

impl FormationActor {
    fn send(&self, robot: usize, state: &mut FormationState, msg: impl FnOnce(u64) -> Downlink) {
        let r = &mut state.robots[robot];
        r.seq += 1;
        let m = msg(r.seq);
        self.ports.commands.send((robot, m));
        if !self.link.send(&self.ports.robots[robot], m) {
            tracing::debug!(robot = %self.ports.robots[robot], "formation: downlink full or closed");
        }
    }

    fn command_all_zero(&self, state: &mut FormationState, now: f64) {
        for i in 0..state.robots.len() {
            state.robots[i].last_cmd = (0.0, 0.0);
            self.send(i, state, |seq| {
                Downlink::Command(Command { seq, stamp_s: now, v_mps: 0.0, w_radps: 0.0 })
            });
        }
    }

    fn disarm_all(&self, state: &mut FormationState) {
        for i in 0..state.robots.len() {
            self.send(i, state, |_| Downlink::Disarm);
        }
    }

    fn stop(&self, state: &mut FormationState, reason: String) {
        tracing::warn!(%reason, "formation stopped");
        self.disarm_all(state);
        state.phase = Phase::Stopped { reason };
        state.arm_allowed = false;
    }

    fn tick(&self, state: &mut FormationState) {
        let now = self.ports.clock.now_s();
        let localised = state.robots.iter().all(|r| r.pose_now(now).is_some());
        let healthy = state.robots.iter().all(RobotView::devices_ok);
        let checks = Checks {
            now,
            healthy,
            ready: localised && healthy && state.lost.is_none(),
            unverified: state.robots.iter().find_map(|r| r.verified(now, &self.ports.robots).err()),
            stopped_by_robot: state.robots.iter().enumerate().find_map(|(i, r)| match r.safety {
                Some(s @ (SafetyState::EStop | SafetyState::Fault | SafetyState::Disarmed(_))) => {
                    Some((i, s))
                }
                _ => None,
            }),
        };
        match state.phase.clone() {
            Phase::Waiting => self.wait(state, &checks),
            Phase::Arming { since_s } => self.arming(state, since_s, now),
            Phase::Running | Phase::Holding { .. } => self.drive(state, checks),
            Phase::Stopped { .. } => {
                if state.arm_allowed {
                    state.phase = Phase::Waiting;
                }
            }
            Phase::Finished => {}
        }
    }

    /// Waiting: arm when every check allows it (and the operator or `--auto-arm` does).
    fn wait(&self, state: &mut FormationState, checks: &Checks) {
        let (now, ready, unverified) = (checks.now, checks.ready, &checks.unverified);
        // A formation that has run before (this one, or an earlier one on this plan, as
        // the progress record says: a restarted server) may arm on its robots' own
        // verified estimates alone: it then holds, closing up on its slots (the plan
        // paused) until V is verified. After faults the robots may stand where the fusion
        // cannot find one of them again, and disarmed they would never move back. A fresh
        // job, its robots placed in their slots, waits for V.
        let own_verified = state.robots.iter().all(|r| r.own_verified_now(now).is_some());
        let has_run = state.plan_s > 0.0 || state.record_s.is_some();
        let may_reform = has_run && own_verified;
        // `--auto-arm` moves only robots that say they drive mock devices.
        let mock: Vec<bool> = state.robots.iter().map(|r| r.mock).collect();
        let auto_may = arm_authorised(self.params.auto_arm, state.by_operator, &mock);
        // No arm while a robot is latched in e-stop or fault: it would refuse it, and the
        // others would be armed beside it.
        let latched =
            state.robots.iter().any(|r| matches!(r.safety, Some(SafetyState::EStop | SafetyState::Fault)));
        if latched && state.arm_allowed {
            // A reset of the latch must not start the formation (ISO 13850): a re-arm
            // given before it lapses, and the operator gives a new one after the reset.
            tracing::warn!("formation: a robot is e-stopped or faulted; the re-arm lapses");
            state.arm_allowed = false;
            state.by_operator = false;
        }
        let may_arm = ready && !latched && (unverified.is_none() || may_reform) && state.arm_allowed;
        if may_arm && !auto_may {
            if !state.auto_refused {
                let real: Vec<&String> = state
                    .robots
                    .iter()
                    .zip(self.ports.robots.iter())
                    .filter(|(r, _)| !r.mock)
                    .map(|(_, n)| n)
                    .collect();
                tracing::warn!(
                    ?real,
                    "auto-arm: these robots drive real hardware; waiting for the operator's rearm"
                );
                state.auto_refused = true;
            }
        } else if may_arm {
            if state.teleop.is_some() {
                // Teleoperated: no plan point to resume at.
            } else if state.plan_s > 0.0 {
                self.resync_plan(state, now);
            } else if state.record_s.is_some() || self.away_from_start(state, now) {
                self.resume_where_v_is(state, now);
            }
            for i in 0..state.robots.len() {
                let stops = state.robots[i].stops;
                self.send(i, state, |seq| Downlink::Arm { seq: seq + 1, stops, stamp_s: now });
            }
            state.phase = Phase::Arming { since_s: now };
        }
    }

    /// Arming: running once every robot is armed, waiting again after [`ARM_TIMEOUT_S`].
    fn arming(&self, state: &mut FormationState, since_s: f64, now: f64) {
        if state.robots.iter().all(|r| r.safety == Some(SafetyState::Armed)) {
            tracing::info!(plan_s = state.plan_s, "formation running");
            self.params.auto_armed.store(true, std::sync::atomic::Ordering::SeqCst);
            state.phase = Phase::Running;
        } else if now - since_s > ARM_TIMEOUT_S {
            state.phase = Phase::Waiting;
        } else {
            self.command_all_zero(state, now);
        }
    }

    /// Running or holding: stop on a robot's stop, hold while a check fails (saying which), else
    /// follow the teleoperator or the plan.
    fn drive(&self, state: &mut FormationState, checks: Checks) {
        let Checks { now, healthy, ready, unverified, stopped_by_robot } = checks;
        if let Some((i, s)) = stopped_by_robot {
            let reason = format!("{} is {s:?}", self.ports.robots[i]);
            self.stop(state, reason);
        } else if !ready {
            let reason = match state.lost {
                Some(i) => format!("{}'s scans stopped", self.ports.robots[i]),
                None if !healthy => "a robot's devices are not all Ok".to_owned(),
                None => "a robot is not localised".to_owned(),
            };
            match self.params.on_robot_lost {
                OnRobotLost::Stop => self.stop(state, reason),
                OnRobotLost::Hold => {
                    if !matches!(state.phase, Phase::Holding { .. }) {
                        tracing::warn!(%reason, "formation holding");
                    }
                    self.command_all_zero(state, now);
                    state.phase = Phase::Holding { reason };
                }
            }
        } else if let Some(why) = unverified {
            // Never on an unverified pose: hold (zero twist, robots armed, the plan
            // paused) whatever `on_robot_lost` says, and resume by itself once verified.
            let reason = format!("localisation not verified: {why}");
            if state.phase != (Phase::Holding { reason: reason.clone() }) {
                tracing::warn!(%reason, "formation holding");
            }
            // With no fused estimate at all but every robot's own estimate verified, the
            // robots close up on their slots around the paused plan point (on those
            // verified poses, the plan not advancing): a formation that stopped, coasted
            // or was pushed out of shape may stand where the fusion cannot find a robot
            // again, and holding there it never would.
            if !self.reform(state, now) {
                self.command_all_zero(state, now);
            }
            state.phase = Phase::Holding { reason };
        } else if let Some(why) = self.out_of_shape(state, now) {
            // On a verified V, but a robot is far from its slot: the plan waits while
            // every robot drives to its slot around the plan's point.
            let (who, detail) = why;
            let reason = format!("re-forming: {who} is out of its slot");
            if state.phase != (Phase::Holding { reason: reason.clone() }) {
                tracing::warn!(%reason, %detail, "formation holding");
            }
            let poses: Option<Vec<Se2>> = state.robots.iter().map(|r| r.pose_now(now)).collect();
            if !poses.is_some_and(|p| self.reform_around_plan(state, now, &p)) {
                self.command_all_zero(state, now);
            }
            state.phase = Phase::Holding { reason };
        } else if let Some((_, _, at)) = state.teleop {
            self.teleoperate(state, now, at);
        } else {
            self.follow_plan(state, now);
        }
    }

    /// On a verified V in shape: the plan's next point, every robot steered to its slot around it;
    /// at the plan's end the formation stops, disarmed, finished.
    fn follow_plan(&self, state: &mut FormationState, now: f64) {
        let dt = self.params.period_s;
        if matches!(state.phase, Phase::Holding { .. }) {
            self.resync_plan(state, now);
        }
        state.phase = Phase::Running;
        let k = (state.plan_s / dt).round() as usize;
        let Some(r) = self.params.plan.get(k).copied() else {
            tracing::info!("formation: plan finished");
            self.params.progress.clear();
            self.command_all_zero(state, now);
            self.disarm_all(state);
            state.phase = Phase::Finished;
            return;
        };
        for i in 0..state.robots.len() {
            let Some(pose) = state.robots[i].pose_now(now) else { continue };
            self.steer(state, i, &r, pose, (r.v_mps, r.w_radps), now);
        }
        state.plan_s += dt;
        self.params.progress.note(&self.params.plan_id, state.plan_s);
    }

    /// Teleoperated, on a verified V in shape: every robot follows V's last twist (received at
    /// `at`) from its slot, within its limits; once the twist is older than [`TELEOP_TIMEOUT_S`], V
    /// stops and the formation holds, armed, until the next.
    fn teleoperate(&self, state: &mut FormationState, now: f64, at: f64) {
        if now - at > TELEOP_TIMEOUT_S {
            let reason = format!("teleoperated: no twist for V in {TELEOP_TIMEOUT_S} s");
            if state.phase != (Phase::Holding { reason: reason.clone() }) {
                tracing::info!(%reason, "formation holding");
            }
            self.command_all_zero(state, now);
            state.phase = Phase::Holding { reason };
            return;
        }
        let Some(r) = self.reference(state, now) else {
            self.command_all_zero(state, now);
            return;
        };
        state.phase = Phase::Running;
        for i in 0..state.robots.len() {
            let Some(pose) = state.robots[i].pose_now(now) else { continue };
            self.steer(state, i, &r, pose, (r.v_mps, r.w_radps), now);
        }
    }

    /// Drive every robot towards its slot around the plan's current point on its own verified
    /// estimate, when there is no fresh fused estimate and every robot has one; whether it did.
    fn reform(&self, state: &mut FormationState, now: f64) -> bool {
        let fused = state.robots.iter().any(|r| r.fused.is_some_and(|a| now - a.stamp_s <= ESTIMATE_FRESH_S));
        let poses: Option<Vec<Se2>> = state.robots.iter().map(|r| r.own_verified_now(now)).collect();
        match (fused, poses) {
            (false, Some(poses)) => self.reform_around_plan(state, now, &poses),
            _ => false,
        }
    }

    /// Drive every robot, at `poses`, to its slot around the plan's current point, the plan
    /// paused; whether it did (not past the plan's end, nor with a robot farther than
    /// [`REFORM_MAX_M`] from its slot). With V at rest the tracking law cannot move a robot
    /// sideways (a differential drive moves sideways only while it moves): the go-to-pose law
    /// does.
    fn reform_around_plan(&self, state: &mut FormationState, now: f64, poses: &[Se2]) -> bool {
        let Some(r) = self.reference(state, now) else { return false };
        // Farther than this, a robot is not driven back on its own: the way may not be clear.
        let far = poses.iter().zip(&self.params.slots).any(|(p, slot)| {
            let in_v = r.pose.inverse() * *p;
            in_v.x.hypot(in_v.y - slot) > REFORM_MAX_M
        });
        if far {
            return false;
        }
        for (i, pose) in poses.iter().enumerate() {
            let cmd = reform_command(self.params.slots[i], &(r.pose.inverse() * *pose));
            self.send_limited(state, i, cmd, now);
        }
        true
    }

    /// The robot farthest from its slot as the first robot sees it, while the formation is out of
    /// shape: its name, and how far. Out of shape from [`OUT_OF_SHAPE`] on, and until every robot
    /// stands in its slot around the plan's point (the go-to-pose law at rest) or the shape is
    /// within [`BACK_IN_SHAPE`].
    fn out_of_shape(&self, state: &mut FormationState, now: f64) -> Option<(String, String)> {
        let poses: Option<Vec<Se2>> = state.robots.iter().map(|r| r.pose_now(now)).collect();
        let poses = poses?;
        let (first, first_slot) = (*poses.first()?, *self.params.slots.first()?);
        // Each robot where the first one sees it, against where its slot puts it: the shape,
        // whatever V's own error.
        let (i, m, rad) = poses
            .iter()
            .zip(&self.params.slots)
            .enumerate()
            .skip(1)
            .map(|(i, (p, slot))| {
                let seen = first.inverse() * *p;
                (i, seen.x.hypot(seen.y - (slot - first_slot)), seen.theta.abs())
            })
            .max_by(|a, b| {
                (a.1 + HEADING_WEIGHT_M_PER_RAD * a.2).total_cmp(&(b.1 + HEADING_WEIGHT_M_PER_RAD * b.2))
            })?;
        let reference = self.reference(state, now);
        state.reforming = if state.reforming {
            let at_rest = reference.is_some_and(|r| {
                poses
                    .iter()
                    .zip(&self.params.slots)
                    .all(|(p, slot)| reform_command(*slot, &(r.pose.inverse() * *p)) == (0.0, 0.0))
            });
            !at_rest && (m > BACK_IN_SHAPE.0 || rad > BACK_IN_SHAPE.1)
        } else {
            m > OUT_OF_SHAPE.0 || rad > OUT_OF_SHAPE.1
        };
        if !state.reforming {
            return None;
        }
        let who = self.ports.robots.get(i).map_or("a robot", String::as_str).to_owned();
        Some((who, format!("{m:.2} m and {:.0}° from its slot", rad.to_degrees())))
    }

    /// What the formation follows now: while teleoperated, V where the robots stand, with the last
    /// twist (zero once it is older than [`TELEOP_TIMEOUT_S`]); else the plan's current point.
    fn reference(&self, state: &FormationState, now: f64) -> Option<Reference> {
        match state.teleop {
            Some((v, w, at)) => {
                let (v_mps, w_radps) = if now - at <= TELEOP_TIMEOUT_S { (v, w) } else { (0.0, 0.0) };
                Self::v_now(state, now).map(|pose| Reference { pose, v_mps, w_radps })
            }
            None => self.params.plan.get((state.plan_s / self.params.period_s).round() as usize).copied(),
        }
    }

    /// Command robot `i`, at `pose`, V's twist `(v, w)` plus the correction towards its slot
    /// around the plan point `r`, within the limits.
    fn steer(
        &self,
        state: &mut FormationState,
        i: usize,
        r: &Reference,
        pose: Se2,
        (v, w): (f64, f64),
        now: f64,
    ) {
        let in_v = r.pose.inverse() * pose;
        let cmd = member_command(v, w, self.params.slots[i], &in_v, &self.params.gains);
        self.send_limited(state, i, cmd, now);
    }

    /// Command robot `i` the twist `cmd` within the limits.
    fn send_limited(&self, state: &mut FormationState, i: usize, cmd: (f64, f64), now: f64) {
        // A pose far beyond any map can overflow the correction: then the robot is slowed to rest.
        let cmd = if cmd.0.is_finite() && cmd.1.is_finite() { cmd } else { (0.0, 0.0) };
        let lim = &self.params.limits;
        let cmd = limit_twist(
            cmd,
            state.robots[i].last_cmd,
            self.params.period_s,
            lim.max_speed_mps.get(),
            lim.max_yaw_rate_radps.get(),
            lim.max_accel_mps2.get(),
        );
        state.robots[i].last_cmd = cmd;
        self.send(i, state, |seq| {
            Downlink::Command(Command { seq, stamp_s: now, v_mps: cmd.0, w_radps: cmd.1 })
        });
    }

    /// V in the map now, from every robot's pose.
    fn v_now(state: &FormationState, now: f64) -> Option<Se2> {
        let poses: Option<Vec<Se2>> = state.robots.iter().map(|r| r.pose_now(now)).collect();
        let poses = poses?;
        let first = *poses.first()?;
        let rel: Vec<(Se2, f64)> = poses.iter().map(|q| (first.inverse() * *q, 1.0)).collect();
        Some(first * virtual_frame(&rel))
    }

    /// Whether V is away from the plan's start (in position or heading).
    fn away_from_start(&self, state: &FormationState, now: f64) -> bool {
        let (Some(v), Some(start)) = (Self::v_now(state, now), self.params.plan.first()) else {
            return false;
        };
        let d = start.pose.inverse() * v;
        d.translation_norm() > AWAY_FROM_START_M || d.theta.abs() > AWAY_FROM_START_RAD
    }

    /// A fresh formation: resume the plan where an earlier formation on this plan got (the record;
    /// the plan's start without one) and V is. Around the record (the formation lags its plan, and
    /// coasts when its server dies) the best match to V, if close; else the first point after the
    /// record that matches V, and on down to the best match of that pass. On a plan of laps every
    /// lap passes the same places: the first match after the record is the lap the job was in,
    /// never a later one.
    fn resume_where_v_is(&self, state: &mut FormationState, now: f64) {
        let Some(v) = Self::v_now(state, now) else { return };
        let off = |r: &Reference| {
            let d = r.pose.inverse() * v;
            (d.translation_norm(), d.theta.abs())
        };
        let cost = |r: &Reference| {
            let (m, rad) = off(r);
            m + HEADING_WEIGHT_M_PER_RAD * rad
        };
        let dt = self.params.period_s;
        let plan = &self.params.plan;
        let k0 = state.record_s.map_or(0, |s| ((s / dt).floor().max(0.0) as usize).min(plan.len()));
        let steps = |s: f64| (s / dt).round() as usize;
        let around = plan
            .iter()
            .enumerate()
            .skip(k0.saturating_sub(steps(RESUME_BACK_S)))
            .take(steps(RESUME_BACK_S + RESUME_AHEAD_S))
            .min_by(|(_, a), (_, b)| cost(a).total_cmp(&cost(b)))
            .filter(|(_, r)| {
                let (m, rad) = off(r);
                m <= RESUME_NEAR_M && rad <= RESUME_NEAR_RAD
            });
        let after = || {
            let (mut k, _) = plan.iter().enumerate().skip(k0).find(|(_, r)| {
                let (m, rad) = off(r);
                m <= RESUME_MATCH_M && rad <= RESUME_MATCH_RAD
            })?;
            while plan.get(k + 1).is_some_and(|n| cost(n) <= cost(&plan[k])) {
                k += 1;
            }
            Some(k)
        };
        let k = match around.map(|(k, _)| k).or_else(after) {
            Some(k) => k,
            None => {
                // V matches no plan point after the record: the nearest one after it (never before).
                let best =
                    plan.iter().enumerate().skip(k0).min_by(|(_, a), (_, b)| cost(a).total_cmp(&cost(b)));
                let Some((k, r)) = best else { return };
                tracing::warn!(
                    from_s = k0 as f64 * dt,
                    off_m = off(r).0,
                    "formation: V matches no plan point after the recorded progress; resuming at the nearest"
                );
                k
            }
        };
        tracing::info!(
            record_s = ?state.record_s,
            to_s = k as f64 * dt,
            "formation: resuming where the job was and V is"
        );
        state.plan_s = k as f64 * dt;
    }

    /// After a stop the robots coasted on (ramping down) while the plan was paused: resume the plan
    /// at its point closest to where V is now, searching forward only.
    fn resync_plan(&self, state: &mut FormationState, now: f64) {
        let poses: Option<Vec<Se2>> = state.robots.iter().map(|r| r.pose_now(now)).collect();
        let weighted: Option<Vec<(Se2, f64)>> = poses.as_ref().and_then(|p| {
            let first = p.first()?;
            Some(p.iter().map(|q| (first.inverse() * *q, 1.0)).collect())
        });
        let (Some(poses), Some(rel)) = (poses, weighted) else { return };
        let v = poses[0] * virtual_frame(&rel);
        let dt = self.params.period_s;
        let k0 = (state.plan_s / dt).round() as usize;
        if let Some(k) = nearest_ahead(&self.params.plan, k0, (30.0 / dt) as usize, v) {
            tracing::info!(from_s = state.plan_s, to_s = k as f64 * dt, "formation: plan resumed where V is");
            state.plan_s = k as f64 * dt;
        }
    }

    /// The status now.
    fn status(&self, state: &FormationState) -> FormationStatus {
        let now = self.ports.clock.now_s();
        let v = state.robots.first().filter(|r| r.fused.is_some_and(|a| now - a.stamp_s <= ESTIMATE_FRESH_S));
        FormationStatus {
            phase: state.phase.clone(),
            plan_s: state.plan_s,
            plan_len_s: self.params.plan.len() as f64 * self.params.period_s,
            v_integrity: v.map(|r| r.fused_integrity),
        }
    }

    fn publish(&self, state: &mut FormationState) {
        let s = self.status(state);
        // Changes at once; progress while running about once a second; and the status as it is
        // at least once a second, so an observer that subscribed late (a recorder, a restarted
        // server's watcher) learns the phase without waiting for the next change.
        let now = self.ports.clock.now_s();
        let progressed = state.published.as_ref().is_none_or(|p| (s.plan_s - p.plan_s).abs() >= 1.0);
        let stale = now - state.published_at_s >= 1.0;
        if state.published.as_ref().map(|p| &p.phase) != Some(&s.phase) || progressed || stale {
            self.status.send(s.clone());
        } else {
            return;
        }
        state.published = Some(s);
        state.published_at_s = now;
    }
}

impl Actor for FormationActor {
    type Msg = FormationMsg;
    type State = FormationState;
    type Arguments = ();

    async fn pre_start(
        &self,
        myself: ActorRef<FormationMsg>,
        (): (),
    ) -> Result<FormationState, ActorProcessingErr> {
        self.ports.uplink.subscribe(myself.clone(), |(u, _)| match u {
            Uplink::Scan(_) => None,
            other => Some(FormationMsg::Uplink(Box::new(other))),
        });
        self.ports.estimates.subscribe(myself.clone(), |e| Some(FormationMsg::Estimate(Box::new(e))));
        self.ports.status.subscribe(myself.clone(), |s| Some(FormationMsg::Fusion(s)));
        myself.send_interval(Duration::from_secs_f64(self.params.period_s.max(0.01)), || FormationMsg::Tick);
        // Sequence numbers start at the fleet clock in milliseconds: a robot refuses any command not
        // newer than the last it accepted, so a restarted formation (a new server) must number
        // above its predecessor, which sent at most 21 messages a second since its own start.
        let seq0 = (self.ports.clock.now_s().max(0.0) * 1000.0) as u64;
        Ok(FormationState {
            phase: Phase::Waiting,
            robots: vec![RobotView { seq: seq0, ..RobotView::default() }; self.ports.robots.len()],
            plan_s: 0.0,
            lost: None,
            arm_allowed: self.params.auto_arm != super::AutoArm::Off
                && !self.params.auto_armed.load(std::sync::atomic::Ordering::SeqCst),
            by_operator: false,
            auto_refused: false,
            record_s: self.params.progress.load(&self.params.plan_id),
            published: None,
            published_at_s: f64::NEG_INFINITY,
            reforming: false,
            teleop: None,
        })
    }

    async fn handle(
        &self,
        _myself: ActorRef<FormationMsg>,
        msg: FormationMsg,
        state: &mut FormationState,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            FormationMsg::Tick => self.tick(state),
            FormationMsg::Uplink(u) => {
                let Some(i) = self.ports.index(u.robot()) else { return Ok(()) };
                let r = &mut state.robots[i];
                match *u {
                    Uplink::Odom { msg, robot } => {
                        if r.odom.is_some_and(|o| o.frame != msg.frame) {
                            // The robot restarted its odometry (its `seq` starts again): the
                            // anchored estimates are of the old frame; its pose is unknown until
                            // an estimate of the new one comes (the formation holds meanwhile).
                            tracing::warn!(%robot, "odometry restarted in a new frame: dropping its old estimates");
                            r.fused = None;
                            r.own = None;
                            r.frame_start_s = msg.stamp_s;
                            r.odom = Some(msg);
                        } else if r.odom.is_none_or(|o| msg.seq > o.seq) {
                            if r.odom.is_none() {
                                r.frame_start_s = msg.stamp_s;
                            }
                            r.odom = Some(msg);
                        }
                    }
                    Uplink::Health { report, .. } => {
                        r.health.insert(report.device, report.health);
                    }
                    Uplink::Safety { state: s, stops, mock, .. } => {
                        r.safety = Some(s);
                        r.stops = stops;
                        r.mock = mock;
                    }
                    Uplink::Scan(_) => {}
                }
            }
            FormationMsg::Estimate(e) => {
                for (i, a) in e.robots.iter().enumerate() {
                    if let (Some(a), Some(r)) = (a, state.robots.get_mut(i)) {
                        if a.stamp_s < r.frame_start_s {
                            // From a scan of the old odometry frame (the localizer lags).
                            continue;
                        }
                        match e.source {
                            EstimateSource::Fused(_) => {
                                r.fused = Some(*a);
                                r.fused_integrity = e.integrity;
                            }
                            EstimateSource::Robot(_) => {
                                r.own = Some(*a);
                                r.own_integrity = e.integrity;
                            }
                        }
                    }
                }
            }
            FormationMsg::Fusion(s) => {
                state.lost = match s {
                    FusionStatus::Fusing => None,
                    FusionStatus::RobotLost(i) => Some(i),
                };
            }
            FormationMsg::Rearm => {
                tracing::info!("formation: re-arm by the operator");
                state.arm_allowed = true;
                state.by_operator = true;
                if matches!(state.phase, Phase::Stopped { .. }) {
                    state.phase = Phase::Waiting;
                }
            }
            FormationMsg::Stop => self.stop(state, "the operator stopped it".to_owned()),
            FormationMsg::Twist { v_mps, w_radps } => {
                if v_mps.is_finite() && w_radps.is_finite() {
                    if state.teleop.is_none() {
                        tracing::info!("formation: teleoperated from now on (the plan paused)");
                    }
                    state.teleop = Some((v_mps, w_radps, self.ports.clock.now_s()));
                } else {
                    tracing::warn!(v_mps, w_radps, "formation: a twist that is not finite, ignored");
                }
            }
            FormationMsg::Status(reply) => {
                let _ = reply.send(self.status(state));
            }
        }
        self.publish(state);
        Ok(())
    }
}

/// The point of `plan` from `k0` on, within `window` points, that best matches `v` (position, and
/// heading at [`HEADING_WEIGHT_M_PER_RAD`]): on a plan that turns on the spot every point of the
/// turn stands at the same position, and the position alone resumed a turn 90° further on.
fn nearest_ahead(plan: &[Reference], k0: usize, window: usize, v: Se2) -> Option<usize> {
    let cost = |r: &Reference| {
        let d = r.pose.inverse() * v;
        d.translation_norm() + HEADING_WEIGHT_M_PER_RAD * d.theta.abs()
    };
    plan.iter()
        .enumerate()
        .skip(k0)
        .take(window)
        .min_by(|(_, a), (_, b)| cost(a).total_cmp(&cost(b)))
        .map(|(k, _)| k)
}

/// Whether an allowed arm may be sent: the operator's `rearm` always; `--auto-arm` only if every
/// robot reports mock devices (`mock`), unless the operator allowed it on hardware too.
fn arm_authorised(auto_arm: super::AutoArm, by_operator: bool, mock: &[bool]) -> bool {
    use super::AutoArm;
    by_operator
        || match auto_arm {
            AutoArm::Off => false,
            AutoArm::Mock => mock.iter().all(|m| *m),
            AutoArm::Hardware => true,
        }
}

/// The formation actor's handling driven directly rather than through its mailbox (fuzzing): the
/// actor built as [`super::start_server`] builds it, its state from its own `pre_start`, each
/// message handled by its own `handle` at once (the handler never waits). No timer runs: ticks are
/// the caller's [`FormationMsg::Tick`]s. Its clock is the tokio clock (a paused one in a test
/// runtime). Must be used inside a tokio runtime.
#[doc(hidden)]
#[derive(Debug)]
pub struct FormationHarness {
    actor: FormationActor,
    state: FormationState,
    /// A stopped actor's reference in place of the formation's own, which its handler does not
    /// use.
    myself: ActorRef<FormationMsg>,
}

/// The stand-in behind [`FormationHarness`]'s own reference.
struct Ignore;

impl Actor for Ignore {
    type Msg = FormationMsg;
    type State = ();
    type Arguments = ();

    async fn pre_start(&self, _myself: ActorRef<FormationMsg>, (): ()) -> Result<(), ActorProcessingErr> {
        Ok(())
    }
}

impl FormationHarness {
    /// The formation of `setup`, sending on `link`, on `clock`.
    pub async fn new(
        setup: &super::ServerSetup,
        link: DownlinkSender,
        clock: crate::clock::FleetClock,
    ) -> Result<Self, ActorProcessingErr> {
        let ids = setup.robots.iter().map(|r| r.id.as_str().to_owned()).collect();
        let sc = &setup.scenario;
        let plan = amr_core::plan::reference(sc, setup.robots.len(), super::FORMATION_PERIOD_S);
        let actor = FormationActor {
            ports: ServerPorts::new(ids, clock),
            params: FormationParams {
                plan_id: super::progress::plan_id(&plan),
                progress: Arc::clone(&setup.progress),
                plan: Arc::new(plan),
                period_s: super::FORMATION_PERIOD_S,
                slots: amr_core::formation::slots(setup.robots.len(), sc.spacing_m.get()),
                gains: FormationGains::DEFAULT,
                limits: sc.limits,
                on_robot_lost: setup.server.on_robot_lost,
                auto_arm: setup.auto_arm,
                auto_armed: Arc::new(std::sync::atomic::AtomicBool::new(false)),
            },
            link,
            status: Arc::new(ractor::OutputPort::default()),
        };
        let (myself, _) = Actor::spawn(None, Ignore, ()).await?;
        let state = actor.pre_start(myself.clone(), ()).await;
        // Stopped, it ends the subscriptions and the timer `pre_start` gave it.
        myself.stop(None);
        Ok(FormationHarness { actor, state: state?, myself })
    }

    /// Handle `msg` as the actor does.
    pub fn handle(&mut self, msg: FormationMsg) -> Result<(), ActorProcessingErr> {
        let handled = self.actor.handle(self.myself.clone(), msg, &mut self.state);
        let mut handled = std::pin::pin!(handled);
        match handled.as_mut().poll(&mut std::task::Context::from_waker(std::task::Waker::noop())) {
            std::task::Poll::Ready(r) => r,
            std::task::Poll::Pending => Err("the formation's handler waited".into()),
        }
    }

    /// The status now.
    #[must_use]
    pub fn status(&self) -> FormationStatus {
        self.actor.status(&self.state)
    }
}

#[cfg(test)]
mod tests;
