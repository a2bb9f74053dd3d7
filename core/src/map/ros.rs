//! ROS map_server maps: the YAML metadata and the PGM/PNG image, loaded and saved with nav2's rules
//! (nav2_map_server `map_io.cpp`): grey = mean of the colour
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
        y.check()?;
        Ok(y)
    }

    /// The rules `parse` applies (the fields are public, so `load_map` applies them again).
    fn check(&self) -> Result<(), MapError> {
        let bad = |key, rule: String| Err(MapError::Invalid { key, rule });
        if self.image.trim().is_empty() {
            return bad("image", "must name the image file".into());
        }
        if !(self.resolution.is_finite() && self.resolution > 0.0) {
            return bad("resolution", format!("must be > 0 m per cell (got {})", self.resolution));
        }
        if self.origin.len() != 3 || self.origin.iter().any(|v| !v.is_finite()) {
            return bad("origin", format!("must be [x, y, yaw] with finite values (got {:?})", self.origin));
        }
        if !(0.0..=1.0).contains(&self.free_thresh) || !(0.0..=1.0).contains(&self.occupied_thresh) {
            return bad("free_thresh", "thresholds must lie in [0, 1]".into());
        }
        if self.free_thresh >= self.occupied_thresh {
            return bad(
                "free_thresh",
                format!("must be below occupied_thresh ({} >= {})", self.free_thresh, self.occupied_thresh),
            );
        }
        Ok(())
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
        match self.origin[..] {
            [x, y, theta] => Se2::new(x, y, theta),
            // `check` refuses any other length.
            _ => Se2::new(0.0, 0.0, 0.0),
        }
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

fn image_err(message: String) -> MapError {
    MapError::Image(message)
}

/// A header token for an error message, shortened if long.
fn token_text(token: &[u8]) -> String {
    let text = String::from_utf8_lossy(token.get(..32).unwrap_or(token));
    if token.len() > 32 { format!("{text}… ({} digits)", token.len()) } else { text.into_owned() }
}

fn decode_pgm(bytes: &[u8]) -> Result<Image, MapError> {
    let binary = match bytes.get(..2) {
        Some(b"P5") => true,
        Some(b"P2") => false,
        _ => return Err(image_err("not a PGM (P2/P5) file".into())),
    };
    // Header: magic, width, height, maxval; whitespace and #-comments between tokens.
    let mut pos = 2;
    let mut fields = [0usize; 3];
    for (field, name) in fields.iter_mut().zip(["width", "height", "maxval"]) {
        loop {
            match bytes.get(pos) {
                Some(b'#') => {
                    while bytes.get(pos).is_some_and(|c| *c != b'\n') {
                        pos += 1;
                    }
                }
                Some(c) if c.is_ascii_whitespace() => pos += 1,
                Some(_) => break,
                None => return Err(image_err(format!("PGM header ends before its {name}"))),
            }
        }
        let start = pos;
        while bytes.get(pos).is_some_and(u8::is_ascii_digit) {
            pos += 1;
        }
        let token = bytes.get(start..pos).unwrap_or_default();
        if token.is_empty() {
            return Err(image_err(format!("PGM header {name} is not a number")));
        }
        *field = std::str::from_utf8(token)
            .ok()
            .and_then(|t| t.parse().ok())
            .ok_or_else(|| image_err(format!("PGM header {name} {} is too large", token_text(token))))?;
    }
    let [width, height, maxval] = fields;
    if width == 0 || height == 0 {
        return Err(image_err(format!("PGM header declares {width} x {height} pixels")));
    }
    if maxval == 0 || maxval > 65535 {
        return Err(image_err(format!("PGM header maxval {maxval} is outside 1–65535")));
    }
    let scale = |v: usize| ((v.min(maxval) * 255 + maxval / 2) / maxval) as u8;
    let data: Vec<u8> = if binary {
        // One whitespace byte ends the header.
        let body = bytes.get(pos + 1..).unwrap_or_default();
        let bpp = if maxval < 256 { 1 } else { 2 };
        // The size is checked against the data before anything is allocated.
        let pixels = width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(bpp))
            .and_then(|len| body.get(..len))
            .ok_or_else(|| {
                image_err(format!(
                    "PGM header declares {width} x {height} pixels of {bpp} byte{} (maxval {maxval}); \
                     the file holds {} bytes of pixel data",
                    if bpp == 1 { "" } else { "s" },
                    body.len()
                ))
            })?;
        if bpp == 1 {
            pixels.iter().map(|v| scale(usize::from(*v))).collect()
        } else {
            pixels.chunks_exact(2).map(|c| scale(usize::from(u16::from_be_bytes([c[0], c[1]])))).collect()
        }
    } else {
        let body = bytes.get(pos..).unwrap_or_default();
        // Every value takes at least one byte.
        let n = width.checked_mul(height).filter(|n| *n <= body.len()).ok_or_else(|| {
            image_err(format!(
                "PGM header declares {width} x {height} pixels; the file holds {} bytes of ASCII pixel data",
                body.len()
            ))
        })?;
        let text = std::str::from_utf8(body).map_err(|_| image_err("PGM pixel data is not ASCII".into()))?;
        let mut values = Vec::with_capacity(n);
        for token in text
            .lines()
            .map(|l| l.split('#').next().unwrap_or(""))
            .flat_map(str::split_ascii_whitespace)
            .take(n)
        {
            let v = token.parse::<usize>().map_err(|_| {
                image_err(format!("PGM pixel value {} is not a number", token_text(token.as_bytes())))
            })?;
            values.push(scale(v));
        }
        if values.len() < n {
            return Err(image_err(format!(
                "PGM header declares {width} x {height} pixels; the file holds {} values",
                values.len()
            )));
        }
        values
    };
    Ok(Image { width, height, channels: 1, data })
}

