//! The fleet as separate processes over the network link: `amr robot`, `amr server` and
//! `amr sim --world-only`, the world whose mock devices `amr robot --mock` drives.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::config::Config;
use amr_actors::config::{ConfigSource, load};
use amr_actors::robot::{DeviceOverrides, RobotOptions, start_robot};
use amr_actors::server::formation::{FormationMsg, Phase};
use amr_actors::server::{ServerSetup, formation_robots, start_server};
use amr_actors::supervisor::RestartPolicy;
use amr_msgs::ServerStatus;
use amr_net::NetSettings;
use amr_net::network::NetworkConfig;
use amr_sim::served::{WorldManifest, serve_world};
use anyhow::Context;

use crate::mock_cmd::runtime;

/// Where `amr sim --world-only` writes its manifest and `amr robot --mock` reads it by default.
pub(crate) fn default_manifest() -> PathBuf {
    std::env::temp_dir().join("amr-world.json")
}

/// Network options shared by `amr robot`, `amr server` and `amr estop`.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct NetArgs {
    /// The fleet's certificates: ca.pem and this machine's NAME.pem, NAME.key (default:
    /// network.toml's `certs_dir`; make them with `amr fleet certs`).
    #[arg(long, value_name = "DIR")]
    pub certs: Option<PathBuf>,
    /// Plain TCP instead of mutual TLS, each peer admitted by its line of a credentials file:
    /// nothing is encrypted and a robot cannot tell the server from whoever answers at its
    /// address. For a closed test bench only.
    #[arg(long, conflicts_with = "certs")]
    pub insecure: bool,
    /// With --insecure: the `user:password` file (default: network.toml's `credentials_file`).
    #[arg(long, requires = "insecure")]
    pub credentials: Option<PathBuf>,
    /// Zenoh endpoints instead of network.toml's (`amr server`: to listen on; `amr robot` and
    /// `amr estop`: to connect to), e.g. tls/127.0.0.1:7447.
    #[arg(long, value_delimiter = ',')]
    pub endpoint: Vec<String>,
}

impl NetArgs {
    fn settings(&self, config: &Config) -> anyhow::Result<NetSettings> {
        let network = NetworkConfig::from_set(config)?;
        let mut s = if self.insecure {
            tracing::warn!(
                "--insecure: the fleet link is plain TCP, unencrypted, the server unauthenticated"
            );
            NetSettings::insecure(network.as_ref(), self.credentials.as_deref())
        } else {
            NetSettings::tls(network.as_ref(), self.certs.as_deref())
        }
        .context("setting up the network link")?;
        if !self.endpoint.is_empty() {
            s.listen = Some(self.endpoint.clone());
            s.connect = Some(self.endpoint.clone());
        }
        Ok(s)
    }
}

/// The configuration set around `file` (its directory), and the id written in it.
fn config_around(file: &Path) -> anyhow::Result<(Config, String)> {
    let dir = file.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let config = load(&ConfigSource::Dir(dir.to_path_buf()))?;
    let text = std::fs::read_to_string(file).with_context(|| format!("reading {}", file.display()))?;
    let table: toml::Table = toml::from_str(&text).with_context(|| format!("parsing {}", file.display()))?;
    let id = table.get("id").and_then(toml::Value::as_str).unwrap_or_default().to_owned();
    Ok((config, id))
}

/// Ctrl-C or SIGTERM.
pub(crate) async fn stop_signal() -> anyhow::Result<()> {
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("listening for SIGTERM")?;
    tokio::select! {
        r = tokio::signal::ctrl_c() => r.context("waiting for Ctrl-C")?,
        _ = term.recv() => {}
    }
    Ok(())
}

/// Where a robot or the server keeps its state by default: systemd's `StateDirectory=`, else the
/// XDG state directory.
fn default_state_dir() -> Option<PathBuf> {
    let var = |name| std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from);
    var("STATE_DIRECTORY")
        .or_else(|| var("XDG_STATE_HOME").map(|d| d.join("amr")))
        .or_else(|| var("HOME").map(|h| h.join(".local/state/amr")))
}

