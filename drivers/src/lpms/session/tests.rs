//! Tests of the LPMS-B2 session: start-up, retries, NACKs, watchdog and backoff, the data layout.

use super::super::data::encode_sensor_data;
use super::super::frame::Frame;
use super::*;

fn drain(s: &mut Session) -> Vec<Event> {
    std::iter::from_fn(|| s.poll_event()).collect()
}

fn sent_commands(s: &mut Session) -> Vec<Command> {
    let mut d = FrameDecoder::new();
    while let Some(b) = s.poll_transmit() {
        d.push(&b);
    }
    std::iter::from_fn(|| d.next_frame()).map(|f| Command::from_frame(&f.unwrap()).unwrap()).collect()
}

fn reply(s: &mut Session, now: Instant, r: Reply) {
    s.handle_bytes(now, &r.to_frame(1).encode().unwrap());
}

/// Opens the link and answers every start-up command like a sensor whose config register is
/// `reg`; returns the commands in the order they came.
fn answer_start_up(s: &mut Session, now: Instant, reg: ConfigRegister) -> Vec<Command> {
    s.handle_timeout(now);
    assert_eq!(drain(s), vec![Event::OpenLink]);
    s.link_up(now);
    let mut seen = Vec::new();
    for _ in 0..9 {
        let cmds = sent_commands(s);
        assert_eq!(cmds.len(), 1, "one request at a time");
        seen.push(cmds[0]);
        let r = match cmds[0] {
            Command::GetConfig => Reply::Config(reg),
            Command::GetImuId => Reply::ImuId(1),
            Command::GetFirmwareVersion => {
                Reply::FirmwareVersion(FirmwareVersion { major: 2, minor: 1, build: 0 })
            }
            _ => Reply::Ack,
        };
        reply(s, now, r);
    }
    seen
}

/// A well-behaved sensor: it applies what it is told.
fn configure(s: &mut Session, now: Instant) -> ConfigRegister {
    let c = s.config().clone();
    let reg = ConfigRegister::from_settings(c.outputs, c.data_mode, c.stream_hz).unwrap();
    answer_start_up(s, now, reg);
    reg
}

#[test]
fn start_up_sends_the_documented_sequence_then_streams() {
    let t0 = Instant::now();
    let mut s = Session::new(SessionConfig::default(), t0);
    let reg = ConfigRegister::from_settings(s.config().outputs, DataMode::Float32, 100).unwrap();
    let seen = answer_start_up(&mut s, t0, reg);
    let c = SessionConfig::default();
    assert_eq!(
        seen,
        vec![
            Command::GotoCommandMode,
            Command::GetConfig,
            Command::GetImuId,
            Command::GetFirmwareVersion,
            Command::SetTransmitData(c.outputs),
            Command::SetStreamFreq(100),
            Command::SetLpbusDataMode(DataMode::Float32),
            Command::GetConfig,
            Command::GotoStreamMode,
        ]
    );
    assert!(matches!(drain(&mut s).as_slice(), [Event::Ready(DeviceInfo { imu_id: 1, .. })]));
    assert_eq!(s.phase(), Phase::Streaming);
    let sample = SensorData { timestamp_ticks: 4, gyro_radps: Some([0.0, 0.0, 0.5]), ..Default::default() };
    let payload = encode_sensor_data(&sample, reg.outputs(), reg.data_mode());
    s.handle_bytes(t0, &Frame::new(1, 9, payload).encode().unwrap());
    match drain(&mut s).as_slice() {
        [Event::Sample(got)] => {
            assert_eq!(got.timestamp_ticks, 4);
            assert_eq!(got.gyro_radps, Some([0.0, 0.0, 0.5]));
        }
        other => panic!("expected one sample, got {other:?}"),
    }
}

#[test]
fn goto_command_mode_is_retried_while_data_streams() {
    let t0 = Instant::now();
    let cfg = SessionConfig::default();
    let mut s = Session::new(cfg.clone(), t0);
    s.handle_timeout(t0);
    assert_eq!(drain(&mut s), vec![Event::OpenLink]);
    s.link_up(t0);
    assert_eq!(sent_commands(&mut s), vec![Command::GotoCommandMode]);
    // The sensor keeps streaming and the reply is lost.
    s.handle_bytes(t0, &Frame::new(1, 9, vec![0; 8]).encode().unwrap());
    assert_eq!(s.poll_timeout(), Some(t0 + cfg.reply_timeout));
    s.handle_timeout(t0 + cfg.reply_timeout);
    assert_eq!(sent_commands(&mut s), vec![Command::GotoCommandMode]);
    reply(&mut s, t0 + cfg.reply_timeout, Reply::Ack);
    assert_eq!(sent_commands(&mut s), vec![Command::GetConfig]);
    assert!(drain(&mut s).is_empty(), "stream leftovers are not errors");
}

