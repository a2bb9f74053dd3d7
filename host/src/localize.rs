//! `amr localize`: AMCL over a CARMEN log or a ROS 2 bag on a ROS map, one pose per scan as CSV.

use amr_core::amcl::log::{Fed, LogLocalizer, Start};
use amr_core::carmen::{Record, parse_line};
use amr_core::config::{AmclParams, parse_file};
use amr_core::map::{MapYaml, OccupancyGrid, load_map};
use amr_core::se2::Se2;
use anyhow::Context as _;
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

/// What to localise.
#[derive(Debug)]
pub(crate) enum Input {
    /// A CARMEN log (.log, .clf).
    Carmen(PathBuf),
    /// A ROS 2 bag: an MCAP file, or a bag directory (its .mcap files in order).
    Bag(PathBuf, amr_record::ros2::bag::BagOptions),
}

/// `amr localize --bag`'s topics and frames.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct BagArgs {
    /// With --bag: the scan topic (sensor_msgs/msg/LaserScan).
    #[arg(long, default_value = "/scan", value_name = "TOPIC")]
    pub scan_topic: String,
    /// With --bag: the odometry topic (nav_msgs/msg/Odometry); if the bag has no such topic, the
    /// odometry is the transform --odom-frame → --base-frame on /tf.
    #[arg(long, default_value = "/odom", value_name = "TOPIC")]
    pub odom_topic: String,
    /// With --bag: take the odometry from /tf even if the odometry topic is there.
    #[arg(long)]
    pub odom_from_tf: bool,
    /// With --bag: the odometry frame of /tf.
    #[arg(long, default_value = "odom", value_name = "FRAME")]
    pub odom_frame: String,
    /// With --bag: the robot's base frame (/tf's odometry child; the laser's mounting is
    /// base → the scan's frame on /tf_static, else the scan's frame is taken as the base).
    #[arg(long, default_value = "base_link", value_name = "FRAME")]
    pub base_frame: String,
}

impl BagArgs {
    pub(crate) fn options(self) -> amr_record::ros2::bag::BagOptions {
        amr_record::ros2::bag::BagOptions {
            scan_topic: self.scan_topic,
            odom_topic: self.odom_topic,
            odom_from_tf: self.odom_from_tf,
            odom_frame: self.odom_frame,
            base_frame: self.base_frame,
            ..Default::default()
        }
    }
}

/// Options of one run.
#[derive(Debug)]
pub(crate) struct Options {
    pub map: PathBuf,
    pub input: Input,
    pub initial: Option<Se2>,
    pub params: AmclParams,
    pub out: Option<PathBuf>,
    pub seed: u64,
    /// Teleport the odometry every this many scans (`amcl::log::kidnapped`, jumps from `seed`).
    pub kidnap: Option<usize>,
}

