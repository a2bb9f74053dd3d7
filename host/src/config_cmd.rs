//! `amr config check`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use amr_actors::config::{Config, ConfigSource, RobotConfig, load};
use amr_drivers::canopen::config::BusTransport;
use amr_drivers::lpms::data::DataMode;
use amr_drivers::sopas::framing::Dialect;
use amr_drivers::sopas::session::DialectChoice;
use amr_net::network::NetworkConfig;

/// Without a directory: `./config` if there is one, else the embedded defaults.
pub(crate) fn source_for(dir: Option<PathBuf>) -> ConfigSource {
    match dir {
        Some(d) => ConfigSource::Dir(d),
        None if Path::new("config").is_dir() => ConfigSource::Dir(PathBuf::from("config")),
        None => ConfigSource::Embedded,
    }
}

pub(crate) fn check(dir: Option<PathBuf>) -> anyhow::Result<()> {
    let source = source_for(dir);
    tracing::debug!(%source, "loading configuration");
    let config = load(&source)?;
    // network.toml is the link's file: its own crate parses and checks it.
    let network = NetworkConfig::from_set(&config)?;
    #[allow(clippy::print_stdout, reason = "the command's report")]
    {
        print!("{}", summary(&source, &config, network.as_ref()));
    }
    Ok(())
}

fn robot_summary(out: &mut String, r: &RobotConfig) -> std::fmt::Result {
    let (x0, y0, x1, y1) = r.chassis.outline_m.bounds();
    let mount = r.lidar_mount.to_se2();
    let d = &r.devices;
    writeln!(out, "robot {}", r.id)?;
    writeln!(
        out,
        "  chassis     {} vertices, {:.2} m x {:.2} m, area {:.3} m²",
        r.chassis.outline_m.vertices().len(),
        x1 - x0,
        y1 - y0,
        r.chassis.outline_m.area()
    )?;
    writeln!(
        out,
        "  kinematics  wheel radius {} m, track width {} m",
        r.kinematics.wheel_radius_m.get(),
        r.kinematics.track_width_m.get()
    )?;
    writeln!(
        out,
        "  limits      {} m/s, {} m/s², {} rad/s; command watchdog {} ms",
        r.limits.max_speed_mps.get(),
        r.limits.max_accel_mps2.get(),
        r.limits.max_yaw_rate_radps.get(),
        r.safety.command_timeout_ms.ms()
    )?;
    let dialect = match d.lidar.dialect {
        DialectChoice::Auto => "auto",
        DialectChoice::Fixed(Dialect::ColaA) => "CoLa-A",
        DialectChoice::Fixed(Dialect::ColaB) => "CoLa-B",
    };
    writeln!(
        out,
        "  lidar       {} {}:{} dialect {dialect}, start-up {}, mounted at ({}, {}, {}°)",
        d.lidar.source.name(),
        d.lidar.host,
        d.lidar.port,
        format!("{:?}", d.lidar.startup).to_lowercase(),
        mount.x,
        mount.y,
        mount.theta.to_degrees()
    )?;
    let transport = match &d.can.transport {
        BusTransport::Socketcan { interface } => format!("socketcan {interface}"),
        BusTransport::Socketcand { address, channel } => format!("socketcand {address} channel {channel}"),
        BusTransport::InProcess => "in-process bus".to_owned(),
    };
    writeln!(
        out,
        "  can         {} {transport}, master node {}, SYNC every {} ms",
        d.can.source.name(),
        d.can.master_node_id,
        d.can.sync_period_ms
    )?;
    let dr = &d.drives;
    writeln!(
        out,
        "  drives      left node {}{}, right node {}{}; {} counts/rev, gear {}:1, heartbeat {}/{} ms",
        dr.left.node_id,
        if dr.left.inverted { " (inverted)" } else { "" },
        dr.right.node_id,
        if dr.right.inverted { " (inverted)" } else { "" },
        dr.encoder_counts_per_rev,
        dr.gear_ratio,
        dr.heartbeat_producer_ms,
        dr.heartbeat_consumer_ms
    )?;
    writeln!(
        out,
        "  imu         {} {} @ {} baud, {} Hz, {} data",
        d.imu.source.name(),
        d.imu.path,
        d.imu.baud,
        d.imu.stream_hz,
        match d.imu.data_mode {
            DataMode::Float32 => "float",
            DataMode::Int16 => "int16",
        }
    )
}

/// What `config check` prints for a valid configuration.
pub(crate) fn summary(source: &ConfigSource, c: &Config, network: Option<&NetworkConfig>) -> String {
    let mut out = String::new();
    let _ = write_summary(&mut out, source, c, network);
    out
}

fn write_summary(
    out: &mut String,
    source: &ConfigSource,
    c: &Config,
    network: Option<&NetworkConfig>,
) -> std::fmt::Result {
    writeln!(out, "configuration: {source}")?;
    for r in &c.robots {
        robot_summary(out, r)?;
    }
    let s = &c.server;
    let members: Vec<String> = s.robots.iter().map(|m| format!("{} (w {})", m.id, m.weight.get())).collect();
    writeln!(out, "server")?;
    writeln!(out, "  configuration {:?}, formation [{}]", s.configuration, members.join(", "))?;
    writeln!(
        out,
        "  gates       stamp spread {} ms, age {} ms, end-to-end {} ms; on robot lost: {:?}",
        s.sync.max_stamp_spread_ms.ms(),
        s.sync.max_age_ms.ms(),
        s.sync.e2e_threshold_ms.ms(),
        s.on_robot_lost
    )?;
    let v = &c.vamr;
    writeln!(out, "vamr")?;
    writeln!(
        out,
        "  median {} / smoothing {} beams; line fit N={}; ε_d {} m, Δθ {}°, ±{} beams; N_miss {}",
        v.preprocess.median_window_beams.get(),
        v.preprocess.smoothing_window_beams.get(),
        v.contour.line_fit_points.get(),
        v.heading.distance_gate_m.get(),
        v.heading.step_deg.get(),
        v.heading.neighbour_window_beams.get(),
        v.tracker.max_missed_packets.get()
    )?;
    let a = &c.amcl;
    writeln!(out, "amcl")?;
    writeln!(
        out,
        "  particles {}..{}, max_beams {}, sigma_hit {}, z_hit {}, z_rand {}, update {} m / {} rad",
        a.min_particles.get(),
        a.max_particles.get(),
        a.max_beams.get(),
        a.sigma_hit.get(),
        a.z_hit.get(),
        a.z_rand.get(),
        a.update_min_d.get(),
        a.update_min_a.get()
    )?;
    for (name, m) in &c.maps {
        let occupied = m.cells.iter().filter(|&&v| v == amr_core::map::OCCUPIED).count();
        writeln!(
            out,
            "map {name}: {} × {} cells at {} m ({:.1} m × {:.1} m), {occupied} occupied",
            m.width,
            m.height,
            m.resolution_m,
            m.width as f64 * m.resolution_m,
            m.height as f64 * m.resolution_m
        )?;
    }
    if let Some(n) = network {
        writeln!(
            out,
            "network: server `{}` listens on {}, robots connect to {}; lease {} ms",
            n.server.user,
            n.server.listen.join(", "),
            n.server.connect.join(", "),
            n.lease_ms.ms()
        )?;
    }
    writeln!(out, "ok: {} robots, server, vamr, amcl and {} maps are valid", c.robots.len(), c.maps.len())
}
