#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]
//! The sans-IO session in memory with simulated time (quinn-proto style): a scripted device
//! answers as the real TiM5xx of `04_command_vectors.txt` section B does.

use std::time::{Duration, Instant};

use amr_drivers::sopas::scan::Channel;
use amr_drivers::sopas::{
    Command, Dialect, DialectChoice, ErrorCode, Event, Framer, Mode, OutputRange, Profile, ProtocolError,
    ReconnectReason, Reply, ScanTelegram, Session, SessionConfig, SopasError, Variable, encode_frame,
};

fn reply_to(cmd: &Command) -> Reply {
    match cmd {
        Command::SetAccessMode { .. } => Reply::AccessMode { granted: true },
        Command::ReadByIndex(_) => {
            Reply::IndexIdent { index: 0, name: "TiM551".into(), version: "V1".into() }
        }
        Command::Read(Variable::SerialNumber) => Reply::SerialNumber("16160456".into()),
        Command::Read(Variable::FirmwareVersion) => Reply::FirmwareVersion("V2.60".into()),
        Command::Read(Variable::DeviceState) => Reply::DeviceState(0),
        Command::Read(Variable::OperatingHours) => Reply::OperatingHours(0x68C),
        Command::Read(Variable::PowerOnCount) => Reply::PowerOnCount(0x79),
        Command::Read(Variable::LocationName) => Reply::LocationName("not defined".into()),
        Command::Read(Variable::OutputRange) => Reply::OutputRange(OutputRange::full_field(0x2710)),
        Command::Read(Variable::ScanDataConfig) => {
            Reply::ScanDataConfig(amr_drivers::sopas::ScanDataConfig::SICK_SCAN_XD)
        }
        Command::Read(Variable::ScanData) => {
            Reply::ScanData { event: false, telegram: Box::new(telegram(0, 0)) }
        }
        Command::Read(Variable::DeviceIdent) => {
            Reply::DeviceIdent { name: "TiM551".into(), version: "V".into() }
        }
        Command::WriteOutputRange(_) => Reply::WriteAck("LMPoutputRange".into()),
        Command::WriteScanDataConfig(_) => Reply::WriteAck("LMDscandatacfg".into()),
        Command::SetDialect(_) => Reply::WriteAck("EIHstCola".into()),
        Command::ScanDataEvents(on) => Reply::ScanDataEvents { enabled: *on },
        Command::Run => Reply::Run { ok: true },
        Command::StartMeasurement => Reply::StartMeasurement { status: 0 },
        Command::StopMeasurement => Reply::StopMeasurement { status: 0 },
        Command::Reboot => Reply::Reboot,
        Command::WriteEeprom => Reply::EepromWritten { ok: true },
    }
}

fn telegram(counter: u16, tick_us: u32) -> ScanTelegram {
    ScanTelegram {
        version: 1,
        device_number: 1,
        serial: 0x1078AAA,
        device_status: [0, 0],
        telegram_counter: counter,
        scan_counter: counter,
        time_since_startup_us: tick_us,
        time_of_transmission_us: tick_us.wrapping_add(5_000),
        input_status: [0, 0],
        output_status: [0, 0],
        reserved_layer_angle: 0,
        scan_frequency_centi_hz: 1500,
        measurement_frequency_hecto_hz: 0x36,
        encoders: vec![],
        channels_16bit: vec![Channel {
            content: "DIST1".into(),
            scale_factor: 1.0,
            scale_offset: 0.0,
            start_angle_1e4deg: -450_000,
            step_1e4deg: 10_000,
            data: (0..271).map(|i| 1000 + i).collect(),
        }],
        channels_8bit: vec![],
        position: None,
        device_name: Some("not defined".into()),
        comment: None,
        time: None,
        event: None,
    }
}

fn scan_frame(dialect: Dialect, counter: u16, tick_us: u32) -> Vec<u8> {
    let reply = Reply::ScanData { event: true, telegram: Box::new(telegram(counter, tick_us)) };
    encode_frame(dialect, &reply.encode(dialect).unwrap())
}

