#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]
//! Properties of the LPBUS decoders: no byte sequence panics them, a valid frame decodes the same
//! however it is split, and encode/decode round-trip for frames, commands and sensor data.

/// In a module named `lpms` so that `cargo test lpms` selects these tests.
mod lpms {
    use amr_drivers::lpms::command::{Command, Reply};
    use amr_drivers::lpms::data::{
        DataMode, OutputMask, SensorData, decode_sensor_data, encode_sensor_data, payload_len,
    };
    use amr_drivers::lpms::frame::{Frame, FrameDecoder, MAX_PAYLOAD_LEN, START};
    use proptest::prelude::*;

    /// Output bit, values sent, values decoded, 16-bit divisor.
    type FieldPair = (OutputMask, Option<Vec<f32>>, Option<Vec<f32>>, f32);

    fn drain(d: &mut FrameDecoder) -> (Vec<Frame>, usize) {
        let mut frames = Vec::new();
        let mut errors = 0;
        // Each call either returns None or consumes at least one byte, so this is bounded.
        for _ in 0..=d.buffered_len() + 1 {
            match d.next_frame() {
                Some(Ok(f)) => frames.push(f),
                Some(Err(_)) => errors += 1,
                None => break,
            }
        }
        (frames, errors)
    }

    fn frame_strategy() -> impl Strategy<Value = Frame> {
        (any::<u16>(), any::<u16>(), proptest::collection::vec(any::<u8>(), 0..=MAX_PAYLOAD_LEN))
            .prop_map(|(id, cmd, data)| Frame::new(id, cmd, data))
    }

    fn mode_strategy() -> impl Strategy<Value = DataMode> {
        prop_oneof![Just(DataMode::Float32), Just(DataMode::Int16)]
    }

    proptest! {
        // No regression files: this crate's tree is shared; failures print their minimal input.
        #![proptest_config(ProptestConfig { cases: 512, failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn no_byte_sequence_panics_the_decoders(
            bytes in proptest::collection::vec(any::<u8>(), 0..2048),
            cuts in proptest::collection::vec(any::<prop::sample::Index>(), 0..8),
            mask in any::<u32>(),
            int16 in any::<bool>(),
        ) {
            let mut positions: Vec<usize> = cuts.iter().map(|i| i.index(bytes.len() + 1)).collect();
            positions.push(bytes.len());
            positions.sort_unstable();
            let mut d = FrameDecoder::new();
            let mut start = 0;
            let mut frames = Vec::new();
            for p in positions {
                d.push(&bytes[start..p]);
                start = p;
                frames.extend(drain(&mut d).0);
            }
            prop_assert!(d.next_frame().is_none());
            let mode = if int16 { DataMode::Int16 } else { DataMode::Float32 };
            for f in &frames {
                let _ = Reply::from_frame(f);
                let _ = Command::from_frame(f);
                let _ = decode_sensor_data(&f.data, OutputMask(mask), mode);
            }
            let _ = decode_sensor_data(&bytes, OutputMask(mask), mode);
            // Every byte is accounted for: skipped, in a frame, or still buffered.
            let stats = d.stats();
            let in_frames: usize = frames.iter().map(|f| f.data.len() + 11).sum();
            prop_assert_eq!(stats.skipped_bytes as usize + in_frames + d.buffered_len(), bytes.len());
        }

        #[test]
        fn a_valid_frame_split_anywhere_decodes_the_same(
            frame in frame_strategy(),
            cut_a in any::<prop::sample::Index>(),
            cut_b in any::<prop::sample::Index>(),
            garbage in proptest::collection::vec(any::<u8>().prop_filter("no start byte", |b| *b != START), 0..32),
        ) {
            let mut bytes = garbage.clone();
            bytes.extend(frame.encode().unwrap());
            let (a, b) = {
                let (x, y) = (cut_a.index(bytes.len() + 1), cut_b.index(bytes.len() + 1));
                (x.min(y), x.max(y))
            };
            let mut d = FrameDecoder::new();
            let mut got = Vec::new();
            for piece in [&bytes[..a], &bytes[a..b], &bytes[b..]] {
                d.push(piece);
                let (frames, errors) = drain(&mut d);
                prop_assert_eq!(errors, 0);
                got.extend(frames);
            }
            prop_assert_eq!(got, vec![frame]);
            prop_assert_eq!(d.stats().skipped_bytes as usize, garbage.len());
            prop_assert_eq!(d.buffered_len(), 0);
        }

        #[test]
        fn a_valid_frame_after_any_garbage_is_still_found(
            frame in frame_strategy(),
            garbage in proptest::collection::vec(any::<u8>(), 0..64),
        ) {
            // Garbage may hold start bytes and lengths. A false header makes the decoder wait for up to
            // MAX_PAYLOAD_LEN bytes, so the stream goes on (as a sensor's does) with zero bytes; then
            // the real frame must have been found.
            let mut bytes = garbage;
            bytes.extend(frame.encode().unwrap());
            bytes.extend(std::iter::repeat_n(0u8, MAX_PAYLOAD_LEN + 11));
            let mut d = FrameDecoder::new();
            d.push(&bytes);
            let (frames, _) = drain(&mut d);
            prop_assert!(frames.contains(&frame), "decoded {frames:?}");
        }

