//! `hil-mocks`: the simulated world and the mock devices.
//!
//! A mock device is a server for the real protocol, backed by the simulated world, with a fault
//! plan (`docs/devices.md` §4). It is built from the same sans-IO codecs as the drivers in
//! `amr-drivers`, used from the device's side. The world (`world`) and the mocks (`tim551`,
//! `teco_drive`, `lpms`) arrive with their issues.

pub mod lpms;
pub mod teco_drive;
pub mod tim551;
pub mod world;