/// Standard input's lines, read on a thread of their own: a read that blocks (an interactive
/// terminal, a pipe held open) never holds up the process's exit, as tokio's stdin, whose read
/// runs on the runtime's blocking pool, does (the runtime waits for it when it shuts down).
fn stdin_lines() -> tokio::sync::mpsc::Receiver<String> {
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let spawned = std::thread::Builder::new().name("stdin".into()).spawn(move || {
        use std::io::BufRead as _;
        for line in std::io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            if tx.blocking_send(line).is_err() {
                break;
            }
        }
    });
    if let Err(e) = spawned {
        tracing::error!(error = %e, "cannot read standard input: no operator commands");
    }
    rx
}

/// `amr robot --config FILE [--mock [MANIFEST]]`: one robot's tree, linked to the server over the
/// network, until Ctrl-C or SIGTERM (the drives quick-stop).
pub(crate) fn robot(
    file: &Path,
    mock: Option<&Path>,
    state_file: Option<PathBuf>,
    net: &NetArgs,
    rec: &crate::record_cmd::RecordArgs,
) -> anyhow::Result<()> {
    let (config, id) = config_around(file)?;
    let robot =
        config.robot(&id).with_context(|| format!("{}: no robot with id `{id}`", file.display()))?.clone();
    let settings = net.settings(&config)?;
    let overrides = match mock {
        None => DeviceOverrides::default(),
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| {
                format!("reading the world manifest {} (start `amr sim --world-only` first)", path.display())
            })?;
            let manifest: WorldManifest = serde_json::from_str(&text)
                .with_context(|| format!("{}: not a world manifest", path.display()))?;
            manifest
                .robots
                .get(&id)
                .with_context(|| format!("{}: the world has no robot `{id}`", path.display()))?
                .overrides()
        }
    };
    let state_file = match state_file {
        Some(f) => f,
        None => default_state_dir()
            .context("no place for the robot's safety state: pass --state-file")?
            .join(format!("{id}.safety")),
    };
    tracing::info!(robot = %id, file = %state_file.display(), "safety state file");
    runtime()?.block_on(async move {
        let clock = FleetClock::wall();
        let (end, bridge) = amr_net::start_robot_bridge(&settings, &id, clock).await?;
        let options =
            RobotOptions { latch_file: Some(state_file), mock: mock.is_some(), ..RobotOptions::default() };
        let tree = start_robot(&robot, overrides, end, clock, options).await.context("starting the robot")?;
        tracing::info!(
            robot = %id,
            mock = mock.is_some(),
            "robot running; SIGUSR1 e-stops it, SIGUSR2 resets the e-stop; Ctrl-C stops it (the drives quick-stop)"
        );
        let mut sources = amr_record::RecordSources::new(clock);
        sources.robots = vec![std::sync::Arc::clone(&tree.ports)];
        sources.mounts = vec![(id.clone(), robot.lidar_mount.to_se2())];
        sources.metadata.insert("robots".into(), id.clone());
        let recording = rec.start(sources).await?;
        // The local e-stop: a signal any process on the robot's computer (a button's handler, an
        // operator's shell) can send, whatever the network does.
        use tokio::signal::unix::{SignalKind, signal};
        let mut estop = signal(SignalKind::user_defined1()).context("listening for SIGUSR1")?;
        let mut reset = signal(SignalKind::user_defined2()).context("listening for SIGUSR2")?;
        let stop = stop_signal();
        tokio::pin!(stop);
        loop {
            tokio::select! {
                r = &mut stop => { r?; break; }
                _ = estop.recv() => {
                    tracing::warn!(robot = %id, "SIGUSR1: e-stop");
                    tree.estop();
                }
                _ = reset.recv() => {
                    tracing::warn!(robot = %id, "SIGUSR2: e-stop reset (the robot stays disarmed until armed)");
                    tree.reset_estop();
                }
            }
        }
        if let Some(r) = recording {
            r.stop().await?;
        }
        tree.shutdown().await;
        bridge.shutdown().await;
        Ok(())
    })
}

