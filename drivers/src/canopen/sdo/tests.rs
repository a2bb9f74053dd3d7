//! Tests of the SDO codec, client and server: golden vectors, segmented transfers, timeouts, aborts.

use std::collections::HashMap;

use super::*;

#[derive(Default)]
struct Od(HashMap<ObjectAddr, Vec<u8>>);

impl ObjectDictionary for Od {
    fn read(&mut self, addr: ObjectAddr) -> Result<Vec<u8>, AbortCode> {
        self.0.get(&addr).cloned().ok_or(AbortCode::NO_OBJECT)
    }
    fn write(&mut self, addr: ObjectAddr, data: &[u8]) -> Result<(), AbortCode> {
        self.0.insert(addr, data.to_vec());
        Ok(())
    }
}

fn exchange(client: &mut SdoClient, server: &mut SdoServer, od: &mut Od, req: SdoRequest) -> SdoStep {
    let now = Instant::now();
    let mut body = client.start(now, req);
    for _ in 0..1000 {
        let resp = server.handle_request(&body, od).unwrap();
        match client.handle_response(now, &resp).unwrap() {
            SdoStep::Send(b) => body = b,
            done @ SdoStep::Done { .. } => return done,
        }
    }
    panic!("transfer did not finish");
}

#[test]
fn canopen_sdo_golden_vectors() {
    // python-canopen test_sdo: upload 0x1018:01.
    assert_eq!(upload_request(ObjectAddr::new(0x1018, 1)), [0x40, 0x18, 0x10, 0x01, 0, 0, 0, 0]);
    // python-canopen test: 0x1017 := 4000 ms is 2B 17 10 00 A0 0F 00 00.
    assert_eq!(
        expedited_download(ObjectAddr::new(0x1017, 0), &4000u16.to_le_bytes()),
        Some([0x2B, 0x17, 0x10, 0x00, 0xA0, 0x0F, 0x00, 0x00])
    );
    // 0x6060 := 3 (one byte): 2F 60 60 00 03.
    assert_eq!(expedited_download(ObjectAddr::new(0x6060, 0), &[3]).unwrap()[..5], [0x2F, 0x60, 0x60, 0, 3]);
    let mut c = SdoClient::new(1, Duration::from_millis(500));
    let now = Instant::now();
    c.start(now, SdoRequest::Upload(ObjectAddr::new(0x1018, 1)));
    let step = c.handle_response(now, &[0x43, 0x18, 0x10, 0x01, 0x04, 0, 0, 0]).unwrap();
    assert_eq!(step, SdoStep::Done { result: Ok(SdoResult::Read(vec![4, 0, 0, 0])), abort: None });
    // Abort 0x06090011 and its name.
    c.start(now, SdoRequest::Upload(ObjectAddr::new(0x1018, 1)));
    let step = c.handle_response(now, &[0x80, 0x18, 0x10, 0x01, 0x11, 0x00, 0x09, 0x06]).unwrap();
    assert_eq!(step, SdoStep::Done { result: Err(SdoFailure::Aborted(AbortCode(0x0609_0011))), abort: None });
    assert_eq!(AbortCode(0x0609_0011).name(), "Sub-index does not exist");
    // DLC < 8 reply (python-canopen: 4F 00 14 02 FE).
    c.start(now, SdoRequest::Upload(ObjectAddr::new(0x1400, 2)));
    let step = c.handle_response(now, &[0x4F, 0x00, 0x14, 0x02, 0xFE]).unwrap();
    assert_eq!(step, SdoStep::Done { result: Ok(SdoResult::Read(vec![0xFE])), abort: None });
}

#[test]
fn canopen_sdo_segmented_both_ways() {
    let mut od = Od::default();
    let mut client = SdoClient::new(3, Duration::from_millis(100));
    let mut server = SdoServer::new();
    let addr = ObjectAddr::new(0x1008, 0);
    let text = b"TECO mock drive, a name longer than seven bytes".to_vec();
    let step = exchange(&mut client, &mut server, &mut od, SdoRequest::Download(addr, text.clone()));
    assert_eq!(step, SdoStep::Done { result: Ok(SdoResult::Written), abort: None });
    assert_eq!(od.0.get(&addr), Some(&text));
    let step = exchange(&mut client, &mut server, &mut od, SdoRequest::Upload(addr));
    assert_eq!(step, SdoStep::Done { result: Ok(SdoResult::Read(text)), abort: None });
    // Exactly 7 and 14 bytes (segment boundaries), and expedited 4.
    for n in [4usize, 5, 7, 14] {
        let v: Vec<u8> = (0..n as u8).collect();
        exchange(&mut client, &mut server, &mut od, SdoRequest::Download(addr, v.clone()));
        let step = exchange(&mut client, &mut server, &mut od, SdoRequest::Upload(addr));
        assert_eq!(step, SdoStep::Done { result: Ok(SdoResult::Read(v)), abort: None }, "{n} bytes");
    }
    let step = exchange(&mut client, &mut server, &mut od, SdoRequest::Upload(ObjectAddr::new(0x2000, 0)));
    assert_eq!(step, SdoStep::Done { result: Err(SdoFailure::Aborted(AbortCode::NO_OBJECT)), abort: None });
}

#[test]
fn canopen_sdo_timeout_and_bad_toggle_abort() {
    let now = Instant::now();
    let mut c = SdoClient::new(1, Duration::from_millis(500));
    c.start(now, SdoRequest::Upload(ObjectAddr::new(0x6041, 0)));
    assert_eq!(c.handle_timeout(now + Duration::from_millis(499)), None);
    let step = c.handle_timeout(now + Duration::from_millis(500)).unwrap();
    assert_eq!(
        step,
        SdoStep::Done {
            result: Err(SdoFailure::Timeout),
            abort: Some(abort_bytes(ObjectAddr::new(0x6041, 0), AbortCode::TIMEOUT))
        }
    );
    assert!(c.is_idle());
    // Segmented upload whose first segment has the wrong toggle.
    c.start(now, SdoRequest::Upload(ObjectAddr::new(0x1008, 0)));
    let step = c.handle_response(now, &[0x41, 0x08, 0x10, 0, 20, 0, 0, 0]).unwrap();
    assert_eq!(step, SdoStep::Send([0x60, 0, 0, 0, 0, 0, 0, 0]));
    let step = c.handle_response(now, &[0x10, 1, 2, 3, 4, 5, 6, 7]).unwrap();
    assert!(matches!(step, SdoStep::Done { result: Err(SdoFailure::Protocol(AbortCode::TOGGLE)), .. }));
    // A stale response for another object is ignored while an initiate is pending.
    c.start(now, SdoRequest::Upload(ObjectAddr::new(0x6041, 0)));
    assert_eq!(c.handle_response(now, &[0x43, 0x00, 0x10, 0, 0x92, 0x01, 0x02, 0]), None);
    assert_eq!(c.handle_response(now, &[0x80, 0x00, 0x10, 0, 0, 0, 0x04, 0x05]), None);
    let step = c.handle_response(now, &[0x4B, 0x41, 0x60, 0, 0x37, 0x02, 0, 0]).unwrap();
    assert_eq!(step, SdoStep::Done { result: Ok(SdoResult::Read(vec![0x37, 0x02])), abort: None });
    // A response with nothing in flight is ignored.
    assert_eq!(c.handle_response(now, &[0x60, 0, 0, 0, 0, 0, 0, 0]), None);
}
