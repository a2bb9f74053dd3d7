//! What the recorder writes for each thing it sees: topics, schemas and JSON bodies. Pure (the
//! caller gives the time), so the recorder, the replay and the live view share it.
//!
//! Topics (frames in [`crate::foxglove`]):
//!
//! | topic | schema | from |
//! |---|---|---|
//! | `/amr/uplink` | `amr.Uplink` (exact) | every message the server received, with its receive time |
//! | `/amr/fused` | `amr.FusedFrame` (exact; points by digest) | every fused frame |
//! | `/amr/estimates` | `amr.Estimate` (exact) | every estimate |
//! | `/amr/status` | `amr.FusionStatus` (exact) | fusion status changes |
//! | `/<robot>/scan` | `foxglove.LaserScan` | the robot's scans (frame `<robot>/laser`) |
//! | `/virtual/scan` | `foxglove.LaserScan` | the virtual scan (frame `V`, 0.5° bins) |
//! | `/<robot>/odom` | `foxglove.PoseInFrame` | odometry (frame `<robot>/odom`) |
//! | `/<robot>/imu`, `/<robot>/wheels` | `amr.Imu`, `amr.Wheels` | robot side only |
//! | `/amcl/V`, `/amcl/<robot>` | `foxglove.PoseInFrame` | fused estimates: V and each robot (frame `map`) |
//! | `/amcl/<robot>/own` | `foxglove.PoseInFrame` | each robot's own AMCL |
//! | `/amcl/particles`, `/amcl/<robot>/particles` | `foxglove.PosesInFrame` | particle clouds, ≤ 1 Hz, ≤ 200 poses |
//! | `/tf` | `foxglove.FrameTransforms` | map→V, map→`<robot>/odom`, `<robot>/odom`→`<robot>`, `<robot>`→`<robot>/laser` |
//! | `/map` | `foxglove.Grid` | the map, once |
//! | `/formation/commands` | `amr.Command` | every command, arm and disarm sent (server) or received (robot) |
//! | `/health` | `foxglove.Log` | health and safety changes |
//! | `/log` | `foxglove.Log` | log lines |

use std::collections::BTreeMap;

use amr_actors::robot::ports::{ImuReading, WheelTravel};
use amr_core::map::OccupancyGrid;
use amr_core::se2::Se2;
use amr_msgs::{
    Device, Downlink, Estimate, EstimateSource, FusedFrame, FusionStatus, Health, HealthReport,
    ParticleCloud, SafetyState, ScanMsg, Uplink,
};
use serde_json::{Value, json};

use crate::foxglove::{self as fg, Level};
use crate::wire::{self, FusedRecord};

/// One message ready for a sink.
#[derive(Debug, Clone)]
pub struct Out {
    pub topic: String,
    /// Schema name; [`schema_text`] gives its JSON schema.
    pub schema: &'static str,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub data: Vec<u8>,
}

pub const IMU_SCHEMA: &str = "amr.Imu";
pub const WHEELS_SCHEMA: &str = "amr.Wheels";
pub const COMMAND_SCHEMA: &str = "amr.Command";

/// The JSON schema text of a schema name we write.
#[must_use]
pub fn schema_text(name: &str) -> String {
    if let Some(s) = fg::schema(name) {
        return s;
    }
    let own = |props: Value| json!({ "title": name, "type": "object", "properties": props }).to_string();
    match name {
        IMU_SCHEMA => own(json!({ "stamp_s": { "type": "number" }, "yaw_rate_radps": { "type": "number" } })),
        WHEELS_SCHEMA => own(json!({
            "stamp_s": { "type": "number" }, "dt_s": { "type": "number" },
            "left_m": { "type": "number" }, "right_m": { "type": "number" }
        })),
        COMMAND_SCHEMA => own(json!({
            "robot": { "type": "string" }, "kind": { "type": "string", "enum": ["command", "arm", "disarm"] },
            "seq": { "type": ["integer", "null"] }, "stamp_s": { "type": ["number", "null"] },
            "v_mps": { "type": ["number", "null"] }, "w_radps": { "type": ["number", "null"] }
        })),
        _ => wire::schema(name),
    }
}

/// A log line for `foxglove.Log`.
#[derive(Debug, Clone)]
pub struct LogLine {
    pub level: Level,
    /// The tracing target (module path).
    pub name: String,
    pub message: String,
    pub file: String,
    pub line: u32,
}

