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
mod tests;
