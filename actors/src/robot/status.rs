//! Health publishing and counters shared by the robot's actors.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};

use super::ports::RobotPorts;
use amr_msgs::{Device, Health, HealthReport};

/// One device's health: published on the health port when it changes, and logged.
#[derive(Debug)]
pub(crate) struct HealthCell {
    device: Device,
    current: Option<Health>,
}

impl HealthCell {
    #[must_use]
    pub(crate) fn new(device: Device) -> Self {
        HealthCell { device, current: None }
    }

    /// The last health set.
    #[must_use]
    pub(crate) fn get(&self) -> Option<Health> {
        self.current
    }

    /// Set the health; publish and log only a change.
    pub(crate) fn set(&mut self, ports: &RobotPorts, health: Health, detail: impl Into<String>) {
        if self.current == Some(health) {
            return;
        }
        let detail = detail.into();
        match health {
            Health::Ok | Health::Starting => {
                tracing::info!(robot = %ports.robot, device = ?self.device, ?health, %detail, "health");
            }
            Health::Degraded | Health::Lost | Health::Fault => {
                tracing::warn!(robot = %ports.robot, device = ?self.device, ?health, %detail, "health");
            }
        }
        self.current = Some(health);
        let report = HealthReport { device: self.device, health, detail };
        ports.health_board.send_modify(|b| {
            b.insert(self.device, report.clone());
        });
        // The safety layer must see every change (a lost drive halts the robot); observers may
        // skip some.
        ports.safety_inbox.push(super::ports::SafetyInput::Health(report.clone()));
        ports.health.send(report);
    }
}

/// Named event counters (scans, rejected frames, link losses…), shared across restarts.
#[derive(Debug, Clone, Default)]
pub struct Counters(Arc<Mutex<BTreeMap<String, u64>>>);

impl Counters {
    /// Add one to `name`.
    pub fn count(&self, name: &str) {
        let mut map = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        *map.entry(name.to_owned()).or_default() += 1;
    }

    /// Count a rejected input under `rejected` and under its reason.
    pub fn rejected(&self, reason: &str) {
        self.count("rejected");
        self.count(reason);
    }

    /// The value of `name` (0 if never counted).
    #[must_use]
    pub fn get(&self, name: &str) -> u64 {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).get(name).copied().unwrap_or(0)
    }

    /// All counters.
    #[must_use]
    pub fn snapshot(&self) -> BTreeMap<String, u64> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).clone()
    }
}
