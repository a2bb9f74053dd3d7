#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]
//! The LPBUS test vectors of `tests/data/lpms/`, read at test time. The README marks three frames of
//! `02_b2_command_frames.txt` as suspect (LRC without the length): those are checked to be rejected.

/// In a module named `lpms` so that `cargo test lpms` selects these tests.
mod lpms {
    use std::path::PathBuf;

    use amr_drivers::lpms::command::{Command, CommandError, Reply};
    use amr_drivers::lpms::data::{DataMode, OutputMask, SensorData, decode_sensor_data, encode_sensor_data};
    use amr_drivers::lpms::frame::{Frame, FrameDecoder, FrameError, lrc};

    fn vectors_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/lpms")
    }

    /// Every run of at least 11 whitespace-separated two-digit hex tokens in the file, in order.
    fn frames_in(file: &str) -> Vec<Vec<u8>> {
        let text = std::fs::read_to_string(vectors_dir().join(file)).unwrap();
        let mut out = Vec::new();
        for line in text.lines() {
            let mut run = Vec::new();
            for tok in line.split_whitespace().chain(std::iter::once("end")) {
                match (tok.len(), u8::from_str_radix(tok, 16)) {
                    (2, Ok(b)) => run.push(b),
                    _ => {
                        if run.len() >= 11 {
                            out.push(std::mem::take(&mut run));
                        }
                        run.clear();
                    }
                }
            }
        }
        out
    }

    fn decode(bytes: &[u8]) -> (Vec<Frame>, Vec<FrameError>, FrameDecoder) {
        let mut d = FrameDecoder::new();
        d.push(bytes);
        let (mut ok, mut bad) = (Vec::new(), Vec::new());
        while let Some(r) = d.next_frame() {
            match r {
                Ok(f) => ok.push(f),
                Err(e) => bad.push(e),
            }
        }
        (ok, bad, d)
    }

    #[test]
    fn the_vectors_directory_is_where_the_tests_expect_it() {
        for f in [
            "01_openzen_test_vectors.txt",
            "02_b2_command_frames.txt",
            "03_ig1_family_frames.txt",
            "04_synthetic_b2_data_packet.txt",
        ] {
            assert!(vectors_dir().join(f).is_file(), "{f} missing under {}", vectors_dir().display());
        }
    }

    #[test]
    fn openzen_frames_decode_including_garbage_in_front() {
        let frames = frames_in("01_openzen_test_vectors.txt");
        assert_eq!(frames.len(), 2);
        let expected = Frame::new(10, 11, vec![1, 2, 3, 4]);
        let (ok, bad, d) = decode(&frames[0]);
        assert_eq!((ok, bad), (vec![expected.clone()], vec![]));
        assert_eq!(d.stats().skipped_bytes, 0);
        assert_eq!(expected.encode().unwrap(), frames[0]);

        let (ok, bad, d) = decode(&frames[1]);
        assert_eq!((ok, bad), (vec![expected], vec![]));
        assert_eq!(d.stats().skipped_bytes, 3, "the three leading bytes are skipped");
    }

    #[test]
    fn b2_command_frames_match_our_encoding_and_the_suspect_ones_are_rejected() {
        let frames = frames_in("02_b2_command_frames.txt");
        assert_eq!(frames.len(), 6);
        assert_eq!(frames[0], Command::ResetOrientationOffset.to_frame(1).encode().unwrap());
        assert_eq!(frames[4], Command::GotoCommandMode.to_frame(1).encode().unwrap());
        assert_eq!(frames[5], Command::GotoStreamMode.to_frame(1).encode().unwrap());
        // SET_ORIENTATION_OFFSET 0/1/2: LRC computed without the length (README/notes: suspect).
        for (i, f) in frames[1..4].iter().enumerate() {
            let (ok, bad, _) = decode(f);
            assert!(ok.is_empty(), "suspect frame {i} accepted");
            let arg = u8::try_from(i).unwrap();
            let right = lrc(1, 18, &[arg, 0, 0, 0]);
            assert_eq!(bad.first(), Some(&FrameError::BadLrc { computed: right, received: right - 4 }));
        }
    }

    #[test]
    fn ig1_family_frames_share_the_framing_but_not_the_ids() {
        let frames = frames_in("03_ig1_family_frames.txt");
        assert_eq!(frames.len(), 4);
        assert_eq!(frames[0], Command::GotoCommandMode.to_frame(1).encode().unwrap());
        assert_eq!(frames[1], Command::GotoStreamMode.to_frame(1).encode().unwrap());
        let (ok, _, _) = decode(&frames[2]);
        assert_eq!(Reply::from_frame(&ok[0]), Ok(Reply::Ack));
        // IG1 SET_IMU_TRANSMIT_DATA (30) decodes as a frame, but 30 is not a B2 command.
        let (ok, bad, _) = decode(&frames[3]);
        assert!(bad.is_empty());
        assert_eq!(ok[0], Frame::new(1, 30, 0x0001_1A82u32.to_le_bytes().to_vec()));
        assert_eq!(Command::from_frame(&ok[0]), Err(CommandError::UnknownCommand(30)));
    }

    #[test]
    fn synthetic_b2_frames_decode_and_re_encode_byte_for_byte() {
        let frames = frames_in("04_synthetic_b2_data_packet.txt");
        assert_eq!(frames.len(), 5);
        let quat = SensorData {
            timestamp_ticks: 1000,
            quaternion_wxyz: Some([1.0, 0.0, 0.0, 0.0]),
            ..Default::default()
        };
        for (bytes, mode) in [(&frames[0], DataMode::Float32), (&frames[1], DataMode::Int16)] {
            let (ok, bad, _) = decode(bytes);
            assert!(bad.is_empty());
            assert_eq!((ok[0].id, ok[0].cmd), (1, 9));
            let data = decode_sensor_data(&ok[0].data, OutputMask::QUATERNION, mode).unwrap();
            assert_eq!(data, quat);
            assert_eq!(data.timestamp_s(), 2.5);
            let again = Frame::new(1, 9, encode_sensor_data(&quat, OutputMask::QUATERNION, mode));
            assert_eq!(&again.encode().unwrap(), bytes);
            // The same payload read with the other mode's layout is a length error, not a guess.
            let other = if mode == DataMode::Float32 { DataMode::Int16 } else { DataMode::Float32 };
            assert!(decode_sensor_data(&ok[0].data, OutputMask::QUATERNION, other).is_err());
        }
        assert_eq!(frames[2], Command::GetConfig.to_frame(1).encode().unwrap());
        assert_eq!(frames[3], Command::SetStreamFreq(100).to_frame(1).encode().unwrap());
        let mask = OutputMask::GYRO
            | OutputMask::ACC
            | OutputMask::QUATERNION
            | OutputMask::EULER
            | OutputMask::LINEAR_ACC;
        assert_eq!(mask, OutputMask(0x0026_1800));
        assert_eq!(frames[4], Command::SetTransmitData(mask).to_frame(1).encode().unwrap());
    }
}
