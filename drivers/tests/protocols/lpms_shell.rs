#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]
//! The tokio shell (`lpms::run`) over in-memory duplex pipes with tokio's paused clock: reopen with
//! backoff when the port is missing or closes, and what it publishes. A small scripted sensor built
//! from the codec answers on the other end.

/// In a module named `lpms` so that `cargo test lpms` selects these tests.
mod lpms {
    use std::sync::{Arc, Mutex};
    use std::time::Duration;

    use amr_drivers::lpms::command::FirmwareVersion;
    use amr_drivers::lpms::data::encode_sensor_data;
    use amr_drivers::lpms::{
        Command, ConfigRegister, Frame, FrameDecoder, Health, ImuMessage, LinkError, LpmsError, Reply,
        SensorData, SessionConfig, run,
    };
    use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};
    use tokio::sync::mpsc;
    use tokio::time::{Instant, timeout};

    /// Answers the start-up sequence, then streams `packets` data packets and closes the pipe.
    async fn scripted_sensor(mut io: DuplexStream, config: SessionConfig, packets: u32) {
        let reg = ConfigRegister::from_settings(config.outputs, config.data_mode, config.stream_hz).unwrap();
        let mut dec = FrameDecoder::new();
        let mut buf = [0u8; 256];
        'startup: loop {
            let n = io.read(&mut buf).await.unwrap();
            assert!(n > 0, "driver closed during start-up");
            dec.push(&buf[..n]);
            while let Some(f) = dec.next_frame() {
                let cmd = Command::from_frame(&f.unwrap()).unwrap();
                let reply = match cmd {
                    Command::GetConfig => Reply::Config(reg),
                    Command::GetImuId => Reply::ImuId(5),
                    Command::GetFirmwareVersion => {
                        Reply::FirmwareVersion(FirmwareVersion { major: 1, minor: 3, build: 5 })
                    }
                    _ => Reply::Ack,
                };
                io.write_all(&reply.to_frame(5).encode().unwrap()).await.unwrap();
                if cmd == Command::GotoStreamMode {
                    break 'startup;
                }
            }
        }
        for i in 1..=packets {
            let data = SensorData {
                timestamp_ticks: 4 * i,
                gyro_radps: Some([0.0, 0.0, 0.1]),
                ..Default::default()
            };
            let payload = encode_sensor_data(&data, reg.outputs(), reg.data_mode());
            io.write_all(&Frame::new(5, 9, payload).encode().unwrap()).await.unwrap();
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    #[tokio::test(start_paused = true)]
    async fn reopens_with_backoff_and_publishes_samples_with_their_receive_time() {
        let config = SessionConfig {
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_millis(250),
            ..SessionConfig::default()
        };
        let attempts: Arc<Mutex<Vec<Instant>>> = Arc::default();
        let connect = {
            let attempts = attempts.clone();
            let config = config.clone();
            move || {
                let mut a = attempts.lock().unwrap();
                a.push(Instant::now());
                // Attempts 1-3 find no port; 4 gets a sensor that streams 5 packets and hangs up;
                // 5 gets one that keeps streaming.
                let result = match a.len() {
                    1..=3 => Err(std::io::Error::new(std::io::ErrorKind::NotFound, "no such tty")),
                    n => {
                        let (host, device) = tokio::io::duplex(4096);
                        tokio::spawn(scripted_sensor(device, config.clone(), if n == 4 { 5 } else { 1000 }));
                        Ok(host)
                    }
                };
                std::future::ready(result)
            }
        };
        let (tx, mut rx) = mpsc::channel(256);
        let driver = tokio::spawn(run(config, connect, tx));

        let mut log = Vec::new();
        let mut samples = Vec::new();
        let mut readies = 0;
        // Bounded: a few dozen messages are expected, 10 000 means something loops.
        for _ in 0..10_000 {
            if readies >= 2 && samples.len() >= 8 {
                break;
            }
            let msg = timeout(Duration::from_secs(30), rx.recv()).await.unwrap().unwrap();
            match &msg {
                ImuMessage::Sample(s) => samples.push(s.clone()),
                ImuMessage::Ready(info) => {
                    assert_eq!(info.imu_id, 5);
                    readies += 1;
                    log.push(msg);
                }
                _ => log.push(msg),
            }
        }

        assert!(readies >= 2 && samples.len() >= 8, "{readies} starts, {} samples", samples.len());
        // Backoff between failed opens: 100, 200, then capped at 250 ms.
        let a = attempts.lock().unwrap().clone();
        let gaps: Vec<Duration> = a.windows(2).take(3).map(|w| w[1] - w[0]).collect();
        assert_eq!(
            gaps,
            vec![Duration::from_millis(100), Duration::from_millis(200), Duration::from_millis(250)]
        );

        let not_found = ImuMessage::Error(LpmsError::Link(LinkError::Io {
            kind: std::io::ErrorKind::NotFound,
            message: "no such tty".into(),
        }));
        let expected_start = [
            ImuMessage::Health(Health::Connecting),
            not_found.clone(),
            ImuMessage::Health(Health::Lost),
            ImuMessage::Health(Health::Connecting),
            not_found.clone(),
            ImuMessage::Health(Health::Lost),
            ImuMessage::Health(Health::Connecting),
            not_found,
            ImuMessage::Health(Health::Lost),
            ImuMessage::Health(Health::Connecting),
            ImuMessage::Health(Health::Configuring),
        ];
        assert_eq!(&log[..expected_start.len()], &expected_start);
        // The first sensor hangs up after 5 packets: end of file is a link loss, then a reopen.
        let eof = log.iter().position(|m| {
            matches!(
                m,
                ImuMessage::Error(LpmsError::Link(LinkError::Io {
                    kind: std::io::ErrorKind::UnexpectedEof,
                    ..
                }))
            )
        });
        assert!(eof.is_some(), "{log:?}");
        assert_eq!(
            samples[..5].iter().map(|s| s.data.timestamp_ticks).collect::<Vec<_>>(),
            vec![4, 8, 12, 16, 20]
        );
        for pair in samples.windows(2) {
            assert!(pair[1].received_at >= pair[0].received_at);
        }
        drop(rx);
        // With the receiver gone the driver ends on its own.
        timeout(Duration::from_secs(30), driver).await.unwrap().unwrap();
    }
}
