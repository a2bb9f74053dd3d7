//! ROS map_server maps: the YAML metadata and the PGM/PNG image, loaded and saved with nav2's rules
//! (nav2_map_server `map_io.cpp`, as summarised in research/amcl.md §1.9): grey = mean of the colour
//! channels (in trinary mode the PNG alpha joins the mean), `occ = 1 − grey/255` (or `grey/255` with
//! `negate`), strict thresholds, image flipped so row 0 is the bottom.
//!
//! Pure: the caller reads the files (the image path in the YAML is relative to the YAML's directory).

use std::io::Cursor;

use serde::Deserialize;

use super::{OCCUPIED, OccupancyGrid, UNKNOWN};
use crate::se2::Se2;

/// How image values become cell values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MapMode {
    /// Occupied, free or unknown by the thresholds.
    #[default]
    Trinary,
    /// Between the thresholds, a graded 1–99; a transparent pixel is unknown.
    Scale,
    /// The grey value is the cell value (0–100), anything else unknown.
    Raw,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(untagged)]
enum IntOrBool {
    Int(i64),
    Bool(bool),
}

/// The map YAML (nav2 keys; keys nav2 ignores are ignored here too).
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct MapYaml {
    pub image: String,
    pub resolution: f64,
    pub origin: Vec<f64>,
    pub occupied_thresh: f64,
    pub free_thresh: f64,
    #[serde(default = "no_negate")]
    negate: IntOrBool,
    #[serde(default)]
    pub mode: MapMode,
}

fn no_negate() -> IntOrBool {
    IntOrBool::Int(0)
}

/// Why a map could not be loaded or saved.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MapError {
    #[error("map YAML: {0}")]
    Yaml(String),
    #[error("map YAML: {key}: {rule}")]
    Invalid { key: &'static str, rule: String },
    #[error("map image: {0}")]
    Image(String),
}

impl MapYaml {
    /// Parse and check the metadata.
    pub fn parse(text: &str) -> Result<Self, MapError> {
        let y: MapYaml = serde_norway::from_str(text).map_err(|e| MapError::Yaml(e.to_string()))?;
        let bad = |key, rule: String| Err(MapError::Invalid { key, rule });
        if y.image.trim().is_empty() {
            return bad("image", "must name the image file".into());
        }
        if !(y.resolution.is_finite() && y.resolution > 0.0) {
            return bad("resolution", format!("must be > 0 m per cell (got {})", y.resolution));
        }
        if y.origin.len() != 3 || y.origin.iter().any(|v| !v.is_finite()) {
            return bad("origin", format!("must be [x, y, yaw] with finite values (got {:?})", y.origin));
        }
        if !(0.0..=1.0).contains(&y.free_thresh) || !(0.0..=1.0).contains(&y.occupied_thresh) {
            return bad("free_thresh", "thresholds must lie in [0, 1]".into());
        }
        if y.free_thresh >= y.occupied_thresh {
            return bad(
                "free_thresh",
                format!("must be below occupied_thresh ({} >= {})", y.free_thresh, y.occupied_thresh),
            );
        }
        Ok(y)
    }

    #[must_use]
    pub fn negate(&self) -> bool {
        match self.negate {
            IntOrBool::Int(v) => v != 0,
            IntOrBool::Bool(b) => b,
        }
    }

    #[must_use]
    pub fn origin_pose(&self) -> Se2 {
        Se2::new(self.origin[0], self.origin[1], self.origin[2])
    }
}

/// A decoded image: 8-bit channels per pixel, top row first.
struct Image {
    width: usize,
    height: usize,
    /// 1 (grey), 2 (grey + alpha), 3 (RGB) or 4 (RGBA).
    channels: usize,
    data: Vec<u8>,
}