/// `amr server` options.
#[derive(Debug, Clone)]
pub(crate) struct ServerArgs {
    pub config: PathBuf,
    pub scenario: String,
    pub seed: u64,
    pub auto_arm: bool,
    pub auto_arm_hardware: bool,
    pub progress_file: Option<PathBuf>,
    pub fresh: bool,
    pub net: NetArgs,
    pub rec: crate::record_cmd::RecordArgs,
}

fn phase_text(p: &Phase) -> String {
    match p {
        Phase::Waiting => "Waiting".into(),
        Phase::Arming { .. } => "Arming".into(),
        Phase::Running => "Running".into(),
        Phase::Holding { reason } => format!("Holding: {reason}"),
        Phase::Stopped { reason } => format!("Stopped: {reason}"),
        Phase::Finished => "Finished".into(),
    }
}

/// `amr server --config FILE`: the fusion server's tree on the network link, until Ctrl-C or
/// SIGTERM. Reads operator commands on standard input: `rearm`, `stop`, `estop` (every robot),
/// `reset-estop`.
pub(crate) fn server(args: &ServerArgs) -> anyhow::Result<()> {
    let (config, _) = config_around(&args.config)?;
    let robots = formation_robots(&config.server, &config.robots)?;
    let chosen = config.scenario(&args.scenario)?;
    let (sc, map) = (chosen.scenario, chosen.map);
    let ids: Vec<String> = robots.iter().map(|r| r.id.as_str().to_owned()).collect();
    let settings = args.net.settings(&config)?;
    let progress = plan_progress(args)?;
    runtime()?.block_on(async move {
        let clock = FleetClock::wall();
        let (end, bridge) = amr_net::start_server_bridge(&settings, &ids, clock).await?;
        let setup = ServerSetup {
            server: config.server.clone(),
            vamr: config.vamr.clone(),
            amcl: config.amcl.clone(),
            map,
            robots,
            scenario: sc,
            seed: args.seed,
            auto_arm: match (args.auto_arm, args.auto_arm_hardware) {
                (_, true) => amr_actors::server::AutoArm::Hardware,
                (true, false) => amr_actors::server::AutoArm::Mock,
                (false, false) => amr_actors::server::AutoArm::Off,
            },
            policy: RestartPolicy::default(),
            progress: std::sync::Arc::new(progress),
        };
        let tree = start_server(setup.clone(), end, clock).await.context("starting the server")?;
        let mut sources = amr_record::RecordSources::server(&tree.ports, &setup);
        sources.formation = Some(std::sync::Arc::clone(&tree.formation));
        sources.metadata.insert("scenario".into(), args.scenario.clone());
        let recording = args.rec.start(sources).await?;
        if let Some(r) = &recording {
            r.ros2_inputs(tree.control()).await?;
        }
        tracing::info!(
            auto_arm = args.auto_arm,
            "server running; commands on stdin: rearm, stop, estop, reset-estop; Ctrl-C stops it"
        );
        let mut lines = stdin_lines();
        let mut stdin_open = true;
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        let mut last: Option<(String, BTreeSet<String>)> = None;
        let stop = stop_signal();
        tokio::pin!(stop);
        loop {
            tokio::select! {
                r = &mut stop => { r?; break; }
                line = lines.recv(), if stdin_open => match line {
                    Some(l) => operator_command(&tree, l.trim()).await,
                    None => stdin_open = false,
                },
                _ = tick.tick() => {
                    let Some(st) = tree.formation_status().await else { continue };
                    let alive = bridge.alive.borrow().clone();
                    let phase = phase_text(&st.phase);
                    if last.as_ref() != Some(&(phase.clone(), alive.clone())) {
                        tracing::info!(%phase, plan_s = st.plan_s, alive = ?alive, "formation");
                        last = Some((phase.clone(), alive.clone()));
                    }
                    bridge.publish_status(ServerStatus {
                        phase, plan_s: st.plan_s, plan_len_s: st.plan_len_s, alive: alive.into_iter().collect(),
                        integrity: st.v_integrity,
                    }).await;
                }
            }
        }
        if let Some(r) = recording {
            r.stop().await?;
        }
        tree.shutdown().await;
        bridge.bridge.shutdown().await;
        Ok(())
    })
}

