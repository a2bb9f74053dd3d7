//! Foxglove's well-known schemas in their JSON form (schema encoding `jsonschema`, message
//! encoding `json`), which Foxglove reads with no plugin and no protobuf.
//!
//! Field names, types and enum values follow Foxglove's schema reference
//! (<https://docs.foxglove.dev/docs/visualization/message-schemas/introduction>: `LaserScan`,
//! `PoseInFrame`, `PosesInFrame`, `FrameTransform`, `FrameTransforms`, `Grid`, `Log`, and the
//! shared `Timestamp` {sec, nsec}, `Pose`, `Vector3`, `Quaternion`, `PackedElementField`). In JSON a
//! `bytes` field is a base64 string (the schema says `"contentEncoding": "base64"`), an enum is
//! its integer value.
//!
//! Our frames: `map`; `V` (the virtual robot); per robot `<id>` (its base), `<id>/odom`,
//! `<id>/laser`.

use amr_core::map::OccupancyGrid;
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use serde_json::{Value, json};

pub const LASER_SCAN: &str = "foxglove.LaserScan";
pub const POSE_IN_FRAME: &str = "foxglove.PoseInFrame";
pub const POSES_IN_FRAME: &str = "foxglove.PosesInFrame";
pub const FRAME_TRANSFORM: &str = "foxglove.FrameTransform";
pub const FRAME_TRANSFORMS: &str = "foxglove.FrameTransforms";
pub const GRID: &str = "foxglove.Grid";
pub const LOG: &str = "foxglove.Log";

/// `foxglove.Log` levels (Log.level enum: UNKNOWN 0, DEBUG 1, INFO 2, WARNING 3, ERROR 4, FATAL 5).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    Debug = 1,
    Info = 2,
    Warning = 3,
    Error = 4,
    Fatal = 5,
}

/// `PackedElementField.type` INT8 (UINT8 1, INT8 2, …, FLOAT64 8).
const NUMERIC_INT8: u32 = 2;

fn time_schema() -> Value {
    json!({
        "type": "object", "title": "time",
        "properties": {
            "sec": { "type": "integer", "minimum": 0 },
            "nsec": { "type": "integer", "minimum": 0, "maximum": 999_999_999 }
        }
    })
}

fn xyz_schema(title: &str, w: bool) -> Value {
    let mut p = serde_json::Map::new();
    for k in ["x", "y", "z"].into_iter().chain(w.then_some("w")) {
        p.insert(k.into(), json!({ "type": "number" }));
    }
    json!({ "type": "object", "title": title, "properties": p })
}

fn pose_schema() -> Value {
    json!({
        "type": "object", "title": "foxglove.Pose",
        "properties": {
            "position": xyz_schema("foxglove.Vector3", false),
            "orientation": xyz_schema("foxglove.Quaternion", true)
        }
    })
}

fn object(title: &str, properties: Value) -> String {
    json!({ "title": title, "type": "object", "properties": properties }).to_string()
}

fn transform_schema() -> Value {
    json!({
        "type": "object", "title": FRAME_TRANSFORM,
        "properties": {
            "timestamp": time_schema(),
            "parent_frame_id": { "type": "string" },
            "child_frame_id": { "type": "string" },
            "translation": xyz_schema("foxglove.Vector3", false),
            "rotation": xyz_schema("foxglove.Quaternion", true)
        }
    })
}

/// The JSON schema of a Foxglove schema by name, `None` for a name not ours.
#[must_use]
pub fn schema(name: &str) -> Option<String> {
    Some(match name {
        LASER_SCAN => object(
            name,
            json!({
                "timestamp": time_schema(),
                "frame_id": { "type": "string" },
                "pose": pose_schema(),
                "start_angle": { "type": "number" },
                "end_angle": { "type": "number" },
                "ranges": { "type": "array", "items": { "type": "number" } },
                "intensities": { "type": "array", "items": { "type": "number" } }
            }),
        ),
        POSE_IN_FRAME => object(
            name,
            json!({ "timestamp": time_schema(), "frame_id": { "type": "string" }, "pose": pose_schema() }),
        ),
        POSES_IN_FRAME => object(
            name,
            json!({
                "timestamp": time_schema(),
                "frame_id": { "type": "string" },
                "poses": { "type": "array", "items": pose_schema() }
            }),
        ),
        FRAME_TRANSFORM => transform_schema().to_string(),
        FRAME_TRANSFORMS => {
            object(name, json!({ "transforms": { "type": "array", "items": transform_schema() } }))
        }
        GRID => object(
            name,
            json!({
                "timestamp": time_schema(),
                "frame_id": { "type": "string" },
                "pose": pose_schema(),
                "column_count": { "type": "integer", "minimum": 0 },
                "cell_size": xyz_schema("foxglove.Vector2", false),
                "row_stride": { "type": "integer", "minimum": 0 },
                "cell_stride": { "type": "integer", "minimum": 0 },
                "fields": { "type": "array", "items": { "type": "object", "title": "foxglove.PackedElementField",
                    "properties": { "name": { "type": "string" }, "offset": { "type": "integer" },
                                    "type": { "type": "integer" } } } },
                "data": { "type": "string", "contentEncoding": "base64" }
            }),
        ),
        LOG => object(
            name,
            json!({
                "timestamp": time_schema(),
                "level": { "type": "integer", "oneOf": [
                    { "title": "UNKNOWN", "const": 0 }, { "title": "DEBUG", "const": 1 },
                    { "title": "INFO", "const": 2 }, { "title": "WARNING", "const": 3 },
                    { "title": "ERROR", "const": 4 }, { "title": "FATAL", "const": 5 } ] },
                "message": { "type": "string" },
                "name": { "type": "string" },
                "file": { "type": "string" },
                "line": { "type": "integer", "minimum": 0 }
            }),
        ),
        _ => return None,
    })
}

