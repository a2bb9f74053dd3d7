//! `hil-mocks`: the simulated world ([`world`]) and the mock devices that serve the real protocols
//! from it: the SICK TiM551 ([`tim551`]), the TECO drives ([`teco_drive`]) and the LPMS-B2
//! ([`lpms`]), each with a fault plan (`docs/devices.md` §4). A mock is built from the same
//! sans-IO codecs as the drivers in `amr-drivers`, used from the device's side; it speaks the
//! device's protocol, never the fleet's messages or actors.

pub mod lpms;
pub mod teco_drive;
pub mod tim551;
pub mod world;
