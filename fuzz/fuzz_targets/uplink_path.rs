//! Fuzz the fusion server's whole uplink path, as the server's bridge and localizer run it on a
//! Zenoh sample: `Envelope::decode`, the key's `Freshness` check (with the server's clock as now),
//! `to_uplink` on the key's robot and channel, then `ServerCore::offer` on one core that lives
//! across inputs (built once from the embedded configuration the way `amr server` builds it, but
//! running T1–T4 side by side so every pipeline runs). The server's clock (fleet clock, Unix
//! seconds) starts at 2026-12-01T00:00:00Z and advances 1/30 s per input (two robots at 15 Hz),
//! never from the wire.
//!
//! The first byte chooses (bit 0) the key's robot, (bits 1–2) the key's channel: the one of the
//! decoded message's kind, `scan`, `odom` or `health`, (bit 6) whether the server's bridge has just
//! restarted (its replay record for the key is empty), and (bit 3) the mode:
//! - raw (bit 3 clear): the rest of the input is the sample's payload;
//! - structured (bit 3 set): the rest is read field by field into a scan that the robot's bridge
//!   could send — a LiDAR scan ray-cast on the paper site with the other robot beside it, or
//!   constant, patterned or raw ranges; beam counts up to 10 000; extreme angles, increments,
//!   range limits, stamps and odometry — encoded as the robot's bridge encodes it, then received
//!   through the same path. Its envelope must decode to exactly the scan that was sent.
//!   Bit 4 repeats the previous structured envelope's sequence number, bit 5 names other robots
//!   in the envelope or the message, bit 7 takes the envelope's session from the input.
//!
//! A zero byte read past the end, or a zero selector, gives the realistic default, so the
//! structured mode of an all-zero tail is a valid TiM551 scan that the core fuses.
//!
//! `UPLINK_PATH_SEEDS=<dir>` writes a few seed inputs (valid scans in both modes) into `<dir>` at
//! start-up (before libFuzzer reads its corpus); `UPLINK_PATH_STATS=1` prints what the bridge
//! refused and what the core did, and the largest allocation: see fuzz/README.md.
#![no_main]

#[path = "common/reader.rs"]
mod reader;
use reader::Reader;

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::RefCell;
use std::collections::BTreeMap;
use std::f64::consts::{PI, TAU};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use amr_actors::config::{ConfigSource, load};
use amr_actors::server::core::ServerCore;
use amr_actors::server::{ServerSetup, core_setup, formation_robots};
use amr_actors::supervisor::RestartPolicy;
use amr_core::config::Configuration;
use amr_core::geometry::{Polygon, cast_ray};
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use amr_core::vamr::pipeline::UpdateError;
use amr_msgs::{SCHEMA_VERSION, ScanMsg, Uplink};
use amr_net::wire::{Body, Envelope, Freshness, Reject, from_uplink, to_uplink, uplink_channel};
use libfuzzer_sys::fuzz_target;

/// The server's clock (the fleet clock, Unix seconds) at the first input: 2026-12-01T00:00:00Z.
const START_S: f64 = 1_796_083_200.0;
/// The server's clock step per input, s.
const RX_STEP_S: f64 = 1.0 / 30.0;
/// Channels a key can name; `None`: the one of the decoded message's kind.
const CHANNELS: [Option<&str>; 4] = [None, Some("scan"), Some("odom"), Some("health")];
/// The paper site (config/maps/paper-site.yaml: 210 x 76 cells of 5 cm from (-5.25, -1.8)).
const SITE: (f64, f64, f64, f64) = (10.5, 3.8, 0.0, 0.1);
/// V's speed along the site's axis in the default motion, m/s, and the length of a leg, m.
const SPEED_MPS: f64 = 0.2;
const LEG_M: f64 = 4.0;

struct Server {
    core: ServerCore,
    robots: Vec<String>,
    /// Per robot: its base in V (the formation's slot) and its LiDAR on its base.
    slots: Vec<(Se2, Se2)>,
    chassis: Vec<Polygon>,
    site: Polygon,
    initial_v: Se2,
    /// Per (robot, channel), as the server's bridge keeps them.
    fresh: BTreeMap<(usize, &'static str), Freshness>,
    rx_s: f64,
    /// The structured mode's sender: its last sequence number.
    seq: u64,
    /// `UPLINK_PATH_STATS=1`: what the bridge refused and what the core did.
    stats: Option<Stats>,
}

fn stats_on() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("UPLINK_PATH_STATS").is_some())
}