fn decode_pgm(bytes: &[u8]) -> Result<Image, MapError> {
    let err = |m: &str| MapError::Image(format!("PGM: {m}"));
    let binary = match bytes.get(..2) {
        Some(b"P5") => true,
        Some(b"P2") => false,
        _ => return Err(err("not a PGM (P2/P5) file")),
    };
    // Header: magic, width, height, maxval; whitespace and #-comments between tokens.
    let mut pos = 2;
    let mut fields = [0usize; 3];
    for field in &mut fields {
        loop {
            match bytes.get(pos) {
                Some(b'#') => {
                    while bytes.get(pos).is_some_and(|c| *c != b'\n') {
                        pos += 1;
                    }
                }
                Some(c) if c.is_ascii_whitespace() => pos += 1,
                Some(_) => break,
                None => return Err(err("truncated header")),
            }
        }
        let start = pos;
        while bytes.get(pos).is_some_and(u8::is_ascii_digit) {
            pos += 1;
        }
        *field = std::str::from_utf8(&bytes[start..pos])
            .ok()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| err("bad header number"))?;
    }
    let [width, height, maxval] = fields;
    if width == 0 || height == 0 || maxval == 0 || maxval > 65535 {
        return Err(err(&format!("bad size or maxval ({width}×{height}, {maxval})")));
    }
    let n = width.checked_mul(height).ok_or_else(|| err("image too large"))?;
    let scale = |v: usize| ((v.min(maxval) * 255 + maxval / 2) / maxval) as u8;
    let data: Vec<u8> = if binary {
        let body = bytes.get(pos + 1..).ok_or_else(|| err("no pixel data"))?;
        let bpp = if maxval < 256 { 1 } else { 2 };
        if body.len() < n * bpp {
            return Err(err(&format!("{} bytes of pixels, expected {}", body.len(), n * bpp)));
        }
        (0..n)
            .map(|k| {
                let v = if bpp == 1 {
                    usize::from(body[k])
                } else {
                    usize::from(body[2 * k]) << 8 | usize::from(body[2 * k + 1])
                };
                scale(v)
            })
            .collect()
    } else {
        let text = std::str::from_utf8(&bytes[pos..]).map_err(|_| err("non-ASCII pixel data"))?;
        let values: Result<Vec<u8>, MapError> = text
            .lines()
            .map(|l| l.split('#').next().unwrap_or(""))
            .flat_map(str::split_ascii_whitespace)
            .take(n)
            .map(|t| t.parse::<usize>().map(scale).map_err(|_| err("bad pixel value")))
            .collect();
        let values = values?;
        if values.len() < n {
            return Err(err(&format!("{} pixels, expected {n}", values.len())));
        }
        values
    };
    Ok(Image { width, height, channels: 1, data })
}

fn decode_png(bytes: &[u8]) -> Result<Image, MapError> {
    let err = |e: png::DecodingError| MapError::Image(format!("PNG: {e}"));
    let mut decoder = png::Decoder::new(Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::normalize_to_color8());
    let mut reader = decoder.read_info().map_err(err)?;
    let size = reader.output_buffer_size().ok_or_else(|| MapError::Image("PNG: image too large".into()))?;
    let mut data = vec![0; size];
    let info = reader.next_frame(&mut data).map_err(err)?;
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err(MapError::Image("PNG: palette was not expanded".into())),
    };
    let (width, height) = (info.width as usize, info.height as usize);
    data.truncate(width * height * channels);
    Ok(Image { width, height, channels, data })
}

