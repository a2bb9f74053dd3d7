//! `--record FILE.mcap` and `--foxglove ADDR` on `amr sim`, `amr robot` and `amr server`, and
//! `amr replay`: wiring around amr-record.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use amr_actors::config::load;
use amr_actors::server::{ServerSetup, formation_robots};
use amr_actors::supervisor::RestartPolicy;
use amr_core::config::Configuration;
use amr_record::{Hub, LiveServer, LogTap, RecordOptions, RecordSources, Recorder};
use anyhow::Context as _;

/// Log lines reach a running recorder through this tap (the `tracing` layer is built once, in
/// `main`, before any command runs).
pub(crate) fn log_tap() -> &'static LogTap {
    static TAP: OnceLock<LogTap> = OnceLock::new();
    TAP.get_or_init(LogTap::default)
}

/// Recording and live-view options.
#[derive(Debug, Clone, Default, clap::Args)]
pub(crate) struct RecordArgs {
    /// Record the run to this MCAP file (Foxglove's schemas: opens in Foxglove with no plugin).
    #[arg(long, value_name = "FILE.mcap")]
    pub record: Option<PathBuf>,
    /// Serve a live Foxglove WebSocket view (default address 127.0.0.1:8765; an address other
    /// than loopback needs `--foxglove-token`). At most 8 clients, 64 subscriptions each.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8765")]
    pub foxglove: Option<SocketAddr>,
    /// The token every live-view client must present (`ws://HOST:PORT/?token=TOKEN`).
    #[arg(long, value_name = "TOKEN")]
    pub foxglove_token: Option<String>,
    /// Write the recording's chunks uncompressed (default: LZ4).
    #[arg(long)]
    pub record_uncompressed: bool,
    /// Write the recording as a ROS 2 bag (rosbag2's MCAP profile, CDR): the scans, the virtual
    /// scan, odometry, estimates, /tf, /tf_static and /map as ROS 2 types, for `ros2 bag play`,
    /// RViz and nav2 (robot ids become `robot_a`-style topic names). Only those topics: such a
    /// file does not `amr replay`. The live view stays Foxglove's.
    #[arg(long, requires = "record")]
    pub ros2: bool,
    /// Publish the fleet live on ROS 2 over this transport: `zenoh` is rmw_zenoh's protocol
    /// (Jazzy and later, and Humble's rmw_zenoh), `dds` is DDS/RTPS (Humble's and Foxy's default:
    /// Fast DDS, Cyclone DDS; discovery by multicast). The topics of a `--ros2` bag, each with the
    /// QoS ROS 2 tools subscribe with (docs/ros2.md).
    #[arg(long, value_name = "TRANSPORT", value_enum)]
    pub ros2_live: Option<Ros2Transport>,
    #[command(flatten)]
    pub node: Ros2NodeArgs,
    /// Let `/cmd_vel` (`geometry_msgs/Twist`: a teleop, nav2's controller) drive the formation as
    /// one robot, V: from the first twist on the plan is paused; every robot's limits apply, and V
    /// stops 0.5 s after the last twist. `/initialpose` is taken whenever `--ros2-live` is on.
    #[arg(long, requires = "ros2_live")]
    pub ros2_cmd_vel: bool,
    /// nav2_amcl localises V from `/virtual/scan` (the paper's mode; `ros2/nav2/v_amcl.yaml`): our
    /// `map` → `V/odom` is not published, nav2_amcl publishes it.
    #[arg(long, requires = "ros2_live")]
    pub ros2_nav2_amcl: bool,
}

/// Where a ROS 2 node joins the graph.
#[derive(Debug, Clone, Default, clap::Args)]
pub(crate) struct Ros2NodeArgs {
    /// The ROS 2 domain (`ROS_DOMAIN_ID`).
    #[arg(long, env = "ROS_DOMAIN_ID", default_value_t = 0, value_name = "ID")]
    pub ros2_domain: u32,
    /// The ROS 2 distribution of the peers: `humble` (no type hashes) or `jazzy` and later.
    #[arg(long, default_value = "jazzy", value_name = "DISTRO")]
    pub ros2_distro: amr_ros2::rmw_zenoh::Distro,
    /// The Zenoh router of the ROS 2 graph to join (rmw_zenohd's default).
    #[arg(long, default_value = "tcp/localhost:7447", value_name = "ENDPOINT")]
    pub ros2_connect: String,
    /// Be the ROS 2 graph's Zenoh router, listening here (no rmw_zenohd needed; ROS 2 nodes
    /// connect to it), instead of joining one.
    #[arg(long, value_name = "ENDPOINT")]
    pub ros2_router: Option<String>,
}

