//! Property tests: no CANopen or socketcand decoder panics on any input; encoders and decoders
//! round-trip; SDO transfers of any length arrive intact; odometry does not care where the 32-bit
//! counters wrap.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

mod canopen {
    use std::collections::HashMap;
    use std::time::{Duration, Instant};

    use amr_drivers::canopen::cia402::{State402, device_transition};
    use amr_drivers::canopen::diff_drive::{
        DiffDrive, DrivesConfig, Geometry, WheelDriveConfig, WheelOdometry,
    };
    use amr_drivers::canopen::emcy::Emcy;
    use amr_drivers::canopen::frame::{CanFrame, Cob};
    use amr_drivers::canopen::master::CommLossReaction;
    use amr_drivers::canopen::nmt::{NmtCommand, NmtState};
    use amr_drivers::canopen::pdo::{self, MapEntry};
    use amr_drivers::canopen::sdo::{
        AbortCode, ObjectAddr, ObjectDictionary, SdoClient, SdoRequest, SdoResult, SdoServer, SdoStep,
    };
    use amr_drivers::canopen::transport::socketcand::{
        Element, ElementDecoder, encode_frame, encode_send, parse_element,
    };
    use proptest::prelude::*;

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

    fn any_frame() -> impl Strategy<Value = CanFrame> {
        prop_oneof![
            (0u32..=0x7FF, proptest::collection::vec(any::<u8>(), 0..=8))
                .prop_map(|(id, d)| CanFrame::with_id(id, false, &d).unwrap()),
            (0u32..=0x1FFF_FFFF, proptest::collection::vec(any::<u8>(), 0..=8))
                .prop_map(|(id, d)| CanFrame::with_id(id, true, &d).unwrap()),
        ]
    }

