//! `amr localize`: AMCL over a CARMEN log on a ROS map, one pose per scan as CSV.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use amr_core::amcl::{Amcl, LikelihoodField, scan_points};
use amr_core::carmen::{Record, parse_line};
use amr_core::config::{AmclParams, parse_file};
use amr_core::map::{MapYaml, OccupancyGrid, load_map};
use amr_core::se2::Se2;
use anyhow::Context as _;

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
    let mut amcl: Option<Amcl> = None;
    let mut last_odom: Option<Se2> = None;
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
        let laser = match record {
            Record::Odometry { pose, .. } => {
                last_odom = Some(pose);
                continue;
            }
            Record::Laser(l) => l,
        };
        summary.scans += 1;
        let Some(odom) = laser.odometry.or(last_odom) else {
            summary.scans_without_odometry += 1;
            continue;
        };
        // The field's z_rand term needs a maximum range: the parameters', else the first scan's.
        let filter = amcl.get_or_insert_with(|| {
            let range_max = opts.params.max_range_m().unwrap_or(laser.scan.range_max_m);
            let field = Arc::new(LikelihoodField::new(&grid, &opts.params, range_max));
            let mut f = Amcl::new(opts.params.clone(), field, opts.seed);
            match (opts.initial, opts.params.initial_pose) {
                (Some(p), spread) => {
                    let (sxy, syaw) = spread.map_or((0.25, 0.2), |s| (s.std_xy_m.get(), s.std_yaw_rad.get()));
                    f.init_pose(p, sxy, syaw);
                }
                (None, Some(ip)) => f.init_pose(ip.pose(), ip.std_xy_m.get(), ip.std_yaw_rad.get()),
                (None, None) => f.init_global(),
            }
            f
        });
        let points = scan_points(&laser.scan, &laser.laser_in_robot, &opts.params);
        filter.update(odom, &points, false);
        // Between filter updates the pose follows the odometry from the last estimate.
        if let (Some(e), Some(pose)) = (filter.estimate(), filter.pose_at(&odom)) {
            let c = e.covariance;
            let _ = write!(out, "{:.6},{:.6},{:.6},{:.6}", laser.timestamp_s, pose.x, pose.y, pose.theta);
            for row in c {
                for v in row {
                    let _ = write!(out, ",{v:.9}");
                }
            }
            out.push('\n');
            summary.poses += 1;
        }
    }
    match &opts.out {
        Some(path) => {
            std::fs::write(path, &out).with_context(|| format!("cannot write {}", path.display()))?
        }
        None => std::io::stdout().lock().write_all(out.as_bytes())?,
    }
    Ok(summary)
}