/// What the bridge refused and what the core did, printed every 2^k inputs (an input refused
/// before decoding counts too).
#[derive(Default)]
struct Stats {
    inputs: u64,
    by: BTreeMap<String, u64>,
}

impl Stats {
    fn add(&mut self, k: String) {
        *self.by.entry(k).or_default() += 1;
        self.inputs += 1;
        if self.inputs.is_power_of_two() {
            let largest = LARGEST.load(Ordering::Relaxed);
            eprintln!(
                "uplink_path: {} inputs, largest allocation {largest} bytes: {:?}",
                self.inputs, self.by
            );
        }
    }

    fn count(&mut self, step: &amr_actors::server::core::Step) {
        let mut add = |k: String| *self.by.entry(k).or_default() += 1;
        match &step.refused {
            Some(r) => add(format!("refused:{}", r.kind())),
            None if step.robot.is_some() => add("accepted".into()),
            None => add("not-a-scan".into()),
        }
        for f in &step.fusions {
            let what = match &f.result {
                Ok(_) => "fused",
                Err(UpdateError::Sync(_)) => "sync-gate",
                Err(UpdateError::RobotCount { .. }) => "robot-count",
                Err(UpdateError::NoPosition { why, .. } | UpdateError::NoHeading { why, .. }) => why,
            };
            add(format!("{:?}:{what}", f.configuration));
        }
        self.add("offered".into());
    }
}

impl Server {
    fn new() -> Server {
        let config = load(&ConfigSource::Embedded).expect("the embedded configuration loads");
        let robots = formation_robots(&config.server, &config.robots).expect("the formation's robots");
        // `amr server`'s default scenario and seed.
        let scenario = config.scenarios["straight"].clone();
        let map = config.maps[&scenario.map].clone();
        let setup = ServerSetup {
            server: config.server.clone(),
            vamr: config.vamr.clone(),
            amcl: config.amcl.clone(),
            map,
            robots,
            scenario,
            seed: 1,
            auto_arm: amr_actors::server::AutoArm::Off,
            policy: RestartPolicy::default(),
            progress: std::sync::Arc::new(amr_actors::server::progress::PlanProgress::in_memory()),
        };
        let cs =
            core_setup(&setup, &[Configuration::T1, Configuration::T2, Configuration::T3, Configuration::T4]);
        let initial_v = cs.initial_v;
        let core = ServerCore::new(cs);
        let robots: Vec<String> = core.members().iter().map(|m| m.id.clone()).collect();
        let slots =
            core.members().iter().map(|m| (Se2::new(0.0, m.slot_y_m, 0.0), m.lidar_to_base)).collect();
        let chassis = core.members().iter().map(|m| m.chassis.clone()).collect();
        let site = Polygon::centered_rectangle(SITE.0, SITE.1).expect("a rectangle");
        Server {
            core,
            robots,
            slots,
            chassis,
            site,
            initial_v,
            fresh: BTreeMap::new(),
            rx_s: START_S,
            seq: 0,
            stats: stats_on().then(Stats::default),
        }
    }

    /// A sample on `fleet/<robot>/<channel>`, received now: the server's bridge, then its localizer.
    /// `restarted`: the server's bridge has just started (its replay records are empty).
    fn receive(
        &mut self,
        bytes: &[u8],
        robot: usize,
        channel: Option<&'static str>,
        restarted: bool,
    ) -> Option<Uplink> {
        self.rx_s += RX_STEP_S;
        let uplink = self.bridge(bytes, robot, channel, restarted);
        let uplink = match uplink {
            Ok(u) => u,
            Err(r) => {
                if let Some(stats) = &mut self.stats {
                    stats.add(format!("link:{}", r.kind()));
                }
                return None;
            }
        };
        let step = self.core.offer(&uplink, self.rx_s, &mut |_| {});
        if let Some(stats) = &mut self.stats {
            stats.count(&step);
        }
        Some(uplink)
    }

    /// The server's bridge on a sample (`start_server_bridge` in net/src/bridge/server.rs).
    fn bridge(
        &mut self,
        bytes: &[u8],
        robot: usize,
        channel: Option<&'static str>,
        restarted: bool,
    ) -> Result<Uplink, Reject> {
        let env = Envelope::decode(bytes)?;
        let channel = channel.unwrap_or(match &env.body {
            Body::Uplink(u) => uplink_channel(u),
            _ => "scan",
        });
        let fresh = self.fresh.entry((robot, channel)).or_default();
        if restarted {
            *fresh = Freshness::default();
        }
        fresh.check(&env, self.rx_s)?;
        to_uplink(env, &self.robots[robot], channel)
    }

