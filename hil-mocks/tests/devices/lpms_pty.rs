#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]
//! The LPMS driver (`amr_drivers::lpms`) against the mock LPMS-B2 over a real pty, opened through
//! tokio-serial by path exactly as on the robot (the 30 s stream runs on virtual time over an
//! in-memory pipe). Every wait is on an event with a timeout.

/// In a module named `lpms` so that `cargo test lpms` selects these tests.
mod lpms {
    use std::time::Duration;

    use amr_settings::value::Backoff;

    use amr_drivers::lpms::{
        CommandId, DataMode, DeviceError, Health, ImuMessage, LinkError, LpmsConfig, LpmsError, OutputMask,
        ProtocolError, serial::run, spawn_serial,
    };
    use hil_mocks::lpms::{
        ConstantYawRate, DeviceSettings, Fault, MockImuHandle, MockImuOptions, start_mock_imu,
        start_mock_imu_in_memory,
    };
    use tokio::sync::mpsc::Receiver;
    use tokio::time::{Instant, timeout};

    const YAW_RATE_RADPS: f64 = 0.3;
    const BIAS_RADPS: f64 = 0.01;

    async fn mock(rate_hz: u32) -> MockImuHandle {
        let options = MockImuOptions {
            device: DeviceSettings { stream_hz: rate_hz, ..DeviceSettings::default() },
            ..MockImuOptions::default()
        };
        start_mock_imu(options, Box::new(ConstantYawRate::new(YAW_RATE_RADPS, BIAS_RADPS, 0.001, 7)))
            .await
            .unwrap()
    }

    fn driver_config(mock: &MockImuHandle) -> LpmsConfig {
        LpmsConfig {
            path: mock.tty_path().to_string_lossy().into_owned(),
            stream_hz: 100,
            outputs: OutputMask::GYRO | OutputMask::ACC | OutputMask::QUATERNION,
            data_mode: DataMode::Float32,
            reply_timeout: Duration::from_millis(200),
            // Generous: CI machines are busy, and only the silence test needs the watchdog to fire.
            data_timeout: Duration::from_secs(2),
            reconnect: Backoff { initial: Duration::from_millis(50), max: Duration::from_millis(200) },
            ..LpmsConfig::default()
        }
    }

    /// Receives until `pred` matches, at most `within`; returns the match and everything seen before it.
    async fn wait_for(
        rx: &mut Receiver<ImuMessage>,
        within: Duration,
        mut pred: impl FnMut(&ImuMessage) -> bool,
    ) -> (ImuMessage, Vec<ImuMessage>) {
        let deadline = Instant::now() + within;
        let mut seen = Vec::new();
        loop {
            let msg = timeout(deadline.saturating_duration_since(Instant::now()), rx.recv())
                .await
                .unwrap_or_else(|_| panic!("timed out after {within:?}; last messages: {:?}", tail(&seen)))
                .expect("driver stopped");
            if pred(&msg) {
                return (msg, seen);
            }
            seen.push(msg);
        }
    }

    fn tail(v: &[ImuMessage]) -> Vec<&ImuMessage> {
        v.iter().filter(|m| !matches!(m, ImuMessage::Sample(_))).rev().take(8).collect()
    }

