//! What ROS 2 may tell the fleet: a pose for V on `/initialpose` (RViz's "2D Pose Estimate") and,
//! when allowed, a twist for V on `/cmd_vel` (a teleop, or nav2's controller). Each message is
//! checked here; what passes goes to the caller as an [`Input`], which hands it to the server (the
//! formation applies every robot's limits and stops V when the twists stop).

use std::sync::Arc;

use amr_core::se2::Se2;
use amr_ros2::msg::{PoseWithCovarianceStamped, Ros2Message as _, Twist, yaw};
use amr_ros2::rmw_zenoh::Qos;
use amr_ros2::transport::{Ros2Error, Ros2Node, Ros2Subscription};
use tokio::sync::mpsc;

/// A checked input.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Input {
    /// V's pose in the map and its spread (standard deviations, m and rad).
    InitialPose { v: Se2, std_xy_m: f64, std_yaw_rad: f64 },
    /// V's velocity: forward m/s, turn rad/s.
    Twist { v_mps: f64, w_radps: f64 },
}

/// The spread taken when a pose comes without one (RViz sends x and y variances of 0.25 m² and a
/// yaw variance of 0.0685 rad²: these), and the smallest taken.
const DEFAULT_STD_XY_M: f64 = 0.5;
const DEFAULT_STD_YAW_RAD: f64 = 0.2617;
const MIN_STD_XY_M: f64 = 0.02;
const MIN_STD_YAW_RAD: f64 = 0.01;

/// A `/initialpose` message as V's pose: in frame `map` (or no frame), finite, its orientation a
/// rotation about z; the spread from the covariance's x, y and yaw variances (`DEFAULT_*` when
/// they are zero or not finite).
pub fn initial_pose(m: &PoseWithCovarianceStamped) -> Result<Input, String> {
    initial_pose_in(m, "map")
}

/// As [`initial_pose`], in the global frame `global` (nav2_amcl's `global_frame_id`).
pub fn initial_pose_in(m: &PoseWithCovarianceStamped, global: &str) -> Result<Input, String> {
    let frame = m.header.frame_id.trim_start_matches('/');
    if !frame.is_empty() && frame != global {
        return Err(format!("an initial pose in frame {frame:?}: only {global:?} is known"));
    }
    let p = &m.pose.pose;
    let [qx, qy, qz, qw] = p.orientation;
    let norm = (qx * qx + qy * qy + qz * qz + qw * qw).sqrt();
    if !(p.position.iter().chain(&p.orientation).all(|v| v.is_finite()) && norm > 1e-6) {
        return Err("an initial pose that is not finite".to_owned());
    }
    if (qx.abs() + qy.abs()) / norm > 0.05 {
        return Err("an initial pose tilted out of the plane".to_owned());
    }
    let c = &m.pose.covariance;
    let std = |var: f64, default: f64, min: f64| {
        if var.is_finite() && var > 0.0 { var.sqrt().max(min) } else { default }
    };
    let std_xy_m = std(c[0].max(c[7]), DEFAULT_STD_XY_M, MIN_STD_XY_M);
    let std_yaw_rad = std(c[35], DEFAULT_STD_YAW_RAD, MIN_STD_YAW_RAD);
    Ok(Input::InitialPose {
        v: Se2::new(p.position[0], p.position[1], yaw(p.orientation)),
        std_xy_m,
        std_yaw_rad,
    })
}

/// A `/cmd_vel` message as V's twist: `linear.x` and `angular.z`, finite. A formation drives as
/// a differential robot: the other components are ignored.
pub fn twist(t: &Twist) -> Result<Input, String> {
    let (v_mps, w_radps) = (t.linear[0], t.angular[2]);
    if !(v_mps.is_finite() && w_radps.is_finite()) {
        return Err("a twist that is not finite".to_owned());
    }
    Ok(Input::Twist { v_mps, w_radps })
}

/// Subscribe `/initialpose` and, if `cmd_vel`, `/cmd_vel` on `node`: the checked inputs, in the
/// order they came. Refused messages are logged and dropped.
pub async fn listen(node: Arc<Ros2Node>, cmd_vel: bool) -> Result<mpsc::Receiver<Input>, Ros2Error> {
    let (tx, rx) = mpsc::channel(64);
    let poses = node.subscription("/initialpose", PoseWithCovarianceStamped::TYPE, Qos::reliable(10)).await?;
    tokio::spawn(forward(poses, tx.clone(), |b| {
        PoseWithCovarianceStamped::from_cdr(b).map_err(|e| e.to_string()).and_then(|m| initial_pose(&m))
    }));
    if cmd_vel {
        let twists = node.subscription("/cmd_vel", Twist::TYPE, Qos::reliable(10)).await?;
        tokio::spawn(forward(twists, tx, |b| {
            Twist::from_cdr(b).map_err(|e| e.to_string()).and_then(|t| twist(&t))
        }));
    }
    Ok(rx)
}