/// The formation's phase as a log line: its level (running or finished: info; waiting, arming,
/// holding: warning; stopped: error) and its text.
#[must_use]
pub fn formation_line(f: &amr_actors::server::formation::FormationStatus) -> (Level, String) {
    use amr_actors::server::formation::Phase;
    let progress = format!("plan {:.1} of {:.1} s", f.plan_s, f.plan_len_s);
    match &f.phase {
        Phase::Running => (Level::Info, format!("running, {progress}")),
        Phase::Finished => (Level::Info, format!("finished, {progress}")),
        Phase::Waiting => {
            (Level::Warning, format!("waiting for every robot to be healthy and localised, {progress}"))
        }
        Phase::Arming { .. } => (Level::Warning, format!("arming, {progress}")),
        Phase::Holding { reason } => (Level::Warning, format!("holding: {reason}, {progress}")),
        Phase::Stopped { reason } => (Level::Error, format!("stopped: {reason}, {progress}")),
    }
}

/// Everything the recorder can see.
#[derive(Debug, Clone)]
pub enum Event {
    /// A message the server received, and when it came off the link.
    Uplink(Uplink, f64),
    Fused(FusedFrame),
    Estimate(Estimate),
    Status(FusionStatus),
    /// The formation's status (its phase and why, the plan's progress, V's integrity).
    Formation(amr_actors::server::formation::FormationStatus),
    Particles(ParticleCloud),
    /// A message the formation sent to robot `.0` (its formation index).
    Command(usize, Downlink),
    /// Robot side: robot id and what its ports carried.
    Scan(ScanMsg),
    Imu(String, ImuReading),
    Wheels(String, WheelTravel),
    Odom(String, amr_msgs::OdomMsg),
    Health(String, HealthReport),
    Safety(String, SafetyState),
    Downlink(String, Downlink),
    Log(LogLine),
    Map(OccupancyGrid),
    /// Each robot's LiDAR in its base (static transforms).
    Mounts(Vec<(String, Se2)>),
    /// Simulation only (`amr eval`): the true poses of V and of each robot, at `stamp_s`.
    Truth {
        stamp_s: f64,
        v: Se2,
        robots: Vec<Se2>,
    },
    /// `amr eval`: one configuration's estimate of V, side by side with the others.
    EvalEstimate {
        stamp_s: f64,
        configuration: amr_core::config::Configuration,
        v: Se2,
    },
    /// `amr eval`: one configuration's virtual scan (points in its V).
    EvalVirtualScan {
        stamp_s: f64,
        configuration: amr_core::config::Configuration,
        points: Vec<[f64; 2]>,
    },
}

/// Particle clouds per source at most this often, ns of log time (a cloud is ~20 kB of JSON).
const PARTICLES_EVERY_NS: u64 = 1_000_000_000;
/// And at most this many poses (evenly picked).
const PARTICLES_MAX: usize = 200;

/// Turns events into messages.
#[derive(Debug, Clone)]
pub struct Encoder {
    /// Robot ids in formation order (server side; empty on a robot).
    robots: Vec<String>,
    last_particles: BTreeMap<String, u64>,
    /// Last health per (robot, device) and safety per robot: `/health` logs changes only (the
    /// robots re-send their whole board now and then; `/amr/uplink` keeps every message).
    last_health: BTreeMap<(String, Device), Health>,
    last_safety: BTreeMap<String, SafetyState>,
}

fn health_level(h: Health) -> Level {
    match h {
        Health::Starting | Health::Ok => Level::Info,
        Health::Degraded => Level::Warning,
        Health::Lost => Level::Error,
        Health::Fault => Level::Fatal,
    }
}

fn safety_level(s: SafetyState) -> Level {
    match s {
        SafetyState::Armed | SafetyState::Disarmed(_) => Level::Info,
        SafetyState::EStop => Level::Error,
        SafetyState::Fault => Level::Fatal,
    }
}

fn command(robot: &str, d: &Downlink) -> Value {
    match d {
        Downlink::Command(c) => json!({
            "robot": robot, "kind": "command", "seq": c.seq, "stamp_s": c.stamp_s,
            "v_mps": c.v_mps, "w_radps": c.w_radps
        }),
        Downlink::Arm { seq, stops, stamp_s } => {
            json!({ "robot": robot, "kind": "arm", "seq": seq, "stops": stops, "stamp_s": stamp_s })
        }
        Downlink::Disarm => json!({ "robot": robot, "kind": "disarm" }),
        Downlink::EStop => json!({ "robot": robot, "kind": "estop" }),
        Downlink::ResetEStop => json!({ "robot": robot, "kind": "reset_estop" }),
    }
}