/// Decodes what the session sent: (dialect, command).
fn sent(session: &mut Session) -> Vec<(Dialect, Command)> {
    let mut framer = Framer::default();
    let mut out = Vec::new();
    while let Some(bytes) = session.poll_transmit() {
        framer.push(&bytes);
        while let Some(frame) = framer.next_frame() {
            let frame = frame.unwrap();
            out.push((frame.dialect, Command::decode(frame.dialect, &frame.payload).unwrap()));
        }
    }
    out
}

fn events(session: &mut Session) -> Vec<Event> {
    std::iter::from_fn(|| session.poll_event()).collect()
}

/// Answers every request until the session is running; returns the commands in order.
fn run_startup(
    session: &mut Session,
    now: Instant,
    fail: Option<(&str, ErrorCode)>,
) -> Vec<(Dialect, Command)> {
    let mut log = Vec::new();
    let mut fail = fail;
    for _ in 0..100 {
        let cmds = sent(session);
        if cmds.is_empty() {
            break;
        }
        for (d, cmd) in cmds {
            let reply = match fail {
                Some((label, code)) if cmd.label() == label => {
                    fail = None;
                    Reply::Error(code)
                }
                _ => reply_to(&cmd),
            };
            let reply_dialect = d;
            log.push((d, cmd));
            session.handle_bytes(now, &encode_frame(reply_dialect, &reply.encode(reply_dialect).unwrap()));
        }
    }
    log
}

fn config(profile: Profile, dialect: DialectChoice) -> SessionConfig {
    SessionConfig { profile, dialect, ..SessionConfig::default() }
}

#[test]
fn sopas_minimal_startup_streams_then_the_watchdog_asks_for_a_reconnect() {
    let t0 = Instant::now();
    let mut s = Session::new(config(Profile::Minimal, DialectChoice::Fixed(Dialect::ColaA)), t0);
    assert!(s.needs_connection(t0));
    s.handle_connected(t0);
    let log = run_startup(&mut s, t0, None);
    let labels: Vec<String> = log.iter().map(|(_, c)| c.label()).collect();
    assert_eq!(
        labels,
        ["sRI 0", "sRN SerialNumber", "sRN FirmwareVersion", "sRN SCdevicestate", "sEN LMDscandata"]
    );
    assert!(log.iter().all(|(d, _)| *d == Dialect::ColaA));
    let ev = events(&mut s);
    assert!(matches!(ev[0], Event::DialectDetected(Dialect::ColaA)));
    let Some(Event::Ready(info)) = ev.last() else { panic!("{ev:?}") };
    assert_eq!(info.serial_number.as_deref(), Some("16160456"));
    assert!(s.is_running());

    // Scans every 66.7 ms, split into 7-byte pieces.
    let period = Duration::from_micros(66_667);
    let mut now = t0;
    for k in 0..30u16 {
        now = t0 + period * u32::from(k);
        for piece in scan_frame(Dialect::ColaA, k, 1_000_000 + u32::from(k) * 66_667).chunks(7) {
            s.handle_bytes(now, piece);
        }
        s.handle_timeout(now);
        let ev = events(&mut s);
        assert_eq!(ev.len(), 1, "{ev:?}");
        let Event::Scan(scan) = &ev[0] else { panic!("{ev:?}") };
        assert_eq!(scan.scan.scan_counter, k);
        assert_eq!(scan.scan.ranges_m[0], 1.0);
    }
    // The watchdog: nothing until the scan timeout has passed, then a reconnect.
    assert_eq!(s.poll_timeout(), Some(now + Duration::from_millis(500)));
    s.handle_timeout(now + Duration::from_millis(499));
    assert!(events(&mut s).is_empty());
    s.handle_timeout(now + Duration::from_millis(500));
    let ev = events(&mut s);
    assert!(matches!(ev[0], Event::ProtocolError(ProtocolError::ScanTimeout { timeout_ms: 500 })));
    assert!(
        matches!(ev[1], Event::Reconnect { reason: ReconnectReason::ScanTimeout, delay } if delay == Duration::from_millis(100))
    );
    let t = now + Duration::from_millis(500);
    assert!(!s.needs_connection(t + Duration::from_millis(99)));
    assert!(s.needs_connection(t + Duration::from_millis(100)));
    // The whole start-up runs again after the reconnect.
    s.handle_connected(t + Duration::from_millis(100));
    assert_eq!(run_startup(&mut s, t, None).len(), 5);
}

