//! The Virtual-AMR measurement-construction pipeline (paper §4, docs/method.md §2–6, §9).

pub mod contour;
pub mod frame;
pub mod fusion;
pub mod heading;
pub mod pipeline;
pub mod preprocess;
pub mod synthetic;
pub mod tracker;

#[cfg(test)]
mod scenes;

/// The shipped `config/vamr.toml`, for tests.
#[cfg(test)]
pub(crate) fn shipped_params() -> crate::config::VamrParams {
    let text = include_str!("../../../config/vamr.toml");
    crate::config::parse_file("vamr.toml", text).expect("shipped vamr.toml is valid")
}
