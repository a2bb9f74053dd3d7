//! The ROS 2 messages this crate writes and reads, their CDR encoding ([`crate::cdr`]) and their
//! `ros2msg` schema text.
//!
//! Field lists as in the `.msg` files of ros2/common_interfaces (`std_msgs`, `sensor_msgs`,
//! `geometry_msgs`, `nav_msgs`), ros2/geometry2 (`tf2_msgs/TFMessage`) and ros2/rcl_interfaces
//! (`builtin_interfaces/Time`); fields are encoded in declaration order, nested messages inline.
//! The schema text is rosbag2's: the message's own definition, then every type it uses once, each
//! after a line of 80 `=` and a line `MSG: pkg/Type` (rosbag2_storage_mcap's
//! message_definition_cache; the MCAP spec's "ros2msg" schema encoding,
//! <https://mcap.dev/spec/registry#ros2msg>).
//!
//! It is one file because each message's struct, its CDR encoding and its schema text list the same
//! fields in the same order, and must change together.

use crate::cdr::{CdrError, CdrReader, CdrWriter};

/// `builtin_interfaces/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// Seconds to `sec` + `nanosec` (nanosec < 10⁹), clamped to what `sec` holds; NaN is 0.
    #[must_use]
    pub fn from_secs(t: f64) -> Self {
        if t.is_nan() {
            return Time::default();
        }
        let t = t.clamp(f64::from(i32::MIN), f64::from(i32::MAX));
        let sec = t.floor();
        let mut nanosec = ((t - sec) * 1e9).round();
        let mut sec = sec as i64;
        if nanosec >= 1e9 {
            nanosec -= 1e9;
            sec += 1;
        }
        Time { sec: i32::try_from(sec).unwrap_or(i32::MAX), nanosec: nanosec as u32 }
    }

    #[must_use]
    pub fn secs(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }

    fn write(&self, w: &mut CdrWriter) {
        w.i32(self.sec);
        w.u32(self.nanosec);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Time { sec: r.i32()?, nanosec: r.u32()? })
    }
}

/// `std_msgs/Header`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

impl Header {
    #[must_use]
    pub fn new(stamp_s: f64, frame_id: &str) -> Self {
        Header { stamp: Time::from_secs(stamp_s), frame_id: frame_id.to_owned() }
    }

    fn write(&self, w: &mut CdrWriter) {
        self.stamp.write(w);
        w.string(&self.frame_id);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Header { stamp: Time::read(r)?, frame_id: r.string()? })
    }
}

/// `geometry_msgs/Pose`: position (x, y, z), orientation quaternion (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub position: [f64; 3],
    pub orientation: [f64; 4],
}

impl Default for Pose {
    fn default() -> Self {
        Pose { position: [0.0; 3], orientation: [0.0, 0.0, 0.0, 1.0] }
    }
}

impl Pose {
    /// A planar pose: z = 0, rotation about z by θ (q = (0, 0, sin θ/2, cos θ/2)).
    #[must_use]
    pub fn planar(x: f64, y: f64, theta: f64) -> Self {
        let (s, c) = (theta / 2.0).sin_cos();
        Pose { position: [x, y, 0.0], orientation: [0.0, 0.0, s, c] }
    }

    /// x, y and the yaw of the orientation.
    #[must_use]
    pub fn planar_parts(&self) -> (f64, f64, f64) {
        (self.position[0], self.position[1], yaw(self.orientation))
    }

    fn write(&self, w: &mut CdrWriter) {
        for v in self.position.iter().chain(&self.orientation) {
            w.f64(*v);
        }
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Pose { position: r.f64_array()?, orientation: r.f64_array()? })
    }
}

/// The yaw (rotation about z, ZYX convention) of a quaternion (x, y, z, w), normalised or not:
/// atan2(2(wz + xy), 1 − 2(y² + z²)) on the unit quaternion.
#[must_use]
pub fn yaw(q: [f64; 4]) -> f64 {
    let [x, y, z, w] = q;
    let n = x * x + y * y + z * z + w * w;
    (2.0 * (w * z + x * y)).atan2(n - 2.0 * (y * y + z * z))
}

/// `sensor_msgs/LaserScan`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LaserScan {
    pub header: Header,
    pub angle_min: f32,
    pub angle_max: f32,
    pub angle_increment: f32,
    pub time_increment: f32,
    pub scan_time: f32,
    pub range_min: f32,
    pub range_max: f32,
    pub ranges: Vec<f32>,
    pub intensities: Vec<f32>,
}