#[test]
fn no_reply_after_every_attempt_takes_the_link_down() {
    let t0 = Instant::now();
    let cfg = SessionConfig { command_attempts: 3, ..SessionConfig::default() };
    let mut s = Session::new(cfg.clone(), t0);
    s.handle_timeout(t0);
    assert_eq!(drain(&mut s), vec![Event::OpenLink]);
    s.link_up(t0);
    let mut now = t0;
    for _ in 0..3 {
        now += cfg.reply_timeout;
        s.handle_timeout(now);
    }
    let events = drain(&mut s);
    assert_eq!(
        events.last(),
        Some(&Event::LinkDown(LinkError::ReplyTimeout { command: CommandId::GotoCommandMode, attempts: 3 }))
    );
    assert_eq!(s.phase(), Phase::Closed);
    assert_eq!(s.poll_timeout(), Some(now + cfg.backoff_initial));
}

#[test]
fn a_nack_names_the_command_and_keeps_the_link() {
    let t0 = Instant::now();
    let mut s = Session::new(SessionConfig::default(), t0);
    s.handle_timeout(t0);
    assert_eq!(drain(&mut s), vec![Event::OpenLink]);
    s.link_up(t0);
    let mut now = t0;
    loop {
        let cmds = sent_commands(&mut s);
        assert_eq!(cmds.len(), 1);
        if let Command::SetStreamFreq(_) = cmds[0] {
            reply(&mut s, now, Reply::Nack);
            break;
        }
        let r = match cmds[0] {
            Command::GetConfig => Reply::Config(ConfigRegister(0)),
            Command::GetImuId => Reply::ImuId(1),
            Command::GetFirmwareVersion => {
                Reply::FirmwareVersion(FirmwareVersion { major: 1, minor: 3, build: 5 })
            }
            _ => Reply::Ack,
        };
        reply(&mut s, now, r);
        now += Duration::from_millis(1);
    }
    assert_eq!(
        drain(&mut s),
        vec![Event::DeviceError(DeviceError::Nack { command: CommandId::SetStreamFreq })]
    );
    assert_eq!(s.phase(), Phase::Configuring);
    // After the backoff the start-up begins again, without a reopen.
    s.handle_timeout(now + s.config().backoff_initial);
    assert_eq!(sent_commands(&mut s), vec![Command::GotoCommandMode]);
    assert!(drain(&mut s).is_empty());
}

#[test]
fn the_watchdog_closes_the_link_and_backoff_doubles_up_to_the_cap() {
    let t0 = Instant::now();
    let cfg = SessionConfig {
        backoff_initial: Duration::from_millis(100),
        backoff_max: Duration::from_millis(300),
        ..SessionConfig::default()
    };
    let mut s = Session::new(cfg.clone(), t0);
    configure(&mut s, t0);
    drain(&mut s);
    let t1 = t0 + cfg.data_timeout;
    assert_eq!(s.poll_timeout(), Some(t1));
    s.handle_timeout(t1);
    assert_eq!(drain(&mut s), vec![Event::LinkDown(LinkError::data_timeout(cfg.data_timeout))]);
    // Each failed open doubles the delay: 100, 200, 300 (cap), 300 ms.
    let mut now = t1;
    let mut delays = Vec::new();
    for _ in 0..4 {
        let next = s.poll_timeout().unwrap();
        delays.push(next - now);
        now = next;
        s.handle_timeout(now);
        assert_eq!(drain(&mut s), vec![Event::OpenLink]);
        s.link_failed(now, LinkError::Io { kind: std::io::ErrorKind::NotFound, message: "gone".into() });
        drain(&mut s);
    }
    let ms = |m| Duration::from_millis(m);
    assert_eq!(delays, vec![ms(100), ms(200), ms(300), ms(300)]);
}

#[test]
fn a_payload_that_does_not_match_the_mask_is_a_protocol_error() {
    let t0 = Instant::now();
    let mut s = Session::new(SessionConfig::default(), t0);
    let reg = configure(&mut s, t0);
    drain(&mut s);
    let good_len = super::super::data::payload_len(reg.outputs(), reg.data_mode());
    s.handle_bytes(t0, &Frame::new(1, 9, vec![0; good_len - 2]).encode().unwrap());
    assert!(matches!(drain(&mut s).as_slice(), [Event::ProtocolError(ProtocolError::Data(_))]));
    assert_eq!(s.stats().samples, 0);
}

#[test]
fn a_config_that_was_not_applied_is_reported_and_the_reported_layout_is_used() {
    let t0 = Instant::now();
    let mut s = Session::new(SessionConfig::default(), t0);
    // The sensor keeps gyro-only 16-bit output at 50 Hz whatever it is told.
    let reported = ConfigRegister::from_settings(OutputMask::GYRO, DataMode::Int16, 50).unwrap();
    answer_start_up(&mut s, t0, reported);
    let events = drain(&mut s);
    assert!(matches!(
        events.as_slice(),
        [Event::DeviceError(DeviceError::ConfigNotApplied { reported: r, .. }), Event::Ready(_)] if *r == reported.0
    ));
    let sample = SensorData { timestamp_ticks: 8, gyro_radps: Some([0.0, 0.0, 1.5]), ..Default::default() };
    let payload = encode_sensor_data(&sample, OutputMask::GYRO, DataMode::Int16);
    s.handle_bytes(t0, &Frame::new(1, 9, payload).encode().unwrap());
    assert_eq!(drain(&mut s), vec![Event::Sample(sample)]);
}