/// Load a map from its YAML text and its image file's bytes (PGM or PNG, by content).
pub fn load_map(yaml: &MapYaml, image_bytes: &[u8]) -> Result<OccupancyGrid, MapError> {
    let img =
        if image_bytes.starts_with(b"\x89PNG") { decode_png(image_bytes)? } else { decode_pgm(image_bytes)? };
    let mut grid = OccupancyGrid::filled(img.width, img.height, yaml.resolution, yaml.origin_pose(), UNKNOWN);
    let (occ_t, free_t, negate) = (yaml.occupied_thresh, yaml.free_thresh, yaml.negate());
    for y in 0..img.height {
        for x in 0..img.width {
            let px = &img.data[(y * img.width + x) * img.channels..][..img.channels];
            let (colour, alpha): (&[u8], Option<u8>) = match img.channels {
                1 => (&px[..1], None),
                2 => (&px[..1], Some(px[1])),
                3 => (&px[..3], None),
                _ => (&px[..3], Some(px[3])),
            };
            // Grey images count their one channel as R = G = B.
            let mut sum: f64 = if colour.len() == 1 {
                3.0 * f64::from(colour[0])
            } else {
                colour.iter().map(|c| f64::from(*c)).sum()
            };
            let mut count = 3.0;
            if yaml.mode == MapMode::Trinary
                && let Some(a) = alpha
            {
                sum += f64::from(a);
                count += 1.0;
            }
            let shade = sum / count / 255.0;
            let occ = if negate { shade } else { 1.0 - shade };
            let cell = match yaml.mode {
                MapMode::Trinary | MapMode::Scale => {
                    if yaml.mode == MapMode::Scale && alpha.is_some_and(|a| a != 255) {
                        UNKNOWN
                    } else if occ > occ_t {
                        OCCUPIED
                    } else if occ < free_t {
                        super::FREE
                    } else if yaml.mode == MapMode::Scale {
                        ((occ - free_t) / (occ_t - free_t) * 100.0).round_ties_even() as i8
                    } else {
                        UNKNOWN
                    }
                }
                MapMode::Raw => {
                    let v = (shade * 255.0).round();
                    if (0.0..=100.0).contains(&v) { v as i8 } else { UNKNOWN }
                }
            };
            grid.set(x, img.height - 1 - y, cell);
        }
    }
    Ok(grid)
}

