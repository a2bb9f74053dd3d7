//! The SOPAS session as a pure state machine (quinn-proto style, STYLE.md): bytes in through
//! [`Session::handle_bytes`], frames out through [`Session::poll_transmit`], events through
//! [`Session::poll_event`], timers through [`Session::poll_timeout`] / [`Session::handle_timeout`].
//! No sockets and no clock: `now` is always passed in.
//!
//! Start-up profiles (devices.md §1, notes §2): `Minimal` is the ROS sick_tim `init_scanner`
//! sequence, `Full` the sick_scan_xd TiM5xx sequence with login. The first command doubles as the
//! dialect probe (sick_scan_xd "checkColaDialect" probes, then falls back to the other dialect).
//! Any `sFA` during start-up is reported and the command retried; a reply timeout likewise; when
//! the retries run out, or no scan arrives within the watchdog time, or the link drops, the session
//! asks for a reconnect after a capped exponential backoff and runs the whole start-up again
//! (sick_scan_xd `checkStateReinitOnError`, sick_tim reconnect loop).

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::clock::DeviceClock;
use super::command::{
    CLIENT_LEVEL, CLIENT_PASSWORD_HASH, Command, OutputRange, Reply, ScanDataConfig, Variable,
};
use super::error::{DeviceError, LinkError, ProtocolError, SopasError};
use super::framing::{Dialect, Framer, encode_frame};
use super::scan::Scan;

/// Which start-up sequence to run (a robot file spells it `minimal` or `full`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all(deserialize = "kebab-case"))]
pub enum Profile {
    /// sick_tim: `sRI 0`, SerialNumber, FirmwareVersion, SCdevicestate, `sEN LMDscandata 1`.
    Minimal,
    /// sick_scan_xd: login, EIHstCola, identity and counters, output range, scan data config,
    /// LMCstartmeas, Run, `sEN LMDscandata 1`.
    Full,
}

/// Which dialect to speak.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum DialectChoice {
    /// Probe CoLa-B, then CoLa-A, and keep what the device speaks.
    Auto,
    /// Probe this dialect first (then the other) and switch the device to it with
    /// `sWN EIHstCola` if it answered in the other.
    Fixed(Dialect),
}

impl<'de> serde::Deserialize<'de> for DialectChoice {
    /// A robot file's spelling: `auto`, `A` (CoLa-A) or `B` (CoLa-B).
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        const NAMES: &[&str] = &["auto", "A", "B"];
        let name = String::deserialize(deserializer)?;
        match name.as_str() {
            "auto" => Ok(DialectChoice::Auto),
            "A" => Ok(DialectChoice::Fixed(Dialect::ColaA)),
            "B" => Ok(DialectChoice::Fixed(Dialect::ColaB)),
            other => Err(serde::de::Error::unknown_variant(other, NAMES)),
        }
    }
}

/// How scans are obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Mode {
    /// `sEN LMDscandata 1`, then one `sSN` per scan.
    Streaming,
    /// `sRN LMDscandata` every period.
    Poll { period: Duration },
}

/// Session settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SessionConfig {
    pub profile: Profile,
    pub dialect: DialectChoice,
    pub mode: Mode,
    /// Per command; sick_tim waits 1 s for each reply.
    pub reply_timeout: Duration,
    /// Watchdog: no scan for this long → reconnect.
    pub scan_timeout: Duration,
    pub backoff_initial: Duration,
    pub backoff_max: Duration,
    /// Attempts per start-up command (after `sFA` or a reply timeout) before reconnecting.
    pub attempts_per_command: u32,
    /// Resolution the `Full` profile writes to LMPoutputRange (0x2710 = 1° on a TiM55x); `None`
    /// writes back what the device reported, as sick_scan_xd does in its start-up log.
    pub output_resolution_1e4deg: Option<u32>,
    /// Pairs in the tick → host time fit.
    pub clock_window: usize,
}