    proptest! {
        #[test]
        fn canopen_prop_frame_decoders_never_panic(id in any::<u32>(), ext in any::<bool>(), data in proptest::collection::vec(any::<u8>(), 0..12)) {
            if let Ok(f) = CanFrame::with_id(id, ext, &data) {
                prop_assert!(f.data().len() <= 8);
                let _ = f.cob();
                let _ = NmtCommand::decode(&f);
                let _ = NmtState::decode(&f);
                let _ = Emcy::decode(&f);
                let _ = pdo::decode_tpdo1(f.data());
                let _ = pdo::decode_tpdo2(f.data());
                let _ = pdo::unpack(&pdo::TPDO1_MAP, f.data());
                if let Some((sw, _)) = pdo::decode_tpdo1(f.data()) {
                    let _ = State402::from_statusword(sw);
                }
            } else {
                let max = if ext { 0x1FFF_FFFF } else { 0x7FF };
                prop_assert!(data.len() > 8 || id > max);
            }
        }

        #[test]
        fn canopen_prop_sdo_endpoints_never_panic(bodies in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..9), 1..20)) {
            let now = Instant::now();
            let mut client = SdoClient::new(1, Duration::from_millis(5));
            let mut server = SdoServer::new();
            let mut od = Od::default();
            od.0.insert(ObjectAddr::new(0x1008, 0), vec![7; 30]);
            for (k, b) in bodies.iter().enumerate() {
                if client.is_idle() {
                    let req = if k % 2 == 0 { SdoRequest::Upload(ObjectAddr::new(0x1008, 0)) } else { SdoRequest::Download(ObjectAddr::new(0x2000, 0), b.clone()) };
                    let _ = client.start(now, req);
                }
                let _ = client.handle_response(now, b);
                let _ = server.handle_request(b, &mut od);
            }
        }

        #[test]
        fn canopen_prop_sdo_any_length_round_trips(data in proptest::collection::vec(any::<u8>(), 0..120), index in any::<u16>(), sub in any::<u8>()) {
            let now = Instant::now();
            let mut client = SdoClient::new(5, Duration::from_millis(5));
            let mut server = SdoServer::new();
            let mut od = Od::default();
            let addr = ObjectAddr::new(index, sub);
            for req in [SdoRequest::Download(addr, data.clone()), SdoRequest::Upload(addr)] {
                let mut body = client.start(now, req);
                let mut done = None;
                for _ in 0..100 {
                    let resp = server.handle_request(&body, &mut od).unwrap();
                    match client.handle_response(now, &resp).unwrap() {
                        SdoStep::Send(b) => body = b,
                        SdoStep::Done { result, .. } => { done = Some(result); break; }
                    }
                }
                let done = done.unwrap();
                prop_assert!(done.is_ok(), "{:?}", done);
                if let Ok(SdoResult::Read(v)) = done {
                    prop_assert_eq!(&v, &data);
                }
            }
        }

        #[test]
        fn canopen_prop_socketcand_parser_never_panics(s in ".{0,200}", bytes in proptest::collection::vec(any::<u8>(), 0..400), split in any::<usize>()) {
            let _ = parse_element(&s);
            let mut d = ElementDecoder::new();
            let split = split % (bytes.len() + 1);
            for piece in [&bytes[..split], &bytes[split..]] {
                d.push(piece);
                // Each call consumes input or returns None: at most one call per byte plus one.
                for _ in 0..=bytes.len() {
                    if d.next_element().is_none() { break; }
                }
            }
        }

        #[test]
        fn canopen_prop_socketcand_lines_round_trip(f in any_frame(), secs in 0u64..1_000_000, usecs in 0u32..1_000_000) {
            let send = encode_send(&f);
            prop_assert_eq!(parse_element(&send[1..send.len() - 1]), Ok(Element::Send(f)));
            let line = encode_frame(&f, secs, usecs);
            let mut d = ElementDecoder::new();
            d.push(line.as_bytes());
            prop_assert_eq!(d.next_element(), Some(Ok(Element::Frame { frame: f, secs, usecs })));
        }

        #[test]
        fn canopen_prop_pdo_pack_unpack(cw in any::<u16>(), v in any::<i32>()) {
            let p = pdo::pack(&pdo::RPDO1_MAP, &[u64::from(cw), u64::from(v as u32)]).unwrap();
            prop_assert_eq!(p.as_slice(), &pdo::encode_rpdo1(cw, v)[..]);
            prop_assert_eq!(pdo::unpack(&pdo::RPDO1_MAP, &p), Some(vec![u64::from(cw), u64::from(v as u32)]));
            let raw = (u32::from(cw) << 16) | 0x0120;
            prop_assert_eq!(MapEntry::from_raw(raw).raw(), raw);
        }

        #[test]
        fn canopen_prop_cia402_transitions_stay_in_table(cw in any::<u16>(), prev in any::<u16>(), s in 0usize..8) {
            let states = [State402::NotReadyToSwitchOn, State402::SwitchOnDisabled, State402::ReadyToSwitchOn, State402::SwitchedOn, State402::OperationEnabled, State402::QuickStopActive, State402::FaultReactionActive, State402::Fault];
            let next = device_transition(states[s], prev, cw);
            // Only the fault reset leaves Fault, and nothing enters Fault by controlword.
            if states[s] == State402::Fault && next != State402::Fault {
                prop_assert!(cw & 0x80 != 0 && prev & 0x80 == 0);
            }
            prop_assert!(next != State402::Fault || states[s] == State402::Fault);
            prop_assert_eq!(State402::from_statusword(next.statusword_bits()), Some(next));
        }

        #[test]
        fn canopen_prop_odometry_ignores_where_counters_wrap(offset_l in any::<i32>(), offset_r in any::<i32>(), steps in proptest::collection::vec((-3000i32..3000, -3000i32..3000), 1..40)) {
            let dd = DiffDrive::new(
                DrivesConfig {
                    left: WheelDriveConfig { node_id: 1, inverted: false },
                    right: WheelDriveConfig { node_id: 2, inverted: true },
                    encoder_counts_per_rev: 10_000,
                    gear_ratio: 20.0,
                    velocity_units_per_rps: 10_000.0,
                    heartbeat_producer_ms: 100,
                    heartbeat_consumer_ms: 300,
                    master_consumer_ms: 300,
                    comm_loss_reaction: CommLossReaction::QuickStop,
                    enable_timeout_ms: 1000,
                    mode_confirm_attempts: 5,
                    quick_stop_decel_mps2: 0.5,
                    estop_input_bit: None,
                    estop_input_active_low: true,
                },
                Geometry { wheel_radius_m: 0.065, track_width_m: 0.33 },
            );
            let (mut a, mut b) = (WheelOdometry::new(), WheelOdometry::new());
            let (mut l, mut r) = (0i32, 0i32);
            a.update(&dd, l, r);
            b.update(&dd, offset_l, offset_r);
            for (dl, dr) in steps {
                l = l.wrapping_add(dl);
                r = r.wrapping_add(dr);
                a.update(&dd, l, r);
                b.update(&dd, l.wrapping_add(offset_l), r.wrapping_add(offset_r));
            }
            prop_assert_eq!(a.pose(), b.pose());
        }
    }

    #[test]
    fn canopen_cob_frame_helper_matches_ids() {
        assert_eq!(Cob::Rpdo(1, 2).frame(&[1]).id(), 0x202);
        assert_eq!(Cob::Tpdo(2, 1).frame(&[]).id(), 0x281);
    }
}
