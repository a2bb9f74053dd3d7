//! Fuzz the socketcand element codec: arbitrary bytes, split where the input says, through the
//! element decoder, and the raw input through `parse_element`. Nothing may panic, and every frame
//! or send element must round-trip through its encoder.
//! Run with `cargo fuzz run socketcand_lines` from `fuzz/`.
#![no_main]

use amr_drivers::canopen::transport::socketcand::{
    Element, ElementDecoder, encode_frame, encode_send, parse_element,
};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|input: &[u8]| {
    let (head, bytes) = input.split_at(input.len().min(1));
    let split = head.first().copied().map_or(0, usize::from).min(bytes.len());
    let mut decoder = ElementDecoder::new();
    let (a, b) = bytes.split_at(split);
    for piece in [a, b] {
        decoder.push(piece);
        // Each call consumes input or returns None: bounded.
        while let Some(result) = decoder.next_element() {
            match result {
                Ok(Element::Send(frame)) => {
                    let line = encode_send(&frame);
                    let inner = &line[1..line.len() - 1];
                    assert_eq!(parse_element(inner), Ok(Element::Send(frame)));
                }
                Ok(Element::Frame { frame, secs, usecs }) if usecs < 1_000_000 => {
                    let line = encode_frame(&frame, secs, usecs);
                    let inner = &line[1..line.len() - 1];
                    assert_eq!(parse_element(inner), Ok(Element::Frame { frame, secs, usecs }));
                }
                _ => {}
            }
        }
    }
    let _ = parse_element(&String::from_utf8_lossy(bytes));
});