    /// Where V is at `t_s` in the default motion: up and down a 4 m leg of the site's axis.
    fn v_progress(t_s: f64) -> f64 {
        let d = (SPEED_MPS * t_s) % (2.0 * LEG_M);
        if d <= LEG_M { d } else { 2.0 * LEG_M - d }
    }

    /// The structured mode: a scan from `robot`'s bridge, encoded as the bridge encodes it.
    fn structured(&mut self, r: &mut Reader<'_>, robot: usize, flags: u8) -> (Vec<u8>, Uplink) {
        let rx_next = self.rx_s + RX_STEP_S;
        let n = match r.u8() {
            0..=159 => 271,
            160..=223 => usize::from(r.u16()) % 601,
            224..=247 => 4088 + usize::from(r.u8() % 16),
            _ => usize::from(r.u16()) % 10_001,
        };
        let dense = (270f64.to_radians() / n.saturating_sub(1).max(1) as f64).min(1f64.to_radians());
        let step = r.real(dense, -0.25, 0.25);
        let angle_min = r.real(-dense * n.saturating_sub(1) as f64 / 2.0, -7.0, 7.0);
        let range_min = r.real(0.05, -1.0, 5.0);
        let range_max = r.real(10.0, 0.0, 120.0);
        let stamp_s = rx_next - r.real(0.01, -1.0, 1.0);
        let received_s = stamp_s + r.real(0.005, -1.0, 1.0);
        let seq = r.u64();
        // The envelope's session: the start of the current second (sessions are the sender's start
        // time, ns: a sender that restarts every second, so that a newer session a raw input left
        // on the key stops refusing these within seconds), or any from the input.
        let session = if flags & 0x80 != 0 { r.u64() } else { (rx_next.floor() as u64) * 1_000_000_000 };
        // Who the envelope says sent it and is about, and whom the scan names.
        let names = if flags & 0x20 != 0 { r.u8() } else { 0 };
        // The default odometry: V's progress along its leg, each robot from its own origin.
        let progress = Self::v_progress(stamp_s);
        let odom = (r.u8() < 240).then(|| Se2 {
            x: r.real(progress, -50.0, 50.0),
            y: r.real(0.0, -50.0, 50.0),
            theta: r.real(0.0, -7.0, 7.0),
        });
        let odom_frame = if r.u8() < 240 { 1 } else { r.u64() };
        // Where the robot really is (the scan is cast from there): V's true pose and an offset.
        let truth = Se2::new(r.real(0.0, -1.0, 1.0), r.real(0.0, -1.0, 1.0), r.real(0.0, -PI, PI));
        let ranges = match r.u8() {
            0..=127 => {
                let v = self.initial_v * Se2::new(Self::v_progress(stamp_s), 0.0, 0.0);
                self.cast(robot, v * truth, step, angle_min, n, r)
            }
            128..=191 => vec![r.real(3.0, 0.0, 120.0); n],
            192..=239 => {
                let pattern: Vec<f64> = (0..=r.u8() % 16).map(|_| r.real(2.0, -1.0, 120.0)).collect();
                (0..n).map(|i| pattern[i % pattern.len()]).collect()
            }
            _ => {
                let raw = r.rest();
                (0..n)
                    .map(|i| {
                        let k = (2 * i) % raw.len().max(2);
                        let v = u16::from_le_bytes([
                            raw.get(k).copied().unwrap_or(0),
                            raw.get(k + 1).copied().unwrap_or(0),
                        ]);
                        match v {
                            0xffff => f64::NAN,
                            0xfffe => f64::INFINITY,
                            v => f64::from(v) / 1000.0,
                        }
                    })
                    .collect()
            }
        };
        let candidates = [self.robots[robot].as_str(), self.robots[1 - robot.min(1)].as_str(), "robot-x", ""];
        let (origin, about, named) = (
            candidates[usize::from(names & 3)],
            candidates[usize::from((names >> 2) & 3)],
            candidates[usize::from((names >> 4) & 3)],
        );
        let uplink = Uplink::Scan(ScanMsg {
            robot: named.to_owned(),
            seq,
            stamp_s,
            received_s,
            scan: Arc::new(Scan::new(angle_min, step, range_min, range_max, ranges)),
            odom,
            odom_frame,
        });
        // The robot's bridge (`Stamper::encode` in net/src/bridge/mod.rs).
        if flags & 0x10 == 0 {
            self.seq += 1;
        }
        let (stamp, body) = from_uplink(&uplink);
        let env = Envelope {
            version: SCHEMA_VERSION,
            session,
            seq: self.seq,
            origin: origin.to_owned(),
            robot: about.to_owned(),
            stamp_s: stamp,
            sent_s: received_s + 0.001,
            body,
        };
        let bytes = env.encode().expect("an envelope always encodes (net/src/wire/mod.rs)");
        (bytes, uplink)
    }