impl Default for SessionConfig {
    fn default() -> Self {
        Self {
            profile: Profile::Minimal,
            dialect: DialectChoice::Auto,
            mode: Mode::Streaming,
            reply_timeout: Duration::from_secs(1),
            scan_timeout: Duration::from_millis(500),
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
            attempts_per_command: 3,
            output_resolution_1e4deg: None,
            clock_window: 32,
        }
    }
}

/// What the start-up learned about the device.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct DeviceInfo {
    pub dialect: Option<Dialect>,
    pub name: Option<String>,
    pub version: Option<String>,
    pub serial_number: Option<String>,
    pub firmware_version: Option<String>,
    /// 0 busy, 1 ready, 2 error.
    pub device_state: Option<u8>,
    pub output_range: Option<OutputRange>,
    pub login_granted: Option<bool>,
}

/// A scan with its host timestamp.
#[derive(Debug, Clone, PartialEq)]
pub struct StampedScan {
    pub scan: Scan,
    /// The generation tick mapped to host time (`None` only before the clock has a pair).
    pub stamp: Option<Instant>,
    pub received: Instant,
}

/// Why the session asks for a reconnect.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ReconnectReason {
    Link(LinkError),
    ScanTimeout,
    StartupFailed(SopasError),
}

/// What the session tells its owner.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    DialectDetected(Dialect),
    /// `sAN SetAccessMode 0` (a real TiM561 answers so in CoLa-A; streaming still works).
    LoginRefused,
    /// The device answered with `sFA`; during start-up the command is retried.
    DeviceError(DeviceError),
    /// A frame or reply was lost or late; only the frames concerned are dropped.
    ProtocolError(ProtocolError),
    /// Start-up done; scans follow.
    Ready(DeviceInfo),
    Scan(Box<StampedScan>),
    /// Close the connection and connect again after `delay`.
    Reconnect {
        reason: ReconnectReason,
        delay: Duration,
    },
}

#[derive(Debug, Clone)]
enum Step {
    Send(Command),
    /// `sWN EIHstCola` to the configured (or detected) dialect, resolved when sent.
    SwitchDialect,
    /// `sWN LMPoutputRange` with the configured resolution or the one just read, resolved when sent.
    WriteOutputRange,
}

#[derive(Debug, Clone)]
enum State {
    /// Waiting for the owner to connect (from the start, or once the backoff has passed).
    Disconnected {
        connect_at: Instant,
    },
    Startup {
        step: usize,
        attempt: u32,
        deadline: Instant,
        probe_switched: bool,
    },
    Running {
        last_scan: Instant,
        next_poll: Option<Instant>,
    },
}

/// The SOPAS client session.
#[derive(Debug)]
pub struct Session {
    config: SessionConfig,
    state: State,
    framer: Framer,
    dialect: Dialect,
    detected: bool,
    steps: Vec<Step>,
    info: DeviceInfo,
    clock: DeviceClock,
    backoff: Duration,
    transmits: VecDeque<Vec<u8>>,
    events: VecDeque<Event>,
}

impl Session {
    pub fn new(config: SessionConfig, now: Instant) -> Self {
        let dialect = match config.dialect {
            DialectChoice::Auto => Dialect::ColaB,
            DialectChoice::Fixed(d) => d,
        };
        Self {
            clock: DeviceClock::new(config.clock_window),
            backoff: config.backoff_initial,
            state: State::Disconnected { connect_at: now },
            framer: Framer::default(),
            dialect,
            detected: false,
            steps: Vec::new(),
            info: DeviceInfo::default(),
            config,
            transmits: VecDeque::new(),
            events: VecDeque::new(),
        }
    }

    /// The dialect the session currently speaks.
    pub fn dialect(&self) -> Dialect {
        self.dialect
    }

    /// Whether the owner should open a connection now.
    pub fn needs_connection(&self, now: Instant) -> bool {
        matches!(self.state, State::Disconnected { connect_at } if now >= connect_at)
    }

