//! Fuzz the map loader: `load_map` on arbitrary image bytes (PGM and PNG), and `MapYaml::parse` on
//! arbitrary YAML. Neither may panic, and no header may make it allocate more than its data can fill.
//!
//! The first byte chooses (bits 0–1) what the rest is:
//! - 0: the image file as it is;
//! - 1: a PGM after the magic, "P5" or "P2" by bit 2;
//! - 2: a PNG after the signature, each chunk's CRC rewritten to match so the decoder reads on;
//! - 3: a map YAML, a NUL byte, then the image file (CRCs rewritten if it is a PNG); the image is
//!   loaded with the YAML if it parses.
//!
//! and (bits 4–5) the mode, (bit 6) `negate` of the YAML the images of 0–2 are loaded with.
#![no_main]

use amr_core::map::{MapYaml, load_map};
use libfuzzer_sys::fuzz_target;

const PNG_SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";

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

/// Rewrite the CRC of every whole chunk after the signature.
fn fix_crcs(png: &mut [u8]) {
    let mut at = PNG_SIGNATURE.len();
    while let Some(len) = png.get(at..at + 4) {
        let len = u32::from_be_bytes([len[0], len[1], len[2], len[3]]) as usize;
        let Some(end) = at.checked_add(8).and_then(|e| e.checked_add(len)) else { return };
        let Some(crc_at) = png.get(at + 4..end).map(crc32) else { return };
        let Some(slot) = png.get_mut(end..end + 4) else { return };
        slot.copy_from_slice(&crc_at.to_be_bytes());
        at = end + 4;
    }
}

fn map_yaml(selector: u8) -> MapYaml {
    let mode = ["trinary", "scale", "raw", "trinary"][usize::from(selector >> 4 & 3)];
    let negate = selector >> 6 & 1;
    let text = format!(
        "image: m.pgm\nresolution: 0.05\norigin: [-1.0, 2.0, 0.0]\noccupied_thresh: 0.65\n\
         free_thresh: 0.196\nmode: {mode}\nnegate: {negate}\n"
    );
    match MapYaml::parse(&text) {
        Ok(y) => y,
        Err(e) => panic!("the harness's YAML is refused: {e}"),
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&selector, rest)) = data.split_first() else { return };
    match selector & 3 {
        0 => {
            let _ = load_map(&map_yaml(selector), rest);
        }
        1 => {
            let magic: &[u8] = if selector & 4 == 0 { b"P5" } else { b"P2" };
            let _ = load_map(&map_yaml(selector), &[magic, rest].concat());
        }
        2 => {
            let mut png = [PNG_SIGNATURE, rest].concat();
            fix_crcs(&mut png);
            let _ = load_map(&map_yaml(selector), &png);
        }
        _ => {
            let split = rest.iter().position(|b| *b == 0).unwrap_or(rest.len());
            let (text, image) = rest.split_at(split);
            let mut image = image.get(1..).unwrap_or_default().to_vec();
            if image.starts_with(PNG_SIGNATURE) {
                fix_crcs(&mut image);
            }
            if let Ok(yaml) = MapYaml::parse(&String::from_utf8_lossy(text)) {
                let _ = load_map(&yaml, &image);
            }
        }
    }
});