impl Encoder {
    #[must_use]
    pub fn new(robots: Vec<String>) -> Self {
        Encoder {
            robots,
            last_particles: BTreeMap::new(),
            last_health: BTreeMap::new(),
            last_safety: BTreeMap::new(),
        }
    }

    fn robot_name(&self, i: usize) -> String {
        self.robots.get(i).cloned().unwrap_or_else(|| format!("robot{i}"))
    }

    /// The messages for `event`, seen at `now_s` on the fleet clock.
    pub fn encode(&mut self, now_s: f64, event: &Event) -> Result<Vec<Out>, wire::WireError> {
        let t = fg::nanos(now_s);
        let out = |topic: String, schema: &'static str, stamp_s: f64, v: Value| Out {
            topic,
            schema,
            log_time_ns: t,
            publish_time_ns: fg::nanos(stamp_s),
            data: v.to_string().into_bytes(),
        };
        let exact = |topic: &str, schema: &'static str, stamp_s: f64, data: Vec<u8>| Out {
            topic: topic.to_owned(),
            schema,
            log_time_ns: t,
            publish_time_ns: fg::nanos(stamp_s),
            data,
        };
        let mut v = Vec::new();
        match event {
            Event::Uplink(u, rx_s) => v.extend(self.uplink(&out, &exact, u, *rx_s)?),
            Event::Truth { stamp_s, v: vt, robots } => v.extend(self.truth(&out, *stamp_s, vt, robots)),
            Event::EvalEstimate { stamp_s, configuration, v: vm } => {
                let c = format!("{configuration:?}");
                v.push(out(
                    format!("/eval/{c}/V"),
                    fg::POSE_IN_FRAME,
                    *stamp_s,
                    fg::pose_in_frame(*stamp_s, "map", vm),
                ));
                let tf = vec![fg::transform(*stamp_s, "map", &format!("eval/{c}/V"), vm)];
                v.push(out("/tf".into(), fg::FRAME_TRANSFORMS, *stamp_s, fg::transforms(tf)));
            }
            Event::EvalVirtualScan { stamp_s, configuration, points } => {
                let c = format!("{configuration:?}");
                v.push(out(
                    format!("/eval/{c}/virtual_scan"),
                    fg::LASER_SCAN,
                    *stamp_s,
                    fg::points_scan(*stamp_s, &format!("eval/{c}/V"), points),
                ));
            }
            Event::Fused(f) => v.extend(self.fused(&out, &exact, f)?),
            Event::Estimate(e) => v.extend(self.estimate(&out, &exact, e)?),
            Event::Status(s) => v.extend(self.status(&out, &exact, now_s, s)?),
            Event::Formation(f) => {
                let (level, text) = formation_line(f);
                v.push(out(
                    "/formation".into(),
                    fg::LOG,
                    now_s,
                    fg::log(now_s, level, "formation", &text, "", 0),
                ));
            }
            Event::Particles(p) => v.extend(self.particles(&out, t, p)),
            Event::Command(i, d) => v.push(self.command(&out, &self.robot_name(*i), now_s, d)),
            Event::Downlink(robot, d) => v.push(self.command(&out, robot, now_s, d)),
            Event::Scan(s) => v.push(out(
                format!("/{}/scan", s.robot),
                fg::LASER_SCAN,
                s.stamp_s,
                fg::laser_scan(s.stamp_s, &format!("{}/laser", s.robot), &s.scan),
            )),
            Event::Imu(robot, r) => v.push(out(
                format!("/{robot}/imu"),
                IMU_SCHEMA,
                r.stamp_s,
                json!({ "stamp_s": r.stamp_s, "yaw_rate_radps": r.yaw_rate_radps }),
            )),
            Event::Wheels(robot, w) => v.push(out(
                format!("/{robot}/wheels"),
                WHEELS_SCHEMA,
                w.stamp_s,
                json!({ "stamp_s": w.stamp_s, "dt_s": w.dt_s, "left_m": w.left_m, "right_m": w.right_m }),
            )),
            Event::Odom(robot, m) => v.extend(self.odom(&out, robot, m)),
            Event::Health(robot, r) => v.extend(self.health(&out, robot, now_s, r)),
            Event::Safety(robot, s) => v.extend(self.safety(&out, robot, now_s, *s)),
            Event::Log(l) => v.push(out(
                "/log".into(),
                fg::LOG,
                now_s,
                fg::log(now_s, l.level, &l.name, &l.message, &l.file, l.line),
            )),
            Event::Map(m) => v.push(out("/map".into(), fg::GRID, now_s, fg::grid(now_s, m))),
            Event::Mounts(m) => {
                let tf = m.iter().map(|(r, p)| fg::transform(now_s, r, &format!("{r}/laser"), p)).collect();
                v.push(out("/tf".into(), fg::FRAME_TRANSFORMS, now_s, fg::transforms(tf)));
            }
        }
        Ok(v)
    }

    /// A fused frame: its exact record and the virtual scan.
    fn fused(
        &self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        exact: &impl Fn(&str, &'static str, f64, Vec<u8>) -> Out,
        f: &FusedFrame,
    ) -> Result<Vec<Out>, wire::WireError> {
        let mut v = Vec::new();
        let record = FusedRecord::of(f);
        v.push(exact("/amr/fused", wire::FUSED_SCHEMA, f.stamp_s, wire::encode_fused(&record)?));
        if let Some(points) = &f.points {
            v.push(out(
                "/virtual/scan".into(),
                fg::LASER_SCAN,
                f.stamp_s,
                fg::points_scan(f.stamp_s, "V", points),
            ));
        }
        Ok(v)
    }

    /// The fusion's status: its exact record and a line in `/health`.
    fn status(
        &self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        exact: &impl Fn(&str, &'static str, f64, Vec<u8>) -> Out,
        now_s: f64,
        s: &FusionStatus,
    ) -> Result<Vec<Out>, wire::WireError> {
        let mut v = Vec::new();
        v.push(exact("/amr/status", wire::STATUS_SCHEMA, now_s, wire::encode_status(*s)?));
        let (level, text) = match s {
            FusionStatus::Fusing => (Level::Info, "fusion: fusing".to_owned()),
            FusionStatus::RobotLost(i) => (Level::Error, format!("fusion: {} lost", self.robot_name(*i))),
        };
        v.push(out("/health".into(), fg::LOG, now_s, fg::log(now_s, level, "fusion", &text, "", 0)));
        Ok(v)
    }

    /// An uplink message: its exact record, and what it shows (a scan, odometry, health, safety).
    fn uplink(
        &mut self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        exact: &impl Fn(&str, &'static str, f64, Vec<u8>) -> Out,
        u: &Uplink,
        rx_s: f64,
    ) -> Result<Vec<Out>, wire::WireError> {
        let mut v = Vec::new();
        v.push(exact("/amr/uplink", wire::UPLINK_SCHEMA, u.stamp_s(), wire::encode_uplink(rx_s, u)?));
        match u {
            Uplink::Scan(s) => v.push(out(
                format!("/{}/scan", s.robot),
                fg::LASER_SCAN,
                s.stamp_s,
                fg::laser_scan(s.stamp_s, &format!("{}/laser", s.robot), &s.scan),
            )),
            Uplink::Odom { robot, msg } => v.extend(self.odom(&out, robot, msg)),
            Uplink::Health { robot, stamp_s, report, .. } => {
                v.extend(self.health(&out, robot, *stamp_s, report));
            }
            Uplink::Safety { robot, stamp_s, state, .. } => {
                v.extend(self.safety(&out, robot, *stamp_s, *state))
            }
        }
        Ok(v)
    }

    /// The simulation's truth: V and each robot in the map, and their frames.
    fn truth(
        &self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        stamp_s: f64,
        vt: &Se2,
        robots: &[Se2],
    ) -> Vec<Out> {
        let mut v = Vec::new();
        v.push(out("/truth/V".into(), fg::POSE_IN_FRAME, stamp_s, fg::pose_in_frame(stamp_s, "map", vt)));
        let mut tf = vec![fg::transform(stamp_s, "map", "truth/V", vt)];
        for (i, p) in robots.iter().enumerate() {
            let name = self.robot_name(i);
            v.push(out(
                format!("/truth/{name}"),
                fg::POSE_IN_FRAME,
                stamp_s,
                fg::pose_in_frame(stamp_s, "map", p),
            ));
            tf.push(fg::transform(stamp_s, "map", &format!("truth/{name}"), p));
        }
        v.push(out("/tf".into(), fg::FRAME_TRANSFORMS, stamp_s, fg::transforms(tf)));
        v
    }

    /// An estimate: its exact record; V's (and each robot's place in it, with map → odom), or a
    /// robot's own.
    fn estimate(
        &self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        exact: &impl Fn(&str, &'static str, f64, Vec<u8>) -> Out,
        e: &Estimate,
    ) -> Result<Vec<Out>, wire::WireError> {
        let mut v = Vec::new();
        v.push(exact("/amr/estimates", wire::ESTIMATE_SCHEMA, e.stamp_s, wire::encode_estimate(e)?));
        match e.source {
            EstimateSource::Fused(_) => {
                let mut tf = Vec::new();
                if let Some(vm) = &e.v {
                    v.push(out(
                        "/amcl/V".into(),
                        fg::POSE_IN_FRAME,
                        e.stamp_s,
                        fg::pose_in_frame(e.stamp_s, "map", vm),
                    ));
                    tf.push(fg::transform(e.stamp_s, "map", "V", vm));
                }
                for (i, a) in e.robots.iter().enumerate() {
                    let Some(a) = a else { continue };
                    let name = self.robot_name(i);
                    v.push(out(
                        format!("/amcl/{name}"),
                        fg::POSE_IN_FRAME,
                        e.stamp_s,
                        fg::pose_in_frame(e.stamp_s, "map", &a.map),
                    ));
                    tf.push(fg::transform(
                        e.stamp_s,
                        "map",
                        &format!("{name}/odom"),
                        &(a.map * a.odom.inverse()),
                    ));
                }
                v.push(out("/tf".into(), fg::FRAME_TRANSFORMS, e.stamp_s, fg::transforms(tf)));
            }
            EstimateSource::Robot(i) => {
                let name = self.robot_name(i);
                if let Some(Some(a)) = e.robots.get(i) {
                    v.push(out(
                        format!("/amcl/{name}/own"),
                        fg::POSE_IN_FRAME,
                        e.stamp_s,
                        fg::pose_in_frame(e.stamp_s, "map", &a.map),
                    ));
                }
            }
        }
        Ok(v)
    }

    /// A filter's particles, at most every [`PARTICLES_EVERY_NS`] per topic and thinned to
    /// [`PARTICLES_MAX`].
    fn particles(
        &mut self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        t: u64,
        p: &ParticleCloud,
    ) -> Option<Out> {
        let (topic, frame) = match p.source {
            EstimateSource::Fused(_) => ("/amcl/particles".to_owned(), "map"),
            EstimateSource::Robot(i) => (format!("/amcl/{}/particles", self.robot_name(i)), "map"),
        };
        let due = self.last_particles.get(&topic).is_none_or(|l| t.saturating_sub(*l) >= PARTICLES_EVERY_NS);
        if !due {
            return None;
        }
        self.last_particles.insert(topic.clone(), t);
        let n = p.poses.len();
        let step = n.div_ceil(PARTICLES_MAX).max(1);
        let poses: Vec<Se2> = p.poses.iter().step_by(step).copied().collect();
        Some(out(topic, fg::POSES_IN_FRAME, p.stamp_s, fg::poses_in_frame(p.stamp_s, frame, &poses)))
    }

    fn odom(
        &self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        robot: &str,
        m: &amr_msgs::OdomMsg,
    ) -> [Out; 2] {
        let frame = format!("{robot}/odom");
        [
            out(
                format!("/{robot}/odom"),
                fg::POSE_IN_FRAME,
                m.stamp_s,
                fg::pose_in_frame(m.stamp_s, &frame, &m.pose),
            ),
            out(
                "/tf".into(),
                fg::FRAME_TRANSFORMS,
                m.stamp_s,
                fg::transforms(vec![fg::transform(m.stamp_s, &frame, robot, &m.pose)]),
            ),
        ]
    }

    fn command(
        &self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        robot: &str,
        now_s: f64,
        d: &Downlink,
    ) -> Out {
        let stamp = match d {
            Downlink::Command(c) => c.stamp_s,
            _ => now_s,
        };
        out("/formation/commands".into(), COMMAND_SCHEMA, stamp, command(robot, d))
    }

    fn health(
        &mut self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        robot: &str,
        stamp_s: f64,
        r: &HealthReport,
    ) -> Option<Out> {
        if self.last_health.insert((robot.to_owned(), r.device), r.health) == Some(r.health) {
            return None;
        }
        let text = format!("{robot} {}: {} {}", r.device, r.health, r.detail);
        let log = fg::log(stamp_s, health_level(r.health), robot, text.trim_end(), "", 0);
        Some(out("/health".into(), fg::LOG, stamp_s, log))
    }

    fn safety(
        &mut self,
        out: &impl Fn(String, &'static str, f64, Value) -> Out,
        robot: &str,
        stamp_s: f64,
        s: SafetyState,
    ) -> Option<Out> {
        if self.last_safety.insert(robot.to_owned(), s) == Some(s) {
            return None;
        }
        let text = format!("{robot} safety: {s}");
        Some(out("/health".into(), fg::LOG, stamp_s, fg::log(stamp_s, safety_level(s), robot, &text, "", 0)))
    }
}
