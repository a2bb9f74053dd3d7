//! Planar geometry shared by the pipeline, the simulator and the configuration.

mod polygon;
mod raycast;

pub use polygon::{Polygon, PolygonError};
pub use raycast::cast_ray;
