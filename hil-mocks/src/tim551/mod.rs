//! Mock SICK TiM551: a SOPAS TCP server (both dialects) streaming scans from a scan source, with a fault plan.
//!
//! - [`source`]: the [`ScanSource`] trait and a static rectangular room.
//! - `device`: the pure device model (replies of a real TiM5xx, telegram building).
//! - [`server`]: the tokio TCP server, per-connection dialect detection, streaming, faults.
//!
//! Built from `amr_drivers::sopas` pieces used from the device side (devices.md §1, §4).

mod device;
pub mod server;
pub mod source;

pub use device::Variant;
pub use server::{Fault, MemoryConnector, MockConfig, MockHandle, Tim551Mock};
pub use source::{RectRoom, ScanSource, SourceScan};
