//! `amr-drivers`: the robot's device protocols, with their configuration sections: SOPAS for the
//! SICK TiM551 ([`sopas`]), CANopen and CiA 402 for the TECO wheel drives ([`canopen`]), LPBUS
//! for the LPMS-B2 IMU ([`lpms`]). Each is a sans-IO codec and state machine (bytes or frames in,
//! events out, `now` passed in) plus a thin tokio shell generic over its transport; the mock devices
//! in `hil-mocks` use the same pure pieces from the device's side. The crate uses nothing of ours
//! but `amr-settings` (`docs/architecture.md`, "Rules between crates"; `docs/devices.md` for the
//! protocols).

pub mod canopen;
pub mod lpms;
pub mod sopas;
