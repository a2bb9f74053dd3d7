//! The simulated world served to separate robot processes (`amr sim --world-only`).
//!
//! Choice: the world process owns the physics and every robot's mock devices, each behind its real
//! transport on this machine (SOPAS on a loopback TCP port, CANopen behind a socketcand server on
//! loopback, LPBUS on a pseudo-terminal). `amr robot --mock --world MANIFEST` then runs the robot's
//! tree exactly as on hardware, only with the device addresses of the manifest. One world sees
//! every robot, so each LiDAR sees the others, and nothing about the physics crosses the fleet's
//! Zenoh link.

use std::collections::BTreeMap;
use std::net::SocketAddr;

use amr_actors::clock::FleetClock;
use amr_actors::config::Config;
use amr_actors::robot::DeviceOverrides;
use amr_actors::robot::canbus::CanLink;
use amr_actors::robot::ports::AbortOnDrop;
use amr_actors::server::formation_robots;
use hil_mocks::world::{Noise, SharedWorld};
use serde::{Deserialize, Serialize};

use crate::{RobotMocks, SimCan, SimError, TruthLog, build_world, spawn_world_loop, start_mocks};

/// Where each robot's mock devices are.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorldManifest {
    pub robots: BTreeMap<String, MockEndpoints>,
}

/// One robot's mock devices.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MockEndpoints {
    /// The TiM551's SOPAS port.
    pub lidar: SocketAddr,
    /// The socketcand server in front of the robot's CAN bus, and its channel.
    pub socketcand: SocketAddr,
    pub can_channel: String,
    /// The LPMS-B2's tty.
    pub imu: String,
}

impl MockEndpoints {
    /// The robot's device addresses replaced by these.
    #[must_use]
    pub fn overrides(&self) -> DeviceOverrides {
        DeviceOverrides {
            lidar: Some((self.lidar.ip().to_string(), self.lidar.port())),
            imu_path: Some(self.imu.clone()),
            can: Some(CanLink::Socketcand {
                address: self.socketcand.to_string(),
                channel: self.can_channel.clone(),
            }),
            ..DeviceOverrides::default()
        }
    }
}

/// A running served world.
#[derive(Debug)]
pub struct ServedWorld {
    pub manifest: WorldManifest,
    pub world: SharedWorld,
    pub truth: TruthLog,
    pub mocks: Vec<RobotMocks>,
    _loop: AbortOnDrop<()>,
}

/// Build the scenario's world with every robot of the formation at its start slot and serve their
/// mock devices on loopback.
pub async fn serve_world(
    config: &Config,
    chosen: &amr_actors::config::ChosenScenario,
    seed: u64,
) -> Result<ServedWorld, SimError> {
    let scenario = &chosen.scenario;
    let robots = formation_robots(&config.server, &config.robots)?;
    let noise = Noise::TYPICAL;
    let site = crate::site_for(&chosen.map_name, &chosen.map)?;
    crate::check_formation(&site, scenario, &robots)?;
    let world = build_world(&robots, scenario, site, &noise, seed)?;
    let mut mocks = Vec::new();
    let mut manifest = WorldManifest { robots: BTreeMap::new() };
    for (i, r) in robots.iter().enumerate() {
        let m = start_mocks(&world, i, r, &noise, seed, SimCan::Socketcand).await?;
        let socketcand = m
            .socketcand
            .as_ref()
            .map(|s| s.address)
            .ok_or(SimError::Mock("socketcand", "not started".into()))?;
        manifest.robots.insert(
            r.id.as_str().to_owned(),
            MockEndpoints {
                lidar: SocketAddr::from(([127, 0, 0, 1], m.lidar.port())),
                socketcand,
                can_channel: "can0".into(),
                imu: m.imu.tty_path().display().to_string(),
            },
        );
        mocks.push(m);
    }
    let truth = TruthLog::default();
    let task = spawn_world_loop(&world, &truth, FleetClock::start(), &robots, &mocks);
    Ok(ServedWorld { manifest, world, truth, mocks, _loop: task })
}