/// `geometry_msgs/PoseWithCovariance` (row-major 6×6 covariance over x, y, z, roll, pitch, yaw).
#[derive(Debug, Clone, PartialEq)]
pub struct PoseWithCovariance {
    pub pose: Pose,
    pub covariance: [f64; 36],
}

impl Default for PoseWithCovariance {
    fn default() -> Self {
        PoseWithCovariance { pose: Pose::default(), covariance: [0.0; 36] }
    }
}

impl PoseWithCovariance {
    fn write(&self, w: &mut CdrWriter) {
        self.pose.write(w);
        for v in &self.covariance {
            w.f64(*v);
        }
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(PoseWithCovariance { pose: Pose::read(r)?, covariance: r.f64_array()? })
    }
}

/// `geometry_msgs/PoseWithCovarianceStamped`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PoseWithCovarianceStamped {
    pub header: Header,
    pub pose: PoseWithCovariance,
}

/// `geometry_msgs/TwistWithCovariance`: linear, angular (each x, y, z), covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct TwistWithCovariance {
    pub linear: [f64; 3],
    pub angular: [f64; 3],
    pub covariance: [f64; 36],
}

impl Default for TwistWithCovariance {
    fn default() -> Self {
        TwistWithCovariance { linear: [0.0; 3], angular: [0.0; 3], covariance: [0.0; 36] }
    }
}

/// `diagnostic_msgs/DiagnosticStatus`: a level (`OK` 0, `WARN` 1, `ERROR` 2, `STALE` 3), a name, a
/// message, the hardware it is about, and key/value pairs.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DiagnosticStatus {
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<(String, String)>,
}

impl DiagnosticStatus {
    pub const OK: u8 = 0;
    pub const WARN: u8 = 1;
    pub const ERROR: u8 = 2;
    pub const STALE: u8 = 3;
}

/// `diagnostic_msgs/DiagnosticArray`: what `/diagnostics` carries (rqt_robot_monitor shows it).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

/// `rosgraph_msgs/Clock`: the time a simulation is at (what ROS 2 nodes with `use_sim_time` follow).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Clock {
    pub clock: Time,
}

/// `geometry_msgs/Twist`: linear and angular velocity (each x, y, z), what `/cmd_vel` carries.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Twist {
    pub linear: [f64; 3],
    pub angular: [f64; 3],
}

/// `nav_msgs/Odometry`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    pub pose: PoseWithCovariance,
    pub twist: TwistWithCovariance,
}

/// `geometry_msgs/TransformStamped`: `child_frame_id` in `header.frame_id`; translation (x, y, z)
/// and rotation (x, y, z, w) of `geometry_msgs/Transform`.
#[derive(Debug, Clone, PartialEq)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
}

impl TransformStamped {
    /// A planar transform from `parent` to `child`.
    #[must_use]
    pub fn planar(stamp_s: f64, parent: &str, child: &str, x: f64, y: f64, theta: f64) -> Self {
        let p = Pose::planar(x, y, theta);
        TransformStamped {
            header: Header::new(stamp_s, parent),
            child_frame_id: child.to_owned(),
            translation: p.position,
            rotation: p.orientation,
        }
    }
}

/// `tf2_msgs/TFMessage`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `nav_msgs/OccupancyGrid` with its `nav_msgs/MapMetaData` inline; `data` row-major from
/// the origin's row, −1 unknown, 0–100 occupancy.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct OccupancyGrid {
    pub header: Header,
    pub map_load_time: Time,
    pub resolution: f32,
    pub width: u32,
    pub height: u32,
    pub origin: Pose,
    pub data: Vec<i8>,
}

/// `nav2_msgs/Particle`: one particle of a particle filter, its pose and weight.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Particle {
    pub pose: Pose,
    pub weight: f64,
}

/// `nav2_msgs/ParticleCloud`: what nav2_amcl publishes on `particle_cloud` (RViz's nav2 plugin
/// draws it).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ParticleCloud {
    pub header: Header,
    pub particles: Vec<Particle>,
}

/// A ROS 2 message type: its name, schema and CDR body.
pub trait Ros2Message: Sized {
    /// The full type name, `pkg/msg/Type` (the MCAP schema name rosbag2 writes).
    const TYPE: &'static str;
    /// The type's hash, `RIHS01_` and 64 hex digits: REP 2011's hash of the type description
    /// (the fields and nested types, names and kinds; no comments or defaults), as ROS 2 from Iron
    /// on names a type by in rmw_zenoh's key expressions and rosbag2's metadata. The same for
    /// Iron, Jazzy and later; Humble has none.
    const TYPE_HASH: &'static str;
    fn write(&self, w: &mut CdrWriter);
    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError>;