        #[test]
        fn commands_round_trip(arg in any::<u32>(), id in any::<u16>(), which in 0usize..14) {
            let cmd = match which {
                0 => Command::GotoCommandMode,
                1 => Command::GotoStreamMode,
                2 => Command::GetConfig,
                3 => Command::GetStatus,
                4 => Command::GetSensorData,
                5 => Command::SetTransmitData(OutputMask(arg)),
                6 => Command::SetStreamFreq(arg),
                7 => Command::WriteRegisters,
                8 => Command::GetImuId,
                9 => Command::GetFirmwareVersion,
                10 => Command::SetLpbusDataMode(if arg % 2 == 0 { DataMode::Float32 } else { DataMode::Int16 }),
                11 => Command::ResetOrientationOffset,
                12 => Command::GetSerialNumber,
                _ => Command::GetDeviceName,
            };
            let mut d = FrameDecoder::new();
            d.push(&cmd.to_frame(id).encode().unwrap());
            let f = d.next_frame().unwrap().unwrap();
            prop_assert_eq!(f.id, id);
            prop_assert_eq!(Command::from_frame(&f), Ok(cmd));
        }

        #[test]
        fn sensor_data_round_trips_in_both_modes(
            mask in any::<u32>(),
            mode in mode_strategy(),
            ticks in any::<u32>(),
            values in proptest::collection::vec(-30.0f32..30.0, 30),
        ) {
            let mask = OutputMask(mask).outputs_only();
            let v3 = |i: usize| Some([values[i], values[i + 1], values[i + 2]]);
            let data = SensorData {
                timestamp_ticks: ticks,
                gyro_radps: v3(0),
                acc_g: v3(3),
                mag_ut: v3(6),
                angular_velocity_radps: v3(9),
                quaternion_wxyz: Some([values[12] / 30.0, values[13] / 30.0, values[14] / 30.0, values[15] / 30.0]),
                euler_rad: Some([values[16] / 10.0, values[17] / 10.0, values[18] / 10.0]),
                linear_acc_g: v3(19),
                pressure_raw: Some(values[22]),
                altitude_m: Some(values[23]),
                temperature_c: Some(values[24]),
                heave_m: Some(values[25]),
            };
            let payload = encode_sensor_data(&data, mask, mode);
            prop_assert_eq!(payload.len(), payload_len(mask, mode));
            let back = decode_sensor_data(&payload, mask, mode).unwrap();
            prop_assert_eq!(back.timestamp_ticks, ticks);
            let pairs: Vec<FieldPair> = vec![
                (OutputMask::GYRO, data.gyro_radps.map(Vec::from), back.gyro_radps.map(Vec::from), 1000.0),
                (OutputMask::ACC, data.acc_g.map(Vec::from), back.acc_g.map(Vec::from), 1000.0),
                (OutputMask::MAG, data.mag_ut.map(Vec::from), back.mag_ut.map(Vec::from), 100.0),
                (OutputMask::ANGULAR_VELOCITY, data.angular_velocity_radps.map(Vec::from), back.angular_velocity_radps.map(Vec::from), 1000.0),
                (OutputMask::QUATERNION, data.quaternion_wxyz.map(Vec::from), back.quaternion_wxyz.map(Vec::from), 10000.0),
                (OutputMask::EULER, data.euler_rad.map(Vec::from), back.euler_rad.map(Vec::from), 10000.0),
                (OutputMask::LINEAR_ACC, data.linear_acc_g.map(Vec::from), back.linear_acc_g.map(Vec::from), 1000.0),
                (OutputMask::PRESSURE, data.pressure_raw.map(|v| vec![v]), back.pressure_raw.map(|v| vec![v]), 100.0),
                (OutputMask::ALTITUDE, data.altitude_m.map(|v| vec![v]), back.altitude_m.map(|v| vec![v]), 10.0),
                (OutputMask::TEMPERATURE, data.temperature_c.map(|v| vec![v]), back.temperature_c.map(|v| vec![v]), 100.0),
                (OutputMask::HEAVE, data.heave_m.map(|v| vec![v]), back.heave_m.map(|v| vec![v]), 1000.0),
            ];
            for (bit, sent, got, divisor) in pairs {
                if !mask.contains(bit) {
                    prop_assert!(got.is_none());
                    continue;
                }
                let (sent, got) = (sent.unwrap(), got.unwrap());
                for (s, g) in sent.iter().zip(&got) {
                    match mode {
                        DataMode::Float32 => prop_assert_eq!(s, g),
                        DataMode::Int16 => {
                            let max = f32::from(i16::MAX) / divisor;
                            let expect = s.clamp(-max - 1.0 / divisor, max);
                            prop_assert!((expect - g).abs() <= 0.5 / divisor + 1e-6 * expect.abs().max(1.0),
                                "{bit:?}: sent {s}, got {g}");
                        }
                    }
                }
            }
        }
    }
}
