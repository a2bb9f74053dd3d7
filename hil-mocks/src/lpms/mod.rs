//! Mock LPMS-B2 behind a pseudo-terminal: the LPBUS command set, streaming from a motion source, with a fault plan.
//!
//! - [`motion`]: the [`MotionSource`] trait and a constant-yaw-rate source with seeded gyro noise.
//! - [`device`]: the sensor as a pure state machine built from `amr_drivers::lpms` codec pieces.
//! - [`pty`]: the tokio task serving it on a pty behind a stable symlink, with faults and replug.
//!
//! `amr mock imu --rate 100` needs [`start_default_mock_imu`] (or [`start_mock_imu`]): it returns a
//! [`MockImuHandle`] whose [`MockImuHandle::tty_path`] is the path to give the driver.

pub mod device;
pub mod motion;
pub mod pty;

pub use device::{DeviceFaults, DeviceSettings, DeviceStats, MockDevice};
pub use motion::{ConstantYawRate, Motion, MotionSource};
pub use pty::{
    Fault, ImuConnector, MockImuError, MockImuHandle, MockImuOptions, MockImuStats, start_default_mock_imu,
    start_mock_imu, start_mock_imu_in_memory,
};
