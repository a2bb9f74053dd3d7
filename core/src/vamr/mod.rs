//! The Virtual-AMR measurement-construction pipeline (paper §4, spec §2–6, §9).

pub mod heading;
pub mod preprocess;
pub mod tracker;
