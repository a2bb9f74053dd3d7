#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]
//! The SOPAS driver (`amr_drivers::sopas::tcp`) against the mock TiM5xx over real loopback TCP (the
//! 30 s stream runs on virtual time over an in-memory pipe).
//! Every wait is bounded by `tokio::time::timeout` and a message count; nothing sleeps to wait.

use std::sync::Arc;
use std::time::Duration;

use amr_drivers::sopas::{
    Dialect, DialectChoice, ErrorCode, FrameError, Health, LidarConfig, LidarMessage, Mode, Profile,
    ProtocolError, SopasError, StampedScan, spawn_tcp, tcp::spawn_stream,
};
use amr_settings::value::Backoff;
use hil_mocks::tim551::{Fault, MockConfig, RectRoom, Tim551Mock, Variant};
use tokio::sync::mpsc::Receiver;
use tokio::time::Instant;

const MAX_MESSAGES: usize = 20_000;

async fn mock(config: MockConfig) -> Tim551Mock {
    Tim551Mock::spawn("127.0.0.1:0", config, Arc::new(RectRoom::default())).await.unwrap()
}

fn lidar(port: u16, profile: Profile, dialect: DialectChoice) -> LidarConfig {
    LidarConfig {
        host: "127.0.0.1".into(),
        port,
        dialect,
        startup: profile,
        mode: Mode::Streaming,
        reply_timeout: Duration::from_millis(300),
        scan_timeout: Duration::from_millis(500),
        reconnect: Backoff { initial: Duration::from_millis(50), max: Duration::from_millis(400) },
        connect_timeout: Duration::from_secs(1),
        ..LidarConfig::default()
    }
}

/// Waits for the first message `f` accepts, collecting everything seen on the way.
async fn wait_for<T>(
    rx: &mut Receiver<LidarMessage>,
    within: Duration,
    seen: &mut Vec<LidarMessage>,
    mut f: impl FnMut(&LidarMessage) -> Option<T>,
) -> T {
    let deadline = Instant::now() + within;
    for _ in 0..MAX_MESSAGES {
        let msg = tokio::time::timeout_at(deadline, rx.recv())
            .await
            .unwrap_or_else(|_| panic!("timed out; seen: {:?}", summary(seen)))
            .expect("driver stopped");
        if let Some(t) = f(&msg) {
            seen.push(msg);
            return t;
        }
        seen.push(msg);
    }
    panic!("too many messages")
}

fn summary(seen: &[LidarMessage]) -> Vec<String> {
    seen.iter()
        .rev()
        .take(20)
        .map(|m| match m {
            LidarMessage::Scan(s) => format!("scan {}", s.scan.scan_counter),
            other => format!("{other:?}").chars().take(200).collect(),
        })
        .collect()
}

fn scan(m: &LidarMessage) -> Option<StampedScan> {
    match m {
        LidarMessage::Scan(s) => Some((**s).clone()),
        _ => None,
    }
}

