//! `amr`: the one binary of the project. Each subcommand is wiring around the library crates.

mod amcl_cmd;
mod carmen_cmd;
mod config_cmd;
mod eval_cmd;
mod fleet_cmd;
mod localize;
mod mock_cmd;
mod record_cmd;
mod sim_cmd;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

/// Logging for our crates at info, everything else at warn, unless RUST_LOG says otherwise.
const DEFAULT_LOG_FILTER: &str =
    "warn,amr=info,amr_core=info,amr_drivers=info,amr_actors=info,amr_sim=info,hil_mocks=info";

/// Caps the log target where Zenoh dumps its configuration (zenoh 1.10 `api/session.rs`).
const ZENOH_CONFIG_LOG: &str = "zenoh::api::session=info";

#[derive(Debug, Parser)]
#[command(
    name = "amr",
    version,
    about = "Actor-based hardware-in-the-loop controller for robots driving in close formation",
    long_about = "Actor-based hardware-in-the-loop controller for robots driving in close formation.\n\n\
        Each robot runs supervised actors for its LiDAR (SOPAS), wheel drives (CANopen CiA 402) and IMU \
        (LPBUS); a fusion server builds one virtual scan from the formation's robots (the Virtual-AMR \
        method) and localises it with AMCL. Logs go to stderr, filtered by RUST_LOG (default: info for \
        our crates)."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Inspect the configuration (robots, devices, server, algorithm parameters).
    #[command(subcommand)]
    Config(ConfigCommand),
    /// Localise a recorded 2D LiDAR log (CARMEN .log/.clf, or a ROS 2 bag) with AMCL on a ROS map
    /// and write one pose per scan as CSV (timestamp, x, y, theta, then the 3×3 covariance row by
    /// row).
    ///
    /// CARMEN: lines are processed in file order with the log's own timestamps; each scan uses the
    /// odometry of its own line (FLASER, ROBOTLASER1) or else the latest ODOM line. Lines that
    /// cannot be read are skipped with a warning naming the line.
    ///
    /// ROS 2 bag (rosbag2 MCAP, CDR): scans (sensor_msgs/msg/LaserScan) in stamp order, each with
    /// the odometry interpolated at its stamp, from nav_msgs/msg/Odometry or else /tf's odometry
    /// frame → base frame; the laser's mounting from /tf_static. Messages that cannot be decoded
    /// are skipped with a warning.
    Localize {
        /// The map's YAML (ROS map_server format); its image path is relative to it.
        #[arg(long)]
        map: PathBuf,
        /// The CARMEN log.
        #[arg(long, required_unless_present = "bag", conflicts_with = "bag")]
        log: Option<PathBuf>,
        /// A ROS 2 bag: a rosbag2 file in either storage (MCAP `.mcap`, sqlite3 `.db3`), or the
        /// bag's directory.
        #[arg(long, value_name = "BAG")]
        bag: Option<PathBuf>,
        #[command(flatten)]
        ros2: localize::BagArgs,
        /// Initial pose `x,y,theta` (m, m, rad), spread as amcl.toml's initial_pose says, else as
        /// RViz's "2D Pose Estimate" (0.5 m, 15°); without it: amcl.toml's initial_pose, else global
        /// localisation.
        #[arg(long, value_parser = localize::parse_pose, allow_hyphen_values = true)]
        initial: Option<amr_core::se2::Se2>,
        /// AMCL parameters (an amcl.toml); default: ./config/amcl.toml if present, else the
        /// embedded one.
        #[arg(long)]
        params: Option<PathBuf>,
        /// AMCL parameters from a nav2 params file (`amcl: ros__parameters:`, nav2_amcl's names)
        /// over the configuration's amcl.toml; `set_initial_pose` and `initial_pose` as nav2 reads
        /// them.
        #[arg(long, value_name = "NAV2_PARAMS.yaml", conflicts_with = "params")]
        nav2_params: Option<PathBuf>,
        /// Where to write the CSV; default: standard output.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Seed of the filter's random draws (same seed, same output).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Teleport the odometry every N scans by 1-5 m and any heading (drawn from the seed), as if
        /// the robot had been carried away: to see the filter report `lost` and re-localise.
        #[arg(long, value_name = "N")]
        kidnap: Option<usize>,
    },
    /// Our AMCL as a ROS 2 node in nav2_amcl's place, for one robot: nav2_amcl's topics (`scan`,
    /// `map`, `initialpose`, `/tf`, `/tf_static`; publishes `amcl_pose`, `particle_cloud` and
    /// map → odom on `/tf`) and its parameter file. Without an initial pose it localises globally
    /// and publishes once it tracks; its integrity goes to `/diagnostics`. docs/ros2.md.
    Amcl(amcl_cmd::AmclArgs),
    /// Measure the algorithms (medians over repeated runs; nothing is asserted).
    #[command(subcommand)]
    Bench(BenchCommand),
    /// The paper's experiments in simulation: world + Virtual-AMR pipeline + AMCL in simulated time,
    /// T1–T4 side by side on identical sensor streams. Writes report.md, report.json and
    /// trials.json (the raw errors) to `OUT/<scenario>/`.
    Eval {
        /// A scenario of the configuration (`config/scenarios/<name>.toml`), or a scenario file's
        /// path (its `map` may be a map YAML's path relative to it: any ROS map).
        #[arg(long, default_value = "straight")]
        scenario: String,
        /// AMCL's map: a simulated SLAM-style survey of the site, or the site's own map.
        #[arg(long, value_enum, default_value = "surveyed")]
        map: eval_cmd::MapSource,
        /// Number of trials (the paper ran 5); trial k uses seed + k.
        #[arg(long, default_value_t = 5)]
        trials: usize,
        /// Seed of the first trial.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Output directory.
        #[arg(long, default_value = "out/eval")]
        out: PathBuf,
        /// Configuration directory (default: ./config, else the embedded defaults).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Robots in the formation (the paper: 2; with 3 they drive in a line, the reference robot in
        /// the middle). Refused if the path would take a robot into a wall.
        #[arg(long, default_value_t = 2)]
        robots: usize,
        /// Instead of T1–T4: the sensitivity study of ε_d (Table 6) or Δθ (Table 7) for T4,
        /// written to `OUT/<scenario>/sweep-<eps|step>.{md,json}`.
        #[arg(long, value_enum)]
        sweep: Option<eval_cmd::Sweep>,
        /// Instead of T1–T4: T4's error budget, each of its sources replaced by the truth in turn
        /// (`OUT/<scenario>/budget.{md,json}`).
        #[arg(long, conflicts_with = "sweep")]
        budget: bool,
        /// Instead of T1–T4 on one scenario: the occlusion study, T1–T4 over spacing 0.5–2.0 m and
        /// teams of 2, 3 and 4 on every scenario given with --study-scenario (default: straight,
        /// turning, hall-straight, hall-turning, corridor, short-racks), written to
        /// OUT/study-occlusion/study.{md,json} with a plot per scenario.
        #[arg(long, value_enum, conflicts_with_all = ["sweep", "budget"])]
        study: Option<eval_cmd::Study>,
        /// A scenario (name or file) for --study; repeat for several.
        #[arg(long = "study-scenario", value_name = "SCENARIO", requires = "study")]
        study_scenarios: Vec<String>,
        /// For --study: a configuration whose --trials leave the study's criterion open (T4 at most
        /// 0.5 cm worse than min(T1, T2, T3), that margin within two standard errors of the paired
        /// difference) runs this many trials in all, the same first ones and the next (0: none does).
        #[arg(long, value_name = "N", default_value_t = 50, requires = "study")]
        confirm_trials: usize,
        /// Record each trial as MCAP (scans, odometry, true poses, T1–T4's estimates side by side):
        /// this file for one trial, `FILE-<seed>.mcap` for several.
        #[arg(long, value_name = "FILE.mcap")]
        record: Option<PathBuf>,
        /// Serve the trials live to Foxglove (WebSocket) here, e.g. 127.0.0.1:8765; they run in
        /// simulated time, faster than real time.
        #[arg(long, value_name = "ADDR")]
        foxglove: Option<std::net::SocketAddr>,
    },
    /// The whole system against the mock devices in real time: every robot's actor tree, the
    /// fusion server and the simulated world, the devices reached through their real protocols and
    /// transports. Prints live status, then the localisation error against the true pose and the
    /// per-stage latency table.
    Sim {
        /// A scenario of the configuration (`scenarios/<name>.toml`), or a scenario file's path
        /// (its `map` may be a map YAML's path relative to it: any ROS map).
        #[arg(long, default_value = "straight")]
        scenario: String,
        /// AMCL's map: the site's own map, or a simulated SLAM-style survey of the site.
        #[arg(long, value_enum, default_value = "true")]
        map: eval_cmd::MapSource,
        /// Seed of the world's noise and of AMCL.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// T1–T4 (default: server.toml's `configuration`).
        #[arg(long, value_parser = record_cmd::parse_configuration)]
        configuration: Option<amr_core::config::Configuration>,
        /// Stop after this many seconds even if the plan is not done.
        #[arg(long)]
        duration: Option<f64>,
        /// How the robots reach their mock drives: socketcand (TCP loopback) or in-process.
        #[arg(long, value_parser = sim_cmd::parse_can, default_value = "socketcand")]
        can: amr_sim::SimCan,
        /// Also write the report as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Configuration directory (default: ./config if present, else the embedded defaults).
        #[arg(long)]
        config: Option<PathBuf>,
        /// No live status lines.
        #[arg(long)]
        quiet: bool,
        /// Exit with an error when an estimate of V that the formation could drive on (verified)
        /// was farther than this from the truth, cm. The run also fails when the plan does not
        /// finish (unless --duration cut it short).
        #[arg(long, default_value_t = 10.0)]
        max_error_cm: f64,
        /// Run on a paused clock with every device over in-memory pipes: faster than real time
        /// and reproducible from the seed (times in the report are simulated).
        #[arg(long)]
        virtual_time: bool,
        /// Only the world and every robot's mock devices, served on loopback (SOPAS/TCP,
        /// socketcand/TCP, LPBUS/pty) for robot processes (`amr robot --mock`) and a server
        /// process (`amr server`) on this machine. Writes the manifest of the devices' addresses.
        #[arg(long)]
        world_only: bool,
        /// Where `--world-only` writes its manifest (default: amr-world.json in the temp directory,
        /// where `amr robot --mock` looks).
        #[arg(long)]
        manifest: Option<PathBuf>,
        #[command(flatten)]
        rec: record_cmd::RecordArgs,
    },
    /// Re-run the server pipeline (fusion + AMCL) on a recording's sensor data, deterministically,
    /// and compare with the recorded estimates (identical with the original parameters). Prints a
    /// JSON report; `--out` writes the new run as MCAP.
    Replay {
        /// A recording of `amr sim --record` or `amr server --record`.
        file: PathBuf,
        /// Write the replayed run here (MCAP, the same topics).
        #[arg(long)]
        out: Option<PathBuf>,
        /// T1–T4 instead of the recorded configuration.
        #[arg(long, value_parser = record_cmd::parse_configuration)]
        configuration: Option<amr_core::config::Configuration>,
        /// Configuration directory for the parameters (default: ./config, else the embedded ones).
        #[arg(long)]
        config: Option<PathBuf>,
        /// The scenario (default: the recorded one).
        #[arg(long)]
        scenario: Option<String>,
        /// AMCL's seed (default: the recorded one).
        #[arg(long)]
        seed: Option<u64>,
    },
    /// Fault-recovery drills against the mock devices in real time: each injects a fault and checks
    /// detection, the safe state, recovery, the event log and the counters. Prints a table; exits
    /// non-zero if a drill failed.
    #[cfg(feature = "drills")]
    Drill {
        /// A drill name, or `all` (the list: `amr drill list`).
        name: String,
        /// Seed of the simulated world's noise (and of the chaos soak's fault draws).
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Length of the chaos soak, seconds (default 600: ten minutes).
        #[arg(long, default_value_t = 600)]
        soak_seconds: u64,
        /// Also write the outcomes as JSON to this file (`-`: standard output, after the table).
        #[arg(long)]
        json: Option<PathBuf>,
        /// Configuration directory (default: ./config if present, else the embedded defaults).
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// One robot's actor tree on its devices, linked to the fusion server over the network
    /// (network.toml: Zenoh with mutual TLS, certificates from `amr fleet certs`), until Ctrl-C or
    /// SIGTERM (the drives quick-stop). SIGUSR1 e-stops the robot, SIGUSR2 resets its e-stop.
    Robot {
        /// The robot's file (`robot-<id>.toml`); the rest of the configuration is read from its
        /// directory.
        #[arg(long)]
        config: PathBuf,
        /// Drive the robot's mock devices in a world served by `amr sim --world-only`, at the
        /// addresses of its manifest (default: amr-world.json in the temp directory).
        #[arg(long, num_args = 0..=1, value_name = "MANIFEST")]
        mock: Option<Option<PathBuf>>,
        /// Where the robot keeps its latched e-stop, fault and stop counter across restarts
        /// (default: `<id>.safety` in $STATE_DIRECTORY, else $XDG_STATE_HOME/amr, else
        /// ~/.local/state/amr). A latch in it holds until reset: SIGUSR2 on the robot, or the
        /// network reset for a network e-stop.
        #[arg(long, value_name = "FILE")]
        state_file: Option<PathBuf>,
        #[command(flatten)]
        net: fleet_cmd::NetArgs,
        #[command(flatten)]
        rec: record_cmd::RecordArgs,
    },
    /// The fusion server's actor tree on the network link (network.toml), until Ctrl-C or SIGTERM.
    /// Operator commands on standard input, one per line: `rearm` (allow the formation to start
    /// again), `stop` (stop the formation, robots disarmed), `estop` (e-stop every robot) and
    /// `reset-estop` (clear every robot's e-stop; they stay disarmed until `rearm`).
    Server {
        /// server.toml; the rest of the configuration is read from its directory.
        #[arg(long)]
        config: PathBuf,
        /// The scenario whose plan the formation follows once armed.
        #[arg(long, default_value = "straight")]
        scenario: String,
        /// Seed of AMCL's random draws.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Arm the formation once, as soon as every robot is healthy and localised (otherwise, and
        /// after any stop: on `rearm`), if every robot reports mock devices (`amr robot --mock`).
        #[arg(long)]
        auto_arm: bool,
        /// `--auto-arm` on real hardware too: the formation moves with nobody's `rearm`.
        #[arg(long)]
        auto_arm_hardware: bool,
        /// Where the formation keeps its progress in the plan, so that a restarted server resumes
        /// the job where it was, never later (default: `server-<scenario>.progress` in
        /// $STATE_DIRECTORY, else $XDG_STATE_HOME/amr, else ~/.local/state/amr). Removed when the
        /// plan finishes.
        #[arg(long, value_name = "FILE")]
        progress_file: Option<PathBuf>,
        /// Start the plan from its beginning: forget the recorded progress.
        #[arg(long)]
        fresh: bool,
        #[command(flatten)]
        net: fleet_cmd::NetArgs,
        #[command(flatten)]
        rec: record_cmd::RecordArgs,
    },
    /// E-stop robots over the network as an operator (network.toml's `server.operators`), or with
    /// `--reset` clear their e-stop (they stay disarmed until the server re-arms them). Waits for
    /// each robot to report the new state; exits non-zero if one does not.
    Estop {
        /// Robots to stop (default: every robot of the formation in server.toml).
        robots: Vec<String>,
        /// Clear the e-stop instead.
        #[arg(long)]
        reset: bool,
        /// The operator's name (its certificate's, or with --insecure its user).
        #[arg(long, default_value = "operator")]
        user: String,
        /// Configuration directory (default: ./config if present, else the embedded defaults).
        #[arg(long)]
        config: Option<PathBuf>,
        /// How long to wait for the robots' confirmation, ms.
        #[arg(long, default_value_t = 3000)]
        timeout_ms: u64,
        #[command(flatten)]
        net: fleet_cmd::NetArgs,
    },
    /// The fleet link's set-up.
    #[command(subcommand)]
    Fleet(FleetCommand),
    /// Run a mock device standalone, serving its real protocol until Ctrl-C (for any client: ours,
    /// the vendor's tools, a ROS driver).
    #[command(subcommand)]
    Mock(MockCommand),
    /// Protocol and data tools: decode a SOPAS capture, check the robot on a kernel CAN interface,
    /// prepare a public CARMEN log for `amr bench localize`.
    #[command(subcommand)]
    Tools(ToolsCommand),
}

