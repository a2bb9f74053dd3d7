//! Fuzz the CANopen frame decoders: arbitrary (id, data) through every service decoder, the SDO
//! client's response handling and the SDO server's request handling. None may panic.
//! Run with `cargo fuzz run canopen_frames` from `fuzz/`.
#![no_main]

use std::time::{Duration, Instant};

use amr_drivers::canopen::cia402::State402;
use amr_drivers::canopen::emcy::Emcy;
use amr_drivers::canopen::frame::CanFrame;
use amr_drivers::canopen::nmt::{NmtCommand, NmtState};
use amr_drivers::canopen::pdo::{TPDO1_MAP, decode_tpdo1, decode_tpdo2, unpack};
use amr_drivers::canopen::sdo::{AbortCode, ObjectAddr, ObjectDictionary, SdoClient, SdoRequest, SdoServer};
use libfuzzer_sys::fuzz_target;

struct Od;

impl ObjectDictionary for Od {
    fn read(&mut self, addr: ObjectAddr) -> Result<Vec<u8>, AbortCode> {
        if addr.index == 0x1008 {
            Ok(vec![0x41; usize::from(addr.sub) * 3])
        } else {
            Err(AbortCode::NO_OBJECT)
        }
    }
    fn write(&mut self, _addr: ObjectAddr, _data: &[u8]) -> Result<(), AbortCode> {
        Ok(())
    }
}

fuzz_target!(|input: &[u8]| {
    let now = Instant::now();
    let mut client = SdoClient::new(1, Duration::from_millis(10));
    let mut server = SdoServer::new();
    let mut od = Od;
    // Records of 3 + up to 8 bytes: id (11 or 29 bits by the top bit), length, data.
    for (k, rec) in input.chunks(11).enumerate() {
        let [a, b, c, data @ ..] = rec else { continue };
        let raw = u32::from_le_bytes([*a, *b, *c, 0]);
        let extended = raw & 0x80_0000 != 0;
        let id = if extended { raw & 0x7F_FFFF } else { raw & 0x7FF };
        let Ok(frame) = CanFrame::with_id(id, extended, data) else { continue };
        let _ = frame.cob();
        let _ = NmtCommand::decode(&frame);
        let _ = NmtState::decode(&frame);
        let _ = Emcy::decode(&frame);
        let _ = decode_tpdo1(frame.data());
        let _ = decode_tpdo2(frame.data());
        let _ = unpack(&TPDO1_MAP, frame.data());
        if let Some((sw, _)) = decode_tpdo1(frame.data()) {
            let _ = State402::from_statusword(sw);
        }
        if client.is_idle() {
            let req = if k % 2 == 0 {
                SdoRequest::Upload(ObjectAddr::new(0x1008, 0))
            } else {
                SdoRequest::Download(ObjectAddr::new(0x2000, 0), data.to_vec())
            };
            let _ = client.start(now, req);
        }
        let _ = client.handle_response(now, frame.data());
        let _ = server.handle_request(frame.data(), &mut od);
    }
});