/// Save a grid as map_server does: the YAML text and the image bytes (PGM for trinary and raw, PNG
/// with alpha for scale). `image_name` is written into the YAML.
///
/// One deliberate difference: map_saver writes unknown cells as grey 205 (occupancy 0.196), which
/// loads back as *free* whenever `free_thresh` is above 0.196 — map_saver's own default is 0.25. So
/// 205 is used only when it loads back as unknown; otherwise unknown gets the grey halfway between
/// the thresholds.
pub fn save_map(
    grid: &OccupancyGrid,
    mode: MapMode,
    occupied_thresh: f64,
    free_thresh: f64,
    image_name: &str,
) -> Result<(String, Vec<u8>), MapError> {
    let (free_i, occ_i) = ((free_thresh * 100.0).round() as i32, (occupied_thresh * 100.0).round() as i32);
    let (w, h) = (grid.width, grid.height);
    let unknown_occ = 1.0 - 205.0 / 255.0;
    let unknown_grey = if (free_thresh..=occupied_thresh).contains(&unknown_occ) {
        205
    } else {
        (255.0 * (1.0 - (free_thresh + occupied_thresh) / 2.0)).round() as u8
    };
    let mut grey = Vec::with_capacity(w * h);
    let mut alpha = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let c = i32::from(grid.cells[(h - 1 - y) * w + x]);
            let known = (0..=100).contains(&c);
            let (g, a) = match mode {
                MapMode::Trinary if !known => (unknown_grey, 255),
                MapMode::Trinary if c <= free_i => (254, 255),
                MapMode::Trinary if c >= occ_i => (0, 255),
                MapMode::Trinary => (unknown_grey, 255),
                MapMode::Scale if !known => (128, 0),
                MapMode::Scale => (((100 - c) as f64 * 2.55).round() as u8, 255),
                MapMode::Raw if !known => (255, 255),
                MapMode::Raw => (c as u8, 255),
            };
            grey.push(g);
            alpha.push(a);
        }
    }
    let image = if mode == MapMode::Scale {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, w as u32, h as u32);
        enc.set_color(png::ColorType::GrayscaleAlpha);
        enc.set_depth(png::BitDepth::Eight);
        let data: Vec<u8> = grey.iter().zip(&alpha).flat_map(|(g, a)| [*g, *a]).collect();
        let e = |e: png::EncodingError| MapError::Image(format!("PNG: {e}"));
        let mut writer = enc.write_header().map_err(e)?;
        writer.write_image_data(&data).map_err(e)?;
        writer.finish().map_err(e)?;
        out
    } else {
        let mut out = format!("P5\n{w} {h}\n255\n").into_bytes();
        out.extend_from_slice(&grey);
        out
    };
    let mode_name = match mode {
        MapMode::Trinary => "trinary",
        MapMode::Scale => "scale",
        MapMode::Raw => "raw",
    };
    let o = grid.origin;
    let yaml = format!(
        "image: {image_name}\nmode: {mode_name}\nresolution: {}\norigin: [{}, {}, {}]\nnegate: 0\noccupied_thresh: {occupied_thresh}\nfree_thresh: {free_thresh}\n",
        grid.resolution_m, o.x, o.y, o.theta
    );
    Ok((yaml, image))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::FREE;

    fn yaml(extra: &str) -> MapYaml {
        MapYaml::parse(&format!("image: m.pgm\nresolution: 0.05\norigin: [-1.0, 2.0, 0.0]\noccupied_thresh: 0.65\nfree_thresh: 0.196\n{extra}")).unwrap()
    }

    /// A 3×2 P5 image, top row first: [0, 128, 254] over [205, 255, 10].
    fn pgm() -> Vec<u8> {
        let mut b = b"P5\n# made by hand\n3 2\n255\n".to_vec();
        b.extend_from_slice(&[0, 128, 254, 205, 255, 10]);
        b
    }

    #[test]
    fn trinary_by_hand_with_flip_and_origin() {
        let g = load_map(&yaml(""), &pgm()).unwrap();
        assert_eq!((g.width, g.height, g.resolution_m), (3, 2, 0.05));
        assert_eq!(g.origin, Se2::new(-1.0, 2.0, 0.0));
        // Bottom row (j = 0) is the image's last row: 205 → occ 0.196 (not < 0.196: unknown),
        // 255 → free, 10 → occupied.
        assert_eq!(&g.cells[0..3], &[UNKNOWN, FREE, OCCUPIED]);
        // Top row: 0 → occupied, 128 → occ 0.498 unknown, 254 → free.
        assert_eq!(&g.cells[3..6], &[OCCUPIED, UNKNOWN, FREE]);
    }

    #[test]
    fn negate_swaps_black_and_white() {
        let g = load_map(&yaml("negate: 1\n"), &pgm()).unwrap();
        assert_eq!(&g.cells[3..6], &[FREE, UNKNOWN, OCCUPIED]);
        let b = load_map(&yaml("negate: true\n"), &pgm()).unwrap();
        assert_eq!(g, b, "negate accepts an int or a bool, as nav2 does");
    }

    #[test]
    fn thresholds_are_strict() {
        // 89 → occ = 1 − 89/255 = 0.6510 > 0.65 → occupied; 90 → 0.6471 → unknown.
        let mut b = b"P5 2 1 255 ".to_vec();
        b.extend_from_slice(&[89, 90]);
        let g = load_map(&yaml(""), &b).unwrap();
        assert_eq!(g.cells, vec![OCCUPIED, UNKNOWN]);
    }

    #[test]
    fn scale_and_raw_modes() {
        let g = load_map(&yaml("mode: scale\n"), &pgm()).unwrap();
        // 128: occ 0.498 → (0.498 − 0.196)/(0.65 − 0.196)·100 = 66.5 → 67 (rint, ties to even).
        let occ: f64 = 1.0 - 128.0 / 255.0;
        let expect = ((occ - 0.196) / (0.65 - 0.196) * 100.0).round_ties_even() as i8;
        assert_eq!(g.cells[4], expect);
        assert_eq!(expect, 67);
        let raw = load_map(&yaml("mode: raw\n"), &pgm()).unwrap();
        // Raw: the grey value itself, unknown above 100.
        assert_eq!(&raw.cells[0..3], &[UNKNOWN, UNKNOWN, 10]);
        assert_eq!(&raw.cells[3..6], &[0, UNKNOWN, UNKNOWN]);
    }

    #[test]
    fn ascii_pgm_and_16_bit_maxval() {
        let g = load_map(&yaml(""), b"P2\n3 2\n255\n0 128 254\n205 255 10\n").unwrap();
        assert_eq!(g, load_map(&yaml(""), &pgm()).unwrap());
        // maxval 1000: 0 → black, 1000 → white.
        let mut b = b"P5 2 1 1000\n".to_vec();
        b.extend_from_slice(&[0, 0, 0x03, 0xE8]);
        assert_eq!(load_map(&yaml(""), &b).unwrap().cells, vec![OCCUPIED, FREE]);
    }

    #[test]
    fn png_with_alpha_in_trinary_and_scale() {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, 2, 1);
        enc.set_color(png::ColorType::Rgba);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().unwrap();
        // An opaque black pixel and a transparent white one.
        w.write_image_data(&[0, 0, 0, 255, 255, 255, 255, 0]).unwrap();
        w.finish().unwrap();
        // Trinary averages alpha in: black+opaque → 63.75/255 → occ 0.75 → occupied;
        // white+transparent → 191.25/255 → occ 0.25 → unknown.
        assert_eq!(load_map(&yaml(""), &out).unwrap().cells, vec![OCCUPIED, UNKNOWN]);
        // Scale: a transparent pixel is unknown; black opaque is occupied.
        assert_eq!(load_map(&yaml("mode: scale\n"), &out).unwrap().cells, vec![OCCUPIED, UNKNOWN]);
    }

    #[test]
    fn save_then_load_round_trips() {
        let mut g = OccupancyGrid::filled(4, 3, 0.1, Se2::new(1.5, -2.0, 0.0), FREE);
        g.set(0, 0, OCCUPIED);
        g.set(3, 2, UNKNOWN);
        g.set(1, 2, OCCUPIED);
        let (y, img) = save_map(&g, MapMode::Trinary, 0.65, 0.25, "m.pgm").unwrap();
        let back = load_map(&MapYaml::parse(&y).unwrap(), &img).unwrap();
        assert_eq!(back, g);
        // With ROS 1's 0.196 the conventional 205 is kept.
        let (_, img) = save_map(&g, MapMode::Trinary, 0.65, 0.196, "m.pgm").unwrap();
        // The image's first row is the grid's top row: cell (3, 2) is its last pixel.
        let first_row = img.len() - 4 * 3;
        assert_eq!(img[first_row + 3], 205, "the top-right cell (3, 2) is unknown");
        // Scale keeps graded values (to within the 8-bit quantisation) and unknown via alpha.
        g.set(2, 1, 40);
        let (y, img) = save_map(&g, MapMode::Scale, 0.65, 0.25, "m.png").unwrap();
        let back = load_map(&MapYaml::parse(&y).unwrap(), &img).unwrap();
        assert_eq!(back.get(3, 2), Some(UNKNOWN));
        assert_eq!(back.get(0, 0), Some(OCCUPIED));
        assert_eq!(back.get(1, 1), Some(FREE));
        let graded = back.get(2, 1).unwrap();
        assert!((1..=99).contains(&graded), "{graded}");
    }

    #[test]
    fn bad_metadata_and_images_are_errors() {
        assert!(matches!(
            MapYaml::parse(
                "image: m.pgm\nresolution: 0\norigin: [0,0,0]\noccupied_thresh: 0.65\nfree_thresh: 0.2\n"
            ),
            Err(MapError::Invalid { key: "resolution", .. })
        ));
        assert!(matches!(
            MapYaml::parse(
                "image: m.pgm\nresolution: 0.05\norigin: [0,0]\noccupied_thresh: 0.65\nfree_thresh: 0.2\n"
            ),
            Err(MapError::Invalid { key: "origin", .. })
        ));
        assert!(matches!(
            MapYaml::parse(
                "image: m.pgm\nresolution: 0.05\norigin: [0,0,0]\noccupied_thresh: 0.2\nfree_thresh: 0.65\n"
            ),
            Err(MapError::Invalid { key: "free_thresh", .. })
        ));
        assert!(matches!(MapYaml::parse("resolution: [\n"), Err(MapError::Yaml(_))));
        let y = yaml("");
        assert!(load_map(&y, b"P5 3 2 255\n\x00").is_err(), "short pixel data");
        assert!(load_map(&y, b"GIF89a").is_err());
        assert!(load_map(&y, b"\x89PNG\r\n\x1a\nbroken").is_err());
        assert!(load_map(&y, b"P5 0 2 255\n").is_err());
    }
}