    /// The CDR message, little endian, with its encapsulation header.
    fn to_cdr(&self) -> Vec<u8> {
        let mut w = CdrWriter::new();
        self.write(&mut w);
        w.finish()
    }

    /// Decode a CDR message (either byte order). Never panics.
    fn from_cdr(bytes: &[u8]) -> Result<Self, CdrError> {
        Self::read(&mut CdrReader::new(bytes)?)
    }
}

impl Ros2Message for LaserScan {
    const TYPE: &'static str = "sensor_msgs/msg/LaserScan";
    const TYPE_HASH: &'static str = "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828";

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        for v in [
            self.angle_min,
            self.angle_max,
            self.angle_increment,
            self.time_increment,
            self.scan_time,
            self.range_min,
            self.range_max,
        ] {
            w.f32(v);
        }
        w.f32s(&self.ranges);
        w.f32s(&self.intensities);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(LaserScan {
            header: Header::read(r)?,
            angle_min: r.f32()?,
            angle_max: r.f32()?,
            angle_increment: r.f32()?,
            time_increment: r.f32()?,
            scan_time: r.f32()?,
            range_min: r.f32()?,
            range_max: r.f32()?,
            ranges: r.f32s()?,
            intensities: r.f32s()?,
        })
    }
}

impl Ros2Message for PoseWithCovarianceStamped {
    const TYPE: &'static str = "geometry_msgs/msg/PoseWithCovarianceStamped";
    const TYPE_HASH: &'static str = "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e";

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        self.pose.write(w);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(PoseWithCovarianceStamped { header: Header::read(r)?, pose: PoseWithCovariance::read(r)? })
    }
}

impl Ros2Message for Clock {
    const TYPE: &'static str = "rosgraph_msgs/msg/Clock";
    const TYPE_HASH: &'static str = "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564";
    fn write(&self, w: &mut CdrWriter) {
        self.clock.write(w);
    }
    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Clock { clock: Time::read(r)? })
    }
}

/// A status's least bytes: the level, three empty strings and an empty sequence.
const MIN_STATUS_BYTES: usize = 1 + 3 * 5 + 4;

impl Ros2Message for DiagnosticArray {
    const TYPE: &'static str = "diagnostic_msgs/msg/DiagnosticArray";
    const TYPE_HASH: &'static str = "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e";
    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.len(self.status.len());
        for st in &self.status {
            w.u8(st.level);
            w.string(&st.name);
            w.string(&st.message);
            w.string(&st.hardware_id);
            w.len(st.values.len());
            for (k, v) in &st.values {
                w.string(k);
                w.string(v);
            }
        }
    }
    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        let header = Header::read(r)?;
        let n = r.len(MIN_STATUS_BYTES)?;
        let mut status = Vec::with_capacity(n);
        for _ in 0..n {
            let level = r.u8()?;
            let (name, message, hardware_id) = (r.string()?, r.string()?, r.string()?);
            let k = r.len(10)?;
            let values = (0..k).map(|_| Ok((r.string()?, r.string()?))).collect::<Result<_, CdrError>>()?;
            status.push(DiagnosticStatus { level, name, message, hardware_id, values });
        }
        Ok(DiagnosticArray { header, status })
    }
}

impl Ros2Message for Twist {
    const TYPE: &'static str = "geometry_msgs/msg/Twist";
    const TYPE_HASH: &'static str = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a";
    fn write(&self, w: &mut CdrWriter) {
        for v in self.linear.iter().chain(&self.angular) {
            w.f64(*v);
        }
    }
    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        let mut t = Twist::default();
        for v in t.linear.iter_mut().chain(t.angular.iter_mut()) {
            *v = r.f64()?;
        }
        Ok(t)
    }
}

impl Ros2Message for Odometry {
    const TYPE: &'static str = "nav_msgs/msg/Odometry";
    const TYPE_HASH: &'static str = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0";

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.string(&self.child_frame_id);
        self.pose.write(w);
        for v in self.twist.linear.iter().chain(&self.twist.angular).chain(&self.twist.covariance) {
            w.f64(*v);
        }
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Odometry {
            header: Header::read(r)?,
            child_frame_id: r.string()?,
            pose: PoseWithCovariance::read(r)?,
            twist: TwistWithCovariance {
                linear: r.f64_array()?,
                angular: r.f64_array()?,
                covariance: r.f64_array()?,
            },
        })
    }
}