#[test]
fn sopas_full_startup_in_cola_b_sends_the_sick_scan_xd_sequence() {
    let t0 = Instant::now();
    let mut s = Session::new(config(Profile::Full, DialectChoice::Fixed(Dialect::ColaB)), t0);
    s.handle_connected(t0);
    let log = run_startup(&mut s, t0, None);
    let labels: Vec<String> = log.iter().map(|(_, c)| c.label()).collect();
    assert_eq!(
        labels,
        [
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
            "sEN LMDscandata"
        ]
    );
    // The output range written back is the one read (sick_scan_xd log).
    assert_eq!(log[8].1, Command::WriteOutputRange(OutputRange::full_field(0x2710)));
    assert_eq!(log[1].1, Command::SetDialect(Dialect::ColaB));
    assert!(s.is_running());
}

#[test]
fn sopas_sfa_during_startup_is_reported_and_retried_then_gives_up() {
    let t0 = Instant::now();
    let mut s = Session::new(config(Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB)), t0);
    s.handle_connected(t0);
    let log = run_startup(&mut s, t0, Some(("sRN FirmwareVersion", ErrorCode::MethodInServerBusy)));
    assert_eq!(log.iter().filter(|(_, c)| c.label() == "sRN FirmwareVersion").count(), 2);
    let ev = events(&mut s);
    let errors: Vec<_> =
        ev.iter().filter_map(|e| if let Event::DeviceError(d) = e { Some(d) } else { None }).collect();
    assert_eq!(errors.len(), 1);
    assert_eq!(errors[0].command, "sRN FirmwareVersion");
    assert_eq!(errors[0].code.name(), "METHODIN_SERVER_BUSY");
    assert!(s.is_running());

    // A device that always refuses: three attempts, then a reconnect for the device error.
    let mut s = Session::new(config(Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB)), t0);
    s.handle_connected(t0);
    for _ in 0..10 {
        let cmds = sent(&mut s);
        if cmds.is_empty() {
            break;
        }
        for (d, _) in cmds {
            let sfa = Reply::Error(ErrorCode::VariableUnknownIndex).encode(d).unwrap();
            s.handle_bytes(t0, &encode_frame(d, &sfa));
        }
    }
    let ev = events(&mut s);
    assert_eq!(ev.iter().filter(|e| matches!(e, Event::DeviceError(_))).count(), 3);
    assert!(matches!(
        ev.last(),
        Some(Event::Reconnect { reason: ReconnectReason::StartupFailed(SopasError::Device(_)), .. })
    ));
}

#[test]
fn sopas_auto_dialect_probes_cola_b_then_cola_a() {
    let t0 = Instant::now();
    let mut s = Session::new(config(Profile::Minimal, DialectChoice::Auto), t0);
    s.handle_connected(t0);
    let first = sent(&mut s);
    assert_eq!(first, [(Dialect::ColaB, Command::ReadByIndex(0))]);
    let deadline = s.poll_timeout().unwrap();
    assert_eq!(deadline, t0 + Duration::from_secs(1));
    s.handle_timeout(deadline);
    let second = sent(&mut s);
    assert_eq!(second, [(Dialect::ColaA, Command::ReadByIndex(0))]);
    let reply = reply_to(&second[0].1).encode(Dialect::ColaA).unwrap();
    s.handle_bytes(deadline, &encode_frame(Dialect::ColaA, &reply));
    assert_eq!(s.dialect(), Dialect::ColaA);
    let log = run_startup(&mut s, deadline, None);
    assert!(log.iter().all(|(d, _)| *d == Dialect::ColaA));
    assert!(s.is_running());
}