    /// Whether start-up is done and scans are expected.
    pub fn is_running(&self) -> bool {
        matches!(self.state, State::Running { .. })
    }

    fn build_steps(&self) -> Vec<Step> {
        use Command as C;
        let mut steps = match self.config.profile {
            Profile::Minimal => vec![
                Step::Send(C::ReadByIndex(0)),
                Step::Send(C::Read(Variable::SerialNumber)),
                Step::Send(C::Read(Variable::FirmwareVersion)),
                Step::Send(C::Read(Variable::DeviceState)),
            ],
            Profile::Full => vec![
                Step::Send(C::SetAccessMode { level: CLIENT_LEVEL, password_hash: CLIENT_PASSWORD_HASH }),
                Step::SwitchDialect,
                Step::Send(C::Read(Variable::FirmwareVersion)),
                Step::Send(C::Read(Variable::DeviceState)),
                Step::Send(C::Read(Variable::OperatingHours)),
                Step::Send(C::Read(Variable::PowerOnCount)),
                Step::Send(C::Read(Variable::LocationName)),
                Step::Send(C::Read(Variable::OutputRange)),
                Step::WriteOutputRange,
                Step::Send(C::Read(Variable::OutputRange)),
                Step::Send(C::WriteScanDataConfig(ScanDataConfig::SICK_SCAN_XD)),
                Step::Send(C::Read(Variable::ScanDataConfig)),
                Step::Send(C::StartMeasurement),
                Step::Send(C::Run),
            ],
        };
        if self.config.mode == Mode::Streaming {
            steps.push(Step::Send(C::ScanDataEvents(true)));
        }
        steps
    }

    fn target_dialect(&self) -> Dialect {
        match self.config.dialect {
            DialectChoice::Auto => self.dialect,
            DialectChoice::Fixed(d) => d,
        }
    }

    fn command_at(&self, step: usize) -> Option<Command> {
        match self.steps.get(step)? {
            Step::Send(c) => Some(c.clone()),
            Step::SwitchDialect => Some(Command::SetDialect(self.target_dialect())),
            Step::WriteOutputRange => {
                let range = match (self.config.output_resolution_1e4deg, &self.info.output_range) {
                    (Some(res), _) => OutputRange::full_field(res),
                    (None, Some(read)) if !read.sectors.is_empty() => read.clone(),
                    (None, _) => OutputRange::full_field(0x2710),
                };
                Some(Command::WriteOutputRange(range))
            }
        }
    }

    fn send(&mut self, cmd: &Command) {
        tracing::debug!(command = %cmd.label(), dialect = ?self.dialect, "sopas send");
        self.transmits.push_back(encode_frame(self.dialect, &cmd.encode(self.dialect)));
    }

    /// The owner opened a connection: run the start-up from the beginning.
    pub fn handle_connected(&mut self, now: Instant) {
        self.framer.clear();
        self.transmits.clear();
        self.detected = false;
        self.dialect = match self.config.dialect {
            DialectChoice::Auto => Dialect::ColaB,
            DialectChoice::Fixed(d) => d,
        };
        self.info = DeviceInfo::default();
        self.steps = self.build_steps();
        self.start_step(now, 0, 0);
    }

    fn start_step(&mut self, now: Instant, step: usize, attempt: u32) {
        match self.command_at(step) {
            Some(cmd) => {
                self.send(&cmd);
                self.state = State::Startup {
                    step,
                    attempt,
                    deadline: now + self.config.reply_timeout,
                    probe_switched: false,
                };
            }
            None => {
                self.info.dialect = Some(self.dialect);
                tracing::info!(dialect = ?self.dialect, "sopas start-up done");
                self.events.push_back(Event::Ready(self.info.clone()));
                let next_poll = match self.config.mode {
                    Mode::Streaming => None,
                    Mode::Poll { .. } => Some(now),
                };
                self.state = State::Running { last_scan: now, next_poll };
                self.handle_timeout(now);
            }
        }
    }

