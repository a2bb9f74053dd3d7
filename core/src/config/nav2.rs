//! nav2's AMCL parameter file (`amcl: ros__parameters:` in a nav2 params YAML, as nav2_bringup's
//! `nav2_params.yaml` has it) read as our [`AmclParams`]: a ROS 2 user's tuned file drives our
//! localiser as it, by nav2_amcl's own parameter names (amcl.toml uses the same names).
//!
//! - The parameters both have (the motion noise `alpha1`–`alpha4`, the particle counts, KLD's
//!   `pf_err`/`pf_z`, the likelihood field's, the update thresholds, recovery, beam skipping,
//!   `laser_model_type` `likelihood_field` or `likelihood_field_prob`) are read as nav2 reads them:
//!   the file's value, else nav2's default (not our tuning); what nav2 does not have (our slip
//!   tail, the integrity monitor) comes from the base configuration.
//! - `set_initial_pose: true` with `initial_pose: {x, y, yaw}` starts there, spread as nav2 spreads
//!   it (0.5 m, π/12: `amcl_node.cpp`'s initial covariance); otherwise the filter localises
//!   globally (nav2 would wait for `/initialpose`).
//! - Frames, topics and the transform's settings (`base_frame_id`, `odom_frame_id`,
//!   `global_frame_id`, `scan_topic`, `map_topic`, `transform_tolerance`, `tf_broadcast`) are
//!   returned for the caller (`amr amcl` is a node with them).
//! - Parameters without an effect here are listed as ignored (the beam model's `z_max`, `z_short`,
//!   `lambda_short`; the omnidirectional `alpha5`; node settings such as `save_pose_rate`); any other
//!   name as unknown. The beam model and the omnidirectional motion model are refused.

use std::collections::BTreeMap;

use super::AmclParams;

/// What a nav2 AMCL file gives.
#[derive(Debug, Clone)]
pub struct Nav2Amcl {
    pub params: AmclParams,
    pub frames: Nav2Frames,
    /// nav2 parameters that have no effect on this localiser.
    pub ignored: Vec<String>,
    /// Names nav2_amcl does not have either (a typo, or another node's).
    pub unknown: Vec<String>,
}

/// nav2_amcl's frames, topics and transform settings (its defaults where the file is silent).
#[derive(Debug, Clone, PartialEq)]
pub struct Nav2Frames {
    pub base_frame_id: String,
    pub odom_frame_id: String,
    pub global_frame_id: String,
    pub scan_topic: String,
    pub map_topic: String,
    /// How far into the future the published map → odom transform is stamped, s.
    pub transform_tolerance_s: f64,
    /// Whether map → odom is published at all.
    pub tf_broadcast: bool,
}

/// Both have these, by the same name and meaning.
const SHARED: [&str; 25] = [
    "alpha1",
    "alpha2",
    "alpha3",
    "alpha4",
    "beam_skip_distance",
    "beam_skip_error_threshold",
    "beam_skip_threshold",
    "do_beamskip",
    "laser_likelihood_max_dist",
    "laser_max_range",
    "laser_min_range",
    "laser_model_type",
    "max_beams",
    "max_particles",
    "min_particles",
    "pf_err",
    "pf_z",
    "recovery_alpha_fast",
    "recovery_alpha_slow",
    "resample_interval",
    "sigma_hit",
    "update_min_a",
    "update_min_d",
    "z_hit",
    "z_rand",
];

