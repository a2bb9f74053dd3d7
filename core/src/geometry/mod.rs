//! Planar geometry shared by the pipeline, the simulator and the configuration.

mod polygon;

pub use polygon::{Polygon, PolygonError};
