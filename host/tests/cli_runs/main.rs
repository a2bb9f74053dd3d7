//! The `amr` binary as a user runs it, one test binary (six before, so that the test build links
//! once): the CLI and its help texts, `amr eval`, `amr localize` on CARMEN logs and ROS 2 bags, the
//! mocks, recording, `amr amcl` on ROS 2.
//! The fleet test (`fleet.rs`) stays on its own: its processes keep real-time deadlines, and
//! `amr eval` beside it would take the cores they need.

mod carmen_prepare;
mod cli;
mod eval;
mod help;
mod localize;
mod mocks;
mod record;
mod ros2_amcl;
mod ros2_bag;
mod ros2_dds;
mod ros2_live;
mod ros2_teleop;