#[derive(Debug, Subcommand)]
enum FleetCommand {
    /// Make the fleet's certificates for the link's mutual TLS: a CA (ca.pem, ca.key), and a key
    /// pair and certificate for the server, each robot and each operator (NAME.pem, NAME.key).
    /// Give each machine ca.pem and its own pair only; keep ca.key offline. A directory that
    /// already holds ca.pem and ca.key keeps its CA, which signs the new members.
    Certs(fleet_cmd::CertsArgs),
}

#[derive(Debug, Subcommand)]
enum MockCommand {
    /// A mock SICK TiM5xx on TCP (SOPAS, CoLa-A and CoLa-B, detected per connection), streaming
    /// scans of a static room at 15 Hz. Prints the address it listens on.
    Lidar {
        /// Address to listen on (port 0 picks a free one).
        #[arg(long, default_value = "127.0.0.1:2112")]
        listen: String,
        /// 271 points (TiM551, 1°) or 811 (TiM561/571, 0.333°).
        #[arg(long, default_value_t = 271)]
        points: u32,
        /// Behave like a device set to one dialect (a | b) instead of answering either.
        #[arg(long, value_parser = parse_dialect)]
        dialect: Option<amr_drivers::sopas::Dialect>,
    },
    /// Mock TECO servo drives (by default two, nodes 1 and 2), CANopen CiA 402 nodes in profile
    /// velocity mode, on a simulated CAN bus behind a socketcand server (CAN over TCP):
    /// python-can's `socketcand` interface or any CiA 402 master can drive them. Prints the
    /// address.
    Drives {
        /// Address of the socketcand server (port 0 picks a free one).
        #[arg(long, default_value = "127.0.0.1:29536")]
        socketcand: String,
        /// Node ids of the drives.
        #[arg(long, value_delimiter = ',', default_value = "1,2")]
        nodes: Vec<u8>,
    },
    /// A mock LP-Research LPMS-B2 (LPBUS) behind a pseudo-terminal, streaming from power-up. Prints
    /// the tty path to open (a stable symlink to the current pty).
    Imu {
        /// Stream rate in Hz (5, 10, 25, 50, 100, 200, 400 or 800).
        #[arg(long, default_value_t = 100)]
        rate: u32,
    },
}

