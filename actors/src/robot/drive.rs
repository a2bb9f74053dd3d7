//! DriveActor: the two wheel drives as one differential drive, on the bus the CAN bus actor
//! provides. It enables the drives on every new connection, applies the safety layer's wheel
//! commands, recovers drive faults (bounded), and turns the encoder positions of each SYNC cycle
//! into wheel travel for odometry. Whatever way it ends — stop, error or panic — it commands zero
//! and a quick stop on its way out.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use amr_drivers::canopen::cia402::State402;
use amr_drivers::canopen::diff_drive::DiffDrive;
use amr_drivers::canopen::error::{CanopenError, LinkError};
use amr_drivers::canopen::frame::NodeId;
use amr_drivers::canopen::master::MasterEvent;
use amr_drivers::canopen::shell::MasterCommand;
use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::ports::{AbortOnDrop, BusLink, RobotPorts, SafetyInput, WheelCommand, WheelTravel};
use super::status::{Counters, HealthCell};
use amr_msgs::{Device, Health};

/// Time given to the master to send the quick stop before the bus goes down on shutdown.
pub(crate) const SHUTDOWN_FLUSH: std::time::Duration = std::time::Duration::from_millis(60);

/// Fault resets tried per drive before its fault is latched (the drive needs attention).
pub(crate) const MAX_FAULT_RESETS: u32 = 3;

/// Messages of the drive actor.
#[derive(Debug)]
pub(crate) enum DriveMsg {
    Bus(Option<BusLink>),
    /// The master's events are waiting in [`RobotPorts::bus_events`].
    Events,
    Master(MasterEvent),
    Wheels(WheelCommand),
}

/// The drive actor.
#[derive(Debug, Clone)]
pub(crate) struct DriveActor {
    pub ports: Arc<RobotPorts>,
    pub drive: DiffDrive,
    pub counters: Counters,
}

/// Its state. Dropping it (any way the actor ends) stops the wheels.
#[derive(Debug)]
pub(crate) struct DriveState {
    _watch: AbortOnDrop<()>,
    /// Wakes this actor when the master has events.
    _events: AbortOnDrop<()>,
    bus: Option<BusLink>,
    health: HealthCell,
    enabled: BTreeSet<NodeId>,
    states: BTreeMap<NodeId, State402>,
    resets: BTreeMap<NodeId, u32>,
    quick_stopped: bool,
    /// Per drive, whether its digital inputs read the e-stop pressed.
    inputs_pressed: std::collections::BTreeMap<NodeId, bool>,
    last_positions: Option<(i32, i32, f64)>,
    nodes: [NodeId; 2],
}

impl Drop for DriveState {
    fn drop(&mut self) {
        if let Some(bus) = &self.bus {
            let _ = bus.commands.try_send(MasterCommand::SetTargets(self.nodes.map(|n| (n, 0)).to_vec()));
            let _ = bus.commands.try_send(MasterCommand::QuickStop);
        }
    }
}

impl DriveActor {
    fn nodes(&self) -> [NodeId; 2] {
        [self.drive.drives().left.node_id, self.drive.drives().right.node_id]
    }

    /// Send `cmd` to the master; whether it was queued (false with no bus, or a full queue).
    fn send(&self, state: &DriveState, cmd: MasterCommand) -> bool {
        let Some(bus) = &state.bus else { return false };
        let sent = bus.commands.try_send(cmd).is_ok();
        if !sent {
            self.counters.count("drives.command_dropped");
        }
        sent
    }

    /// Ask for a quick stop (`true`) or enabled drives; remembered as done only once the master has
    /// it (a full queue: asked again next cycle), or with no bus at all, when the next bus gets it.
    fn set_quick_stop(&self, state: &mut DriveState, on: bool) {
        let cmd = if on { MasterCommand::QuickStop } else { MasterCommand::Enable };
        if self.send(state, cmd) || state.bus.is_none() {
            state.quick_stopped = on;
        }
    }