async fn forward(
    sub: Ros2Subscription,
    tx: mpsc::Sender<Input>,
    check: impl Fn(&[u8]) -> Result<Input, String>,
) {
    while let Some(payload) = sub.recv().await {
        match check(&payload) {
            Ok(input) => {
                if tx.send(input).await.is_err() {
                    return;
                }
            }
            Err(why) => tracing::warn!(topic = %sub.describe(), %why, "ROS 2: a message refused"),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]
    use amr_ros2::msg::{Header, Pose, PoseWithCovariance};

    use super::*;

    fn pose(frame: &str, x: f64, y: f64, theta: f64, cov: [f64; 36]) -> PoseWithCovarianceStamped {
        PoseWithCovarianceStamped {
            header: Header::new(1.0, frame),
            pose: PoseWithCovariance { pose: Pose::planar(x, y, theta), covariance: cov },
        }
    }

    #[test]
    fn rviz_pose_estimates_become_vs_pose_and_spread() {
        // What RViz's "2D Pose Estimate" sends: variances 0.25, 0.25 and 0.0685.
        let mut cov = [0.0; 36];
        (cov[0], cov[7], cov[35]) = (0.25, 0.25, 0.068_538_919_452_009_54);
        let Input::InitialPose { v, std_xy_m, std_yaw_rad } =
            initial_pose(&pose("map", 1.5, -2.0, 2.5, cov)).unwrap()
        else {
            panic!()
        };
        assert!(
            (v.x - 1.5).abs() < 1e-12 && (v.y + 2.0).abs() < 1e-12 && (v.theta - 2.5).abs() < 1e-9,
            "{v:?}"
        );
        assert!((std_xy_m - 0.5).abs() < 1e-12 && (std_yaw_rad - 0.2618).abs() < 1e-3);
        // No covariance: the defaults; a tiny one: the floor.
        let Input::InitialPose { std_xy_m, .. } = initial_pose(&pose("", 0.0, 0.0, 0.0, [0.0; 36])).unwrap()
        else {
            panic!()
        };
        assert_eq!(std_xy_m, DEFAULT_STD_XY_M);
        let mut tiny = [0.0; 36];
        (tiny[0], tiny[35]) = (1e-12, 1e-12);
        let Input::InitialPose { std_xy_m, std_yaw_rad, .. } =
            initial_pose(&pose("/map", 0.0, 0.0, 0.0, tiny)).unwrap()
        else {
            panic!()
        };
        assert_eq!((std_xy_m, std_yaw_rad), (MIN_STD_XY_M, MIN_STD_YAW_RAD));
    }

    #[test]
    fn poses_in_other_frames_not_finite_or_tilted_are_refused() {
        assert!(initial_pose(&pose("odom", 0.0, 0.0, 0.0, [0.0; 36])).is_err());
        assert!(initial_pose(&pose("map", f64::NAN, 0.0, 0.0, [0.0; 36])).is_err());
        let mut tilted = pose("map", 0.0, 0.0, 0.0, [0.0; 36]);
        let h = std::f64::consts::FRAC_1_SQRT_2;
        tilted.pose.pose.orientation = [h, 0.0, 0.0, h];
        assert!(initial_pose(&tilted).is_err());
        let mut zero = pose("map", 0.0, 0.0, 0.0, [0.0; 36]);
        zero.pose.pose.orientation = [0.0; 4];
        assert!(initial_pose(&zero).is_err());
    }

    #[test]
    fn twists_take_forward_and_turn_and_refuse_what_is_not_finite() {
        let t = Twist { linear: [0.3, 0.1, 0.0], angular: [0.0, 0.0, -0.2] };
        assert_eq!(twist(&t).unwrap(), Input::Twist { v_mps: 0.3, w_radps: -0.2 });
        assert!(twist(&Twist { linear: [f64::INFINITY, 0.0, 0.0], angular: [0.0; 3] }).is_err());
        assert!(twist(&Twist { linear: [0.0; 3], angular: [0.0, 0.0, f64::NAN] }).is_err());
    }
}
