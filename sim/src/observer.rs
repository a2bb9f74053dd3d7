//! The observer of a simulation: an actor that scores the fused estimates of V against the truth
//! and records the formation's status and phases, the robots' odometry poses and the health of
//! every device, for the simulation's status line and report.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use amr_actors::robot::RobotTree;
use amr_actors::server::ServerTree;
use amr_actors::server::formation::{FormationStatus, Phase};
use amr_core::se2::{Se2, angle_diff};
use amr_msgs::{Estimate, EstimateSource};
use amr_msgs::{Health, HealthReport};
use ractor::{Actor, ActorProcessingErr, ActorRef};
use tokio::task::JoinHandle;

use crate::options::SimError;
use crate::report;
use crate::truth::TruthLog;
use crate::world::v_of;

/// What the observer collected.
#[derive(Debug, Default)]
pub(crate) struct Observed {
    pub(crate) samples: Vec<report::ErrorSample>,
    /// Fused estimates of V waiting for the truth to pass their stamp (the world is sampled every
    /// physics step, so the latest estimate is usually a little ahead of it).
    pending: std::collections::VecDeque<(f64, Se2, bool)>,
    /// The integrity of the latest fused estimate.
    pub(crate) integrity: Option<amr_msgs::EstimateIntegrity>,
    pub(crate) health: BTreeMap<String, BTreeMap<String, (Health, Health)>>,
    pub(crate) formation: Option<FormationStatus>,
    /// Every formation phase seen, in order (a repeated phase once).
    pub(crate) phases: Vec<Phase>,
    /// The latest fused estimate: V, and each robot's pose with its odometry pose at the stamp.
    pub(crate) last_fused: Option<(Se2, Vec<Option<amr_msgs::Anchored>>)>,
    /// Each robot's latest odometry pose.
    pub(crate) odom: BTreeMap<String, Se2>,
}

/// The observer follows `server`'s estimates and formation.
pub(crate) fn observe_server(server: &ServerTree, observer: &ActorRef<ObserverMsg>) {
    server.ports.estimates.subscribe(observer.clone(), |e| Some(ObserverMsg::Estimate(Box::new(e))));
    server.formation.subscribe(observer.clone(), |s| Some(ObserverMsg::Formation(s)));
}

/// Start the observer on `server` and the robots `trees`, scoring V against `truth`: what it
/// collects, the observer itself, and the task that samples the robots' health boards into it.
pub(crate) async fn start(
    truth: &TruthLog,
    server: &ServerTree,
    trees: &[RobotTree],
) -> Result<(Arc<std::sync::Mutex<Observed>>, ActorRef<ObserverMsg>, JoinHandle<()>), SimError> {
    let observed = Arc::new(std::sync::Mutex::new(Observed::default()));
    let (observer, _) = Observer::spawn(
        None,
        Observer { observed: Arc::clone(&observed), truth: truth.clone(), weights_equal: true },
        (),
    )
    .await
    .map_err(|e| SimError::Mock("observer", e.to_string()))?;
    observe_server(server, &observer);
    for t in trees {
        let id = t.id.clone();
        t.ports.odom.subscribe(observer.clone(), move |m| Some(ObserverMsg::Odom(id.clone(), m.pose)));
    }
    let health_task = sample_health(trees, &observer);
    Ok((observed, observer, health_task))
}

/// The task that hands every device's state on the robots' health boards to the observer, every
/// 50 ms, until the observer is gone.
fn sample_health(trees: &[RobotTree], observer: &ActorRef<ObserverMsg>) -> JoinHandle<()> {
    // Health: the boards hold every device's state; sampling them misses nothing that lasts.
    let boards: Vec<(String, Arc<amr_actors::robot::ports::RobotPorts>)> =
        trees.iter().map(|t| (t.id.clone(), Arc::clone(&t.ports))).collect();
    let obs = observer.clone();
    tokio::spawn(async move {
        let mut every = tokio::time::interval(Duration::from_millis(50));
        loop {
            every.tick().await;
            for (id, ports) in &boards {
                let board: Vec<HealthReport> = ports.health_board.borrow().values().cloned().collect();
                for report in board {
                    if obs.cast(ObserverMsg::Health(id.clone(), report)).is_err() {
                        return;
                    }
                }
            }
        }
    })
}

/// Messages of the observer.
#[derive(Debug)]
pub(crate) enum ObserverMsg {
    Estimate(Box<Estimate>),
    Formation(FormationStatus),
    Health(String, HealthReport),
    /// A robot's odometry pose.
    Odom(String, Se2),
}

#[derive(Debug)]
struct Observer {
    observed: Arc<std::sync::Mutex<Observed>>,
    truth: TruthLog,
    weights_equal: bool,
}

impl Observer {
    /// Score every pending estimate the truth has caught up with.
    fn score(&self, o: &mut Observed) {
        let Some((latest, _)) = self.truth.latest() else { return };
        while let Some((t, v, verified)) = o.pending.front().copied() {
            if t > latest {
                return;
            }
            o.pending.pop_front();
            if let Some(truth) = self.truth.at(t).and_then(|p| v_of(&p)) {
                o.samples.push(report::ErrorSample {
                    t_s: t,
                    e_x_m: v.x - truth.x,
                    e_y_m: v.y - truth.y,
                    e_theta_rad: angle_diff(v.theta, truth.theta),
                    verified,
                });
            }
        }
    }
}

impl Actor for Observer {
    type Msg = ObserverMsg;
    type State = ();
    type Arguments = ();

    async fn pre_start(&self, _myself: ActorRef<ObserverMsg>, (): ()) -> Result<(), ActorProcessingErr> {
        Ok(())
    }

    async fn handle(
        &self,
        _myself: ActorRef<ObserverMsg>,
        msg: ObserverMsg,
        (): &mut (),
    ) -> Result<(), ActorProcessingErr> {
        let mut o = self.observed.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        match msg {
            ObserverMsg::Estimate(e) => {
                if let (EstimateSource::Fused(_), Some(v)) = (e.source, e.v) {
                    o.last_fused = Some((v, e.robots.clone()));
                    o.integrity = Some(e.integrity);
                    if self.weights_equal {
                        o.pending.push_back((e.stamp_s, v, e.integrity.verified()));
                    }
                }
                self.score(&mut o);
            }
            ObserverMsg::Odom(robot, pose) => {
                o.odom.insert(robot, pose);
            }
            ObserverMsg::Formation(s) => {
                if o.phases
                    .last()
                    .is_none_or(|p| std::mem::discriminant(p) != std::mem::discriminant(&s.phase))
                {
                    o.phases.push(s.phase.clone());
                }
                o.formation = Some(s);
            }
            ObserverMsg::Health(robot, h) => {
                let entry = o
                    .health
                    .entry(robot)
                    .or_default()
                    .entry(format!("{:?}", h.device))
                    .or_insert((h.health, h.health));
                if report::rank(h.health) < report::rank(entry.0) {
                    entry.0 = h.health;
                }
                entry.1 = h.health;
            }
        }
        Ok(())
    }
}