#[derive(Debug, Subcommand)]
enum ToolsCommand {
    /// Decode a captured SOPAS telegram (CoLa-A or CoLa-B, framed or not) and print every field as
    /// JSON.
    SopasDecode {
        /// The captured bytes.
        file: PathBuf,
    },
    /// Prepare a Radish "corrected" CARMEN log (e.g. from github.com/acschaefer/ple, data/carmen/) for
    /// `amr bench localize`: writes NAME-raw.log (the log with its raw odometry only, rebuilt from
    /// the corrected log's odometry increments), NAME-gt.csv (the corrected pose of every scan:
    /// scan,timestamp,x,y,theta) and NAME_map.yaml + NAME_map.pgm (a 0.05 m map built from every
    /// scan at its corrected pose) into DIR.
    ///
    /// The log may be gzip-compressed (the public logs are published as .log.gz), or piped in as
    /// `-` with --name.
    CarmenPrepare {
        /// The corrected log (`-`: standard input).
        log: PathBuf,
        /// Directory to write into (created if missing).
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// The files' prefix (default: the log's file name without `-corrected.log`).
        #[arg(long)]
        name: Option<String>,
    },
    /// The robot on a kernel CAN interface (SocketCAN, e.g. a vcan): mock drives and the robot's
    /// CANopen master on sockets of their own, a velocity move, a quick stop, then malformed and
    /// error frames written by can-utils' `cansend`. One PASS/FAIL line per check; `tests/vm/run`
    /// runs it in a Linux VM.
    #[cfg(feature = "drills")]
    CanCheck {
        /// The interface.
        #[arg(long, default_value = "vcan0")]
        iface: String,
        /// can-utils' cansend.
        #[arg(long, default_value = "cansend")]
        cansend: PathBuf,
        /// Seed of the simulated world's noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Configuration directory (default: ./config if present, else the embedded defaults).
        #[arg(long)]
        config: Option<PathBuf>,
    },
}