    /// The owner could not connect.
    pub fn handle_connect_failed(&mut self, now: Instant, error: LinkError) {
        self.reconnect(now, ReconnectReason::Link(error));
    }

    /// The connection broke or the device closed it.
    pub fn handle_disconnected(&mut self, now: Instant, error: LinkError) {
        if !matches!(self.state, State::Disconnected { .. }) {
            self.reconnect(now, ReconnectReason::Link(error));
        }
    }

    fn reconnect(&mut self, now: Instant, reason: ReconnectReason) {
        let delay = self.backoff;
        self.backoff = (self.backoff * 2).min(self.config.backoff_max);
        tracing::warn!(?reason, delay_ms = delay.as_millis() as u64, "sopas reconnect");
        self.state = State::Disconnected { connect_at: now + delay };
        self.transmits.clear();
        self.framer.clear();
        self.events.push_back(Event::Reconnect { reason, delay });
    }

    /// Bytes received from the device.
    pub fn handle_bytes(&mut self, now: Instant, bytes: &[u8]) {
        if matches!(self.state, State::Disconnected { .. }) {
            return;
        }
        self.framer.push(bytes);
        for _ in 0..100_000 {
            let Some(result) = self.framer.next_frame() else { break };
            match result {
                Err(e) => {
                    tracing::warn!(error = %e, "sopas frame dropped");
                    self.events.push_back(Event::ProtocolError(e.into()));
                }
                Ok(frame) => match Reply::decode(frame.dialect, &frame.payload) {
                    Err(e) => {
                        tracing::warn!(error = %e, "sopas telegram did not decode");
                        self.events.push_back(Event::ProtocolError(e.into()));
                    }
                    Ok(reply) => self.handle_reply(now, frame.dialect, reply),
                },
            }
            if matches!(self.state, State::Disconnected { .. }) {
                break;
            }
        }
    }

    fn handle_reply(&mut self, now: Instant, dialect: Dialect, reply: Reply) {
        if let Reply::ScanData { telegram, .. } = &reply {
            match Scan::from_telegram(telegram) {
                Ok(scan) => self.deliver_scan(now, scan),
                Err(e) => self.events.push_back(Event::ProtocolError(e.into())),
            }
            if !matches!(self.state, State::Startup { .. }) {
                return;
            }
        }
        let State::Startup { step, attempt, .. } = self.state else {
            if let Reply::Error(code) = reply {
                let command = match (&self.state, self.config.mode) {
                    (State::Running { .. }, Mode::Poll { .. }) => Command::Read(Variable::ScanData).label(),
                    _ => "(unsolicited)".to_string(),
                };
                self.events.push_back(Event::DeviceError(DeviceError { command, code }));
            }
            return;
        };
        let Some(cmd) = self.command_at(step) else { return };
        if !reply.answers(&cmd) {
            tracing::debug!(reply = %reply.name(), command = %cmd.label(), "sopas reply ignored");
            return;
        }
        if !self.detected {
            self.detected = true;
            self.dialect = dialect;
            self.events.push_back(Event::DialectDetected(dialect));
            if let (Profile::Minimal, DialectChoice::Fixed(want)) = (self.config.profile, self.config.dialect)
                && want != dialect
            {
                self.steps.insert(step + 1, Step::SwitchDialect);
            }
        }
        match reply {
            Reply::Error(code) => {
                let err = DeviceError { command: cmd.label(), code };
                tracing::warn!(error = %err, attempt, "sopas start-up command refused");
                self.events.push_back(Event::DeviceError(err.clone()));
                if attempt + 1 >= self.config.attempts_per_command {
                    self.reconnect(now, ReconnectReason::StartupFailed(err.into()));
                } else {
                    self.start_step(now, step, attempt + 1);
                }
                return;
            }
            Reply::AccessMode { granted } => {
                self.info.login_granted = Some(granted);
                if !granted {
                    self.events.push_back(Event::LoginRefused);
                }
            }
            Reply::IndexIdent { name, version, .. } | Reply::DeviceIdent { name, version } => {
                self.info.name = Some(name);
                self.info.version = Some(version);
            }
            Reply::SerialNumber(s) => self.info.serial_number = Some(s),
            Reply::FirmwareVersion(s) => self.info.firmware_version = Some(s),
            Reply::DeviceState(s) => self.info.device_state = Some(s),
            Reply::OutputRange(r) => self.info.output_range = Some(r),
            Reply::WriteAck(_) => {
                if let Command::SetDialect(d) = cmd {
                    self.dialect = d;
                }
            }
            _ => {}
        }
        self.start_step(now, step + 1, 0);
    }