    /// The drive's digital inputs read `bits`: the e-stop input's level into the latch; a press
    /// stops at once (`changed`: a new reading, counted).
    fn on_inputs(&self, state: &mut DriveState, node: NodeId, bits: u32, changed: bool) {
        let pressed = self.drive.drives().estop_pressed(bits);
        let was = self.ports.estop_latch.sources() & crate::robot::ports::EStopSource::Input as u8 != 0;
        // Pressed on any drive that reads the chain.
        state.inputs_pressed.insert(node, pressed);
        self.ports.estop_latch.input(state.inputs_pressed.values().any(|p| *p));
        if pressed && (changed || !was) {
            // The e-stop chain wired to the drive: latched like every e-stop (only a local reset
            // clears it, once the input is released).
            tracing::error!(robot = %self.ports.robot, node, bits, "e-stop input pressed");
            self.counters.count("drives.estop_input");
            self.ports.safety_inbox.push(SafetyInput::EStopInput);
        }
        if pressed && !state.quick_stopped {
            // Not waiting for the safety layer's next cycle.
            self.set_quick_stop(state, true);
        }
    }

    fn odometry(&self, state: &mut DriveState, positions: &[(NodeId, i32)]) {
        let [l, r] = self.nodes();
        let find = |n| positions.iter().find(|(k, _)| *k == n).map(|(_, p)| *p);
        let (Some(pl), Some(pr)) = (find(l), find(r)) else { return };
        let now = self.ports.clock.now_s();
        if let Some((ll, lr, t)) = state.last_positions {
            // Exact across the 32-bit wrap.
            let dl = i64::from(pl.wrapping_sub(ll));
            let dr = i64::from(pr.wrapping_sub(lr));
            let d = self.drive.drives();
            self.ports.wheels.send(WheelTravel {
                stamp_s: now,
                dt_s: now - t,
                left_m: self.drive.counts_to_m(d.left, dl),
                right_m: self.drive.counts_to_m(d.right, dr),
            });
        }
        state.last_positions = Some((pl, pr, now));
    }

    fn update_health(&self, state: &mut DriveState) {
        if state.bus.is_none() {
            state.health.set(&self.ports, Health::Lost, "no CAN bus");
        } else if state.resets.values().any(|n| *n > MAX_FAULT_RESETS) {
            state.health.set(&self.ports, Health::Fault, "a drive stays in Fault after resets");
        } else if state.enabled.len() == 2 {
            state.health.set(&self.ports, Health::Ok, "both drives enabled");
        } else if state.health.get() == Some(Health::Ok) {
            state.health.set(&self.ports, Health::Degraded, format!("enabled: {:?}", state.enabled));
        }
    }
}

impl Actor for DriveActor {
    type Msg = DriveMsg;
    type State = DriveState;
    type Arguments = ();

    async fn pre_start(&self, myself: ActorRef<DriveMsg>, (): ()) -> Result<DriveState, ActorProcessingErr> {
        // Events from before this actor started belong to an earlier bus or actor: not ours.
        let _ = self.ports.bus_events.take();
        let events = super::ports::wake_on(
            Arc::clone(&self.ports),
            |p| &p.bus_events,
            myself.clone(),
            || DriveMsg::Events,
        );
        self.ports.wheel_cmd.subscribe(myself.clone(), |c| Some(DriveMsg::Wheels(c)));
        let mut rx = self.ports.bus.subscribe();
        rx.mark_changed();
        let watch = tokio::spawn(async move {
            while rx.changed().await.is_ok() {
                let link = rx.borrow_and_update().clone();
                if myself.cast(DriveMsg::Bus(link)).is_err() {
                    return;
                }
            }
        });
        let mut health = HealthCell::new(Device::Drives);
        health.set(&self.ports, Health::Starting, "waiting for the CAN bus");
        Ok(DriveState {
            _watch: AbortOnDrop(watch),
            _events: events,
            bus: None,
            health,
            enabled: BTreeSet::new(),
            states: BTreeMap::new(),
            resets: BTreeMap::new(),
            quick_stopped: false,
            inputs_pressed: std::collections::BTreeMap::new(),
            last_positions: None,
            nodes: self.nodes(),
        })
    }

