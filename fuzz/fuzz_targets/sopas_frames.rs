//! Fuzz the SOPAS stream framer and the reply/command decoders: arbitrary bytes, fed in pieces
//! whose sizes come from the input itself, must never panic.
#![no_main]

use amr_drivers::sopas::{Command, Framer, Reply};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&step, bytes)) = data.split_first() else { return };
    let step = usize::from(step).max(1);
    let mut framer = Framer::new(4096);
    for piece in bytes.chunks(step) {
        framer.push(piece);
        while let Some(frame) = framer.next_frame() {
            if let Ok(frame) = frame {
                let _ = Reply::decode(frame.dialect, &frame.payload);
                let _ = Command::decode(frame.dialect, &frame.payload);
            }
        }
    }
});
