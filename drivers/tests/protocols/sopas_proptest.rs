#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]
//! Properties of the SOPAS codec: no byte sequence panics the framer or the decoders; valid
//! frames decode the same however the stream is split or concatenated; encode → decode round trips.

use amr_drivers::sopas::scan::{Channel, DeviceTime, Encoder, EventInfo, PositionBlock};
use amr_drivers::sopas::{
    Command, Dialect, ErrorCode, Frame, Framer, OutputRange, Reply, Scan, ScanDataConfig, ScanTelegram,
    Sector, Variable, decode_capture, encode_frame,
};
use proptest::prelude::*;

fn dialect() -> impl Strategy<Value = Dialect> {
    prop_oneof![Just(Dialect::ColaA), Just(Dialect::ColaB)]
}

fn text(max: usize) -> impl Strategy<Value = String> {
    // Printable ASCII including spaces: CoLa-A strings may contain spaces (notes §1.1).
    proptest::collection::vec(0x20u8..0x7F, 0..=max).prop_map(|b| String::from_utf8(b).unwrap())
}

fn finite_f32() -> impl Strategy<Value = f32> {
    -1.0e6f32..1.0e6f32
}

fn channel<T: std::fmt::Debug + Clone + 'static>(
    data: impl Strategy<Value = T> + 'static,
    n: usize,
) -> impl Strategy<Value = Channel<T>> {
    (
        prop_oneof![Just("DIST1"), Just("RSSI1"), Just("DIST2")],
        finite_f32(),
        finite_f32(),
        any::<i32>(),
        any::<u16>(),
        proptest::collection::vec(data, n),
    )
        .prop_map(|(content, scale_factor, scale_offset, start_angle_1e4deg, step_1e4deg, data)| {
            Channel {
                content: content.into(),
                scale_factor,
                scale_offset,
                start_angle_1e4deg,
                step_1e4deg,
                data,
            }
        })
}

prop_compose! {
    fn telegram()(
        head in (any::<u16>(), any::<u16>(), any::<u32>(), any::<[u8; 2]>(), any::<u16>(), any::<u16>(), any::<u32>(), any::<u32>()),
        io in (any::<[u8; 2]>(), any::<[u8; 2]>(), any::<u16>(), any::<u32>(), any::<u32>()),
        encoders in proptest::collection::vec((any::<u32>(), any::<u16>()), 0..3),
        n in 0usize..40,
        n16 in 0usize..3,
        n8 in 0usize..2,
        seed16 in proptest::collection::vec(channel(any::<u16>(), 40), 3),
        seed8 in proptest::collection::vec(channel(any::<u8>(), 40), 2),
        position in proptest::option::of((proptest::array::uniform6(finite_f32()), any::<u8>(), any::<u8>())),
        device_name in proptest::option::of(text(16)),
        comment in proptest::option::of(text(40)),
        time in proptest::option::of((any::<u16>(), any::<[u8; 5]>(), any::<u32>())),
        event in proptest::option::of((any::<u32>(), any::<u32>(), any::<i32>())),
    ) -> ScanTelegram {
        let cut16 = |mut c: Channel<u16>| { c.data.truncate(n); c };
        let cut8 = |mut c: Channel<u8>| { c.data.truncate(n); c };
        ScanTelegram {
            version: head.0, device_number: head.1, serial: head.2, device_status: head.3,
            telegram_counter: head.4, scan_counter: head.5, time_since_startup_us: head.6,
            time_of_transmission_us: head.7, input_status: io.0, output_status: io.1,
            reserved_layer_angle: io.2, scan_frequency_centi_hz: io.3, measurement_frequency_hecto_hz: io.4,
            encoders: encoders.into_iter().map(|(position, speed)| Encoder { position, speed }).collect(),
            channels_16bit: seed16.into_iter().take(n16).map(cut16).collect(),
            channels_8bit: seed8.into_iter().take(n8).map(cut8).collect(),
            position: position.map(|(p, rotation_type, transmit_device_name)| PositionBlock {
                x: p[0], y: p[1], z: p[2], rot_x: p[3], rot_y: p[4], rot_z: p[5], rotation_type, transmit_device_name,
            }),
            device_name,
            comment,
            time: time.map(|(year, b, microsecond)| DeviceTime {
                year, month: b[0], day: b[1], hour: b[2], minute: b[3], second: b[4], microsecond,
            }),
            event: event.map(|(encoder_position, event_time_us, angle_1e4deg)| EventInfo {
                kind: "FDIN".into(), encoder_position, event_time_us, angle_1e4deg,
            }),
        }
    }
}

