//! The recorder: an actor subscribed to the server's and/or the robots' ports that writes every
//! message to an MCAP file and/or the live view. Messages are written in the order the actor
//! receives them, stamped with the fleet clock at that moment (MCAP `log_time`, non-decreasing);
//! the message's own stamp is its `publish_time`.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, PoisonError, RwLock};
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::robot::ports::RobotPorts;
use amr_actors::server::ports::ServerPorts;
use amr_core::map::OccupancyGrid;
use amr_core::se2::Se2;
use ractor::{Actor, ActorProcessingErr, ActorRef, RpcReplyPort};

use crate::encode::{Encoder, Event, Out};
use crate::live::Hub;
use crate::sink::{FlushPolicy, Format, McapFile, SinkError, WriteStats};

/// What to record.
#[derive(Debug, Clone)]
pub struct RecordSources {
    pub clock: FleetClock,
    /// The fusion server (`amr server`, `amr sim`, `amr eval`).
    pub server: Option<Arc<ServerPorts>>,
    /// The server's formation status ([`amr_actors::server::ServerTree::formation`]).
    pub formation: Option<Arc<ractor::OutputPort<amr_actors::server::formation::FormationStatus>>>,
    /// Robots whose own ports to record (`amr robot`). With a server too (`amr sim`) only their IMU
    /// and wheels are taken from here: the uplink carries the rest.
    pub robots: Vec<Arc<RobotPorts>>,
    /// Written once as `/map`.
    pub map: Option<OccupancyGrid>,
    /// Each robot's LiDAR in its base, written once on `/tf`.
    pub mounts: Vec<(String, Se2)>,
    /// Written as the MCAP metadata record `amr` (e.g. command, configuration, seed).
    pub metadata: BTreeMap<String, String>,
    /// Log lines from a [`crate::log_layer::LogLayer`] built on this tap go to `/log`.
    pub logs: Option<LogTap>,
}

impl RecordSources {
    /// Nothing yet, on `clock`.
    #[must_use]
    pub fn new(clock: FleetClock) -> Self {
        RecordSources {
            clock,
            server: None,
            formation: None,
            robots: Vec::new(),
            map: None,
            mounts: Vec::new(),
            metadata: BTreeMap::new(),
            logs: None,
        }
    }
}

impl RecordSources {
    /// A server's ports with what a replay needs to know: the map, the LiDAR mounts, and as
    /// metadata `amr` the configuration, the seed and the robots (add the command line and the
    /// scenario's name to `metadata`).
    #[must_use]
    pub fn server(ports: &Arc<ServerPorts>, setup: &amr_actors::server::ServerSetup) -> Self {
        let mut s = RecordSources::new(ports.clock);
        s.server = Some(Arc::clone(ports));
        s.map = Some(setup.map.clone());
        s.mounts = setup.robots.iter().map(|r| (r.id.as_str().to_owned(), r.lidar_mount.to_se2())).collect();
        s.metadata.insert("configuration".into(), format!("{:?}", setup.server.configuration));
        s.metadata.insert("seed".into(), setup.seed.to_string());
        s.metadata.insert("robots".into(), ports.robots.join(","));
        s.metadata.insert("record_version".into(), crate::wire::VERSION.to_string());
        s
    }
}

/// Where to record.
#[derive(Debug, Clone, Default)]
pub struct RecordOptions {
    pub file: Option<PathBuf>,
    pub live: Option<Hub>,
    pub flush: FlushPolicy,
    /// Write the file as a ROS 2 bag (rosbag2's MCAP profile, CDR; [`crate::ros2`]) instead of
    /// Foxglove's JSON schemas. The live view is Foxglove's either way.
    pub ros2: bool,
    /// Publish what a ROS 2 bag would hold, live, on a ROS 2 node.
    pub ros2_live: Option<crate::ros2::live::Ros2Live>,
}