    /// `n` beams from `robot`'s LiDAR with its base's V at `v`, on the site with the other robots
    /// in their slots, each beam perturbed by one input byte (0x7f: no return, 0x80: infinite).
    fn cast(
        &self,
        robot: usize,
        v: Se2,
        step: f64,
        angle_min: f64,
        n: usize,
        r: &mut Reader<'_>,
    ) -> Vec<f64> {
        let (slot, mount) = self.slots[robot];
        let lidar = v * slot * mount;
        let site = Se2::new(SITE.2, SITE.3, 0.0);
        let mut scene: Vec<(Se2, &Polygon)> = vec![(site, &self.site)];
        for (k, (s, _)) in self.slots.iter().enumerate() {
            if k != robot {
                scene.push((v * *s, &self.chassis[k]));
            }
        }
        let noise = r.rest();
        (0..n)
            .map(|i| {
                let a = lidar.theta + angle_min + step * i as f64;
                let d = cast_ray([lidar.x, lidar.y], a, 1000.0, &scene).unwrap_or(f64::NAN);
                match noise.get(i % noise.len().max(1)).copied().unwrap_or(0) {
                    0x7f => f64::NAN,
                    0x80 => f64::INFINITY,
                    b => d + f64::from(b as i8) * 0.002,
                }
            })
            .collect()
    }
}

impl Reader<'_> {
    /// Mostly `default`, else a value in `lo..=hi`, else one of the edge values.
    fn real(&mut self, default: f64, lo: f64, hi: f64) -> f64 {
        match self.u8() {
            0..=127 => default,
            128..=223 => lo + (hi - lo) * f64::from(self.u16()) / f64::from(u16::MAX),
            s => match s - 224 {
                0 => 0.0,
                1 => -0.0,
                2 => f64::NAN,
                3 => f64::INFINITY,
                4 => f64::NEG_INFINITY,
                5 => f64::MIN_POSITIVE,
                6 => -f64::MIN_POSITIVE,
                7 => 5e-324,
                8 => 1e-300,
                9 => 1e-9,
                10 => -1e-9,
                11 => f64::MAX,
                12 => f64::MIN,
                13 => f64::EPSILON,
                14 => 5e-4,
                15 => -5e-4,
                16 => 4.999_999e-4,
                17 => 0.2,
                18 => 0.200_000_1,
                19 => -0.2,
                20 => TAU,
                21 => -TAU,
                22 => TAU + 1e-9,
                23 => PI,
                24 => 100.0,
                25 => 100.000_000_1,
                26 => 1e6,
                27 => -1.0,
                28 => 1e300,
                29 => -default,
                30 => default * (1.0 + 1e-12),
                _ => f64::from_bits(self.u64()),
            },
        }
    }
}

/// Bit-for-bit equality of two scan messages (NaN ranges are invalid beams: NaN on both sides).
fn same_scan(a: &ScanMsg, b: &ScanMsg) -> bool {
    let bits = |x: f64, y: f64| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan());
    a.robot == b.robot
        && a.seq == b.seq
        && bits(a.stamp_s, b.stamp_s)
        && bits(a.received_s, b.received_s)
        && a.odom_frame == b.odom_frame
        && match (a.odom, b.odom) {
            (Some(p), Some(q)) => bits(p.x, q.x) && bits(p.y, q.y) && bits(p.theta, q.theta),
            (None, None) => true,
            _ => false,
        }
        && bits(a.scan.angle_min_rad, b.scan.angle_min_rad)
        && bits(a.scan.angle_increment_rad, b.scan.angle_increment_rad)
        && bits(a.scan.range_min_m, b.scan.range_min_m)
        && bits(a.scan.range_max_m, b.scan.range_max_m)
        && a.scan.len() == b.scan.len()
        && a.scan.ranges_m().iter().zip(b.scan.ranges_m()).all(|(x, y)| bits(*x, *y))
}

