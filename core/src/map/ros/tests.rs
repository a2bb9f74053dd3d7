//! Tests of ROS map loading and saving: nav2's thresholds and modes, PGM and PNG, bad or forged input.

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
        prop_oneof![Just(D::One), Just(D::Two), Just(D::Four), Just(D::Eight)].prop_map(|d| (C::Indexed, d)),
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