/// Why recording could not start or finish.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error(transparent)]
    Sink(#[from] SinkError),
    #[error("an event: {0}")]
    Encode(#[from] crate::wire::WireError),
    #[error("the recorder actor: {0}")]
    Actor(String),
}

/// Where log lines go: set while a recorder runs.
#[derive(Debug, Clone, Default)]
pub struct LogTap(pub(crate) Arc<RwLock<Option<ActorRef<RecMsg>>>>);

impl LogTap {
    pub(crate) fn send(&self, ev: Event) {
        if let Some(a) = self.0.read().unwrap_or_else(PoisonError::into_inner).as_ref() {
            let _ = a.cast(RecMsg::Event(Box::new(ev)));
        }
    }

    fn set(&self, to: Option<ActorRef<RecMsg>>) {
        *self.0.write().unwrap_or_else(PoisonError::into_inner) = to;
    }
}

/// Messages of the recorder actor.
#[derive(Debug)]
pub enum RecMsg {
    Event(Box<Event>),
    /// Close the open chunk if it has waited long enough.
    Tick,
    /// Finish the file and stop.
    Stop(RpcReplyPort<Result<WriteStats, String>>),
}

struct RecorderActor;

struct Args {
    options: RecordOptions,
    sources: RecordSources,
}

struct State {
    clock: FleetClock,
    encoder: Encoder,
    /// Set when the file is a ROS 2 bag: the file's messages come from here.
    ros2: Option<crate::ros2::Ros2Encoder>,
    file: Option<McapFile>,
    live: Option<Hub>,
    /// The live ROS 2 output and its own encoder.
    ros2_live: Option<(crate::ros2::live::Ros2Live, crate::ros2::Ros2Encoder)>,
    logs: Option<LogTap>,
    /// The first write error (the file is then closed; the live view goes on).
    failed: Option<String>,
}

impl State {
    fn put(&mut self, now_s: f64, ev: &Event) {
        // Foxglove's JSON for the live view, and for the file unless it is a ROS 2 bag.
        let outs: Vec<Out> = if self.live.is_some() || self.ros2.is_none() {
            match self.encoder.encode(now_s, ev) {
                Ok(o) => o,
                Err(e) => {
                    tracing::debug!(error = %e, "record: event not encodable");
                    return;
                }
            }
        } else {
            Vec::new()
        };
        let file_outs = match &mut self.ros2 {
            Some(r) if self.file.is_some() => r.encode(now_s, ev),
            _ => Vec::new(),
        };
        let to_file = if self.ros2.is_some() { &file_outs } else { &outs };
        for out in to_file {
            if let Some(f) = &mut self.file
                && let Err(e) = f.write(out)
            {
                tracing::error!(error = %e, "record: writing the file failed; recording stops");
                self.failed = Some(e.to_string());
                self.file = None;
            }
        }
        if let Some(h) = &self.live {
            for out in &outs {
                h.publish(out);
            }
        }
        if let Some((live, encoder)) = &mut self.ros2_live {
            live.clock(now_s);
            for out in encoder.encode(now_s, ev) {
                live.publish(&out);
            }
        }
    }
}

fn subscribe_server(me: &ActorRef<RecMsg>, p: &ServerPorts) {
    let ev = |e: Event| Some(RecMsg::Event(Box::new(e)));
    p.uplink.subscribe(me.clone(), move |(u, rx)| ev(Event::Uplink(u, rx)));
    p.fused.subscribe(me.clone(), move |f| ev(Event::Fused(f)));
    p.estimates.subscribe(me.clone(), move |e| ev(Event::Estimate(e)));
    p.status.subscribe(me.clone(), move |s| ev(Event::Status(s)));
    p.particles.subscribe(me.clone(), move |c| ev(Event::Particles(c)));
    p.commands.subscribe(me.clone(), move |(i, d)| ev(Event::Command(i, d)));
}

/// A robot's ports. With a server recorded too (`amr sim`), its uplink already carries the scans,
/// odometry, health and safety, and its commands port the downlink: only the IMU and the wheels
/// are taken from the robot then.
fn subscribe_robot(me: &ActorRef<RecMsg>, p: &RobotPorts, with_server: bool) {
    let ev = |e: Event| Some(RecMsg::Event(Box::new(e)));
    let id = p.robot.clone();
    let r = id.clone();
    p.imu.subscribe(me.clone(), move |s| ev(Event::Imu(r.clone(), s)));
    let r = id.clone();
    p.wheels.subscribe(me.clone(), move |s| ev(Event::Wheels(r.clone(), s)));
    if with_server {
        return;
    }
    p.scans.subscribe(me.clone(), move |s| ev(Event::Scan(s)));
    let r = id.clone();
    p.odom.subscribe(me.clone(), move |s| ev(Event::Odom(r.clone(), s)));
    let r = id.clone();
    p.health.subscribe(me.clone(), move |s| ev(Event::Health(r.clone(), s)));
    let r = id.clone();
    p.safety.subscribe(me.clone(), move |s| ev(Event::Safety(r.clone(), s)));
    p.downlink.subscribe(me.clone(), move |s| ev(Event::Downlink(id.clone(), s)));
}

impl Actor for RecorderActor {
    type Msg = RecMsg;
    type State = State;
    type Arguments = Args;

    async fn pre_start(&self, me: ActorRef<RecMsg>, args: Args) -> Result<State, ActorProcessingErr> {
        let Args { options, sources } = args;
        let format = if options.ros2 { Format::Ros2 } else { Format::Foxglove };
        let mut file = match &options.file {
            Some(path) => Some(McapFile::create_as(path, options.flush, format)?),
            None => None,
        };
        if let Some(f) = &mut file
            && !sources.metadata.is_empty()
        {
            f.metadata("amr", sources.metadata.clone())?;
        }
        let robots = sources.server.as_ref().map(|s| s.robots.clone()).unwrap_or_default();
        let robots_for_live = robots.clone();
        let mut state = State {
            clock: sources.clock,
            ros2: options.ros2.then(|| crate::ros2::Ros2Encoder::new(robots.clone())),
            encoder: Encoder::new(robots),
            file,
            live: options.live,
            ros2_live: options.ros2_live.map(|l| {
                let encoder = crate::ros2::Ros2Encoder::new(robots_for_live);
                let encoder = if l.nav2_amcl() { encoder.without_v_map_tf() } else { encoder };
                (l, encoder)
            }),
            logs: sources.logs.clone(),
            failed: None,
        };
        let now = state.clock.now_s();
        if let Some(m) = sources.map {
            state.put(now, &Event::Map(m));
        }
        if !sources.mounts.is_empty() {
            state.put(now, &Event::Mounts(sources.mounts));
        }
        if let Some(s) = &sources.server {
            subscribe_server(&me, s);
        }
        if let Some(f) = &sources.formation {
            f.subscribe(me.clone(), |s| Some(RecMsg::Event(Box::new(Event::Formation(s)))));
        }
        for r in &sources.robots {
            subscribe_robot(&me, r, sources.server.is_some());
        }
        if let Some(t) = &sources.logs {
            t.set(Some(me.clone()));
        }
        me.send_interval(Duration::from_millis(250), || RecMsg::Tick);
        Ok(state)
    }

    async fn handle(
        &self,
        me: ActorRef<RecMsg>,
        msg: RecMsg,
        state: &mut State,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            RecMsg::Event(ev) => {
                let now = state.clock.now_s();
                state.put(now, &ev);
            }
            RecMsg::Tick => {
                // A quiet stream still reaches the disk within the policy's interval.
                let now = crate::foxglove::nanos(state.clock.now_s());
                if let Some(f) = &mut state.file
                    && let Err(e) = f.flush_if_due(now)
                {
                    state.failed = Some(e.to_string());
                    state.file = None;
                }
            }
            RecMsg::Stop(reply) => {
                if let Some(t) = &state.logs {
                    t.set(None);
                }
                let result = match (state.file.take(), state.failed.take()) {
                    (_, Some(e)) => Err(e),
                    (Some(f), None) => f.finish().map_err(|e| e.to_string()),
                    (None, None) => Ok(WriteStats::default()),
                };
                let _ = reply.send(result);
                me.stop(None);
            }
        }
        Ok(())
    }

    async fn post_stop(&self, _me: ActorRef<RecMsg>, state: &mut State) -> Result<(), ActorProcessingErr> {
        if let Some(t) = &state.logs {
            t.set(None);
        }
        // Stopped without `Stop` (e.g. killed with its parent): still finish the file.
        if let Some(f) = state.file.take() {
            f.finish()?;
        }
        Ok(())
    }
}

