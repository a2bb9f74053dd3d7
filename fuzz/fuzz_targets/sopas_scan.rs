//! Fuzz the LMDscandata decoder in both dialects, the robot-unit conversion and the capture-file
//! decoder: arbitrary bytes must never panic.
#![no_main]

use amr_drivers::sopas::{Dialect, Scan, ScanTelegram, decode_capture};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    for dialect in [Dialect::ColaA, Dialect::ColaB] {
        if let Ok(t) = ScanTelegram::decode_args(dialect, data) {
            let _ = Scan::from_telegram(&t);
        }
    }
    let _ = decode_capture(data);
});