fn parse_dialect(s: &str) -> Result<amr_drivers::sopas::Dialect, String> {
    match s.to_ascii_lowercase().as_str() {
        "a" => Ok(amr_drivers::sopas::Dialect::ColaA),
        "b" => Ok(amr_drivers::sopas::Dialect::ColaB),
        _ => Err(format!("`{s}`: expected a (CoLa-A) or b (CoLa-B)")),
    }
}

#[derive(Debug, Subcommand)]
enum BenchCommand {
    /// Per-stage times of the Virtual-AMR pipeline (paper Table 4 layout) at 2 × 271 and 2 × 655
    /// points on a synthetic two-robot scene, with the paper-faithful KD-tree heading search as the
    /// baseline measured in the same run; then the time per fused update (T4) for teams of 2, 3, 4
    /// and 8 robots, with failed heading searches. Uses vamr.toml from the configuration.
    Vamr(BenchOptions),
    /// Time of one AMCL update at 2 000 particles, with 60 beams and with a whole virtual scan, of
    /// resampling + estimate alone, at 10 000 particles × 100 beams; a 200 m × 600 m map's load time
    /// and memory; with `--log`, the same on a recorded log beside nav2's core (`--nav2`). Uses
    /// amcl.toml from the configuration.
    Amcl {
        #[command(flatten)]
        common: BenchOptions,
        /// A recorded log's prefix, `DIR/NAME` (`NAME_map.yaml`, `NAME-raw.log`, `NAME-gt.csv`).
        #[arg(long)]
        log: Option<PathBuf>,
        /// nav2's reference harness (docs/nav2-reference.md), run with `--bench` on that log.
        #[arg(long, requires = "log")]
        nav2: Option<PathBuf>,
        /// Skip the large-map measurement (it writes a 48 MB file to the temporary directory).
        #[arg(long)]
        no_large_map: bool,
    },
    /// AMCL on recorded real logs (public CARMEN logs turned into raw-odometry logs, SLAM-built
    /// maps and reference trajectories; none ships with amr) against their references: tracking
    /// from the first reference pose and global localisation, per log and seed, beside the
    /// odometry alone and nav2's figures (from `--nav2 DIR/<name>.csv`).
    Localize {
        /// Directory holding `<name>-raw.log`, `<name>_map.yaml` and `<name>-gt.csv`.
        #[arg(long)]
        logs: PathBuf,
        /// Only these logs (default: every complete one in the directory).
        #[arg(long = "log")]
        only: Vec<String>,
        /// Seeds, comma-separated.
        #[arg(long, value_delimiter = ',', default_values_t = [1u64, 2, 3])]
        seeds: Vec<u64>,
        /// A directory with nav2's estimate per log, `<name>.csv` (`timestamp,x,y,theta`).
        #[arg(long)]
        nav2: Option<PathBuf>,
        /// AMCL parameters (an amcl.toml); default: the configuration's.
        #[arg(long)]
        params: Option<PathBuf>,
        /// Configuration directory (default: ./config, else the embedded defaults).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Print JSON instead of a Markdown table.
        #[arg(long)]
        json: bool,
        /// Also track each log with its odometry teleported every N scans (1-5 m, any heading;
        /// drawn from the seed): whether the filter reports `Lost` and tracks again.
        #[arg(long, value_name = "N")]
        kidnap: Option<usize>,
    },
}

