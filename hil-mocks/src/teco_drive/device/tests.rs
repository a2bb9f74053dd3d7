//! Tests of the mock TECO drive: the PDO remap rules and the reaction to master loss (0x6007).

use amr_drivers::canopen::sdo::{expedited_download, upload_request};

use super::*;

fn drive() -> (TecoDrive, Instant) {
    let now = Instant::now();
    let mut d = TecoDrive::new(TecoDriveConfig::new(3), now);
    assert_eq!(d.poll_transmit(now), Some(NmtState::BootUp.heartbeat(3)));
    (d, now)
}

fn sdo(d: &mut TecoDrive, now: Instant, body: [u8; 8]) -> [u8; 8] {
    d.handle_frame(now, &Cob::SdoRequest(3).frame(&body));
    let f = d.poll_transmit(now).unwrap();
    assert_eq!(f.cob(), Cob::SdoResponse(3));
    f.data().try_into().unwrap()
}

fn abort_code(r: [u8; 8]) -> Option<u32> {
    (r[0] == 0x80).then(|| u32::from_le_bytes([r[4], r[5], r[6], r[7]]))
}

#[test]
fn teco_device_enforces_the_remap_rules() {
    let (mut d, now) = drive();
    let map = |sub, raw: u32| expedited_download(ObjectAddr::new(0x1A00, sub), &raw.to_le_bytes()).unwrap();
    // TPDO1 is valid: its mapping may not change.
    assert_eq!(abort_code(sdo(&mut d, now, map(1, 0x606C_0020))), Some(AbortCode::DEVICE_STATE.0));
    // Invalidate, clear, then an object that cannot go into a TPDO, then a good one.
    let cob =
        expedited_download(ObjectAddr::new(0x1800, 1), &(0x183u32 | COB_ID_INVALID).to_le_bytes()).unwrap();
    assert_eq!(sdo(&mut d, now, cob)[0], 0x60);
    assert_eq!(sdo(&mut d, now, expedited_download(ObjectAddr::new(0x1A00, 0), &[0]).unwrap())[0], 0x60);
    assert_eq!(abort_code(sdo(&mut d, now, map(1, 0x6040_0010))), Some(0x0604_0041));
    assert_eq!(sdo(&mut d, now, map(1, 0x606C_0020))[0], 0x60);
    // Read-only, missing object, wrong length.
    let ro = expedited_download(ObjectAddr::new(0x6041, 0), &[0, 0]).unwrap();
    assert_eq!(abort_code(sdo(&mut d, now, ro)), Some(AbortCode::READ_ONLY.0));
    assert_eq!(
        abort_code(sdo(&mut d, now, upload_request(ObjectAddr::new(0x2345, 0)))),
        Some(AbortCode::NO_OBJECT.0)
    );
    let short = expedited_download(ObjectAddr::new(0x6083, 0), &[1, 2]).unwrap();
    assert_eq!(abort_code(sdo(&mut d, now, short)), Some(AbortCode::LENGTH.0));
    // The injected abort answers the next request to that index once.
    d.inject(now, Fault::SdoAbort { index: 0x1000, code: 0x0800_0000 });
    assert_eq!(abort_code(sdo(&mut d, now, upload_request(ObjectAddr::new(0x1000, 0)))), Some(0x0800_0000));
    assert_eq!(sdo(&mut d, now, upload_request(ObjectAddr::new(0x1000, 0)))[4..], [0x92, 0x01, 0x02, 0x00]);
}

/// Enable by SDO writes of the controlword, then let the master's heartbeat lapse.
fn comm_loss(reaction: i16) -> (DriveSnapshot, Vec<CanFrame>) {
    let (mut d, mut now) = drive();
    for (index, sub, data) in [
        (0x6007u16, 0u8, reaction.to_le_bytes().to_vec()),
        (0x1016, 1, ((127u32 << 16) | 200).to_le_bytes().to_vec()),
        (0x6060, 0, vec![3]),
        (0x6040, 0, vec![0x06, 0]),
        (0x6040, 0, vec![0x07, 0]),
        (0x6040, 0, vec![0x0F, 0]),
    ] {
        assert_eq!(
            sdo(&mut d, now, expedited_download(ObjectAddr::new(index, sub), &data).unwrap())[0],
            0x60
        );
    }
    assert_eq!(d.snapshot().state, State402::OperationEnabled);
    d.handle_frame(now, &NmtState::Operational.heartbeat(127));
    now += Duration::from_millis(199);
    d.handle_timeout(now);
    assert_eq!(d.snapshot().state, State402::OperationEnabled, "not yet");
    now += Duration::from_millis(1);
    d.handle_timeout(now);
    let mut out = Vec::new();
    while let Some(f) = d.poll_transmit(now) {
        out.push(f);
    }
    (d.snapshot(), out)
}

#[test]
fn teco_device_reacts_to_master_loss_per_0x6007() {
    let emcy_8130 =
        |out: &[CanFrame]| out.iter().any(|f| Emcy::decode(f).is_some_and(|(_, e)| e.code == 0x8130));
    let (s, out) = comm_loss(1);
    assert_eq!(s.state, State402::Fault);
    assert!(emcy_8130(&out));
    let (s, out) = comm_loss(2);
    assert_eq!(s.state, State402::SwitchOnDisabled);
    assert!(emcy_8130(&out));
    let (s, _) = comm_loss(3);
    assert_eq!(s.state, State402::QuickStopActive);
    let (s, out) = comm_loss(0);
    assert_eq!((s.state, s.master_losses), (State402::OperationEnabled, 1));
    assert!(emcy_8130(&out));
}