/// The system allocator, noting the largest single allocation (`UPLINK_PATH_STATS=1` prints it
/// whenever an input sets a new largest: the measure behind the README's allocation bound).
struct Measured;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

fn note(size: usize) {
    if size > LARGEST.load(Ordering::Relaxed) {
        LARGEST.fetch_max(size, Ordering::Relaxed);
    }
}

// SAFETY: every call is passed to `System` unchanged.
unsafe impl GlobalAlloc for Measured {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Measured = Measured;

thread_local! {
    static SERVER: RefCell<Option<Server>> = const { RefCell::new(None) };
}

fn with_server<R>(f: impl FnOnce(&mut Server) -> R) -> R {
    SERVER.with(|s| f(s.borrow_mut().get_or_insert_with(Server::new)))
}

/// Seed inputs: valid TiM551 scans of each robot in both modes.
fn write_seeds(dir: &std::path::Path) {
    std::fs::create_dir_all(dir).expect("the seed directory");
    let mut seeds: Vec<(String, Vec<u8>)> = Vec::new();
    for robot in 0..2u8 {
        // Structured, all defaults: a ray-cast TiM551 scan (channel: the message's own).
        seeds.push((format!("structured-tim551-{robot}"), vec![0x08 | robot]));
        // Structured with sensor noise on every beam.
        let mut noisy = vec![0x08 | robot];
        noisy.extend(std::iter::repeat_n(0u8, 30));
        noisy.extend((0..271u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8 & 0x0f));
        seeds.push((format!("structured-noisy-{robot}"), noisy));
        // Raw: the same scan's envelope, as a sample's payload on the scan key, the bridge just
        // started (so that the envelope's session and sequence number stay fresh).
        let bytes = with_server(|s| s.structured(&mut Reader(&[]), usize::from(robot), 0).0);
        let mut raw = vec![0x40 | 0x02 | robot];
        raw.extend(bytes);
        seeds.push((format!("raw-tim551-{robot}"), raw));
    }
    // A fresh core for the run: the seeds' envelopes advanced nothing that stays.
    SERVER.with(|s| *s.borrow_mut() = None);
    for (name, bytes) in seeds {
        std::fs::write(dir.join(name), bytes).expect("a seed file");
    }
}

fuzz_target!(
    init: {
        if let Some(dir) = std::env::var_os("UPLINK_PATH_SEEDS") {
            write_seeds(std::path::Path::new(&dir));
        }
        // Build the core before libFuzzer starts counting allocations.
        with_server(|_| ());
        if stats_on() {
            eprintln!("uplink_path: largest allocation while building the core: {} bytes", LARGEST.load(Ordering::Relaxed));
        }
        LARGEST.store(0, Ordering::Relaxed);
    },
    |data: &[u8]| {
        let before = LARGEST.load(Ordering::Relaxed);
        run(data);
        let after = LARGEST.load(Ordering::Relaxed);
        if after > before && after > 1 << 20 && stats_on() {
            let head: String = data.iter().take(48).map(|b| format!("{b:02x}")).collect();
            eprintln!("uplink_path: new largest allocation {after} bytes, input of {} bytes: {head}...", data.len());
        }
    }
);

fn run(data: &[u8]) {
    let Some((&b0, rest)) = data.split_first() else { return };
    let robot = usize::from(b0 & 1);
    let channel = CHANNELS[usize::from((b0 >> 1) & 3)];
    with_server(|s| {
        let robot = robot % s.robots.len();
        if b0 & 0x08 == 0 {
            s.receive(rest, robot, channel, b0 & 0x40 != 0);
        } else {
            let (bytes, sent) = s.structured(&mut Reader(rest), robot, b0);
            if let Some(got) = s.receive(&bytes, robot, channel, b0 & 0x40 != 0) {
                let (Uplink::Scan(a), Uplink::Scan(b)) = (&sent, &got) else {
                    panic!("a scan was sent, {got:?} received");
                };
                assert!(same_scan(a, b), "the scan changed on the wire: sent {a:?}, received {b:?}");
            }
        }
    });
}
