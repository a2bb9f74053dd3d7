//! The `amr` command line: its commands, options and help texts (clap), parsed in `main`.

use std::path::PathBuf;

use clap::{Parser, Subcommand};

use crate::{amcl_cmd, eval_cmd, fleet_cmd, localize, record_cmd, sim_cmd};

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
pub(crate) struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub(crate) enum Command {
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
    Localize(LocalizeArgs),
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
    Eval(EvalArgs),
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
        /// On a virtual clock (tokio's, paused; devices over in-memory pipes): the same outcome,
        /// timings included, from the same seed, whatever the machine's load. The drills that need
        /// the wall clock (`amr drill list` marks them) are left out of `all`.
        #[arg(long)]
        virtual_time: bool,
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
pub(crate) enum FleetCommand {
    /// Make the fleet's certificates for the link's mutual TLS: a CA (ca.pem, ca.key), and a key
    /// pair and certificate for the server, each robot and each operator (NAME.pem, NAME.key).
    /// Give each machine ca.pem and its own pair only; keep ca.key offline. A directory that
    /// already holds ca.pem and ca.key keeps its CA, which signs the new members.
    Certs(fleet_cmd::CertsArgs),
}

#[derive(Debug, Subcommand)]
pub(crate) enum MockCommand {
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
pub(crate) enum ToolsCommand {
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
    /// Write a CARMEN log with its odometry teleported every N scans (the kidnappings of `amr
    /// bench localize --kidnap N` with the same seed): for another localiser (nav2's core) to be
    /// run on the very log ours is kidnapped in. Prints the kidnappings (scan, jump).
    CarmenKidnap {
        /// The log (e.g. NAME-raw.log of `amr tools carmen-prepare`).
        log: PathBuf,
        /// Teleport the odometry every this many scans.
        #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
        every: u64,
        /// Draws the jumps (1-5 m, any direction and heading).
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// The log to write.
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
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

pub(crate) fn parse_dialect(s: &str) -> Result<amr_drivers::sopas::Dialect, String> {
    match s.to_ascii_lowercase().as_str() {
        "a" => Ok(amr_drivers::sopas::Dialect::ColaA),
        "b" => Ok(amr_drivers::sopas::Dialect::ColaB),
        _ => Err(format!("`{s}`: expected a (CoLa-A) or b (CoLa-B)")),
    }
}

#[derive(Debug, Subcommand)]
pub(crate) enum BenchCommand {
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
        /// A directory with nav2's estimate per log, `<name>.csv` (`timestamp,x,y,theta`), and
        /// with `--kidnap N` per seed S `<name>-kidnap<N>-s<S>.csv`: its estimate on the log
        /// `amr tools carmen-kidnap <name>-raw.log --every N --seed S` writes.
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
        /// Which runs to make of each log and seed (the kidnapped ones need `--kidnap N`).
        #[arg(long, value_enum, value_delimiter = ',', default_values_t = [RunKind::Tracking, RunKind::Global, RunKind::Kidnapped])]
        runs: Vec<RunKind>,
    },
}

/// A run of `amr bench localize`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum RunKind {
    /// From the first reference pose.
    Tracking,
    /// With no initial pose.
    Global,
    /// From the first reference pose, the odometry teleported every `--kidnap` scans.
    Kidnapped,
}

#[derive(Debug, clap::Args)]
pub(crate) struct BenchOptions {
    /// Print JSON instead of a Markdown table.
    #[arg(long)]
    pub json: bool,
    /// Fewer repetitions (for a quick look; the medians are noisier).
    #[arg(long)]
    pub quick: bool,
    /// Configuration directory (default: ./config, else the embedded defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

#[derive(Debug, Subcommand)]
pub(crate) enum ConfigCommand {
    /// Load and validate every file of a configuration directory and print what it holds.
    ///
    /// Without DIR: ./config if it exists, else the defaults embedded in this binary. Exits 1 with
    /// the first broken rule (file, line, key and rule) if the configuration is invalid.
    Check {
        /// A directory laid out like config/ (`robot-<id>.toml`, server.toml, vamr.toml, amcl.toml).
        dir: Option<PathBuf>,
    },
}

/// `amr eval`'s options.
#[derive(Debug, clap::Args)]
pub(crate) struct EvalArgs {
    /// A scenario of the configuration (`config/scenarios/<name>.toml`), or a scenario file's
    /// path (its `map` may be a map YAML's path relative to it: any ROS map).
    #[arg(long, default_value = "straight")]
    pub scenario: String,
    /// AMCL's map: a simulated SLAM-style survey of the site, or the site's own map.
    #[arg(long, value_enum, default_value = "surveyed")]
    pub map: eval_cmd::MapSource,
    /// Number of trials (the paper ran 5); trial k uses seed + k.
    #[arg(long, default_value_t = 5)]
    pub trials: usize,
    /// Seed of the first trial.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, default_value = "out/eval")]
    pub out: PathBuf,
    /// Configuration directory (default: ./config, else the embedded defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Robots in the formation (the paper: 2; with 3 they drive in a line, the reference robot in
    /// the middle). Refused if the path would take a robot into a wall.
    #[arg(long, default_value_t = 2)]
    pub robots: usize,
    /// Instead of T1–T4: the sensitivity study of ε_d (Table 6) or Δθ (Table 7) for T4,
    /// written to `OUT/<scenario>/sweep-<eps|step>.{md,json}`.
    #[arg(long, value_enum)]
    pub sweep: Option<eval_cmd::Sweep>,
    /// Instead of T1–T4: T4's error budget, each of its sources replaced by the truth in turn
    /// (`OUT/<scenario>/budget.{md,json}`).
    #[arg(long, conflicts_with = "sweep")]
    pub budget: bool,
    /// Instead of T1–T4 on one scenario: the occlusion study, T1–T4 over spacing 0.5–2.0 m and
    /// teams of 2, 3 and 4 on every scenario given with --study-scenario (default: straight,
    /// turning, hall-straight, hall-turning, corridor, short-racks), written to
    /// OUT/study-occlusion/study.{md,json} with a plot per scenario.
    #[arg(long, value_enum, conflicts_with_all = ["sweep", "budget"])]
    pub study: Option<eval_cmd::Study>,
    /// A scenario (name or file) for --study; repeat for several.
    #[arg(long = "study-scenario", value_name = "SCENARIO", requires = "study")]
    pub study_scenarios: Vec<String>,
    /// For --study: a configuration whose --trials leave the study's criterion open (T4 at most
    /// 0.5 cm worse than min(T1, T2, T3), that margin within two standard errors of the paired
    /// difference) runs this many trials in all, the same first ones and the next (0: none does).
    #[arg(long, value_name = "N", default_value_t = 50, requires = "study")]
    pub confirm_trials: usize,
    /// Record each trial as MCAP (scans, odometry, true poses, T1–T4's estimates side by side):
    /// this file for one trial, `FILE-<seed>.mcap` for several.
    #[arg(long, value_name = "FILE.mcap")]
    pub record: Option<PathBuf>,
    /// Serve the trials live to Foxglove (WebSocket) here, e.g. 127.0.0.1:8765; they run in
    /// simulated time, faster than real time.
    #[arg(long, value_name = "ADDR")]
    pub foxglove: Option<std::net::SocketAddr>,
}

/// `amr localize`'s options.
#[derive(Debug, clap::Args)]
pub(crate) struct LocalizeArgs {
    /// The map's YAML (ROS map_server format); its image path is relative to it.
    #[arg(long)]
    pub map: PathBuf,
    /// The CARMEN log.
    #[arg(long, required_unless_present = "bag", conflicts_with = "bag")]
    pub log: Option<PathBuf>,
    /// A ROS 2 bag: a rosbag2 file in either storage (MCAP `.mcap`, sqlite3 `.db3`), or the
    /// bag's directory.
    #[arg(long, value_name = "BAG")]
    pub bag: Option<PathBuf>,
    #[command(flatten)]
    pub ros2: localize::BagArgs,
    /// Initial pose `x,y,theta` (m, m, rad), spread as amcl.toml's initial_pose says, else as
    /// RViz's "2D Pose Estimate" (0.5 m, 15°); without it: amcl.toml's initial_pose, else global
    /// localisation.
    #[arg(long, value_parser = localize::parse_pose, allow_hyphen_values = true)]
    pub initial: Option<amr_core::se2::Se2>,
    /// AMCL parameters (an amcl.toml); default: ./config/amcl.toml if present, else the
    /// embedded one.
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// AMCL parameters from a nav2 params file (`amcl: ros__parameters:`, nav2_amcl's names)
    /// over the configuration's amcl.toml; `set_initial_pose` and `initial_pose` as nav2 reads
    /// them.
    #[arg(long, value_name = "NAV2_PARAMS.yaml", conflicts_with = "params")]
    pub nav2_params: Option<PathBuf>,
    /// Where to write the CSV; default: standard output.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Seed of the filter's random draws (same seed, same output).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Teleport the odometry every N scans by 1-5 m and any heading (drawn from the seed), as if
    /// the robot had been carried away: to see the filter report `lost` and re-localise.
    #[arg(long, value_name = "N")]
    pub kidnap: Option<usize>,
}