    fn sample_ticks(m: &ImuMessage) -> Option<u32> {
        match m {
            ImuMessage::Sample(s) => Some(s.data.timestamp_ticks),
            _ => None,
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn handshake_configures_the_requested_layout_in_16_bit_mode() {
        let mock = mock(100).await;
        let config = LpmsConfig {
            stream_hz: 50,
            data_mode: DataMode::Int16,
            outputs: OutputMask::GYRO | OutputMask::QUATERNION,
            ..driver_config(&mock)
        };
        let (mut rx, _task) = spawn_serial(config, 1024).unwrap();
        let (ready, _) =
            wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Ready(_))).await;
        let ImuMessage::Ready(info) = ready else { unreachable!() };
        assert_eq!(info.imu_id, 1);
        assert_eq!(info.config.stream_hz(), 50);
        assert_eq!(info.config.data_mode(), DataMode::Int16);
        assert_eq!(info.config.outputs(), OutputMask::GYRO | OutputMask::QUATERNION);
        assert_eq!((info.firmware.major, info.firmware.minor, info.firmware.build), (2, 0, 5));

        // The mock saw the documented start-up sequence (GOTO_COMMAND_MODE may repeat while it streamed).
        let seen: Vec<CommandId> = mock
            .stats()
            .device
            .commands
            .into_iter()
            .skip_while(|c| *c == CommandId::GotoCommandMode)
            .collect();
        assert_eq!(
            seen,
            vec![
                CommandId::GetConfig,
                CommandId::GetImuId,
                CommandId::GetFirmwareVersion,
                CommandId::SetTransmitData,
                CommandId::SetStreamFreq,
                CommandId::SetLpbusDataMode,
                CommandId::GetConfig,
                CommandId::GotoStreamMode,
            ]
        );

        // Samples carry the 16-bit-scaled values of the motion source: 50 Hz = 8 ticks apart.
        let mut last = None;
        for _ in 0..10 {
            let (m, seen) =
                wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Sample(_))).await;
            assert!(
                !seen.iter().any(|m| matches!(m, ImuMessage::Error(_) | ImuMessage::Health(Health::Lost))),
                "errors while streaming: {seen:?}"
            );
            let ImuMessage::Sample(s) = m else { unreachable!() };
            let gyro = s.data.gyro_radps.unwrap();
            assert!((f64::from(gyro[2]) - (YAW_RATE_RADPS + BIAS_RADPS)).abs() < 0.01, "gyro z {}", gyro[2]);
            let q = s.data.quaternion_wxyz.unwrap();
            let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((norm - 1.0).abs() < 1e-3, "quaternion norm {norm}");
            assert!(s.data.acc_g.is_none() && s.data.euler_rad.is_none());
            if let Some(prev) = last {
                let stats = mock.stats();
                assert_eq!(s.data.timestamp_ticks.wrapping_sub(prev), 8, "mock: {stats:?}");
            }
            last = Some(s.data.timestamp_ticks);
        }
    }

    /// The long stream on virtual time: the same driver and mock over an in-memory pipe instead
    /// of the pty (the tests around it keep the pty), 30 s of sensor time in well under a second,
    /// whatever else the machine does.
    #[tokio::test(start_paused = true)]
    async fn streams_100_hz_for_30_s_of_sensor_time_without_losing_a_packet() {
        let options = MockImuOptions {
            device: DeviceSettings { stream_hz: 100, ..DeviceSettings::default() },
            ..MockImuOptions::default()
        };
        let motion = Box::new(ConstantYawRate::new(YAW_RATE_RADPS, BIAS_RADPS, 0.001, 7));
        let (mock, connector) = start_mock_imu_in_memory(options, motion);
        let config = LpmsConfig { outputs: OutputMask::ALL, ..driver_config(&mock) };
        let (tx, mut rx) = tokio::sync::mpsc::channel(4096);
        let connect = move || {
            let c = connector.clone();
            async move { c.connect().await }
        };
        let _task = tokio::spawn(run(config.session_config(), connect, tx));
        wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Ready(_))).await;
        let (first, _) = wait_for(&mut rx, Duration::from_secs(10), |m| sample_ticks(m).is_some()).await;
        let first = sample_ticks(&first).unwrap();
        // 30 s of sensor time = 12000 ticks of 2.5 ms = 3000 packets at 100 Hz after the first.
        let end = first.wrapping_add(12_000);
        let mut prev = first;
        let mut packets = 1u32;
        let mut gaps = Vec::new();
        let mut errors = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(90);
        while prev != end && packets <= 3001 {
            let msg = timeout(deadline.saturating_duration_since(Instant::now()), rx.recv())
                .await
                .unwrap()
                .unwrap();
            match msg {
                ImuMessage::Sample(s) => {
                    let d = s.data.timestamp_ticks.wrapping_sub(prev);
                    if d != 4 {
                        gaps.push((prev, s.data.timestamp_ticks));
                    }
                    prev = s.data.timestamp_ticks;
                    packets += 1;
                }
                ImuMessage::Error(e) => errors.push(e),
                _ => {}
            }
        }
        assert!(gaps.is_empty(), "timestamp gaps: {gaps:?}");
        assert!(errors.is_empty(), "errors while streaming: {errors:?}");
        assert_eq!(packets, 3001);
        assert_eq!(prev, end);
        tracing::info!(packets, "30 s at 100 Hz");
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn garbage_bad_checksums_and_truncated_frames_are_skipped_without_a_reconnect() {
        let mock = mock(100).await;
        let (mut rx, _task) = spawn_serial(driver_config(&mock), 1024).unwrap();
        wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Ready(_))).await;
        let (m, _) = wait_for(&mut rx, Duration::from_secs(10), |m| sample_ticks(m).is_some()).await;
        let before = sample_ticks(&m).unwrap();

        // A fake header promising 64 bytes, stray start bytes, then three data packets with a bad LRC
        // and two cut in half.
        let mut garbage = vec![0x3A, 0x01, 0x00, 0x09, 0x00, 0x40, 0x00, 0xFF, 0x3A, 0x3A, 0x0D, 0x0A];
        garbage.extend((0u8..40).map(|i| i.wrapping_mul(37)));
        mock.inject(Fault::Garbage(garbage)).await.unwrap();
        mock.inject(Fault::WrongLrc(3)).await.unwrap();
        mock.inject(Fault::Truncate(2)).await.unwrap();

        let mut prev = before;
        let mut missing = 0;
        let mut bad_lrc = 0;
        let mut received_after = 0;
        // At most 1000 samples (10 s at 100 Hz): the faults are applied within the first few.
        for _ in 0..1000 {
            if received_after >= 100 {
                break;
            }
            let (m, seen) = wait_for(&mut rx, Duration::from_secs(10), |m| sample_ticks(m).is_some()).await;
            for s in &seen {
                assert!(!matches!(s, ImuMessage::Health(Health::Lost)), "link dropped: {seen:?}");
                if let ImuMessage::Error(LpmsError::Protocol(ProtocolError::Frame(
                    amr_drivers::lpms::FrameError::BadLrc { .. },
                ))) = s
                {
                    bad_lrc += 1;
                }
            }
            let t = sample_ticks(&m).unwrap();
            missing += t.wrapping_sub(prev) / 4 - 1;
            prev = t;
            if bad_lrc > 0 {
                received_after += 1;
            }
        }
        assert_eq!(received_after, 100, "the faults never showed");
        // Exactly the three corrupted and two truncated packets are lost; the garbage costs none.
        assert_eq!(missing, 5);
        assert!(bad_lrc >= 3, "bad LRC reports: {bad_lrc}");
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn unplug_and_replug_recovers_within_a_second_of_the_tty_reappearing() {
        let mock = mock(100).await;
        let (mut rx, _task) = spawn_serial(driver_config(&mock), 1024).unwrap();
        wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Ready(_))).await;
        wait_for(&mut rx, Duration::from_secs(10), |m| sample_ticks(m).is_some()).await;
        assert!(mock.stats().pty_path.is_some());

        mock.unplug().await.unwrap();
        assert!(mock.stats().pty_path.is_none());
        assert!(std::fs::symlink_metadata(mock.tty_path()).is_err(), "the symlink is gone while unplugged");
        wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Health(Health::Lost))).await;
        // Stay unplugged until the driver has failed to reopen the vanished path twice.
        for _ in 0..2 {
            wait_for(&mut rx, Duration::from_secs(10), |m| {
                matches!(
                    m,
                    ImuMessage::Error(LpmsError::Link(LinkError::Io {
                        kind: std::io::ErrorKind::NotFound,
                        ..
                    }))
                )
            })
            .await;
        }

        let new_pty = mock.replug().await.unwrap();
        let replugged_at = Instant::now();
        // The kernel may hand out the same pts number again; the symlink is what the driver follows.
        assert_eq!(std::fs::read_link(mock.tty_path()).unwrap(), new_pty);
        wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Ready(_))).await;
        wait_for(&mut rx, Duration::from_secs(10), |m| sample_ticks(m).is_some()).await;
        let recovery = replugged_at.elapsed();
        tracing::info!(?recovery, "LPMS recovery after replug");
        eprintln!("LPMS recovery after replug: {recovery:?}");
        assert!(recovery < Duration::from_secs(1), "recovered after {recovery:?}");
        assert_eq!(mock.stats().plugs, 2);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_nack_is_a_device_error_naming_the_command_and_start_up_recovers_on_the_same_link() {
        let mock = mock(100).await;
        mock.inject(Fault::Nack { command: CommandId::SetStreamFreq, times: 1 }).await.unwrap();
        let (mut rx, _task) = spawn_serial(driver_config(&mock), 1024).unwrap();
        let (err, _) =
            wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Error(_))).await;
        assert_eq!(
            err,
            ImuMessage::Error(LpmsError::Device(DeviceError::Nack { command: CommandId::SetStreamFreq }))
        );
        let ImuMessage::Error(e) = &err else { unreachable!() };
        assert!(e.to_string().contains("SetStreamFreq(11)"), "{e}");
        let (_, between) =
            wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Ready(_))).await;
        assert!(
            !between.iter().any(|m| matches!(m, ImuMessage::Health(Health::Lost | Health::Connecting))),
            "a NACK is not a broken link: {between:?}"
        );
        assert_eq!(mock.stats().device.nacks, 1);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_lost_first_reply_is_retried_and_silence_trips_the_watchdog() {
        let mock = mock(100).await;
        mock.inject(Fault::DropReplies(1)).await.unwrap();
        let (mut rx, _task) = spawn_serial(driver_config(&mock), 1024).unwrap();
        wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Ready(_))).await;
        let commands = mock.stats().device.commands;
        assert_eq!(&commands[..2], &[CommandId::GotoCommandMode, CommandId::GotoCommandMode]);

        wait_for(&mut rx, Duration::from_secs(10), |m| sample_ticks(m).is_some()).await;
        mock.inject(Fault::Silence(true)).await.unwrap();
        let (m, _) = wait_for(&mut rx, Duration::from_secs(10), |m| {
            matches!(m, ImuMessage::Error(LpmsError::Link(_)))
        })
        .await;
        assert!(matches!(m, ImuMessage::Error(LpmsError::Link(LinkError::DataTimeout { .. }))), "{m:?}");
        mock.inject(Fault::Silence(false)).await.unwrap();
        wait_for(&mut rx, Duration::from_secs(10), |m| matches!(m, ImuMessage::Ready(_))).await;
        wait_for(&mut rx, Duration::from_secs(10), |m| sample_ticks(m).is_some()).await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_default_mock_streams_on_power_up_behind_its_symlink() {
        use amr_drivers::lpms::data::decode_sensor_data;
        use amr_drivers::lpms::{FrameDecoder, open_serial};
        use tokio::io::AsyncReadExt;

        let mock = hil_mocks::lpms::start_default_mock_imu(200).await.unwrap();
        let target = std::fs::read_link(mock.tty_path()).unwrap();
        assert_eq!(Some(target), mock.stats().pty_path);
        let mut port =
            open_serial(&mock.tty_path().to_string_lossy(), amr_drivers::lpms::serial::DEFAULT_BAUD).unwrap();
        let (outputs, mode) = (DeviceSettings::default().outputs, DeviceSettings::default().data_mode);
        let mut dec = FrameDecoder::new();
        let mut ticks = Vec::new();
        let mut buf = [0u8; 512];
        // Bytes written before we opened the tty may be stale; look at 20 consecutive packets.
        for _ in 0..1000 {
            if ticks.len() >= 21 {
                break;
            }
            let n = timeout(Duration::from_secs(10), port.read(&mut buf)).await.unwrap().unwrap();
            dec.push(&buf[..n]);
            while let Some(f) = dec.next_frame() {
                // A partial frame from before the open is skipped, not an error.
                let Ok(f) = f else { continue };
                assert_eq!((f.id, f.cmd), (1, 9));
                ticks.push(decode_sensor_data(&f.data, outputs, mode).unwrap().timestamp_ticks);
            }
        }
        let tail = &ticks[ticks.len() - 20..];
        for w in tail.windows(2) {
            assert_eq!(w[1].wrapping_sub(w[0]), 2, "200 Hz is 2 ticks of 2.5 ms: {ticks:?}");
        }
        let path = mock.tty_path().to_path_buf();
        drop(mock);
        assert!(std::fs::symlink_metadata(path).is_err(), "dropping the handle removes the symlink");
    }
}