    async fn post_stop(
        &self,
        _myself: ActorRef<DriveMsg>,
        state: &mut DriveState,
    ) -> Result<(), ActorProcessingErr> {
        tracing::info!(robot = %self.ports.robot, "drives: quick stop on shutdown");
        self.send(state, MasterCommand::SetTargets(self.nodes().map(|n| (n, 0)).to_vec()));
        self.send(state, MasterCommand::QuickStop);
        // The CAN bus actor is stopped next and takes the master with it: give the master a few
        // SYNC cycles to put the quick stop on the bus first (bounded; a panic skips this, and
        // then the drives' own heartbeat consumer stops them).
        if state.bus.is_some() {
            tokio::time::sleep(SHUTDOWN_FLUSH).await;
        }
        Ok(())
    }

    async fn handle(
        &self,
        _myself: ActorRef<DriveMsg>,
        msg: DriveMsg,
        state: &mut DriveState,
    ) -> Result<(), ActorProcessingErr> {
        if let DriveMsg::Events = msg {
            let (events, lost) = self.ports.bus_events.take();
            // Health after each event, not once per batch: a drive that left Operation Enabled
            // and was enabled again within one batch (a robot thawed after its drives quick-stopped
            // on their own) must still reach the safety layer as a change, or the robot would
            // drive on as if nothing had happened.
            for ev in events {
                self.apply(state, DriveMsg::Master(ev));
                self.update_health(state);
            }
            if lost {
                // What the drives did is unknown: they count as not enabled (which halts the robot)
                // until the master confirms them again.
                tracing::error!(robot = %self.ports.robot, "CANopen events lost: drives degraded");
                self.counters.count("drives.events_lost");
                state.enabled.clear();
                state.health.set(&self.ports, Health::Degraded, "CANopen events lost");
                if !state.quick_stopped {
                    self.send(state, MasterCommand::Enable);
                }
            }
        } else {
            self.apply(state, msg);
        }
        self.update_health(state);
        Ok(())
    }
}

impl DriveActor {
    fn apply(&self, state: &mut DriveState, msg: DriveMsg) {
        match msg {
            DriveMsg::Events => {}
            DriveMsg::Bus(link) => {
                let new = link.as_ref().map(|l| l.generation) != state.bus.as_ref().map(|l| l.generation);
                if new {
                    state.enabled.clear();
                    state.states.clear();
                    state.last_positions = None;
                    state.bus = link;
                    if state.bus.is_some() {
                        state.health.set(
                            &self.ports,
                            Health::Starting,
                            "configuring and enabling the drives",
                        );
                        // The master keeps the goal: drives still booting are enabled once configured.
                        self.send(
                            state,
                            if state.quick_stopped {
                                MasterCommand::QuickStop
                            } else {
                                MasterCommand::Enable
                            },
                        );
                    }
                }
            }
            DriveMsg::Master(ev) => self.on_master(state, ev),
            DriveMsg::Wheels(c) => {
                if c.quick_stop != state.quick_stopped {
                    self.set_quick_stop(state, c.quick_stop);
                }
                let targets = if c.quick_stop {
                    self.nodes().map(|n| (n, 0))
                } else {
                    self.drive.wheel_targets(c.v_mps, c.w_radps)
                };
                self.send(state, MasterCommand::SetTargets(targets.to_vec()));
            }
        }
    }