/// The plan's progress file (`--progress-file`, else in the state directory), emptied first with
/// `--fresh`.
fn plan_progress(args: &ServerArgs) -> anyhow::Result<amr_actors::server::progress::PlanProgress> {
    let progress_file = match &args.progress_file {
        Some(f) => f.clone(),
        None => default_state_dir()
            .context("no place for the plan's progress: pass --progress-file")?
            .join(format!("server-{}.progress", args.scenario)),
    };
    if args.fresh && progress_file.exists() {
        std::fs::remove_file(&progress_file)
            .with_context(|| format!("removing the plan's progress {}", progress_file.display()))?;
    }
    let progress = amr_actors::server::progress::PlanProgress::file(&progress_file)?;
    tracing::info!(file = %progress_file.display(), "plan progress file");
    Ok(progress)
}

/// One operator command from `amr server`'s standard input.
async fn operator_command(tree: &amr_actors::server::ServerTree, command: &str) {
    match command {
        "rearm" => {
            tree.rearm().await;
        }
        "stop" => {
            if let Some(f) = tree.formation_actor().await {
                let _ = f.cast(FormationMsg::Stop);
            }
        }
        "estop" => {
            let refused = tree.estop_all().await;
            if refused.is_empty() {
                tracing::warn!("e-stop sent to every robot");
            } else {
                tracing::error!(
                    ?refused,
                    "e-stop NOT queued for these robots (link full or closed): stop them locally"
                );
            }
        }
        "reset-estop" => {
            let refused = tree.reset_estop_all();
            tracing::info!(?refused, "e-stop reset sent (robots stay disarmed until rearm)");
        }
        "" => {}
        other => tracing::warn!(command = other, "unknown command (have: rearm, stop, estop, reset-estop)"),
    }
}

/// `amr fleet certs`'s arguments.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct CertsArgs {
    /// Where to write them (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// The robots (default: the formation's in server.toml).
    #[arg(long, value_delimiter = ',')]
    pub robots: Vec<String>,
    /// Operators and observers (default: network.toml's `server.operators`; with --no-server,
    /// none).
    #[arg(long, value_delimiter = ',')]
    pub operators: Option<Vec<String>>,
    /// Host names and addresses robots dial to reach the server (default: the hosts of
    /// network.toml's `server.connect`, plus localhost and 127.0.0.1).
    #[arg(long, value_delimiter = ',')]
    pub server_hosts: Vec<String>,
    /// Only make certificates for the robots and operators named, not the server's (a robot
    /// joining a fleet whose directory holds the CA).
    #[arg(long)]
    pub no_server: bool,
    /// Validity of the members' certificates, days (the CA's: ten years).
    #[arg(long, default_value_t = 825)]
    pub days: u32,
    /// Configuration directory (default: ./config if present, else the embedded defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

/// `amr fleet certs`: the fleet's CA and every member's key pair (see `amr_net::certs`).
pub(crate) fn certs(args: &CertsArgs) -> anyhow::Result<()> {
    let config = load(&crate::config_cmd::source_for(args.config.clone()))?;
    let network = NetworkConfig::from_set(&config)?;
    let robots: Vec<String> = if args.robots.is_empty() {
        config.server.robots.iter().map(|m| m.id.as_str().to_owned()).collect()
    } else {
        args.robots.clone()
    };
    // Joining a fleet (--no-server) makes only the members named.
    let operators = args.operators.clone().unwrap_or_else(|| {
        let listed = network.iter().flat_map(|n| n.server.operators.iter().map(|o| o.as_str().to_owned()));
        if args.no_server { Vec::new() } else { listed.collect() }
    });
    let server_hosts = if args.server_hosts.is_empty() {
        let mut hosts: Vec<String> = network
            .iter()
            .flat_map(|n| n.server.connect.iter())
            .filter_map(|e| {
                e.split_once('/').and_then(|(_, a)| a.rsplit_once(':')).map(|(h, _)| h.to_owned())
            })
            .collect();
        hosts.extend(["localhost".to_owned(), "127.0.0.1".to_owned()]);
        hosts.dedup();
        hosts
    } else {
        args.server_hosts.clone()
    };
    let server_name =
        network.as_ref().map_or_else(|| "server".to_owned(), |n| n.server.user.as_str().to_owned());
    // Joining a fleet, the server's name and hosts are still not any member's.
    let reserved = if args.no_server {
        std::iter::once(server_name.clone()).chain(server_hosts.iter().cloned()).collect()
    } else {
        Vec::new()
    };
    let req = amr_net::certs::CertRequest {
        server_hosts: if args.no_server { Vec::new() } else { server_hosts.clone() },
        server: (!args.no_server).then_some(server_name),
        robots,
        others: operators,
        reserved,
        days: args.days,
    };
    let made = amr_net::certs::make(&args.out, &req)?;
    #[allow(clippy::print_stdout, reason = "the command's report")]
    {
        let ca = if made.new_ca { "a new fleet CA" } else { "the directory's CA" };
        println!("{}: {ca} signed {}", args.out.display(), made.members.join(", "));
        if !args.no_server {
            println!("the server's certificate is valid for: {}", server_hosts.join(", "));
        }
        println!("give each machine ca.pem and its own NAME.pem and NAME.key; keep ca.key offline");
    }
    Ok(())
}