fn expected_sequence(profile: Profile) -> Vec<&'static str> {
    match profile {
        Profile::Minimal => {
            vec!["sRI 0", "sRN SerialNumber", "sRN FirmwareVersion", "sRN SCdevicestate", "sEN LMDscandata"]
        }
        Profile::Full => vec![
            "sMN SetAccessMode",
            "sWN EIHstCola",
            "sRN FirmwareVersion",
            "sRN SCdevicestate",
            "sRN ODoprh",
            "sRN ODpwrc",
            "sRN LocationName",
            "sRN LMPoutputRange",
            "sWN LMPoutputRange",
            "sRN LMPoutputRange",
            "sWN LMDscandatacfg",
            "sRN LMDscandatacfg",
            "sMN LMCstartmeas",
            "sMN Run",
            "sEN LMDscandata",
        ],
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_both_profiles_in_both_dialects_reach_streaming() {
    for profile in [Profile::Minimal, Profile::Full] {
        for dialect in [Dialect::ColaA, Dialect::ColaB] {
            let m = mock(MockConfig::default()).await;
            let (task, mut rx) = spawn_tcp(lidar(m.port(), profile, DialectChoice::Fixed(dialect)), 64);
            let mut seen = Vec::new();
            let info = wait_for(&mut rx, Duration::from_secs(5), &mut seen, |m| match m {
                LidarMessage::Health(Health::Ok(info)) => Some(info.clone()),
                _ => None,
            })
            .await;
            assert_eq!(info.dialect, Some(dialect));
            assert_eq!(info.firmware_version.as_deref(), Some("V2.60"));
            if profile == Profile::Minimal {
                assert_eq!(info.name.as_deref(), Some("TiM551"));
                assert_eq!(info.serial_number.as_deref(), Some("16921686"));
            } else {
                assert_eq!(info.login_granted, Some(true));
                assert_eq!(info.output_range.as_ref().unwrap().sectors[0].resolution_1e4deg, 0x2710);
            }
            let s = wait_for(&mut rx, Duration::from_secs(2), &mut seen, scan).await;
            // TiM551: 271 beams, 1°, robot frame −135°..135°, from the room (front wall at 4 m).
            assert_eq!(s.scan.ranges_m.len(), 271);
            assert!((s.scan.angle_min_rad + 135f64.to_radians()).abs() < 1e-9);
            assert!((s.scan.angle_increment_rad - 1f64.to_radians()).abs() < 1e-12);
            assert!((s.scan.ranges_m[135] - 4.0).abs() < 1e-3, "{}", s.scan.ranges_m[135]);
            assert!((s.scan.ranges_m[45] - 2.5).abs() < 1e-3, "right wall {}", s.scan.ranges_m[45]);
            assert_eq!(s.scan.measurement_frequency_hz, 5400.0);
            assert_eq!(s.scan.rssi.as_ref().map(Vec::len), Some(271));
            assert!(s.stamp.is_some());
            let log: Vec<(Dialect, String)> =
                m.handle.command_log().into_iter().map(|(_, d, l)| (d, l)).collect();
            let want: Vec<(Dialect, String)> =
                expected_sequence(profile).into_iter().map(|l| (dialect, l.to_string())).collect();
            assert_eq!(log, want, "{profile:?} {dialect:?}");
            task.abort();
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_dialect_is_detected_and_switched() {
    // A device fixed to CoLa-A ignores CoLa-B: the driver's CoLa-B probe times out, it retries in
    // CoLa-A, then switches the device with `sWN EIHstCola 1` and continues in CoLa-B.
    let m = mock(MockConfig { dialect: Some(Dialect::ColaA), ..MockConfig::default() }).await;
    let (task, mut rx) =
        spawn_tcp(lidar(m.port(), Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB)), 64);
    let mut seen = Vec::new();
    let info = wait_for(&mut rx, Duration::from_secs(5), &mut seen, |m| match m {
        LidarMessage::Health(Health::Ok(info)) => Some(info.clone()),
        _ => None,
    })
    .await;
    assert_eq!(info.dialect, Some(Dialect::ColaB));
    wait_for(&mut rx, Duration::from_secs(2), &mut seen, scan).await;
    let log: Vec<(Dialect, String)> = m.handle.command_log().into_iter().map(|(_, d, l)| (d, l)).collect();
    assert_eq!(log[0], (Dialect::ColaA, "sRI 0".to_string()));
    assert_eq!(log[1], (Dialect::ColaA, "sWN EIHstCola".to_string()));
    assert!(log[2..].iter().all(|(d, _)| *d == Dialect::ColaB), "{log:?}");
    task.abort();

    // Auto keeps whatever the device speaks.
    let m = mock(MockConfig { dialect: Some(Dialect::ColaA), ..MockConfig::default() }).await;
    let (task, mut rx) = spawn_tcp(lidar(m.port(), Profile::Full, DialectChoice::Auto), 64);
    let info = wait_for(&mut rx, Duration::from_secs(5), &mut seen, |m| match m {
        LidarMessage::Health(Health::Ok(info)) => Some(info.clone()),
        _ => None,
    })
    .await;
    assert_eq!(info.dialect, Some(Dialect::ColaA));
    wait_for(&mut rx, Duration::from_secs(2), &mut seen, scan).await;
    task.abort();
}

/// The long stream on virtual time: the same driver and mock over an in-memory pipe instead of
/// TCP (the tests around it keep the socket), 30 s of scans in well under a second, whatever else
/// the machine does.
#[tokio::test(start_paused = true)]
async fn tim551_streams_15hz_for_30s_without_losing_a_scan() {
    // Ticks start just below the 32-bit wrap (~71.6 min), so the wrap happens during the run.
    let initial_tick_us = u32::MAX - 10_000_000;
    let config = MockConfig { initial_tick_us, ..MockConfig::default() };
    let (_m, connector) = Tim551Mock::spawn_in_memory(config, Arc::new(RectRoom::default()));
    let connect = move |_: String| {
        let c = connector.clone();
        async move { c.connect().await }
    };
    let (task, mut rx) =
        spawn_stream(lidar(0, Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB)), connect, 256);
    let mut seen = Vec::new();
    let first = wait_for(&mut rx, Duration::from_secs(5), &mut seen, scan).await;
    let start = Instant::now();
    let mut scans = vec![first];
    for _ in 0..MAX_MESSAGES {
        let remaining = Duration::from_secs(30).saturating_sub(start.elapsed());
        if remaining.is_zero() {
            break;
        }
        match tokio::time::timeout(remaining, rx.recv()).await {
            Err(_) => break,
            Ok(None) => panic!("driver stopped"),
            Ok(Some(LidarMessage::Scan(s))) => scans.push(*s),
            Ok(Some(LidarMessage::Health(Health::Lost { .. }))) => panic!("connection lost during streaming"),
            Ok(Some(LidarMessage::Error(e))) => panic!("error during clean streaming: {e}"),
            Ok(Some(_)) => {}
        }
    }
    // 30 s at 15 Hz is 450 scans; the mock never skips one, so only the window edges vary.
    assert!(scans.len() >= 445, "only {} scans in 30 s", scans.len());
    for w in scans.windows(2) {
        assert_eq!(w[1].scan.scan_counter, w[0].scan.scan_counter.wrapping_add(1), "lost a scan");
        assert_eq!(w[1].scan.telegram_counter, w[0].scan.telegram_counter.wrapping_add(1));
        // Host stamps come from the device ticks: strictly increasing, ~66.7 ms apart, through the wrap.
        let dt = w[1].stamp.unwrap().duration_since(w[0].stamp.unwrap()).as_secs_f64();
        assert!((dt - 1.0 / 15.0).abs() < 0.005, "stamp step {dt}");
    }
    assert!(
        scans.first().unwrap().scan.generation_tick_us > scans.last().unwrap().scan.generation_tick_us,
        "no wrap"
    );
    // A stamp is never later than its receipt (the scan ended before it was sent).
    for s in &scans[20..] {
        assert!(s.stamp.unwrap() <= s.received + Duration::from_millis(1));
    }
    tracing::info!(scans = scans.len(), "streamed");
    eprintln!("30 s streaming: {} scans", scans.len());
    task.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_streams_again_within_1s_after_a_drop() {
    let m = mock(MockConfig::default()).await;
    let (task, mut rx) = spawn_tcp(lidar(m.port(), Profile::Full, DialectChoice::Fixed(Dialect::ColaB)), 64);
    let mut seen = Vec::new();
    wait_for(&mut rx, Duration::from_secs(5), &mut seen, scan).await;
    let refuse_for = Duration::from_millis(700);
    m.handle.inject(Fault::Drop { refuse_for });
    let accepting_again = Instant::now() + refuse_for;
    wait_for(&mut rx, Duration::from_secs(2), &mut seen, |m| {
        matches!(m, LidarMessage::Health(Health::Lost { .. })).then_some(())
    })
    .await;
    wait_for(&mut rx, Duration::from_secs(5), &mut seen, scan).await;
    let after = Instant::now().saturating_duration_since(accepting_again);
    eprintln!("streaming again {} ms after the mock accepted again", after.as_millis());
    assert!(after < Duration::from_secs(1), "took {after:?}");
    assert!(m.handle.connections() >= 3, "the refused attempts count too");
    task.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_stall_is_detected_within_the_watchdog_time() {
    let m = mock(MockConfig::default()).await;
    let (task, mut rx) = spawn_tcp(lidar(m.port(), Profile::Minimal, DialectChoice::Auto), 64);
    let mut seen = Vec::new();
    wait_for(&mut rx, Duration::from_secs(5), &mut seen, scan).await;
    m.handle.inject(Fault::Stall);
    let mut last_scan = Instant::now();
    let lost_at = wait_for(&mut rx, Duration::from_secs(3), &mut seen, |m| match m {
        LidarMessage::Scan(_) => {
            last_scan = Instant::now();
            None
        }
        LidarMessage::Error(SopasError::Protocol(ProtocolError::ScanTimeout { timeout_ms })) => {
            assert_eq!(*timeout_ms, 500);
            Some(Instant::now())
        }
        _ => None,
    })
    .await;
    let silence = lost_at.duration_since(last_scan);
    eprintln!("stall detected {} ms after the last scan", silence.as_millis());
    assert!(silence >= Duration::from_millis(450), "watchdog fired early: {silence:?}");
    assert!(silence < Duration::from_millis(800), "watchdog late: {silence:?}");
    m.handle.inject(Fault::Resume);
    wait_for(&mut rx, Duration::from_secs(5), &mut seen, scan).await;
    task.abort();
}

/// Scan counters of the next `n` scans, and the frame errors seen meanwhile.
async fn collect(rx: &mut Receiver<LidarMessage>, n: usize) -> (Vec<u16>, Vec<SopasError>) {
    let mut counters = Vec::new();
    let mut errors = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(5);
    for _ in 0..MAX_MESSAGES {
        if counters.len() >= n {
            break;
        }
        match tokio::time::timeout_at(deadline, rx.recv()).await.unwrap().unwrap() {
            LidarMessage::Scan(s) => counters.push(s.scan.scan_counter),
            LidarMessage::Error(e) => errors.push(e),
            LidarMessage::Health(h) => panic!("unexpected health change {h:?}"),
        }
    }
    (counters, errors)
}

fn gaps(counters: &[u16]) -> u32 {
    counters.windows(2).map(|w| u32::from(w[1].wrapping_sub(w[0])) - 1).sum()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_garbage_and_broken_frames_cost_only_the_frames_they_touch() {
    for dialect in [Dialect::ColaA, Dialect::ColaB] {
        let m = mock(MockConfig::default()).await;
        let mut cfg = lidar(m.port(), Profile::Minimal, DialectChoice::Fixed(dialect));
        cfg.scan_timeout = Duration::from_secs(2);
        let (task, mut rx) = spawn_tcp(cfg, 256);
        let mut seen = Vec::new();
        let first = wait_for(&mut rx, Duration::from_secs(5), &mut seen, scan).await;
        let mut last = first.scan.scan_counter;
        // Each phase's counters start with the last counter of the phase before.
        let mut phase = async |rx: &mut Receiver<LidarMessage>| {
            let (mut counters, errors) = collect(rx, 8).await;
            counters.insert(0, last);
            last = *counters.last().unwrap();
            (counters, errors)
        };

        // Garbage (with fake STX / magic bytes) before a scan: no scan lost.
        m.handle.inject(Fault::Garbage(b"\x02\x02xx\x03junk\x02\x02\x02\x02\x7f\x00\x00\x01zz\x02".to_vec()));
        let (counters, _) = phase(&mut rx).await;
        assert_eq!(gaps(&counters), 0, "{dialect:?} garbage: {counters:?}");

        // A corrupted scan: exactly that one is lost, and reported.
        m.handle.inject(Fault::CorruptNext);
        let (counters, errors) = phase(&mut rx).await;
        assert_eq!(gaps(&counters), 1, "{dialect:?} corrupt: {counters:?} {errors:?}");
        match dialect {
            Dialect::ColaB => assert!(
                errors.iter().any(|e| matches!(
                    e,
                    SopasError::Protocol(ProtocolError::Frame(FrameError::Checksum { .. }))
                )),
                "{errors:?}"
            ),
            Dialect::ColaA => assert!(
                errors.iter().any(|e| matches!(e, SopasError::Protocol(ProtocolError::Decode(_)))),
                "{errors:?}"
            ),
        }

        // A truncated scan: that one is lost. In CoLa-B the cut frame's length field swallows the
        // start of the next frame; the resync finds it again unless the swallowed bytes happen to
        // pass the XOR (p = 1/256), which would cost that next frame too.
        m.handle.inject(Fault::TruncateNext);
        let (counters, errors) = phase(&mut rx).await;
        let lost = gaps(&counters);
        assert!(lost == 1 || (dialect == Dialect::ColaB && lost == 2), "{dialect:?} truncated: {counters:?}");
        assert!(!errors.is_empty());
        task.abort();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_sfa_during_startup_is_reported_by_name_and_retried() {
    let m = mock(MockConfig::default()).await;
    m.handle.inject(Fault::ErrorReply {
        command: "sRN SerialNumber".into(),
        code: ErrorCode::MethodInServerBusy,
        times: 1,
    });
    let (task, mut rx) =
        spawn_tcp(lidar(m.port(), Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB)), 64);
    let mut seen = Vec::new();
    let err = wait_for(&mut rx, Duration::from_secs(5), &mut seen, |m| match m {
        LidarMessage::Error(SopasError::Device(e)) => Some(e.clone()),
        _ => None,
    })
    .await;
    assert_eq!(err.command, "sRN SerialNumber");
    assert_eq!(err.code.name(), "METHODIN_SERVER_BUSY");
    assert!(err.to_string().contains("METHODIN_SERVER_BUSY"));
    let info = wait_for(&mut rx, Duration::from_secs(5), &mut seen, |m| match m {
        LidarMessage::Health(Health::Ok(info)) => Some(info.clone()),
        LidarMessage::Health(Health::Lost { .. }) => panic!("one sFA must not cost the connection"),
        _ => None,
    })
    .await;
    assert!(info.serial_number.is_some());
    wait_for(&mut rx, Duration::from_secs(2), &mut seen, scan).await;
    let serial_requests = m.handle.command_log().iter().filter(|(_, _, l)| l == "sRN SerialNumber").count();
    assert_eq!(serial_requests, 2, "refused once, retried once");
    task.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_slow_replies_time_out_and_the_session_recovers() {
    let m = mock(MockConfig::default()).await;
    m.handle.inject(Fault::SlowReplies(Duration::from_millis(500)));
    let (task, mut rx) =
        spawn_tcp(lidar(m.port(), Profile::Minimal, DialectChoice::Fixed(Dialect::ColaA)), 64);
    let mut seen = Vec::new();
    wait_for(&mut rx, Duration::from_secs(5), &mut seen, |m| {
        matches!(m, LidarMessage::Error(SopasError::Protocol(ProtocolError::ReplyTimeout { .. })))
            .then_some(())
    })
    .await;
    m.handle.inject(Fault::Resume);
    wait_for(&mut rx, Duration::from_secs(8), &mut seen, scan).await;
    task.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_reboot_restarts_counters_and_the_clock_follows() {
    let m = mock(MockConfig { initial_tick_us: 900_000_000, ..MockConfig::default() }).await;
    let (task, mut rx) = spawn_tcp(lidar(m.port(), Profile::Full, DialectChoice::Fixed(Dialect::ColaB)), 64);
    let mut seen = Vec::new();
    // Let some scans pass so the counters are well above zero.
    let mut before = wait_for(&mut rx, Duration::from_secs(5), &mut seen, scan).await;
    for _ in 0..10 {
        before = wait_for(&mut rx, Duration::from_secs(2), &mut seen, scan).await;
    }
    m.handle.inject(Fault::Reboot { down_for: Duration::from_millis(300) });
    wait_for(&mut rx, Duration::from_secs(2), &mut seen, |m| {
        matches!(m, LidarMessage::Health(Health::Lost { .. })).then_some(())
    })
    .await;
    let after = wait_for(&mut rx, Duration::from_secs(5), &mut seen, scan).await;
    assert!(
        after.scan.scan_counter < before.scan.scan_counter,
        "{} !< {}",
        after.scan.scan_counter,
        before.scan.scan_counter
    );
    assert!(after.scan.generation_tick_us < 900_000_000 + 2_000_000);
    // The tick went back; the mapping restarted rather than stamping the scan in the past.
    let stamp = after.stamp.unwrap();
    let lag = after.received.duration_since(stamp);
    assert!(lag < Duration::from_millis(100), "stamp {lag:?} before receipt");
    assert!(stamp > before.received);
    task.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tim551_polls_an_811_point_device_and_serves_two_clients() {
    let m = mock(MockConfig { variant: Variant::Tim561, ..MockConfig::default() }).await;
    let mut poll_cfg = lidar(m.port(), Profile::Full, DialectChoice::Fixed(Dialect::ColaA));
    poll_cfg.mode = Mode::Poll { period: Duration::from_millis(100) };
    let (poll_task, mut poll_rx) = spawn_tcp(poll_cfg, 64);
    let (stream_task, mut stream_rx) =
        spawn_tcp(lidar(m.port(), Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB)), 64);
    let mut seen = Vec::new();
    let mut polled = Vec::new();
    for _ in 0..3 {
        polled.push(wait_for(&mut poll_rx, Duration::from_secs(5), &mut seen, scan).await);
    }
    for s in &polled {
        assert_eq!(s.scan.ranges_m.len(), 811);
        assert!((s.scan.angle_increment_rad - 0.3333f64.to_radians()).abs() < 1e-12);
        assert_eq!(s.scan.measurement_frequency_hz, 16_200.0);
    }
    assert!(polled.windows(2).all(|w| w[1].scan.telegram_counter == w[0].scan.telegram_counter + 1));
    let streamed = wait_for(&mut stream_rx, Duration::from_secs(5), &mut seen, scan).await;
    assert_eq!(streamed.scan.ranges_m.len(), 811);
    let log = m.handle.command_log();
    assert!(log.iter().filter(|(_, _, l)| l == "sRN LMDscandata").count() >= 3);
    assert_eq!(log.iter().map(|(c, _, _)| *c).collect::<std::collections::BTreeSet<_>>().len(), 2);
    poll_task.abort();
    stream_task.abort();
}