/// A running recorder.
#[derive(Debug)]
pub struct Recorder {
    actor: ActorRef<RecMsg>,
    join: tokio::task::JoinHandle<()>,
}

impl Recorder {
    /// Open the file (if any), write the map, the mounts and the metadata, and subscribe to every
    /// port of `sources`. Start it before the robots send anything: a replay begins with the
    /// first recorded message.
    pub async fn start(options: RecordOptions, sources: RecordSources) -> Result<Recorder, RecordError> {
        let (actor, join) = Actor::spawn(None, RecorderActor, Args { options, sources })
            .await
            .map_err(|e| RecordError::Actor(e.to_string()))?;
        Ok(Recorder { actor, join })
    }

    /// Write what is queued, finish the file (summary and index) and stop.
    pub async fn stop(self) -> Result<WriteStats, RecordError> {
        let r = ractor::call!(self.actor, RecMsg::Stop).map_err(|e| RecordError::Actor(e.to_string()))?;
        let _ = self.join.await;
        r.map_err(RecordError::Actor)
    }

    /// The actor, to send it events by hand (tests, or sources that are not ports).
    #[must_use]
    pub fn actor(&self) -> &ActorRef<RecMsg> {
        &self.actor
    }
}

/// A recorder without actors or ports, for code that runs the algorithms itself (a replay, an
/// evaluation in simulated time): each event is written with the time the caller gives.
#[derive(Debug)]
pub struct FileRecorder {
    file: Option<McapFile>,
    live: Option<crate::live::Hub>,
    encoder: Encoder,
    /// Set when the file is a ROS 2 bag.
    ros2: Option<crate::ros2::Ros2Encoder>,
}