impl TransformStamped {
    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.string(&self.child_frame_id);
        for v in self.translation.iter().chain(&self.rotation) {
            w.f64(*v);
        }
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(TransformStamped {
            header: Header::read(r)?,
            child_frame_id: r.string()?,
            translation: r.f64_array()?,
            rotation: r.f64_array()?,
        })
    }
}

/// Smallest CDR size of a `TransformStamped` (header with empty frame, empty child, 7 doubles).
const MIN_TRANSFORM_BYTES: usize = 8 + 5 + 5 + 7 * 8;

impl Ros2Message for TfMessage {
    const TYPE: &'static str = "tf2_msgs/msg/TFMessage";
    const TYPE_HASH: &'static str = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087";

    fn write(&self, w: &mut CdrWriter) {
        w.len(self.transforms.len());
        for t in &self.transforms {
            t.write(w);
        }
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        let n = r.len(MIN_TRANSFORM_BYTES)?;
        let transforms = (0..n).map(|_| TransformStamped::read(r)).collect::<Result<_, _>>()?;
        Ok(TfMessage { transforms })
    }
}

impl Ros2Message for OccupancyGrid {
    const TYPE: &'static str = "nav_msgs/msg/OccupancyGrid";
    const TYPE_HASH: &'static str = "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7";

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        self.map_load_time.write(w);
        w.f32(self.resolution);
        w.u32(self.width);
        w.u32(self.height);
        self.origin.write(w);
        w.i8s(&self.data);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(OccupancyGrid {
            header: Header::read(r)?,
            map_load_time: Time::read(r)?,
            resolution: r.f32()?,
            width: r.u32()?,
            height: r.u32()?,
            origin: Pose::read(r)?,
            data: r.i8s()?,
        })
    }
}

/// CDR size of a `nav2_msgs/Particle` (7 + 1 doubles).
const PARTICLE_BYTES: usize = 8 * 8;

impl Ros2Message for ParticleCloud {
    const TYPE: &'static str = "nav2_msgs/msg/ParticleCloud";
    const TYPE_HASH: &'static str = "RIHS01_193d8cb88ca2b98cd81ece15342744f054bb398ebfa8f6369914432303f42b11";

    fn write(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.len(self.particles.len());
        for p in &self.particles {
            p.pose.write(w);
            w.f64(p.weight);
        }
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        let header = Header::read(r)?;
        let n = r.len(PARTICLE_BYTES)?;
        let particles = (0..n)
            .map(|_| Ok(Particle { pose: Pose::read(r)?, weight: r.f64()? }))
            .collect::<Result<_, _>>()?;
        Ok(ParticleCloud { header, particles })
    }
}

/// Every message type here, `(TYPE, TYPE_HASH)`.
pub const TYPE_HASHES: [(&str, &str); 9] = [
    (LaserScan::TYPE, LaserScan::TYPE_HASH),
    (PoseWithCovarianceStamped::TYPE, PoseWithCovarianceStamped::TYPE_HASH),
    (Odometry::TYPE, Odometry::TYPE_HASH),
    (TfMessage::TYPE, TfMessage::TYPE_HASH),
    (OccupancyGrid::TYPE, OccupancyGrid::TYPE_HASH),
    (Twist::TYPE, Twist::TYPE_HASH),
    (Clock::TYPE, Clock::TYPE_HASH),
    (DiagnosticArray::TYPE, DiagnosticArray::TYPE_HASH),
    (ParticleCloud::TYPE, ParticleCloud::TYPE_HASH),
];

/// The REP 2011 hash of a type here (`pkg/msg/Type`).
#[must_use]
pub fn type_hash(type_name: &str) -> Option<&'static str> {
    TYPE_HASHES.iter().find(|(t, _)| *t == type_name).map(|(_, h)| *h)
}