#[derive(Debug, clap::Args)]
struct BenchOptions {
    /// Print JSON instead of a Markdown table.
    #[arg(long)]
    json: bool,
    /// Fewer repetitions (for a quick look; the medians are noisier).
    #[arg(long)]
    quick: bool,
    /// Configuration directory (default: ./config, else the embedded defaults).
    #[arg(long)]
    config: Option<PathBuf>,
}

#[derive(Debug, Subcommand)]
enum ConfigCommand {
    /// Load and validate every file of a configuration directory and print what it holds.
    ///
    /// Without DIR: ./config if it exists, else the defaults embedded in this binary. Exits 1 with
    /// the first broken rule (file, line, key and rule) if the configuration is invalid.
    Check {
        /// A directory laid out like config/ (`robot-<id>.toml`, server.toml, vamr.toml, amcl.toml).
        dir: Option<PathBuf>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(DEFAULT_LOG_FILTER));
    // Zenoh prints its whole configuration, passwords included, at debug level when a session
    // opens: that target never goes below info, whatever RUST_LOG asks (credentials stay out of logs).
    let filter = match ZENOH_CONFIG_LOG.parse() {
        Ok(d) => filter.add_directive(d),
        Err(_) => filter,
    };
    // Colour only on a terminal: logs piped to a file or another program stay plain text.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    {
        use tracing_subscriber::prelude::*;
        tracing_subscriber::registry()
            .with(filter)
            .with(tracing_subscriber::fmt::layer().with_writer(std::io::stderr).with_ansi(ansi))
            .with(amr_record::LogLayer::new(record_cmd::log_tap().clone()))
            .init();
    }

    let result = match cli.command {
        Command::Config(ConfigCommand::Check { dir }) => config_cmd::check(dir),
        Command::Bench(BenchCommand::Vamr(opts)) => bench(
            opts,
            "the Virtual-AMR pipeline",
            |c, quick| amr_lab::bench::run(&c.vamr, quick),
            amr_lab::bench::markdown,
        ),
        Command::Bench(BenchCommand::Localize { logs, only, seeds, nav2, params, config, json, kidnap }) => {
            (|| -> anyhow::Result<()> {
                let params = localize::load_params(params.as_deref(), config)?;
                let report =
                    amr_lab::bench_localize::run(&params, &logs, &only, &seeds, nav2.as_deref(), kidnap)?;
                let text = if json {
                    serde_json::to_string_pretty(&report)? + "\n"
                } else {
                    amr_lab::bench_localize::markdown(&report)
                };
                #[allow(clippy::print_stdout, reason = "the command's report")]
                {
                    print!("{text}");
                }
                Ok(())
            })()
        }
        Command::Bench(BenchCommand::Amcl { common, log, nav2, no_large_map }) => {
            let extras = amr_lab::bench::AmclExtras { log, nav2, no_large_map };
            bench(
                common,
                "AMCL",
                |c, quick| amr_lab::bench::run_amcl(&c.amcl, &c.vamr, quick, &extras),
                amr_lab::bench::amcl_markdown,
            )
        }
        Command::Mock(MockCommand::Lidar { listen, points, dialect }) => {
            mock_cmd::lidar(&listen, points, dialect)
        }
        Command::Mock(MockCommand::Drives { socketcand, nodes }) => mock_cmd::drives(&socketcand, &nodes),
        Command::Mock(MockCommand::Imu { rate }) => {
            if amr_drivers::lpms::B2_STREAM_RATES_HZ.contains(&rate) {
                mock_cmd::imu(rate)
            } else {
                Err(anyhow::anyhow!(
                    "--rate must be one of {:?}, not {rate}",
                    amr_drivers::lpms::B2_STREAM_RATES_HZ
                ))
            }
        }
        Command::Tools(ToolsCommand::SopasDecode { file }) => mock_cmd::sopas_decode(&file),
        Command::Tools(ToolsCommand::CarmenPrepare { log, out, name }) => {
            carmen_cmd::prepare_log(&log, &out, name)
        }
        #[cfg(feature = "drills")]
        Command::Tools(ToolsCommand::CanCheck { iface, cansend, seed, config }) => {
            sim_cmd::can_check(&iface, &cansend, seed, config)
        }
        Command::Sim { scenario, seed, config, world_only: true, manifest, .. } => fleet_cmd::world_only(
            config,
            &scenario,
            seed,
            &manifest.unwrap_or_else(fleet_cmd::default_manifest),
        ),
        Command::Sim {
            scenario,
            seed,
            configuration,
            duration,
            can,
            json,
            config,
            quiet,
            virtual_time,
            rec,
            map,
            max_error_cm,
            ..
        } => match duration.map(std::time::Duration::try_from_secs_f64) {
            Some(Err(_)) => Err(anyhow::anyhow!("--duration must be a positive number of seconds")),
            d => sim_cmd::sim(sim_cmd::SimArgs {
                scenario,
                seed,
                configuration,
                duration: d.and_then(Result::ok),
                can,
                json,
                config,
                quiet,
                virtual_time,
                rec,
                surveyed_map: map == eval_cmd::MapSource::Surveyed,
                max_error_cm,
            }),
        },
        Command::Robot { config, mock, state_file, net, rec } => {
            let manifest = mock.map(|m| m.unwrap_or_else(fleet_cmd::default_manifest));
            fleet_cmd::robot(&config, manifest.as_deref(), state_file, &net, &rec)
        }
        Command::Replay { file, out, configuration, config, scenario, seed } => {
            record_cmd::replay(&file, out.as_deref(), config, scenario, configuration, seed)
        }
        #[cfg(feature = "drills")]
        Command::Drill { name, .. } if name == "list" => {
            #[allow(clippy::print_stdout, reason = "the command's report")]
            for d in amr_sim::drills::DRILLS {
                println!("{:16} {}", d.name, d.about);
            }
            Ok(())
        }
        #[cfg(feature = "drills")]
        Command::Drill { name, seed, soak_seconds, json, config } => {
            sim_cmd::drill(&name, seed, soak_seconds, json.as_deref(), config)
        }
        Command::Fleet(FleetCommand::Certs(args)) => fleet_cmd::certs(&args),
        Command::Estop { robots, reset, user, config, timeout_ms, net } => {
            fleet_cmd::estop(&fleet_cmd::EstopArgs { robots, reset, user, config, timeout_ms, net })
        }
        Command::Server {
            config,
            scenario,
            seed,
            auto_arm,
            auto_arm_hardware,
            progress_file,
            fresh,
            net,
            rec,
        } => fleet_cmd::server(&fleet_cmd::ServerArgs {
            config,
            scenario,
            seed,
            auto_arm,
            auto_arm_hardware,
            progress_file,
            fresh,
            net,
            rec,
        }),
        Command::Eval {
            scenario,
            map,
            trials,
            seed,
            out,
            config,
            robots,
            sweep,
            budget,
            study,
            study_scenarios,
            confirm_trials,
            record,
            foxglove,
        } => (|| {
            let config = amr_actors::config::load(&config_cmd::source_for(config))?;
            let plan = amr_lab::eval::Plan {
                config: &config,
                scenario: &scenario,
                map: map.into(),
                robots,
                trials,
                seed,
            };
            let report = match sweep {
                None if study.is_some() => {
                    let scenarios: Vec<String> = if study_scenarios.is_empty() {
                        amr_lab::study::STUDY_SCENARIOS.iter().map(|s| (*s).to_owned()).collect()
                    } else {
                        study_scenarios
                    };
                    let study = amr_lab::study::Occlusion {
                        config: &config,
                        scenarios: &scenarios,
                        map: map.into(),
                        trials,
                        confirm_trials,
                        seed,
                    };
                    amr_lab::study::occlusion(&study, &out)?
                }
                None if budget => amr_lab::study::budget(&plan, &out)?,
                Some(which) => amr_lab::eval::sweep(&plan, which.into(), &out)?,
                None => eval_cmd::run(&plan, &out, record.as_deref(), foxglove)?.join("report.md"),
            };
            #[allow(clippy::print_stdout, reason = "the command's report")]
            {
                print!("{}", std::fs::read_to_string(&report)?);
                println!("\nwritten to {}", report.display());
            }
            Ok(())
        })(),
        Command::Amcl(args) => amcl_cmd::amcl(args),
        Command::Localize { map, log, bag, ros2, initial, params, nav2_params, out, seed, kidnap } => {
            (|| {
                let params = match nav2_params {
                    Some(f) => localize::load_nav2_params(&f, None)?,
                    None => localize::load_params(params.as_deref(), None)?,
                };
                let input = match (log, bag) {
                    (_, Some(bag)) => localize::Input::Bag(bag, ros2.options()),
                    (Some(log), None) => localize::Input::Carmen(log),
                    (None, None) => anyhow::bail!("give --log or --bag"),
                };
                let s = localize::run(&localize::Options { map, input, initial, params, out, seed, kidnap })?;
                tracing::info!(
                    scans = s.scans,
                    poses = s.poses,
                    skipped = s.skipped,
                    without_odometry = s.scans_without_odometry,
                    "localised the log"
                );
                Ok(())
            })()
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            #[allow(clippy::print_stderr, reason = "the CLI's own error report")]
            {
                eprintln!("error: {e:#}");
            }
            ExitCode::FAILURE
        }
    }
}

/// Load the configuration, run a benchmark and print its report as Markdown or JSON.
fn bench<R: serde::Serialize>(
    opts: BenchOptions,
    what: &str,
    run: impl FnOnce(&amr_actors::config::Config, bool) -> anyhow::Result<R>,
    markdown: fn(&R) -> String,
) -> anyhow::Result<()> {
    let config = amr_actors::config::load(&config_cmd::source_for(opts.config))?;
    tracing::info!(quick = opts.quick, "benchmarking {what}");
    let report = run(&config, opts.quick)?;
    let text = if opts.json { serde_json::to_string_pretty(&report)? + "\n" } else { markdown(&report) };
    #[allow(clippy::print_stdout, reason = "the command's report")]
    {
        print!("{text}");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn cli_definition_is_consistent() {
        Cli::command().debug_assert();
    }

    #[test]
    fn default_filter_parses() {
        assert!(EnvFilter::try_new(DEFAULT_LOG_FILTER).is_ok());
        assert!(ZENOH_CONFIG_LOG.parse::<tracing_subscriber::filter::Directive>().is_ok());
    }
}
