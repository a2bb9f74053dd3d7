//! `amr-drivers`: the robot's device protocols.
//!
//! One module per protocol, each a sans-IO codec and state machine (bytes or frames in, events out,
//! `now` passed in) plus a thin tokio shell generic over its transport. The mock devices in
//! `hil-mocks` use the same pure pieces from the other side. This crate depends on nothing else of
//! ours but `amr-settings` (see `docs/architecture.md`, "Rules between crates").
//!
//! The protocol modules arrive with their issues: `sopas` (SICK TiM551), `canopen` + `cia402`
//! (TECO drives), `lpms` (LPMS-B2).

pub mod canopen;
pub mod lpms;
pub mod sopas;