#[test]
fn sopas_backoff_doubles_and_is_capped_and_resets_after_a_scan() {
    let t0 = Instant::now();
    let mut cfg = config(Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB));
    cfg.backoff_max = Duration::from_millis(700);
    let mut s = Session::new(cfg, t0);
    let mut now = t0;
    let mut delays = Vec::new();
    for _ in 0..5 {
        assert!(s.needs_connection(now));
        s.handle_connect_failed(now, amr_drivers::sopas::LinkError::Closed);
        let ev = events(&mut s);
        let Some(Event::Reconnect { delay, .. }) = ev.last() else { panic!("{ev:?}") };
        delays.push(delay.as_millis());
        now += *delay;
    }
    assert_eq!(delays, [100, 200, 400, 700, 700]);
    s.handle_connected(now);
    run_startup(&mut s, now, None);
    s.handle_bytes(now, &scan_frame(Dialect::ColaB, 1, 5));
    s.handle_disconnected(now, amr_drivers::sopas::LinkError::Closed);
    let ev = events(&mut s);
    assert!(
        matches!(ev.last(), Some(Event::Reconnect { delay, .. }) if *delay == Duration::from_millis(100))
    );
}

#[test]
fn sopas_poll_mode_requests_a_scan_every_period() {
    let t0 = Instant::now();
    let mut cfg = config(Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB));
    cfg.mode = Mode::Poll { period: Duration::from_millis(200) };
    cfg.scan_timeout = Duration::from_secs(2);
    let mut s = Session::new(cfg, t0);
    s.handle_connected(t0);
    let log = run_startup(&mut s, t0, None);
    // No subscription in poll mode; the first poll went out with the last answer.
    assert!(!log.iter().any(|(_, c)| matches!(c, Command::ScanDataEvents(_))));
    assert_eq!(log.last().unwrap().1, Command::Read(Variable::ScanData));
    let mut polls = 0;
    for ms in (0..=1000).step_by(50) {
        s.handle_timeout(t0 + Duration::from_millis(ms));
        polls += sent(&mut s).len();
    }
    assert_eq!(polls, 5, "polls at 200, 400, 600, 800, 1000 ms");
}

#[test]
fn sopas_protocol_errors_are_reported_and_do_not_break_the_session() {
    let t0 = Instant::now();
    let mut s = Session::new(config(Profile::Minimal, DialectChoice::Fixed(Dialect::ColaB)), t0);
    s.handle_connected(t0);
    run_startup(&mut s, t0, None);
    events(&mut s);
    let mut bad = scan_frame(Dialect::ColaB, 1, 10);
    let n = bad.len();
    bad[n - 1] ^= 1;
    let mut stream = b"\x00\xffgarbage".to_vec();
    stream.extend_from_slice(&bad);
    stream.extend_from_slice(&scan_frame(Dialect::ColaB, 2, 20));
    s.handle_bytes(t0, &stream);
    let ev = events(&mut s);
    // The broken frame is reported (the resync through its bytes may report more pseudo-frames),
    // and the good frame behind it arrives: exactly one scan, the right one, last.
    assert!(matches!(ev[0], Event::ProtocolError(ProtocolError::Frame(_))));
    let scans: Vec<u16> = ev
        .iter()
        .filter_map(|e| if let Event::Scan(sc) = e { Some(sc.scan.scan_counter) } else { None })
        .collect();
    assert_eq!(scans, [2]);
    assert!(matches!(ev.last(), Some(Event::Scan(_))));
    assert!(s.is_running());
}

/// The same inputs at the same instants give the same events and the same bytes out.
#[test]
fn sopas_session_is_deterministic() {
    let run = |t0: Instant| {
        let mut s = Session::new(config(Profile::Full, DialectChoice::Auto), t0);
        s.handle_connected(t0);
        let mut log =
            format!("{:?}", run_startup(&mut s, t0, Some(("sRN ODpwrc", ErrorCode::BufferUnderflow))));
        for k in 0..20u16 {
            let now = t0 + Duration::from_millis(67 * u64::from(k));
            s.handle_bytes(now, &scan_frame(Dialect::ColaB, k, 3_000 + 66_700 * u32::from(k)));
            s.handle_timeout(now);
        }
        s.handle_timeout(t0 + Duration::from_secs(5));
        for e in events(&mut s) {
            log.push_str(&format!("{e:?}\n"));
        }
        log
    };
    let t0 = Instant::now();
    let a = run(t0);
    assert_eq!(a, run(t0));
    assert!(a.contains("BufferUnderflow") && a.contains("ScanTimeout"));
}