    fn deliver_scan(&mut self, now: Instant, scan: Scan) {
        self.clock.observe(scan.transmission_tick_us, now);
        let stamp = self.clock.to_host(scan.generation_tick_us);
        if let State::Running { last_scan, .. } = &mut self.state {
            *last_scan = now;
            self.backoff = self.config.backoff_initial;
        }
        self.events.push_back(Event::Scan(Box::new(StampedScan { scan, stamp, received: now })));
    }

    /// Timers: reply timeouts, the scan watchdog, polls and the reconnect backoff.
    pub fn handle_timeout(&mut self, now: Instant) {
        match self.state.clone() {
            State::Disconnected { .. } => {}
            State::Startup { step, attempt, deadline, probe_switched } if now >= deadline => {
                let command = self.command_at(step).map(|c| c.label()).unwrap_or_default();
                if step == 0 && !self.detected && !probe_switched {
                    self.dialect = self.dialect.other();
                    tracing::info!(dialect = ?self.dialect, "no reply to the probe; trying the other dialect");
                    if let Some(cmd) = self.command_at(0) {
                        self.send(&cmd);
                    }
                    self.state = State::Startup {
                        step,
                        attempt,
                        deadline: now + self.config.reply_timeout,
                        probe_switched: true,
                    };
                    return;
                }
                let err = ProtocolError::ReplyTimeout {
                    command,
                    timeout_ms: self.config.reply_timeout.as_millis() as u64,
                };
                self.events.push_back(Event::ProtocolError(err.clone()));
                if attempt + 1 >= self.config.attempts_per_command {
                    self.reconnect(now, ReconnectReason::StartupFailed(err.into()));
                } else {
                    self.start_step(now, step, attempt + 1);
                }
            }
            State::Startup { .. } => {}
            State::Running { last_scan, next_poll } => {
                if now >= last_scan + self.config.scan_timeout {
                    let timeout_ms = self.config.scan_timeout.as_millis() as u64;
                    self.events.push_back(Event::ProtocolError(ProtocolError::ScanTimeout { timeout_ms }));
                    self.reconnect(now, ReconnectReason::ScanTimeout);
                    return;
                }
                if let (Some(at), Mode::Poll { period }) = (next_poll, self.config.mode)
                    && now >= at
                {
                    self.send(&Command::Read(Variable::ScanData));
                    let mut next = at + period;
                    if next <= now {
                        next = now + period;
                    }
                    self.state = State::Running { last_scan, next_poll: Some(next) };
                }
            }
        }
    }

    /// The next instant at which [`Session::handle_timeout`] must run.
    pub fn poll_timeout(&self) -> Option<Instant> {
        match &self.state {
            State::Disconnected { connect_at } => Some(*connect_at),
            State::Startup { deadline, .. } => Some(*deadline),
            State::Running { last_scan, next_poll } => {
                let watchdog = *last_scan + self.config.scan_timeout;
                Some(next_poll.map_or(watchdog, |p| p.min(watchdog)))
            }
        }
    }

    /// The next framed bytes to send.
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.transmits.pop_front()
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }
}