/// `x,y,θ` (θ in radians) → pose.
pub(crate) fn parse_pose(s: &str) -> Result<Se2, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{s}`: {e}"))?;
    match v[..] {
        [x, y, t] if v.iter().all(|a| a.is_finite()) => Ok(Se2::new(x, y, t)),
        _ => Err(format!("`{s}`: expected x,y,theta (metres, metres, radians)")),
    }
}

pub(crate) fn load_params(file: Option<&Path>, config: Option<PathBuf>) -> anyhow::Result<AmclParams> {
    match file {
        Some(f) => {
            let text = std::fs::read_to_string(f).with_context(|| format!("cannot read {}", f.display()))?;
            Ok(parse_file::<AmclParams>(&f.display().to_string(), &text)?)
        }
        None => Ok(amr_actors::config::load(&crate::config_cmd::source_for(config))?.amcl),
    }
}

/// AMCL parameters from a nav2 params file (`amcl: ros__parameters:`, nav2's names) over the
/// configuration's `amcl.toml` (what nav2 does not have: the slip tail, the integrity monitor).
/// Parameters without effect here, and unknown names, are logged.
pub(crate) fn load_nav2_params(file: &Path, config: Option<PathBuf>) -> anyhow::Result<AmclParams> {
    Ok(load_nav2(file, config)?.params)
}

/// A nav2 params file's AMCL section: our parameters (as [`load_nav2_params`]), nav2's frames,
/// topics and transform settings.
pub(crate) fn load_nav2(
    file: &Path,
    config: Option<PathBuf>,
) -> anyhow::Result<amr_core::config::nav2::Nav2Amcl> {
    let yaml = std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
    let files = amr_actors::config::read_files(&crate::config_cmd::source_for(config))?;
    let base = files
        .iter()
        .find(|f| f.path == "amcl.toml")
        .context("the configuration has no amcl.toml")?
        .text()?
        .to_owned();
    let n = amr_core::config::nav2::from_nav2_params(&file.display().to_string(), &yaml, &base)
        .map_err(|e| anyhow::anyhow!(e))?;
    if !n.ignored.is_empty() {
        tracing::info!(parameters = ?n.ignored, "nav2 parameters without an effect here");
    }
    if !n.unknown.is_empty() {
        tracing::warn!(parameters = ?n.unknown, "not nav2_amcl parameters: ignored");
    }
    tracing::info!(base_frame = %n.frames.base_frame_id, odom_frame = %n.frames.odom_frame_id, scan_topic = %n.frames.scan_topic, "nav2 parameters read");
    Ok(n)
}

pub(crate) fn read_map(yaml_path: &Path) -> anyhow::Result<OccupancyGrid> {
    let text =
        std::fs::read_to_string(yaml_path).with_context(|| format!("cannot read {}", yaml_path.display()))?;
    let yaml = MapYaml::parse(&text).with_context(|| yaml_path.display().to_string())?;
    let image = yaml_path.parent().unwrap_or(Path::new(".")).join(&yaml.image);
    let bytes =
        std::fs::read(&image).with_context(|| format!("cannot read the map image {}", image.display()))?;
    load_map(&yaml, &bytes).with_context(|| image.display().to_string())
}

/// The pose, its covariance, and the integrity of the estimate (`amcl::integrity`): the state, the
/// share of the scan the map explains at the estimate, the level this sensor explains when
/// tracked, and whether another place explains the scans as well (1: a rival stands).
const HEADER: &str = "timestamp,x,y,theta,cov_xx,cov_xy,cov_xtheta,cov_yx,cov_yy,cov_ytheta,cov_thetax,cov_thetay,cov_thetatheta,integrity,explained,level,ambiguous";

/// Summary of a run, for the log.
#[derive(Debug, Default)]
pub(crate) struct Summary {
    pub scans: usize,
    pub poses: usize,
    /// Lines (CARMEN) or messages (bag) that could not be read, skipped.
    pub skipped: usize,
    pub scans_without_odometry: usize,
}

/// The files of a bag: the file itself, or a bag directory's `.mcap` and `.db3` files in name order
/// (rosbag2 splits as `<name>_0.mcap`, `<name>_1.mcap`, …: shorter names first, so `_10` after
/// `_9`).
fn bag_files(path: &Path) -> anyhow::Result<Vec<PathBuf>> {
    if !path.is_dir() {
        return Ok(vec![path.to_owned()]);
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(path)
        .with_context(|| format!("cannot read the bag directory {}", path.display()))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap" || e == "db3"))
        .collect();
    files.sort_by_key(|p| (p.as_os_str().len(), p.clone()));
    anyhow::ensure!(
        !files.is_empty(),
        "no .mcap or .db3 file in the bag directory {} (rosbag2 stores a bag as MCAP or sqlite3)",
        path.display()
    );
    Ok(files)
}

/// What a bag file is, by its first bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Storage {
    Mcap,
    Sqlite3,
}

/// MCAP's magic (the MCAP specification, "Magic": 0x89 `MCAP0` CR LF).
const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

fn storage_of(file: &Path, bytes: &[u8]) -> anyhow::Result<Storage> {
    if bytes.starts_with(MCAP_MAGIC) {
        return Ok(Storage::Mcap);
    }
    if bytes.starts_with(amr_record::ros2::db3::SQLITE_MAGIC) {
        return Ok(Storage::Sqlite3);
    }
    let head: String =
        bytes.iter().take(16).map(|b| if b.is_ascii_graphic() { *b as char } else { '.' }).collect();
    let what = match bytes {
        [] => "an empty file".to_owned(),
        [b'#', b'R', b'O', b'S', b'B', b'A', b'G', ..] => "a ROS 1 bag".to_owned(),
        b if b.starts_with(b"\x89PNG") => "a PNG image".to_owned(),
        b if b.starts_with(b"P5") || b.starts_with(b"P2") => "a PGM image (a map?)".to_owned(),
        _ => format!("a file that starts with {head:?}"),
    };
    anyhow::bail!(
        "{} is {what}, not a ROS 2 bag: `--bag` reads rosbag2 bags stored as MCAP (.mcap) or sqlite3 \
         (.db3), a file or the bag's directory",
        file.display()
    )
}

/// A bag's scans as records, skipped messages logged and counted.
fn bag_records(
    path: &Path,
    opts: &amr_record::ros2::bag::BagOptions,
    summary: &mut Summary,
) -> anyhow::Result<Vec<Record>> {
    let mut messages = Vec::new();
    let mut stopped = None;
    let wanted = [&opts.scan_topic, &opts.odom_topic, &opts.tf_topic, &opts.tf_static_topic];
    let want = |t: &str| wanted.iter().any(|w| *w == t);
    for file in bag_files(path)? {
        let bytes = std::fs::read(&file).with_context(|| format!("cannot read {}", file.display()))?;
        let (read, why) = match storage_of(&file, &bytes)? {
            Storage::Mcap => {
                let rec = amr_record::read::read_bytes_where(&bytes, want)
                    .with_context(|| format!("cannot read {}", file.display()))?;
                (rec.messages, rec.stopped)
            }
            Storage::Sqlite3 => {
                let db = amr_record::ros2::db3::read(&file, want)
                    .with_context(|| format!("cannot read {} (rosbag2 sqlite3)", file.display()))?;
                (db.messages, db.stopped)
            }
        };
        if let Some(why) = &why {
            tracing::warn!(file = %file.display(), reason = %why, "the bag is not whole; reading what is there");
            stopped.get_or_insert_with(|| format!("{}: {why}", file.display()));
        }
        messages.extend(read);
    }
    if let (true, Some(why)) = (messages.is_empty(), stopped) {
        anyhow::bail!("no message of the bag could be read: {why}");
    }
    let log = amr_record::ros2::bag::read(&messages, opts).with_context(|| path.display().to_string())?;
    for s in &log.skipped {
        tracing::warn!(topic = %s.topic, log_time_ns = s.log_time_ns, error = %s.reason, "skipping a message the bag reader cannot use");
    }
    summary.skipped = log.skipped.len();
    for (frame, (mount, from_tf)) in &log.mounts {
        if *from_tf {
            tracing::info!(frame = %frame, x = mount.x, y = mount.y, theta = mount.theta, "laser mounting from /tf_static");
        } else {
            tracing::warn!(frame = %frame, base = %opts.base_frame, "no transform from the base to the scan's frame on /tf_static: the scan's frame is taken as the base");
        }
    }
    tracing::info!(odometry = %log.odometry, samples = log.odometry_samples, scans = log.records.len(), "read the bag");
    Ok(log.records)
}

pub(crate) fn run(opts: &Options) -> anyhow::Result<Summary> {
    let grid = read_map(&opts.map)?;
    let mut summary = Summary::default();
    let records = match &opts.input {
        Input::Carmen(path) => {
            let log =
                std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
            let mut records = Vec::new();
            for (n, line) in log.lines().enumerate() {
                match parse_line(line) {
                    Ok(Some(r)) => records.push(r),
                    Ok(None) => {}
                    Err(e) => {
                        summary.skipped += 1;
                        tracing::warn!(line = n + 1, error = %e, "skipping a line the log reader cannot use");
                    }
                }
            }
            records
        }
        Input::Bag(path, bag) => bag_records(path, bag, &mut summary)?,
    };
    let records = match opts.kidnap {
        Some(every) => {
            let (records, kidnaps) = amr_core::amcl::log::kidnapped(&records, every, opts.seed);
            for k in &kidnaps {
                tracing::info!(
                    scan = k.scan,
                    x = k.jump.x,
                    y = k.jump.y,
                    theta = k.jump.theta,
                    "odometry teleported"
                );
            }
            records
        }
        None => records,
    };
    let mut out = String::from(HEADER);
    out.push('\n');
    let start = Start::resolve(opts.initial, &opts.params);
    let mut localizer = LogLocalizer::new(&grid, opts.params.clone(), start, opts.seed);
    for record in &records {
        if let Some(Fed { pose: Some(p), .. }) = localizer.feed(record) {
            let _ = write!(out, "{:.6},{:.6},{:.6},{:.6}", p.timestamp_s, p.pose.x, p.pose.y, p.pose.theta);
            for row in p.covariance {
                for v in row {
                    let _ = write!(out, ",{v:.9}");
                }
            }
            match p.integrity {
                Some(i) => {
                    let ambiguous = u8::from(i.ambiguous);
                    let _ = write!(out, ",{},{:.4},{:.4},{ambiguous}", i.state, i.explained, i.level);
                }
                None => out.push_str(",uncertain,,,0"),
            }
            out.push('\n');
            summary.poses += 1;
        }
    }
    summary.scans = localizer.scans;
    summary.scans_without_odometry = localizer.scans_without_odometry;
    match &opts.out {
        Some(path) => {
            std::fs::write(path, &out).with_context(|| format!("cannot write {}", path.display()))?
        }
        None => std::io::stdout().lock().write_all(out.as_bytes())?,
    }
    Ok(summary)
}
