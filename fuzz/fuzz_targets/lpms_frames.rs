//! Fuzz the LPBUS decoders: arbitrary bytes through the frame decoder (split where the input says),
//! and every decoded frame (and the raw input) through the reply, command and sensor-data decoders.
//! None of them may panic. Run with `cargo fuzz run lpms_frames` from `fuzz/`.
#![no_main]

use amr_drivers::lpms::command::{Command, Reply};
use amr_drivers::lpms::data::{DataMode, OutputMask, decode_sensor_data};
use amr_drivers::lpms::frame::FrameDecoder;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|input: &[u8]| {
    // First byte: where to split the stream; next four: an output mask; bit 0 of the split byte: data mode.
    let (head, bytes) = input.split_at(input.len().min(5));
    let split = head.first().copied().map_or(0, usize::from);
    let mask = OutputMask(head.get(1..5).map_or(0, |b| u32::from_le_bytes([b[0], b[1], b[2], b[3]])));
    let mode = if split % 2 == 1 { DataMode::Int16 } else { DataMode::Float32 };

    let mut decoder = FrameDecoder::new();
    let (a, b) = bytes.split_at(split.min(bytes.len()));
    for piece in [a, b] {
        decoder.push(piece);
        // Each call consumes a byte or returns None, so this loop is bounded.
        while let Some(result) = decoder.next_frame() {
            if let Ok(frame) = result {
                let _ = Reply::from_frame(&frame);
                let _ = Command::from_frame(&frame);
                let _ = decode_sensor_data(&frame.data, mask, mode);
            }
        }
    }
    let _ = decode_sensor_data(bytes, mask, mode);
});