/// Each type's own definition (fields only) and the types it uses, `pkg/Type` as `.msg` files
/// name them.
fn definition(name: &str) -> Option<(&'static str, &'static [&'static str])> {
    Some(match name {
        "builtin_interfaces/Time" => ("int32 sec\nuint32 nanosec\n", &[]),
        "rosgraph_msgs/Clock" => ("builtin_interfaces/Time clock\n", &["builtin_interfaces/Time"]),
        "diagnostic_msgs/KeyValue" => ("string key\nstring value\n", &[]),
        "diagnostic_msgs/DiagnosticStatus" => (
            "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\n\
             string hardware_id\ndiagnostic_msgs/KeyValue[] values\n",
            &["diagnostic_msgs/KeyValue"],
        ),
        "diagnostic_msgs/DiagnosticArray" => (
            "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n",
            &["std_msgs/Header", "diagnostic_msgs/DiagnosticStatus"],
        ),
        "std_msgs/Header" => {
            ("builtin_interfaces/Time stamp\nstring frame_id\n", &["builtin_interfaces/Time"])
        }
        "geometry_msgs/Point" | "geometry_msgs/Vector3" => ("float64 x\nfloat64 y\nfloat64 z\n", &[]),
        "geometry_msgs/Quaternion" => ("float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n", &[]),
        "geometry_msgs/Pose" => (
            "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
            &["geometry_msgs/Point", "geometry_msgs/Quaternion"],
        ),
        "geometry_msgs/PoseWithCovariance" => {
            ("geometry_msgs/Pose pose\nfloat64[36] covariance\n", &["geometry_msgs/Pose"])
        }
        "geometry_msgs/PoseWithCovarianceStamped" => (
            "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose\n",
            &["std_msgs/Header", "geometry_msgs/PoseWithCovariance"],
        ),
        "geometry_msgs/Twist" => {
            ("geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n", &["geometry_msgs/Vector3"])
        }
        "geometry_msgs/TwistWithCovariance" => {
            ("geometry_msgs/Twist twist\nfloat64[36] covariance\n", &["geometry_msgs/Twist"])
        }
        "geometry_msgs/Transform" => (
            "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
            &["geometry_msgs/Vector3", "geometry_msgs/Quaternion"],
        ),
        "geometry_msgs/TransformStamped" => (
            "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
            &["std_msgs/Header", "geometry_msgs/Transform"],
        ),
        "tf2_msgs/TFMessage" => {
            ("geometry_msgs/TransformStamped[] transforms\n", &["geometry_msgs/TransformStamped"])
        }
        "sensor_msgs/LaserScan" => (
            "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n\
             float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n\
             float32[] ranges\nfloat32[] intensities\n",
            &["std_msgs/Header"],
        ),
        "nav_msgs/Odometry" => (
            "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n\
             geometry_msgs/TwistWithCovariance twist\n",
            &["std_msgs/Header", "geometry_msgs/PoseWithCovariance", "geometry_msgs/TwistWithCovariance"],
        ),
        "nav_msgs/MapMetaData" => (
            "builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\nuint32 height\n\
             geometry_msgs/Pose origin\n",
            &["builtin_interfaces/Time", "geometry_msgs/Pose"],
        ),
        "nav_msgs/OccupancyGrid" => (
            "std_msgs/Header header\nnav_msgs/MapMetaData info\nint8[] data\n",
            &["std_msgs/Header", "nav_msgs/MapMetaData"],
        ),
        "nav2_msgs/Particle" => ("geometry_msgs/Pose pose\nfloat64 weight\n", &["geometry_msgs/Pose"]),
        "nav2_msgs/ParticleCloud" => (
            "std_msgs/Header header\nnav2_msgs/Particle[] particles\n",
            &["std_msgs/Header", "nav2_msgs/Particle"],
        ),
        _ => return None,
    })
}

/// The `ros2msg` schema text of a type (`pkg/msg/Type` or `pkg/Type`) we know, else `None`.
#[must_use]
pub fn schema_text(type_name: &str) -> Option<String> {
    let short = type_name.replacen("/msg/", "/", 1);
    let (own, deps) = definition(&short)?;
    let mut text = own.to_owned();
    // Every type used, directly or not, once, in the order first met (depth first).
    let mut seen: Vec<&str> = Vec::new();
    let mut stack: Vec<&str> = deps.iter().rev().copied().collect();
    while let Some(d) = stack.pop() {
        if seen.contains(&d) {
            continue;
        }
        seen.push(d);
        let (body, sub) = definition(d)?;
        text.push_str(&"=".repeat(80));
        text.push_str("\nMSG: ");
        text.push_str(d);
        text.push('\n');
        text.push_str(body);
        stack.extend(sub.iter().rev());
    }
    Some(text)
}

#[cfg(test)]
mod tests;