/// A ROS 2 transport for `--ros2-live`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum Ros2Transport {
    /// rmw_zenoh's key expressions, liveliness tokens and attachments.
    Zenoh,
    /// DDS/RTPS, as ROS 2's DDS middlewares name topics and types.
    Dds,
}

/// A running recording and/or live view.
#[derive(Debug)]
pub(crate) struct Recording {
    recorder: Recorder,
    _live: Option<LiveServer>,
    file: Option<PathBuf>,
    /// The live ROS 2 node, and whether `/cmd_vel` may drive.
    ros2: Option<(Arc<amr_ros2::transport::Ros2Node>, bool)>,
}

impl RecordArgs {
    /// Start what was asked for (nothing: `None`). The command line goes into the metadata.
    pub(crate) async fn start(&self, mut sources: RecordSources) -> anyhow::Result<Option<Recording>> {
        if self.record.is_none() && self.foxglove.is_none() && self.ros2_live.is_none() {
            return Ok(None);
        }
        let argv: Vec<String> = std::env::args().collect();
        sources.metadata.insert("command".into(), argv.join(" "));
        sources.logs = Some(log_tap().clone());
        let (hub, live) = match self.foxglove {
            Some(addr) => {
                let hub = Hub::default();
                let options =
                    amr_record::LiveOptions { token: self.foxglove_token.clone(), ..Default::default() };
                let live = amr_record::serve_with(addr, hub.clone(), "amr", options)
                    .await
                    .with_context(|| format!("serving the Foxglove live view on {addr}"))?;
                tracing::info!(address = %live.addr, "Foxglove live view: open ws://{} in Foxglove", live.addr);
                (Some(hub), Some(live))
            }
            None => (None, None),
        };
        let flush = amr_record::FlushPolicy { lz4: !self.record_uncompressed, ..Default::default() };
        let node = match self.ros2_live {
            Some(t) => Some(Arc::new(self.node.open(t, "amr").await?)),
            None => None,
        };
        let ros2_live = node.as_ref().map(|n| {
            let live = amr_record::ros2::live::Ros2Live::start(Arc::clone(n));
            if self.ros2_nav2_amcl { live.for_nav2_amcl() } else { live }
        });
        let options =
            RecordOptions { file: self.record.clone(), live: hub, flush, ros2: self.ros2, ros2_live };
        let recorder = Recorder::start(options, sources).await.context("starting the recorder")?;
        if let Some(f) = &self.record {
            tracing::info!(file = %f.display(), ros2 = self.ros2, "recording");
        }
        let ros2 = node.map(|n| (n, self.ros2_cmd_vel));
        Ok(Some(Recording { recorder, _live: live, file: self.record.clone(), ros2 }))
    }
}

impl Ros2NodeArgs {
    /// A ROS 2 node named `name` over `transport`.
    pub(crate) async fn open(
        &self,
        transport: Ros2Transport,
        name: &str,
    ) -> anyhow::Result<amr_ros2::transport::Ros2Node> {
        use amr_ros2::node::{Mode, NodeOptions};
        use amr_ros2::transport::{Ros2Node, Transport};
        let mut o = NodeOptions::new(name);
        o.domain = self.ros2_domain;
        o.distro = self.ros2_distro;
        match &self.ros2_router {
            Some(listen) => {
                o.mode = Mode::Router;
                o.connect = Vec::new();
                o.listen = vec![listen.clone()];
            }
            None => o.connect = vec![self.ros2_connect.clone()],
        }
        let t = match transport {
            Ros2Transport::Zenoh => Transport::Zenoh,
            Ros2Transport::Dds => Transport::Dds,
        };
        let node = Ros2Node::open(t, &o).await.context("opening the ROS 2 node")?;
        tracing::info!(domain = o.domain, node = %node.describe(), "ROS 2 node");
        Ok(node)
    }
}