/// Seconds (≥ 0) as Foxglove's `{sec, nsec}`.
#[must_use]
pub fn time(t_s: f64) -> Value {
    let ns = nanos(t_s);
    json!({ "sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000 })
}

/// Seconds as nanoseconds for MCAP's `log_time` (negative and NaN as 0, saturating).
#[must_use]
pub fn nanos(t_s: f64) -> u64 {
    if t_s.is_nan() || t_s <= 0.0 { 0 } else { (t_s * 1e9).round().min(u64::MAX as f64) as u64 }
}

/// A display value to 0.1 mm (or 0.1 mrad): a third of the text of a full `f64`. The exact
/// values are on the `/amr/...` channels.
fn short(x: f64) -> f64 {
    (x * 1e4).round() / 1e4
}

/// A pose for display: position to 0.1 mm, orientation to 1e-4.
fn short_pose(p: &Se2) -> Value {
    let (s, c) = (p.theta / 2.0).sin_cos();
    json!({
        "position": { "x": short(p.x), "y": short(p.y), "z": 0.0 },
        "orientation": { "x": 0.0, "y": 0.0, "z": short(s), "w": short(c) }
    })
}

fn pose(p: &Se2) -> Value {
    let (s, c) = (p.theta / 2.0).sin_cos();
    json!({ "position": { "x": p.x, "y": p.y, "z": 0.0 }, "orientation": { "x": 0.0, "y": 0.0, "z": s, "w": c } })
}

/// A `foxglove.LaserScan` of a device scan, ranges to 0.1 mm. Invalid beams are 0 (Foxglove draws them at the
/// sensor); the exact beams are on `/amr/uplink`.
#[must_use]
pub fn laser_scan(stamp_s: f64, frame: &str, scan: &Scan) -> Value {
    let n = scan.len();
    let ranges: Vec<f64> =
        scan.ranges_m().iter().map(|r| if r.is_finite() { short(*r) } else { 0.0 }).collect();
    json!({
        "timestamp": time(stamp_s),
        "frame_id": frame,
        "pose": pose(&Se2::IDENTITY),
        "start_angle": scan.angle_min_rad,
        "end_angle": scan.angle_min_rad + scan.angle_increment_rad * n.saturating_sub(1) as f64,
        "ranges": ranges,
        "intensities": []
    })
}

/// Bins of the virtual scan's `foxglove.LaserScan`: 0.5° over the full circle.
pub const VIRTUAL_BINS: usize = 720;

/// The virtual scan's bins: `(start, step, ranges)`, [`VIRTUAL_BINS`] bins of 0.5° from −π; each
/// point goes to the bin of its bearing, the nearest point per bin wins, empty bins are 0. Shared
/// by the Foxglove and the ROS 2 views.
#[must_use]
pub fn virtual_bins(points: &[[f64; 2]]) -> (f64, f64, Vec<f64>) {
    let step = std::f64::consts::TAU / VIRTUAL_BINS as f64;
    let start = -std::f64::consts::PI;
    let mut ranges = vec![0.0f64; VIRTUAL_BINS];
    for p in points {
        let r = p[0].hypot(p[1]);
        if !r.is_finite() {
            continue;
        }
        let k = ((p[1].atan2(p[0]) - start) / step).round();
        let k = if k.is_finite() && k >= 0.0 { (k as usize) % VIRTUAL_BINS } else { 0 };
        if ranges[k] == 0.0 || r < ranges[k] {
            ranges[k] = r;
        }
    }
    (start, step, ranges)
}

/// A `foxglove.LaserScan` of a point set (the virtual scan, points in V's frame), binned by
/// [`virtual_bins`], ranges to 0.1 mm. For display; the exact points are on `/amr/fused`.
#[must_use]
pub fn points_scan(stamp_s: f64, frame: &str, points: &[[f64; 2]]) -> Value {
    let (start, step, mut ranges) = virtual_bins(points);
    for r in &mut ranges {
        *r = short(*r);
    }
    json!({
        "timestamp": time(stamp_s),
        "frame_id": frame,
        "pose": pose(&Se2::IDENTITY),
        "start_angle": start,
        "end_angle": start + step * (VIRTUAL_BINS - 1) as f64,
        "ranges": ranges,
        "intensities": []
    })
}

/// A `foxglove.PoseInFrame`.
#[must_use]
pub fn pose_in_frame(stamp_s: f64, frame: &str, p: &Se2) -> Value {
    json!({ "timestamp": time(stamp_s), "frame_id": frame, "pose": pose(p) })
}

/// A `foxglove.PosesInFrame` (for display: to 0.1 mm).
#[must_use]
pub fn poses_in_frame(stamp_s: f64, frame: &str, poses: &[Se2]) -> Value {
    json!({ "timestamp": time(stamp_s), "frame_id": frame, "poses": poses.iter().map(short_pose).collect::<Vec<_>>() })
}

/// A `foxglove.FrameTransform`: `child`'s pose in `parent`.
#[must_use]
pub fn transform(stamp_s: f64, parent: &str, child: &str, p: &Se2) -> Value {
    let (s, c) = (p.theta / 2.0).sin_cos();
    json!({
        "timestamp": time(stamp_s),
        "parent_frame_id": parent,
        "child_frame_id": child,
        "translation": { "x": p.x, "y": p.y, "z": 0.0 },
        "rotation": { "x": 0.0, "y": 0.0, "z": s, "w": c }
    })
}

/// A `foxglove.FrameTransforms`.
#[must_use]
pub fn transforms(list: Vec<Value>) -> Value {
    json!({ "transforms": list })
}

/// The map as a `foxglove.Grid` in frame `map`: one INT8 field `occupancy` (−1 unknown, 0–100),
/// rows from the origin corner up (the grid's own order, Foxglove's y-major order).
#[must_use]
pub fn grid(stamp_s: f64, map: &OccupancyGrid) -> Value {
    let bytes: Vec<u8> = map.cells.iter().map(|c| c.to_le_bytes()[0]).collect();
    json!({
        "timestamp": time(stamp_s),
        "frame_id": "map",
        "pose": pose(&map.origin),
        "column_count": map.width,
        "cell_size": { "x": map.resolution_m, "y": map.resolution_m },
        "row_stride": map.width,
        "cell_stride": 1,
        "fields": [ { "name": "occupancy", "offset": 0, "type": NUMERIC_INT8 } ],
        "data": base64(&bytes)
    })
}

/// A `foxglove.Log`.
#[must_use]
pub fn log(stamp_s: f64, level: Level, name: &str, message: &str, file: &str, line: u32) -> Value {
    json!({
        "timestamp": time(stamp_s),
        "level": level as u8,
        "message": message,
        "name": name,
        "file": file,
        "line": line
    })
}

/// Standard base64 with padding (RFC 4648 §4).
#[must_use]
pub fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let b = [c[0], c.get(1).copied().unwrap_or(0), c.get(2).copied().unwrap_or(0)];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for k in 0..4 {
            if k <= c.len() {
                out.push(char::from(ALPHABET[((n >> (18 - 6 * k)) & 63) as usize]));
            } else {
                out.push('=');
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
    use super::*;

    #[test]
    fn base64_matches_rfc_4648_test_vectors() {
        // RFC 4648 §10.
        for (i, o) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(i.as_bytes()), o);
        }
    }

    #[test]
    fn every_schema_is_json_naming_itself() {
        for name in [LASER_SCAN, POSE_IN_FRAME, POSES_IN_FRAME, FRAME_TRANSFORM, FRAME_TRANSFORMS, GRID, LOG]
        {
            let v: Value = serde_json::from_str(&schema(name).unwrap()).unwrap();
            assert_eq!(v["title"], name);
            assert_eq!(v["type"], "object");
        }
        assert!(schema("foxglove.Nope").is_none());
    }

    #[test]
    fn times_and_quaternions() {
        assert_eq!(time(12.25), json!({ "sec": 12, "nsec": 250_000_000 }));
        assert_eq!(nanos(-1.0), 0);
        assert_eq!(nanos(f64::NAN), 0);
        let t = transform(0.0, "map", "V", &Se2::new(1.0, 2.0, std::f64::consts::PI));
        assert!((t["rotation"]["z"].as_f64().unwrap() - 1.0).abs() < 1e-12);
        assert!(t["rotation"]["w"].as_f64().unwrap().abs() < 1e-12);
    }

    #[test]
    fn the_virtual_scan_keeps_the_nearest_point_per_bearing() {
        let v = points_scan(1.0, "V", &[[2.0, 0.0], [1.0, 0.0], [0.0, 3.0], [f64::NAN, 1.0]]);
        let ranges: Vec<f64> = v["ranges"].as_array().unwrap().iter().map(|r| r.as_f64().unwrap()).collect();
        assert_eq!(ranges.len(), VIRTUAL_BINS);
        assert_eq!(ranges[VIRTUAL_BINS / 2], 1.0);
        assert_eq!(ranges[VIRTUAL_BINS * 3 / 4], 3.0);
        assert_eq!(ranges.iter().filter(|r| **r > 0.0).count(), 2);
    }
}