/// nav2's values for the parameters both have, where the file is silent (nav2_amcl's
/// `amcl_node.cpp` defaults, as nav2_bringup's `nav2_params.yaml` also sets them): the file is
/// read as nav2 would read it, not over our tuning.
fn nav2_defaults() -> [(&'static str, toml::Value); 25] {
    [
        ("alpha1", toml::Value::Float(0.2)),
        ("alpha2", toml::Value::Float(0.2)),
        ("alpha3", toml::Value::Float(0.2)),
        ("alpha4", toml::Value::Float(0.2)),
        ("beam_skip_distance", toml::Value::Float(0.5)),
        ("beam_skip_error_threshold", toml::Value::Float(0.9)),
        ("beam_skip_threshold", toml::Value::Float(0.3)),
        ("do_beamskip", toml::Value::Boolean(false)),
        ("laser_likelihood_max_dist", toml::Value::Float(2.0)),
        ("laser_max_range", toml::Value::Float(100.0)),
        ("laser_min_range", toml::Value::Float(-1.0)),
        ("laser_model_type", toml::Value::String("likelihood_field".to_owned())),
        ("max_beams", toml::Value::Integer(60)),
        ("max_particles", toml::Value::Integer(2000)),
        ("min_particles", toml::Value::Integer(500)),
        ("pf_err", toml::Value::Float(0.05)),
        ("pf_z", toml::Value::Float(0.99)),
        ("recovery_alpha_fast", toml::Value::Float(0.0)),
        ("recovery_alpha_slow", toml::Value::Float(0.0)),
        ("resample_interval", toml::Value::Integer(1)),
        ("sigma_hit", toml::Value::Float(0.2)),
        ("update_min_a", toml::Value::Float(0.2)),
        ("update_min_d", toml::Value::Float(0.25)),
        ("z_hit", toml::Value::Float(0.5)),
        ("z_rand", toml::Value::Float(0.5)),
    ]
}

/// nav2_amcl's parameters that change nothing here.
const IGNORED: [&str; 14] = [
    "alpha5",
    "always_reset_initial_pose",
    "bond_heartbeat_period",
    "first_map_only",
    "introspection_mode",
    "lambda_short",
    "robot_model_type",
    "save_pose_rate",
    "service_introspection_mode",
    "use_sim_time",
    "z_max",
    "z_short",
    "freespace_downsampling",
    "random_seed",
];

/// nav2_amcl's initial spread (`amcl_node.cpp`: 0.5 m, π/12).
const INITIAL_STD_XY_M: f64 = 0.5;
const INITIAL_STD_YAW_RAD: f64 = std::f64::consts::PI / 12.0;

/// A YAML scalar as a TOML value.
fn toml_value(key: &str, v: &serde_norway::Value) -> Result<toml::Value, String> {
    use serde_norway::Value as Y;
    Ok(match v {
        Y::Bool(b) => toml::Value::Boolean(*b),
        Y::Number(n) => match (n.as_i64(), n.as_f64()) {
            (Some(i), _) => toml::Value::Integer(i),
            (None, Some(f)) => toml::Value::Float(f),
            _ => return Err(format!("{key}: {n:?} is not a number amcl can take")),
        },
        Y::String(s) => toml::Value::String(s.clone()),
        other => return Err(format!("{key}: expected a value, found {other:?}")),
    })
}

/// Read nav2's AMCL parameters from the params file `yaml` (named `file` in errors) over `base`,
/// the text of an `amcl.toml` that supplies what nav2 does not have.
pub fn from_nav2_params(file: &str, yaml: &str, base: &str) -> Result<Nav2Amcl, String> {
    let doc: serde_norway::Value =
        serde_norway::from_str(yaml).map_err(|e| format!("{file}: not YAML: {e}"))?;
    let Some(params) = doc.get("amcl").and_then(|a| a.get("ros__parameters")).and_then(|p| p.as_mapping())
    else {
        return Err(format!(
            "{file}: no `amcl: ros__parameters:` section (a nav2 params file names the node first)"
        ));
    };
    let mut table: toml::Table = base.parse().map_err(|e| format!("the base amcl.toml: {e}"))?;
    for (k, v) in nav2_defaults() {
        table.insert(k.to_owned(), v);
    }
    let mut frames = Nav2Frames {
        base_frame_id: "base_footprint".into(),
        odom_frame_id: "odom".into(),
        global_frame_id: "map".into(),
        scan_topic: "scan".into(),
        map_topic: "map".into(),
        transform_tolerance_s: 1.0,
        tf_broadcast: true,
    };
    let (mut ignored, mut unknown) = (Vec::new(), Vec::new());
    let mut initial: BTreeMap<String, f64> = BTreeMap::new();
    let mut set_initial = false;
    for (k, v) in params {
        let Some(key) = k.as_str() else {
            return Err(format!("{file}: a parameter name that is not text: {k:?}"));
        };
        let text = || v.as_str().map(str::to_owned).ok_or_else(|| format!("{file}: {key} must be text"));
        match key {
            "laser_model_type" if v.as_str() == Some("beam") => {
                return Err(format!(
                    "{file}: laser_model_type beam is not supported (likelihood_field, likelihood_field_prob)"
                ));
            }
            "robot_model_type" if v.as_str().is_some_and(|m| m.contains("Omni")) => {
                return Err(format!(
                    "{file}: {} is not supported: the fleet's robots drive differentially",
                    text()?
                ));
            }
            k if SHARED.contains(&k) => {
                table.insert(k.to_owned(), toml_value(k, v).map_err(|e| format!("{file}: {e}"))?);
            }
            "base_frame_id" => frames.base_frame_id = text()?,
            "odom_frame_id" => frames.odom_frame_id = text()?,
            "global_frame_id" => frames.global_frame_id = text()?,
            "scan_topic" => frames.scan_topic = text()?,
            "map_topic" => frames.map_topic = text()?,
            "transform_tolerance" => {
                frames.transform_tolerance_s = v
                    .as_f64()
                    .filter(|t| t.is_finite() && *t >= 0.0)
                    .ok_or_else(|| format!("{file}: transform_tolerance must be seconds, 0 or more"))?
            }
            "tf_broadcast" => {
                frames.tf_broadcast =
                    v.as_bool().ok_or_else(|| format!("{file}: tf_broadcast must be true or false"))?
            }
            "set_initial_pose" => {
                set_initial =
                    v.as_bool().ok_or_else(|| format!("{file}: set_initial_pose must be true or false"))?
            }
            "initial_pose" => {
                let m =
                    v.as_mapping().ok_or_else(|| format!("{file}: initial_pose must be {{x, y, z, yaw}}"))?;
                for (ik, iv) in m {
                    let (Some(name), Some(x)) = (ik.as_str(), iv.as_f64()) else {
                        return Err(format!("{file}: initial_pose.{ik:?} must be a number"));
                    };
                    initial.insert(name.to_owned(), x);
                }
            }
            k if IGNORED.contains(&k) => ignored.push(k.to_owned()),
            k => unknown.push(k.to_owned()),
        }
    }
    if set_initial {
        let get = |n: &str| initial.get(n).copied().unwrap_or(0.0);
        let mut pose = toml::Table::new();
        pose.insert("x".into(), toml::Value::Float(get("x")));
        pose.insert("y".into(), toml::Value::Float(get("y")));
        pose.insert("yaw".into(), toml::Value::Float(get("yaw")));
        pose.insert("std_xy_m".into(), toml::Value::Float(INITIAL_STD_XY_M));
        pose.insert("std_yaw_rad".into(), toml::Value::Float(INITIAL_STD_YAW_RAD));
        table.insert("initial_pose".into(), toml::Value::Table(pose));
    } else {
        table.remove("initial_pose");
    }
    let merged = toml::to_string(&table).map_err(|e| format!("{file}: {e}"))?;
    // Errors name the parameter, not a line of the merged text.
    let params: AmclParams =
        amr_settings::parse_file(file, &merged).map_err(|e| format!("{file}: {}: {}", e.key, e.rule))?;
    Ok(Nav2Amcl { params, frames, ignored, unknown })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]
    use super::*;

    /// The shipped amcl.toml.
    fn base() -> String {
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/amcl.toml")).unwrap()
    }

    /// nav2_bringup's `nav2_params.yaml` AMCL section as Humble and Jazzy ship it (the values of
    /// ros-navigation/navigation2's `nav2_bringup/params/nav2_params.yaml`).
    const NAV2_DEFAULTS: &str = "\
amcl:
  ros__parameters:
    use_sim_time: True
    alpha1: 0.2
    alpha2: 0.2
    alpha3: 0.2
    alpha4: 0.2
    alpha5: 0.2
    base_frame_id: \"base_footprint\"
    beam_skip_distance: 0.5
    beam_skip_error_threshold: 0.9
    beam_skip_threshold: 0.3
    do_beamskip: false
    global_frame_id: \"map\"
    lambda_short: 0.1
    laser_likelihood_max_dist: 2.0
    laser_max_range: 100.0
    laser_min_range: -1.0
    laser_model_type: \"likelihood_field\"
    max_beams: 60
    max_particles: 2000
    min_particles: 500
    odom_frame_id: \"odom\"
    pf_err: 0.05
    pf_z: 0.99
    recovery_alpha_fast: 0.0
    recovery_alpha_slow: 0.0
    resample_interval: 1
    robot_model_type: \"nav2_amcl::DifferentialMotionModel\"
    save_pose_rate: 0.5
    sigma_hit: 0.2
    tf_broadcast: true
    transform_tolerance: 1.0
    update_min_a: 0.2
    update_min_d: 0.25
    z_hit: 0.5
    z_max: 0.05
    z_rand: 0.5
    z_short: 0.05
    scan_topic: scan
";

    #[test]
    fn nav2s_own_defaults_become_our_parameters_by_name() {
        let n = from_nav2_params("nav2_params.yaml", NAV2_DEFAULTS, &base()).unwrap();
        let p = &n.params;
        assert_eq!((p.alpha1.get(), p.alpha4.get()), (0.2, 0.2));
        assert_eq!((p.min_particles.get(), p.max_particles.get(), p.max_beams.get()), (500, 2000, 60));
        assert_eq!((p.update_min_d.get(), p.update_min_a.get()), (0.25, 0.2));
        assert_eq!((p.z_hit.get(), p.z_rand.get(), p.sigma_hit.get()), (0.5, 0.5, 0.2));
        assert_eq!(p.laser_max_range.get(), 100.0);
        assert!(p.initial_pose.is_none(), "no set_initial_pose: global localisation");
        assert_eq!(n.frames.base_frame_id, "base_footprint");
        assert_eq!(n.frames.scan_topic, "scan");
        assert!(n.unknown.is_empty(), "{:?}", n.unknown);
        assert_eq!((n.frames.map_topic.as_str(), n.frames.transform_tolerance_s), ("map", 1.0));
        assert!(n.frames.tf_broadcast);
        for k in ["alpha5", "z_max", "z_short", "lambda_short", "use_sim_time"] {
            assert!(n.ignored.contains(&k.to_owned()), "{k} in {:?}", n.ignored);
        }
    }

    #[test]
    fn the_fleets_v_file_sets_its_frames_and_initial_pose() {
        let yaml = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../ros2/nav2/v_amcl.yaml"))
            .unwrap();
        let n = from_nav2_params("v_amcl.yaml", &yaml, &base()).unwrap();
        assert_eq!((n.frames.base_frame_id.as_str(), n.frames.odom_frame_id.as_str()), ("V", "V/odom"));
        assert_eq!(n.frames.scan_topic, "/virtual/scan");
        let i = n.params.initial_pose.unwrap();
        assert_eq!((i.x.get(), i.y.get(), i.yaw.get()), (-2.0, 0.0, 0.0));
        assert_eq!(i.std_xy_m.get(), 0.5);
        assert_eq!(n.params.max_beams.get(), 120);
    }

    #[test]
    fn what_cannot_work_is_refused_with_its_name() {
        let with = |line: &str| format!("amcl:\n  ros__parameters:\n    {line}\n");
        let e = |y: &str| from_nav2_params("f.yaml", y, &base()).unwrap_err();
        assert!(e(&with("laser_model_type: beam")).contains("beam is not supported"));
        assert!(e(&with("robot_model_type: nav2_amcl::OmniMotionModel")).contains("not supported"));
        assert!(e(&with("min_particles: -3")).contains("min_particles"), "{}", e(&with("min_particles: -3")));
        assert!(e(&with("z_hit: 1.5")).contains("z_hit"));
        assert!(
            e("map_server:\n  ros__parameters:\n    yaml_filename: m.yaml\n")
                .contains("no `amcl: ros__parameters:`")
        );
        assert!(e(": : :").contains("not YAML"));
        let n = from_nav2_params("f.yaml", &with("min_partciles: 100"), &base()).unwrap();
        assert_eq!(n.unknown, ["min_partciles"]);
    }

    #[test]
    fn a_silent_file_means_nav2s_defaults_not_our_tuning() {
        let ours: AmclParams = amr_settings::parse_file("amcl.toml", &base()).unwrap();
        assert_ne!(ours.alpha1.get(), 0.2, "the test needs a base tuned away from nav2");
        let n =
            from_nav2_params("f.yaml", "amcl:\n  ros__parameters:\n    max_beams: 30\n", &base()).unwrap();
        assert_eq!((n.params.alpha1.get(), n.params.max_beams.get()), (0.2, 30));
        assert!(!n.params.do_beamskip);
        assert!(matches!(n.params.laser_model_type, crate::config::LaserModel::LikelihoodField));
        // What nav2 has not: ours.
        assert_eq!(n.params.odom_slip_share.get(), ours.odom_slip_share.get());
    }
}