/// Deflate's largest expansion: a 258-byte match coded in 2 bits gives 1032 bytes per input byte.
const DEFLATE_MAX_RATIO: u128 = 1032;

/// The bytes in a PNG's IDAT chunks (the compressed image), as far as its chunks can be walked.
fn png_idat_bytes(bytes: &[u8]) -> usize {
    let mut total = 0usize;
    let mut rest = bytes.get(8..).unwrap_or_default();
    // Each chunk: length (4, big-endian), type (4), data, CRC (4).
    while let Some((head, tail)) = rest.split_first_chunk::<8>() {
        let [l0, l1, l2, l3, kind @ ..] = *head;
        let len = usize::try_from(u32::from_be_bytes([l0, l1, l2, l3])).unwrap_or(usize::MAX);
        if &kind == b"IDAT" {
            total = total.saturating_add(len.min(tail.len()));
        }
        rest = tail.get(len.saturating_add(4)..).unwrap_or_default();
    }
    total
}

fn decode_png(bytes: &[u8]) -> Result<Image, MapError> {
    let err = |e: png::DecodingError| image_err(format!("PNG: {e}"));
    let mut decoder = png::Decoder::new(Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::normalize_to_color8());
    let header = decoder.read_header_info().map_err(err)?;
    // The pixel data the header declares must fit in what the compressed data can inflate to,
    // before the output buffer (sized by the header) is allocated.
    let (w, h) = (header.width, header.height);
    let pixel_bytes = u128::from(w) * u128::from(h) * header.bits_per_pixel() as u128 / 8;
    let idat = png_idat_bytes(bytes);
    let most = idat as u128 * DEFLATE_MAX_RATIO;
    if pixel_bytes > most {
        return Err(image_err(format!(
            "PNG header declares {w} x {h} pixels ({pixel_bytes} bytes of pixel data); \
             the file's {idat} bytes of IDAT data inflate to at most {most}"
        )));
    }
    let mut reader = decoder.read_info().map_err(err)?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| image_err(format!("PNG header declares {w} x {h} pixels, too many to hold")))?;
    let mut data = vec![0; size];
    let info = reader.next_frame(&mut data).map_err(err)?;
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err(image_err("PNG: palette was not expanded".into())),
    };
    let (width, height) = (info.width as usize, info.height as usize);
    let len = width
        .checked_mul(height)
        .and_then(|n| n.checked_mul(channels))
        .filter(|len| *len <= data.len())
        .ok_or_else(|| {
            image_err(format!(
                "PNG frame of {width} x {height} pixels of {channels} bytes does not fit its {} byte buffer",
                data.len()
            ))
        })?;
    data.truncate(len);
    Ok(Image { width, height, channels, data })
}