    /// One event of the CANopen master: odometry and inputs each cycle, the drives' states (a
    /// fault reset up to [`MAX_FAULT_RESETS`] times), reboots, lost heartbeats and events.
    fn on_master(&self, state: &mut DriveState, ev: MasterEvent) {
        match ev {
            MasterEvent::Cycle { positions, inputs } => {
                self.odometry(state, &positions);
                // The inputs' level every cycle: a lost change event cannot hide a press.
                for (node, bits) in inputs {
                    self.on_inputs(state, node, bits, false);
                }
            }
            MasterEvent::Enabled { node } => {
                state.enabled.insert(node);
                state.resets.remove(&node);
            }
            MasterEvent::StateChanged { node, state: s } => {
                state.states.insert(node, s);
                if s != State402::OperationEnabled {
                    state.enabled.remove(&node);
                }
                if s.is_fault() {
                    let n = state.resets.entry(node).or_default();
                    *n += 1;
                    if *n <= MAX_FAULT_RESETS {
                        tracing::warn!(robot = %self.ports.robot, node, attempt = *n, "drive fault: resetting");
                        self.send(state, MasterCommand::Recover(node));
                    }
                }
            }
            MasterEvent::Recovered { node } => {
                tracing::info!(robot = %self.ports.robot, node, "drive fault reset confirmed");
                if !state.quick_stopped {
                    self.send(state, MasterCommand::Enable);
                }
            }
            MasterEvent::BootUp { node } => {
                // A reboot: the encoder may restart anywhere; the master reconfigures the drive
                // before it is enabled again.
                state.enabled.remove(&node);
                state.last_positions = None;
                self.counters.count("drives.boot_up");
            }
            MasterEvent::Error(CanopenError::Link(LinkError::HeartbeatLost { node })) => {
                self.counters.count("drives.heartbeat_lost");
                state.enabled.remove(&node);
                state.health.set(&self.ports, Health::Lost, format!("drive {node}: heartbeat lost"));
            }
            MasterEvent::Error(e) => {
                self.counters.count("drives.error");
                tracing::warn!(robot = %self.ports.robot, error = %e, "drive error");
            }
            MasterEvent::TargetsExpired => self.counters.count("drives.targets_expired"),
            MasterEvent::Inputs { node, bits } => self.on_inputs(state, node, bits, true),
            MasterEvent::EventsLost { count } => {
                tracing::error!(robot = %self.ports.robot, count, "CANopen events lost: drives degraded");
                self.counters.count("drives.events_lost");
                state.enabled.clear();
                state.health.set(&self.ports, Health::Degraded, "CANopen events lost");
                if !state.quick_stopped {
                    self.send(state, MasterCommand::Enable);
                }
            }
            // The bus's error state is the CAN bus actor's health.
            MasterEvent::Configured { .. }
            | MasterEvent::EmcyReset { .. }
            | MasterEvent::SdoDone { .. }
            | MasterEvent::BusError { .. } => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::FleetClock;
    use crate::config::{ConfigSource, load};
    use amr_msgs::HealthReport;
    use std::time::Duration;

    /// The drives' health reports queued for the safety layer so far.
    fn drive_healths(ports: &RobotPorts) -> Vec<Health> {
        ports
            .safety_inbox
            .take()
            .0
            .into_iter()
            .filter_map(|i| match i {
                SafetyInput::Health(HealthReport { device: Device::Drives, health, .. }) => Some(health),
                _ => None,
            })
            .collect()
    }

    async fn settle() {
        for _ in 0..20 {
            tokio::task::yield_now().await;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    #[tokio::test]
    async fn a_drive_that_left_operation_enabled_is_reported_even_if_enabled_again_in_the_same_batch() {
        let cfg = load(&ConfigSource::Embedded).unwrap();
        let robot = cfg.robots.iter().find(|r| r.id.as_str() == "robot-a").unwrap();
        let ports = RobotPorts::new("robot-a", FleetClock::start());
        let actor = DriveActor {
            ports: Arc::clone(&ports),
            drive: robot.diff_drive(),
            counters: Counters::default(),
        };
        let (me, handle) = Actor::spawn(None, actor, ()).await.unwrap();
        let (tx, _rx) = tokio::sync::mpsc::channel(64);
        ports.bus.send_replace(Some(BusLink { generation: 1, commands: tx }));
        settle().await;
        for node in [1, 2] {
            ports.bus_events.push(MasterEvent::Enabled { node });
        }
        settle().await;
        assert_eq!(drive_healths(&ports).last(), Some(&Health::Ok));
        // One batch: both drives seen in their own quick stop (the master's heartbeat lost), then
        // enabled again by the master, before the actor ran.
        for node in [1, 2] {
            ports.bus_events.push(MasterEvent::StateChanged { node, state: State402::QuickStopActive });
        }
        for node in [1, 2] {
            ports.bus_events.push(MasterEvent::Enabled { node });
        }
        settle().await;
        let seen = drive_healths(&ports);
        assert!(
            seen.first().is_some_and(|h| *h != Health::Ok) && seen.last() == Some(&Health::Ok),
            "the safety layer must see the drives leave Ok and come back: {seen:?}"
        );
        me.stop(None);
        let _ = handle.await;
    }
}
