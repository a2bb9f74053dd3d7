//! CanBusActor: owns the CAN connection (SocketCAN, socketcand over TCP, or the in-process bus)
//! and the CANopen master running on it (NMT, SYNC, its heartbeat, the drives' configuration). It
//! reconnects with capped exponential backoff when the transport fails, publishing each connection
//! as a new [`BusLink`] generation; the drive actor, started after it (rest-for-one), follows.

use std::sync::Arc;
use std::time::Duration;

use amr_drivers::canopen::error::{BusState, CanopenError, LinkError, TransportError};
use amr_drivers::canopen::master::{Master, MasterConfig, MasterEvent};
use amr_drivers::canopen::shell::spawn_master;
use amr_drivers::canopen::transport::CanTransport;
use amr_drivers::canopen::transport::in_process::InProcessBus;
use amr_drivers::canopen::transport::socketcan::SocketCan;
use amr_drivers::canopen::transport::socketcand::SocketcandClient;
use ractor::{Actor, ActorProcessingErr, ActorRef};
use tokio::time::Instant;

use super::ports::{AbortOnDrop, BusLink, RobotPorts};
use super::status::{Counters, HealthCell};
use amr_msgs::{Device, Health};

/// Where the CAN frames go.
#[derive(Debug, Clone)]
pub enum CanLink {
    SocketCan {
        interface: String,
    },
    Socketcand {
        address: String,
        channel: String,
    },
    /// A bus in this process (simulation, tests).
    InProcess(InProcessBus),
}

/// Messages of the CAN bus actor.
#[derive(Debug)]
pub enum CanBusMsg {
    /// The bus task reports.
    Up {
        generation: u64,
    },
    Down {
        reason: String,
        retry_in: Duration,
    },
    /// The controller's error state changed (SocketCAN error frames).
    BusState(BusState),
    /// Fail now, as a bug would (drills).
    #[cfg(feature = "fault-injection")]
    InjectFailure(String),
}

/// The CAN bus actor.
#[derive(Debug, Clone)]
pub(crate) struct CanBusActor {
    pub ports: Arc<RobotPorts>,
    pub link: CanLink,
    pub master: MasterConfig,
    pub backoff: (Duration, Duration),
    pub counters: Counters,
}

#[derive(Debug)]
pub(crate) struct CanBusState {
    _bus: AbortOnDrop<()>,
    health: HealthCell,
}

impl Actor for CanBusActor {
    type Msg = CanBusMsg;
    type State = CanBusState;
    type Arguments = ();

    async fn pre_start(
        &self,
        myself: ActorRef<CanBusMsg>,
        (): (),
    ) -> Result<CanBusState, ActorProcessingErr> {
        // A new actor never inherits a previous one's bus.
        self.ports.bus.send_replace(None);
        let mut health = HealthCell::new(Device::CanBus);
        health.set(&self.ports, Health::Starting, format!("connecting {:?}", self.link));
        let bus = tokio::spawn(run_bus(self.clone(), myself));
        Ok(CanBusState { _bus: AbortOnDrop(bus), health })
    }

    async fn post_stop(
        &self,
        _myself: ActorRef<CanBusMsg>,
        _state: &mut CanBusState,
    ) -> Result<(), ActorProcessingErr> {
        self.ports.bus.send_replace(None);
        Ok(())
    }