impl FileRecorder {
    /// Create `path`; `robots` are the formation's ids in order (names estimates' robots).
    pub fn create(
        path: &std::path::Path,
        robots: Vec<String>,
        metadata: BTreeMap<String, String>,
    ) -> Result<Self, RecordError> {
        Self::to(Some(path), None, robots, metadata)
    }

    /// To a file and/or a live view (neither: the events are only encoded).
    pub fn to(
        path: Option<&std::path::Path>,
        live: Option<crate::live::Hub>,
        robots: Vec<String>,
        metadata: BTreeMap<String, String>,
    ) -> Result<Self, RecordError> {
        let file = match path {
            Some(p) => {
                let mut file = McapFile::create(p, FlushPolicy::default())?;
                if !metadata.is_empty() {
                    file.metadata("amr", metadata)?;
                }
                Some(file)
            }
            None => None,
        };
        Ok(FileRecorder { file, live, encoder: Encoder::new(robots), ros2: None })
    }

    /// A ROS 2 bag at `path` ([`crate::ros2`]); `robots` as for [`FileRecorder::create`].
    pub fn create_ros2(path: &std::path::Path, robots: Vec<String>) -> Result<Self, RecordError> {
        let file = McapFile::create_as(path, FlushPolicy::default(), Format::Ros2)?;
        Ok(FileRecorder {
            file: Some(file),
            live: None,
            ros2: Some(crate::ros2::Ros2Encoder::new(robots.clone())),
            encoder: Encoder::new(robots),
        })
    }

    /// Write `event` as seen at `t_s` (fleet-clock seconds; keep it non-decreasing).
    pub fn put(&mut self, t_s: f64, event: &Event) -> Result<(), RecordError> {
        if let Some(r) = &mut self.ros2 {
            for o in &r.encode(t_s, event) {
                if let Some(f) = self.file.as_mut() {
                    f.write(o)?;
                }
            }
            if self.live.is_none() {
                return Ok(());
            }
        }
        let outs = self.encoder.encode(t_s, event)?;
        for o in &outs {
            if self.ros2.is_none()
                && let Some(f) = self.file.as_mut()
            {
                f.write(o)?;
            }
            if let Some(h) = &self.live {
                h.publish(o);
            }
        }
        Ok(())
    }

    /// Finish the file (summary and index).
    pub fn finish(self) -> Result<WriteStats, RecordError> {
        match self.file {
            Some(f) => Ok(f.finish()?),
            None => Ok(WriteStats::default()),
        }
    }
}
