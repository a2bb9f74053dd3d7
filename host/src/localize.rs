//! `amr localize`: AMCL over a CARMEN log on a ROS map, one pose per scan as CSV.

use amr_core::amcl::log::{Fed, LogLocalizer, Start};
use amr_core::carmen::parse_line;
use amr_core::config::{AmclParams, parse_file};
use amr_core::map::{MapYaml, OccupancyGrid, load_map};
use amr_core::se2::Se2;
use anyhow::Context as _;
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

/// Options of one run.
#[derive(Debug)]
pub(crate) struct Options {
    pub map: PathBuf,
    pub log: PathBuf,
    pub initial: Option<Se2>,
    pub params: AmclParams,
    pub out: Option<PathBuf>,
    pub seed: u64,
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

pub(crate) fn read_map(yaml_path: &Path) -> anyhow::Result<OccupancyGrid> {
    let text =
        std::fs::read_to_string(yaml_path).with_context(|| format!("cannot read {}", yaml_path.display()))?;
    let yaml = MapYaml::parse(&text).with_context(|| yaml_path.display().to_string())?;
    let image = yaml_path.parent().unwrap_or(Path::new(".")).join(&yaml.image);
    let bytes =
        std::fs::read(&image).with_context(|| format!("cannot read the map image {}", image.display()))?;
    load_map(&yaml, &bytes).with_context(|| image.display().to_string())
}

const HEADER: &str = "timestamp,x,y,theta,cov_xx,cov_xy,cov_xtheta,cov_yx,cov_yy,cov_ytheta,cov_thetax,cov_thetay,cov_thetatheta";

/// Summary of a run, for the log.
#[derive(Debug, Default)]
pub(crate) struct Summary {
    pub scans: usize,
    pub poses: usize,
    pub bad_lines: usize,
    pub scans_without_odometry: usize,
}

pub(crate) fn run(opts: &Options) -> anyhow::Result<Summary> {
    let grid = read_map(&opts.map)?;
    let log =
        std::fs::read_to_string(&opts.log).with_context(|| format!("cannot read {}", opts.log.display()))?;
    let mut out = String::from(HEADER);
    out.push('\n');
    let mut summary = Summary::default();
    let start = Start::resolve(opts.initial, &opts.params);
    let mut localizer = LogLocalizer::new(&grid, opts.params.clone(), start, opts.seed);
    for (n, line) in log.lines().enumerate() {
        let record = match parse_line(line) {
            Ok(Some(r)) => r,
            Ok(None) => continue,
            Err(e) => {
                summary.bad_lines += 1;
                tracing::warn!(line = n + 1, error = %e, "skipping a line the log reader cannot use");
                continue;
            }
        };
        if let Some(Fed { pose: Some(p), .. }) = localizer.feed(&record) {
            let _ = write!(out, "{:.6},{:.6},{:.6},{:.6}", p.timestamp_s, p.pose.x, p.pose.y, p.pose.theta);
            for row in p.covariance {
                for v in row {
                    let _ = write!(out, ",{v:.9}");
                }
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