fn command() -> impl Strategy<Value = Command> {
    let variable = prop_oneof![
        Just(Variable::ScanData),
        Just(Variable::DeviceIdent),
        Just(Variable::SerialNumber),
        Just(Variable::FirmwareVersion),
        Just(Variable::DeviceState),
        Just(Variable::OperatingHours),
        Just(Variable::PowerOnCount),
        Just(Variable::LocationName),
        Just(Variable::OutputRange),
        Just(Variable::ScanDataConfig),
    ];
    let range = proptest::collection::vec((any::<u32>(), any::<i32>(), any::<i32>()), 0..3).prop_map(|v| {
        OutputRange {
            sectors: v
                .into_iter()
                .map(|(r, a, b)| Sector { resolution_1e4deg: r, start_1e4deg: a, stop_1e4deg: b })
                .collect(),
        }
    });
    let cfg = (any::<u16>(), any::<[u8; 3]>(), any::<u16>(), any::<[u8; 4]>(), any::<u16>()).prop_map(
        |(c, a, e, b, o)| ScanDataConfig {
            output_channel: c,
            remission: a[0],
            resolution: a[1],
            unit: a[2],
            encoder: e,
            position: b[0],
            device_name: b[1],
            comment: b[2],
            time: b[3],
            output_interval: o,
        },
    );
    prop_oneof![
        (any::<u8>(), any::<u32>())
            .prop_map(|(level, password_hash)| Command::SetAccessMode { level, password_hash }),
        any::<u16>().prop_map(Command::ReadByIndex),
        variable.prop_map(Command::Read),
        range.prop_map(Command::WriteOutputRange),
        cfg.prop_map(Command::WriteScanDataConfig),
        dialect().prop_map(Command::SetDialect),
        any::<bool>().prop_map(Command::ScanDataEvents),
        Just(Command::Run),
        Just(Command::StartMeasurement),
        Just(Command::StopMeasurement),
        Just(Command::Reboot),
        Just(Command::WriteEeprom),
    ]
}

fn reply() -> impl Strategy<Value = Reply> {
    prop_oneof![
        any::<u16>().prop_map(|c| Reply::Error(ErrorCode::from_code(c))),
        any::<bool>().prop_map(|granted| Reply::AccessMode { granted }),
        (any::<u16>(), text(20), text(20)).prop_map(|(index, name, version)| Reply::IndexIdent {
            index,
            name,
            version
        }),
        (any::<bool>(), telegram()).prop_map(|(event, t)| Reply::ScanData { event, telegram: Box::new(t) }),
        any::<bool>().prop_map(|enabled| Reply::ScanDataEvents { enabled }),
        (text(20), text(20)).prop_map(|(name, version)| Reply::DeviceIdent { name, version }),
        text(12).prop_map(Reply::SerialNumber),
        text(12).prop_map(Reply::FirmwareVersion),
        any::<u8>().prop_map(Reply::DeviceState),
        any::<u32>().prop_map(Reply::OperatingHours),
        text(16).prop_map(Reply::LocationName),
        prop_oneof![Just("EIHstCola"), Just("LMPoutputRange"), Just("LMDscandatacfg")]
            .prop_map(|n| Reply::WriteAck(n.into())),
        any::<bool>().prop_map(|ok| Reply::Run { ok }),
        any::<u8>().prop_map(|status| Reply::StartMeasurement { status }),
        Just(Reply::Reboot),
    ]
}

