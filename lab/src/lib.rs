//! The experiments behind `amr eval` and `amr bench`: what they run, the figures they compute from
//! the runs, and the reports and plots they write. The `amr` binary parses the arguments and calls
//! these.
//!
//! - [`eval`]: T1–T4 side by side in simulated time ([`eval::run`]), the sensitivity sweeps of the
//!   paper's Tables 6–7 ([`eval::sweep`]), and the [`eval::Plan`] they share with the error budget.
//! - [`study`]: T4's error budget ([`study::budget`]) and the occlusion study over spacing, team
//!   size and site ([`study::occlusion`]), with its statistics and verdicts.
//! - [`plots`]: an evaluation trial's plots and the study's line charts, as PNG and SVG.
//! - [`bench`](mod@bench): the Virtual-AMR pipeline's and AMCL's timing harness, with the process's peak
//!   memory.
//! - [`bench_localize`]: AMCL on recorded real logs against their references.

pub mod bench;
pub mod bench_localize;
pub mod eval;
pub mod plots;
pub mod study;