    async fn handle(
        &self,
        _myself: ActorRef<CanBusMsg>,
        msg: CanBusMsg,
        state: &mut CanBusState,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            CanBusMsg::Up { generation } => {
                state.health.set(&self.ports, Health::Ok, format!("connected (connection {generation})"));
            }
            CanBusMsg::BusState(s) => {
                self.counters.count(match s {
                    BusState::ErrorActive => "can.error_active",
                    BusState::ErrorWarning => "can.error_warning",
                    BusState::ErrorPassive => "can.error_passive",
                });
                // Error passive: the controller may no longer signal errors it sees, and one step
                // on is bus-off; the robot may still move (the drives' heartbeats guard the link).
                match s {
                    BusState::ErrorPassive => {
                        state.health.set(&self.ports, Health::Degraded, "CAN controller error passive");
                    }
                    BusState::ErrorActive if state.health.get() == Some(Health::Degraded) => {
                        state.health.set(&self.ports, Health::Ok, "CAN controller error active again");
                    }
                    BusState::ErrorActive | BusState::ErrorWarning => {}
                }
            }
            CanBusMsg::Down { reason, retry_in } => {
                self.counters.count("can.link_lost");
                state.health.set(
                    &self.ports,
                    Health::Lost,
                    format!("{reason}; reconnecting in {retry_in:?}"),
                );
            }
            #[cfg(feature = "fault-injection")]
            CanBusMsg::InjectFailure(why) => {
                self.ports.bus.send_replace(None);
                return Err(why.into());
            }
        }
        Ok(())
    }
}

/// Connect, run the master until the transport fails, back off, repeat. Ends only when aborted.
async fn run_bus(actor: CanBusActor, myself: ActorRef<CanBusMsg>) {
    let (initial, max) = actor.backoff;
    let mut delay = initial;
    let mut generation = 0u64;
    // Bounded by time: every pass either runs a connection or sleeps at least `initial`.
    loop {
        let started = Instant::now();
        let outcome = match &actor.link {
            CanLink::InProcess(bus) => run_connection(&actor, &myself, &mut generation, bus.port()).await,
            CanLink::Socketcand { address, channel } => {
                match SocketcandClient::connect(address, channel, Duration::from_secs(2)).await {
                    Ok(t) => run_connection(&actor, &myself, &mut generation, t).await,
                    Err(e) => format!("socketcand {address}: {e}"),
                }
            }
            CanLink::SocketCan { interface } => match SocketCan::open(interface) {
                Ok(t) => run_connection(&actor, &myself, &mut generation, t).await,
                Err(e) => format!("SocketCAN {interface}: {e}"),
            },
        };
        // A connection that lasted a while starts the backoff again.
        if started.elapsed() > max {
            delay = initial;
        }
        tracing::warn!(robot = %actor.ports.robot, reason = %outcome, retry_in = ?delay, "CAN bus down");
        if myself.cast(CanBusMsg::Down { reason: outcome, retry_in: delay }).is_err() {
            return;
        }
        tokio::time::sleep(delay).await;
        delay = (delay * 2).min(max);
    }
}

/// Run the master on one connection until it ends; returns why.
async fn run_connection<T: CanTransport + 'static>(
    actor: &CanBusActor,
    myself: &ActorRef<CanBusMsg>,
    generation: &mut u64,
    transport: T,
) -> String {
    let mut handle = spawn_master(Master::new(actor.master.clone(), Instant::now().into_std()), transport);
    let task = AbortOnDrop(handle.task);
    *generation += 1;
    actor
        .ports
        .bus
        .send_replace(Some(BusLink { generation: *generation, commands: handle.commands.clone() }));
    let _ = myself.cast(CanBusMsg::Up { generation: *generation });
    let mut reason = String::from("the master stopped");
    while let Some(ev) = handle.events.recv().await {
        match &ev {
            MasterEvent::Error(e @ CanopenError::Link(LinkError::Transport(t))) => {
                if *t == TransportError::BusOff {
                    actor.counters.count("can.bus_off");
                }
                reason = e.to_string();
            }
            MasterEvent::BusError { class, state } => {
                tracing::warn!(robot = %actor.ports.robot, class = format!("{class:#x}"), ?state, "CAN error frame");
                actor.counters.count("can.error_frames");
                if let Some(s) = state {
                    let _ = myself.cast(CanBusMsg::BusState(*s));
                }
            }
            _ => {}
        }
        actor.ports.bus_events.push(ev);
    }
    actor.ports.bus.send_replace(None);
    drop(task);
    reason
}