/// Load a map from its YAML text and its image file's bytes (PGM or PNG, by content).
pub fn load_map(yaml: &MapYaml, image_bytes: &[u8]) -> Result<OccupancyGrid, MapError> {
    yaml.check()?;
    let img =
        if image_bytes.starts_with(b"\x89PNG") { decode_png(image_bytes)? } else { decode_pgm(image_bytes)? };
    // The decoders guarantee these; checked again so that no index below can fail.
    let cells = img.width.checked_mul(img.height).filter(|n| {
        (1..=4).contains(&img.channels)
            && n.checked_mul(img.channels).is_some_and(|len| len <= img.data.len())
    });
    let Some(cells) = cells else {
        return Err(image_err(format!(
            "{} x {} pixels of {} channels do not fit the {} bytes decoded",
            img.width,
            img.height,
            img.channels,
            img.data.len()
        )));
    };
    let mut grid = OccupancyGrid::filled(img.width, img.height, yaml.resolution, yaml.origin_pose(), UNKNOWN);
    let (occ_t, free_t, negate) = (yaml.occupied_thresh, yaml.free_thresh, yaml.negate());
    for (k, px) in img.data.chunks_exact(img.channels).take(cells).enumerate() {
        let (x, y) = (k % img.width, k / img.width);
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
    use proptest::collection;
    use proptest::prelude::*;

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

    /// The error text of a load that must fail.
    fn load_err(image: &[u8]) -> String {
        match load_map(&yaml(""), image) {
            Ok(g) => panic!("loaded a {}×{} grid", g.width, g.height),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn pgm_16_bit_huge_header_is_refused() {
        let mut b = b"P5 4294967295 4294967295 65535\n".to_vec();
        b.extend_from_slice(&[7; 12]);
        let e = load_err(&b);
        assert!(e.contains("declares 4294967295 x 4294967295 pixels of 2 bytes"), "{e}");
        assert!(e.contains("the file holds 12 bytes of pixel data"), "{e}");
    }

    #[test]
    fn pgm_8_bit_huge_header_is_refused() {
        let mut b = b"P5 4294967295 4294967295 255\n".to_vec();
        b.extend_from_slice(&[7; 12]);
        let e = load_err(&b);
        assert!(e.contains("declares 4294967295 x 4294967295 pixels of 1 byte"), "{e}");
        assert!(e.contains("the file holds 12 bytes of pixel data"), "{e}");
    }

    #[test]
    fn pgm_ascii_huge_header_is_refused() {
        let e = load_err(b"P2 1000000 1000000 255\n0 128 254\n");
        assert!(e.contains("declares 1000000 x 1000000 pixels"), "{e}");
        assert!(e.contains("the file holds 11 bytes of ASCII pixel data"), "{e}");
        // Enough bytes for the pixel count, but not enough values.
        let e = load_err(b"P2 3 2 255\n0 128 254          \n");
        assert!(e.contains("declares 3 x 2 pixels; the file holds 3 values"), "{e}");
    }

    #[test]
    fn pgm_size_overflowing_usize_is_refused() {
        let m = usize::MAX;
        for magic in ["P5", "P2"] {
            for (w, h) in [(m, m), (m, 2), (2, m)] {
                let e = load_err(format!("{magic} {w} {h} 255\n0 1 2 3\n").as_bytes());
                assert!(e.contains(&format!("declares {w} x {h} pixels")), "{e}");
            }
        }
        // A number past usize is named as such.
        let e = load_err(b"P5 99999999999999999999999 1 255\n0");
        assert!(e.contains("width") && e.contains("99999999999999999999999"), "{e}");
    }

    /// CRC-32 (ISO-HDLC, as PNG chunks use).
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for b in bytes {
            crc ^= u32::from(*b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
            }
        }
        !crc
    }

    /// A valid 1×1 PNG of `colour` whose IHDR then claims `width × height` (CRC recomputed).
    fn forged_png(width: u32, height: u32, colour: png::ColorType, depth: png::BitDepth) -> Vec<u8> {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, 1, 1);
        enc.set_color(colour);
        enc.set_depth(depth);
        if colour == png::ColorType::Indexed {
            enc.set_palette(vec![0, 0, 0]);
        }
        let mut w = enc.write_header().unwrap();
        w.write_image_data(&vec![0; (colour.samples() * depth as usize).div_ceil(8)]).unwrap();
        w.finish().unwrap();
        // Signature (8), IHDR length (4), "IHDR" (4), width (4), height (4), 5 more bytes, CRC.
        assert_eq!(&out[12..16], b"IHDR");
        out[16..20].copy_from_slice(&width.to_be_bytes());
        out[20..24].copy_from_slice(&height.to_be_bytes());
        let crc = crc32(&out[12..29]);
        out[29..33].copy_from_slice(&crc.to_be_bytes());
        out
    }

    #[test]
    fn forged_png_decodes_when_its_header_is_honest() {
        let b = forged_png(1, 1, png::ColorType::Grayscale, png::BitDepth::Eight);
        assert_eq!(load_map(&yaml(""), &b).unwrap().cells, vec![OCCUPIED]);
    }

    #[test]
    fn png_huge_dimensions_are_refused() {
        let b = forged_png(100_000, 100_000, png::ColorType::Rgba, png::BitDepth::Eight);
        let e = load_err(&b);
        assert!(e.contains("PNG header declares 100000 x 100000 pixels"), "{e}");
        assert!(e.contains("bytes of IDAT data"), "{e}");
        // The largest dimensions PNG allows, at one bit per pixel.
        let b = forged_png(0x7FFF_FFFF, 0x7FFF_FFFF, png::ColorType::Grayscale, png::BitDepth::One);
        let e = load_err(&b);
        assert!(e.contains("declares 2147483647 x 2147483647 pixels"), "{e}");
    }

    #[test]
    fn highly_compressed_png_loads() {
        // A uniform image compresses close to deflate's limit; the size check must let it through.
        for (colour, depth, w, h) in [
            (png::ColorType::Grayscale, png::BitDepth::One, 4000, 1000),
            (png::ColorType::Grayscale, png::BitDepth::Eight, 1000, 1000),
        ] {
            let mut out = Vec::new();
            let mut enc = png::Encoder::new(&mut out, w, h);
            enc.set_color(colour);
            enc.set_depth(depth);
            enc.set_compression(png::Compression::High);
            let mut writer = enc.write_header().unwrap();
            let row = (w as usize * depth as usize).div_ceil(8);
            writer.write_image_data(&vec![0; row * h as usize]).unwrap();
            writer.finish().unwrap();
            let g = load_map(&yaml(""), &out).unwrap();
            assert_eq!((g.width, g.height), (w as usize, h as usize));
            assert!(g.cells.iter().all(|c| *c == OCCUPIED));
            assert!(
                out.len() * 200 < row * h as usize,
                "{} bytes for {} bytes of rows",
                out.len(),
                row * h as usize
            );
        }
    }

    #[test]
    fn load_map_checks_metadata_changed_after_parse() {
        let mut y = yaml("");
        y.resolution = f64::NAN;
        assert!(matches!(load_map(&y, &pgm()), Err(MapError::Invalid { key: "resolution", .. })));
        y.resolution = f64::INFINITY;
        assert!(matches!(load_map(&y, &pgm()), Err(MapError::Invalid { key: "resolution", .. })));
        let mut y = yaml("");
        y.origin = vec![0.0, 0.0];
        assert!(matches!(load_map(&y, &pgm()), Err(MapError::Invalid { key: "origin", .. })));
        y.origin = vec![0.0, f64::NEG_INFINITY, 0.0];
        assert!(matches!(load_map(&y, &pgm()), Err(MapError::Invalid { key: "origin", .. })));
        let mut y = yaml("");
        y.free_thresh = f64::NAN;
        assert!(matches!(load_map(&y, &pgm()), Err(MapError::Invalid { key: "free_thresh", .. })));
    }

    /// A map YAML in any mode, negated or not.
    fn any_yaml() -> impl Strategy<Value = MapYaml> {
        (prop_oneof![Just(""), Just("mode: scale\n"), Just("mode: raw\n")], any::<bool>())
            .prop_map(|(mode, negate)| yaml(&format!("{mode}negate: {negate}\n")))
    }

    /// Header numbers: small, at the u32 and usize limits, past usize, or any.
    fn header_number() -> impl Strategy<Value = u128> {
        prop_oneof![
            0u128..6,
            Just(u128::from(u32::MAX)),
            Just(usize::MAX as u128),
            Just(usize::MAX as u128 + 1),
            any::<u64>().prop_map(u128::from),
            any::<u128>(),
        ]
    }

    /// Pixel data: random bytes, or ASCII digits, spaces and comment marks.
    fn body() -> impl Strategy<Value = Vec<u8>> {
        let ascii = prop_oneof![Just(b' '), Just(b'\n'), Just(b'#'), b'0'..=b'9'];
        prop_oneof![collection::vec(any::<u8>(), 0..96), collection::vec(ascii, 0..96)]
    }

    /// Colour types with a bit depth PNG allows for each.
    fn png_format() -> impl Strategy<Value = (png::ColorType, png::BitDepth)> {
        use png::{BitDepth as D, ColorType as C};
        prop_oneof![
            prop_oneof![Just(D::One), Just(D::Two), Just(D::Four), Just(D::Eight), Just(D::Sixteen)]
                .prop_map(|d| (C::Grayscale, d)),
            prop_oneof![Just(D::One), Just(D::Two), Just(D::Four), Just(D::Eight)]
                .prop_map(|d| (C::Indexed, d)),
            prop_oneof![Just(C::Rgb), Just(C::GrayscaleAlpha), Just(C::Rgba)].prop_flat_map(|c| prop_oneof![
                Just(D::Eight),
                Just(D::Sixteen)
            ]
            .prop_map(move |d| (c, d))),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        /// Arbitrary bytes, as they are or behind a PGM or PNG signature, load or fail without
        /// panicking.
        #[test]
        fn load_map_never_panics_on_arbitrary_bytes(
            y in any_yaml(),
            prefix in prop_oneof![Just(&b""[..]), Just(&b"P5"[..]), Just(&b"P2"[..]), Just(&b"\x89PNG\r\n\x1a\n"[..])],
            rest in collection::vec(any::<u8>(), 0..256),
        ) {
            let _ = load_map(&y, &[prefix, &rest].concat());
        }

        /// Forged PGM headers (P5 and P2, any sizes and maxvals) over short bodies: refused
        /// unless the body holds the declared pixels, never a panic.
        #[test]
        fn load_map_never_panics_on_forged_pgm_headers(
            y in any_yaml(),
            binary in any::<bool>(),
            w in header_number(),
            h in header_number(),
            maxval in prop_oneof![0u128..3, Just(255u128), Just(256), Just(65535), Just(65536), header_number()],
            body in body(),
        ) {
            let magic = if binary { "P5" } else { "P2" };
            let mut b = format!("{magic} {w} {h} {maxval}\n").into_bytes();
            b.extend_from_slice(&body);
            if let Ok(g) = load_map(&y, &b) {
                prop_assert_eq!(g.cells.len() as u128, w * h);
                prop_assert!(g.cells.len() <= body.len());
            }
        }

        /// PNGs whose IHDR claims any size, in every format, with the image data cut or changed
        /// after the header.
        #[test]
        fn load_map_never_panics_on_forged_png_headers(
            y in any_yaml(),
            w in prop_oneof![1u32..8, any::<u32>()],
            h in prop_oneof![1u32..8, any::<u32>()],
            (colour, depth) in png_format(),
            cut in any::<prop::sample::Index>(),
            flip in any::<(prop::sample::Index, u8)>(),
        ) {
            let mut b = forged_png(w, h, colour, depth);
            let at = 33 + flip.0.index(b.len() - 33);
            b[at] ^= flip.1;
            b.truncate(33 + cut.index(b.len() - 32));
            let _ = load_map(&y, &b);
        }
    }
}