/// `amr estop`'s arguments.
#[derive(Debug)]
pub(crate) struct EstopArgs {
    pub robots: Vec<String>,
    pub reset: bool,
    pub user: String,
    pub config: Option<PathBuf>,
    pub timeout_ms: u64,
    pub net: NetArgs,
}

/// `amr estop`: the operator's network e-stop (or reset) of `robots`, confirmed by each robot.
pub(crate) fn estop(args: &EstopArgs) -> anyhow::Result<()> {
    let config = load(&crate::config_cmd::source_for(args.config.clone()))?;
    let settings = args.net.settings(&config)?;
    let robots: Vec<String> = if args.robots.is_empty() {
        config.server.robots.iter().map(|m| m.id.as_str().to_owned()).collect()
    } else {
        args.robots.clone()
    };
    let timeout = Duration::from_millis(args.timeout_ms);
    let what = if args.reset { "e-stop reset" } else { "e-stop" };
    let outcome = runtime()?.block_on(amr_net::operator_estop(
        &settings,
        &args.user,
        &robots,
        args.reset,
        FleetClock::wall(),
        timeout,
    ))?;
    let unconfirmed: Vec<&String> = outcome.iter().filter(|(_, s)| s.is_none()).map(|(r, _)| r).collect();
    #[allow(clippy::print_stdout, reason = "the command's report")]
    for (robot, state) in &outcome {
        match state {
            Some(s) => println!("{robot}: {what} confirmed, now {s}"),
            None => println!("{robot}: {what} NOT confirmed within {timeout:?}"),
        }
    }
    anyhow::ensure!(unconfirmed.is_empty(), "{what} not confirmed by {unconfirmed:?}: stop them locally");
    Ok(())
}

/// `amr sim --world-only`: the world and every robot's mock devices, served on loopback, until
/// Ctrl-C or SIGTERM. Writes the manifest `amr robot --mock` reads.
pub(crate) fn world_only(
    config: Option<PathBuf>,
    scenario: &str,
    seed: u64,
    manifest: &Path,
) -> anyhow::Result<()> {
    let config = load(&crate::config_cmd::source_for(config))?;
    let chosen = config.scenario(scenario)?;
    runtime()?.block_on(async move {
        let world = serve_world(&config, &chosen, seed).await.context("starting the world")?;
        let text = serde_json::to_string_pretty(&world.manifest)?;
        // Written whole, then renamed: a robot never reads half a manifest.
        let tmp = manifest.with_extension("tmp");
        std::fs::write(&tmp, text + "\n").with_context(|| format!("writing {}", tmp.display()))?;
        std::fs::rename(&tmp, manifest).with_context(|| format!("writing {}", manifest.display()))?;
        tracing::info!(manifest = %manifest.display(), robots = world.manifest.robots.len(), "world ready; Ctrl-C stops it");
        stop_signal().await?;
        drop(world);
        Ok(())
    })
}