impl Recording {
    /// Take `/initialpose` (and `/cmd_vel` if allowed) from the live ROS 2 node into the server,
    /// until the node closes. Nothing without `--ros2-live`.
    pub(crate) async fn ros2_inputs(&self, control: amr_actors::server::ServerControl) -> anyhow::Result<()> {
        use amr_record::ros2::inputs::{Input, listen};
        let Some((node, cmd_vel)) = &self.ros2 else { return Ok(()) };
        let mut rx =
            listen(Arc::clone(node), *cmd_vel).await.context("subscribing /initialpose and /cmd_vel")?;
        tokio::spawn(async move {
            while let Some(input) = rx.recv().await {
                let taken = match input {
                    Input::InitialPose { v, std_xy_m, std_yaw_rad } => {
                        tracing::info!(x = v.x, y = v.y, theta = v.theta, "ROS 2: an initial pose for V");
                        control.initial_pose(v, std_xy_m, std_yaw_rad).await
                    }
                    Input::Twist { v_mps, w_radps } => control.twist(v_mps, w_radps).await,
                };
                if !taken {
                    tracing::warn!(?input, "ROS 2: the server is not running; input dropped");
                }
            }
        });
        Ok(())
    }

    /// Close the file (its summary and index) and stop the live view.
    pub(crate) async fn stop(self) -> anyhow::Result<()> {
        let stats = self.recorder.stop().await.context("finishing the recording")?;
        if let Some(f) = &self.file {
            tracing::info!(file = %f.display(), messages = stats.messages, topics = stats.per_topic.len(), "recording written");
        }
        Ok(())
    }
}

/// A configuration by its name, `T1` to `T4` (any case): `--configuration` of `amr sim` and
/// `amr replay`, and the one a recording's metadata names.
pub(crate) fn parse_configuration(s: &str) -> Result<Configuration, String> {
    match s.to_ascii_uppercase().as_str() {
        "T1" => Ok(Configuration::T1),
        "T2" => Ok(Configuration::T2),
        "T3" => Ok(Configuration::T3),
        "T4" => Ok(Configuration::T4),
        _ => Err(format!("`{s}`: expected T1, T2, T3 or T4")),
    }
}

/// `amr replay FILE`: the server pipeline (fusion + AMCL) again on a recording's sensor data.
pub(crate) fn replay(
    input: &Path,
    out: Option<&Path>,
    config: Option<PathBuf>,
    scenario: Option<String>,
    configuration: Option<Configuration>,
    seed: Option<u64>,
) -> anyhow::Result<()> {
    let bytes = std::fs::read(input).with_context(|| format!("reading {}", input.display()))?;
    let meta = amr_record::read::metadata(&bytes).remove("amr").unwrap_or_default();
    let config = load(&crate::config_cmd::source_for(config))?;
    let scenario = scenario.or_else(|| meta.get("scenario").cloned()).unwrap_or_else(|| "straight".into());
    let chosen = config.scenario(&scenario)?;
    let (sc, map) = (chosen.scenario, chosen.map);
    let recorded_seed = meta.get("seed").and_then(|s| s.parse::<u64>().ok());
    let seed = seed.or(recorded_seed).unwrap_or(1);
    let mut server = config.server.clone();
    if let Some(c) = meta.get("configuration").and_then(|c| parse_configuration(c).ok()) {
        server.configuration = c;
    }
    let setup = ServerSetup {
        robots: formation_robots(&server, &config.robots)?,
        server,
        vamr: config.vamr.clone(),
        amcl: config.amcl.clone(),
        map,
        scenario: sc,
        seed,
        auto_arm: amr_actors::server::AutoArm::Off,
        policy: RestartPolicy::default(),
        progress: std::sync::Arc::new(amr_actors::server::progress::PlanProgress::in_memory()),
    };
    let report = amr_record::replay(input, out, &setup, configuration)
        .with_context(|| format!("replaying {}", input.display()))?;
    #[allow(clippy::print_stdout, reason = "the command's report")]
    {
        println!("{}", serde_json::to_string_pretty(&report_json(&report))?);
        if let Some(o) = out {
            println!("written to {}", o.display());
        }
    }
    Ok(())
}

fn report_json(r: &amr_record::ReplayReport) -> serde_json::Value {
    serde_json::json!({
        "configuration": r.configuration.map(|c| format!("{c:?}")),
        "uplink_messages": r.uplink,
        "scans": r.scans,
        "fused": r.fused,
        "recorded_fused": r.recorded_fused,
        "fused_identical": r.fused_identical,
        "estimates": r.estimates,
        "recorded_estimates": r.recorded_estimates,
        "compared": r.compared,
        "identical": r.identical,
        "missing": r.missing,
        "extra": r.extra,
        "exact": r.exact(),
        "truncated_input": r.truncated,
        "first_difference": r.first_difference,
    })
}