/// Feeds `bytes` in pieces cut at `cuts` and returns every frame (errors dropped).
fn frames(bytes: &[u8], cuts: &[usize]) -> (Vec<Frame>, usize) {
    let mut framer = Framer::default();
    let mut out = Vec::new();
    let mut errors = 0;
    let mut points: Vec<usize> = cuts.iter().map(|c| c % (bytes.len() + 1)).collect();
    points.push(0);
    points.push(bytes.len());
    points.sort_unstable();
    for w in points.windows(2) {
        framer.push(&bytes[w[0]..w[1]]);
        for _ in 0..100_000 {
            match framer.next_frame() {
                Some(Ok(f)) => out.push(f),
                Some(Err(_)) => errors += 1,
                None => break,
            }
        }
    }
    (out, errors)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn sopas_no_byte_sequence_panics_the_framer_or_decoders(
        bytes in proptest::collection::vec(any::<u8>(), 0..2048),
        cuts in proptest::collection::vec(any::<usize>(), 0..8),
    ) {
        let (found, _) = frames(&bytes, &cuts);
        for f in found {
            let _ = Reply::decode(f.dialect, &f.payload);
            let _ = Command::decode(f.dialect, &f.payload);
        }
        for d in [Dialect::ColaA, Dialect::ColaB] {
            if let Ok(Reply::ScanData { telegram, .. }) = Reply::decode(d, &bytes) {
                let _ = Scan::from_telegram(&telegram);
            }
            let _ = ScanTelegram::decode_args(d, &bytes);
        }
        let _ = decode_capture(&bytes);
    }

    #[test]
    fn sopas_scan_decoder_survives_mutated_real_telegrams(
        which in 0usize..2,
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..6),
        cut in any::<usize>(),
    ) {
        let dir = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/sopas");
        let name = ["03_tim781s_colaB_sSN_LMDscandata.frame1.bin", "01_tim561_colaA_sRA_LMDscandata.framed.bin"][which];
        let mut bytes = std::fs::read(dir.join(name)).unwrap();
        for (at, v) in edits {
            let i = at % bytes.len();
            bytes[i] = v;
        }
        let _ = decode_capture(&bytes);
        let _ = decode_capture(&bytes[..cut % (bytes.len() + 1)]);
        let payload = &bytes[8.min(bytes.len())..];
        let _ = Reply::decode(Dialect::ColaB, payload);
        let _ = Reply::decode(Dialect::ColaA, payload);
    }

    #[test]
    fn sopas_valid_frames_split_anywhere_and_concatenated_decode_the_same(
        replies in proptest::collection::vec((dialect(), reply()), 1..5),
        cuts in proptest::collection::vec(any::<usize>(), 0..12),
        garbage in proptest::collection::vec(0x04u8..0xFF, 0..16),
    ) {
        let mut stream = garbage.clone();
        let mut want = Vec::new();
        for (d, r) in &replies {
            let payload = r.encode(*d).unwrap();
            stream.extend_from_slice(&encode_frame(*d, &payload));
            want.push(Frame { dialect: *d, payload });
        }
        let (got, errors) = frames(&stream, &cuts);
        prop_assert_eq!(errors, 0);
        prop_assert_eq!(&got, &want);
        for (f, (_, r)) in got.iter().zip(&replies) {
            prop_assert_eq!(&Reply::decode(f.dialect, &f.payload).unwrap(), r);
        }
    }

    #[test]
    fn sopas_commands_round_trip_in_both_dialects(cmd in command(), d in dialect()) {
        let payload = cmd.encode(d);
        prop_assert_eq!(Command::decode(d, &payload).unwrap(), cmd);
    }

    #[test]
    fn sopas_replies_round_trip_in_both_dialects(r in reply(), d in dialect()) {
        let payload = r.encode(d).unwrap();
        prop_assert_eq!(&Reply::decode(d, &payload).unwrap(), &r);
        // A scan telegram is the same in both dialects.
        if let Reply::ScanData { telegram, .. } = &r {
            let other = r.encode(d.other()).unwrap();
            let Reply::ScanData { telegram: back, .. } = Reply::decode(d.other(), &other).unwrap() else {
                return Err(TestCaseError::fail("not a scan"));
            };
            prop_assert_eq!(&back, telegram);
        }
    }
}
