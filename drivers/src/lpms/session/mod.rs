//! The sans-IO LPMS-B2 session (quinn-proto style): bytes and time in, transmits and events out.
//!
//! Start-up follows the host sequence of the notes (Part A2; OpenZen `ConnectionNegotiator.cpp`,
//! OpenMAT `LpmsSensor.cpp` STATE_GET_SETTINGS): GOTO_COMMAND_MODE (retried: the first reply can be
//! lost while the sensor streams) → GET_CONFIG → GET_IMU_ID → GET_FIRMWARE_VERSION →
//! SET_TRANSMIT_DATA → SET_STREAM_FREQ → SET_LPBUS_DATA_MODE → GET_CONFIG (the register the data is
//! decoded with) → GOTO_STREAM_MODE. While streaming, a watchdog closes the link after
//! `data_timeout` without data; the link is reopened with capped exponential backoff.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::command::{Command, CommandId, FirmwareVersion, Reply};
use super::data::{ConfigRegister, DataMode, OutputMask, SensorData, decode_sensor_data};
use super::error::{DeviceError, LinkError, ProtocolError};
use super::frame::{DecoderStats, FrameDecoder};

/// What the session asks of the sensor and how patient it is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionConfig {
    /// Id requests are addressed to (LpSensor default 1; replies from any id are accepted).
    pub imu_id: u16,
    /// Stream rate, Hz: one of 5, 10, 25, 50, 100, 200, 400.
    pub stream_hz: u32,
    /// Outputs to stream.
    pub outputs: OutputMask,
    /// Float or 16-bit data.
    pub data_mode: DataMode,
    /// Time to wait for each reply.
    pub reply_timeout: Duration,
    /// Attempts per command before the link is declared broken.
    pub command_attempts: u32,
    /// No data for this long while streaming closes and reopens the link.
    pub data_timeout: Duration,
    /// First reopen delay.
    pub backoff_initial: Duration,
    /// Longest reopen delay.
    pub backoff_max: Duration,
}

impl Default for SessionConfig {
    fn default() -> Self {
        Self {
            imu_id: 1,
            stream_hz: 100,
            outputs: OutputMask::GYRO | OutputMask::ACC | OutputMask::QUATERNION | OutputMask::EULER,
            data_mode: DataMode::Float32,
            // OpenZen waits up to 2 s for GOTO_COMMAND_MODE in 200 ms steps (notes A2).
            reply_timeout: Duration::from_millis(200),
            command_attempts: 5,
            data_timeout: Duration::from_secs(1),
            // Reopening a missing tty is one failed open(): cheap enough to retry twice a second, so
            // a sensor that comes back is streaming again within about a second.
            backoff_initial: Duration::from_millis(50),
            backoff_max: Duration::from_millis(500),
        }
    }
}

/// What the sensor told us during start-up.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DeviceInfo {
    /// GET_IMU_ID reply.
    pub imu_id: u32,
    /// GET_FIRMWARE_VERSION reply.
    pub firmware: FirmwareVersion,
    /// Config register after our settings; data is decoded with it.
    pub config: ConfigRegister,
}

/// Output of the session, taken with [`Session::poll_event`].
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// Open the port now, then call [`Session::link_up`] or [`Session::link_failed`].
    OpenLink,
    /// The link is down (the shell drops the port); a reopen follows after the backoff.
    LinkDown(LinkError),
    /// Start-up finished; streaming.
    Ready(DeviceInfo),
    /// One decoded data packet.
    Sample(SensorData),
    /// The sensor refused a command; start-up is retried after the backoff on the same link.
    DeviceError(DeviceError),
    /// A bad frame or payload was dropped.
    ProtocolError(ProtocolError),
}

/// Coarse state for health reporting.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Phase {
    /// Link down, waiting to reopen.
    Closed,
    /// Waiting for the shell to open the port.
    Opening,
    /// Start-up sequence running (or paused after a NACK).
    Configuring,
    /// Data flowing.
    Streaming,
}

/// Counters for tests and health.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SessionStats {
    /// Frame decoder counters.
    pub decoder: DecoderStats,
    /// Samples decoded.
    pub samples: u64,
    /// Protocol errors (bad frames, replies, payloads).
    pub protocol_errors: u64,
    /// NACKs received.
    pub nacks: u64,
    /// Times the link went down.
    pub link_downs: u64,
    /// Times start-up completed.
    pub ready: u64,
}

#[derive(Debug)]
enum State {
    Closed { reopen_at: Instant },
    Opening,
    Configuring { step: usize, attempt: u32, deadline: Instant },
    Paused { until: Instant },
    Streaming { last_data: Instant },
}

/// The LPMS-B2 host session. See the module docs for the sequence.
#[derive(Debug)]
pub struct Session {
    config: SessionConfig,
    steps: Vec<Command>,
    state: State,
    decoder: FrameDecoder,
    transmits: VecDeque<Vec<u8>>,
    events: VecDeque<Event>,
    backoff: Duration,
    imu_id: Option<u32>,
    firmware: Option<FirmwareVersion>,
    active: ConfigRegister,
    stats: SessionStats,
}

impl Session {
    /// A session whose link is down and due to be opened at `now`.
    pub fn new(config: SessionConfig, now: Instant) -> Self {
        let steps = vec![
            Command::GotoCommandMode,
            Command::GetConfig,
            Command::GetImuId,
            Command::GetFirmwareVersion,
            Command::SetTransmitData(config.outputs.outputs_only()),
            Command::SetStreamFreq(config.stream_hz),
            Command::SetLpbusDataMode(config.data_mode),
            Command::GetConfig,
            Command::GotoStreamMode,
        ];
        Self {
            backoff: config.backoff_initial,
            config,
            steps,
            state: State::Closed { reopen_at: now },
            decoder: FrameDecoder::new(),
            transmits: VecDeque::new(),
            events: VecDeque::new(),
            imu_id: None,
            firmware: None,
            active: ConfigRegister::default(),
            stats: SessionStats::default(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &SessionConfig {
        &self.config
    }

    /// Counters.
    pub fn stats(&self) -> SessionStats {
        SessionStats { decoder: self.decoder.stats(), ..self.stats }
    }

    /// Coarse state.
    pub fn phase(&self) -> Phase {
        match self.state {
            State::Closed { .. } => Phase::Closed,
            State::Opening => Phase::Opening,
            State::Configuring { .. } | State::Paused { .. } => Phase::Configuring,
            State::Streaming { .. } => Phase::Streaming,
        }
    }

    /// The next bytes to write to the port.
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.transmits.pop_front()
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// When [`Session::handle_timeout`] must be called next, if at all.
    pub fn poll_timeout(&self) -> Option<Instant> {
        match self.state {
            State::Closed { reopen_at } => Some(reopen_at),
            State::Opening => None,
            State::Configuring { deadline, .. } => Some(deadline),
            State::Paused { until } => Some(until),
            State::Streaming { last_data } => Some(last_data + self.config.data_timeout),
        }
    }

    /// Acts on expired timers: reopen, resend or give up on a command, resume after a NACK, watchdog.
    pub fn handle_timeout(&mut self, now: Instant) {
        match self.state {
            State::Closed { reopen_at } if now >= reopen_at => {
                self.state = State::Opening;
                self.events.push_back(Event::OpenLink);
            }
            State::Configuring { step, attempt, deadline } if now >= deadline => {
                let command = self.steps.get(step).copied().unwrap_or(Command::GotoCommandMode);
                if attempt < self.config.command_attempts {
                    tracing::debug!(%attempt, command = %command.id(), "LPMS reply timeout, resending");
                    self.send(command);
                    self.state = State::Configuring {
                        step,
                        attempt: attempt + 1,
                        deadline: now + self.config.reply_timeout,
                    };
                } else {
                    self.fail(now, LinkError::ReplyTimeout { command: command.id(), attempts: attempt });
                }
            }
            State::Paused { until } if now >= until => self.start_configuring(now),
            State::Streaming { last_data } if now >= last_data + self.config.data_timeout => {
                self.fail(now, LinkError::data_timeout(self.config.data_timeout));
            }
            _ => {}
        }
    }

    /// The shell opened the port: start the start-up sequence.
    pub fn link_up(&mut self, now: Instant) {
        self.decoder.clear();
        self.transmits.clear();
        self.start_configuring(now);
    }

    /// The shell could not open, read or write the port (or it reached end of file).
    pub fn link_failed(&mut self, now: Instant, err: LinkError) {
        self.fail(now, err);
    }

    /// Bytes read from the port, in any pieces.
    pub fn handle_bytes(&mut self, now: Instant, bytes: &[u8]) {
        if matches!(self.state, State::Closed { .. } | State::Opening) {
            return;
        }
        self.decoder.push(bytes);
        while let Some(next) = self.decoder.next_frame() {
            match next {
                Ok(frame) if frame.cmd == CommandId::GetSensorData.code() => {
                    self.handle_data(now, &frame.data)
                }
                Ok(frame) => match Reply::from_frame(&frame) {
                    Ok(reply) => self.handle_reply(now, reply),
                    Err(e) => self.protocol_error(e.into()),
                },
                Err(e) => self.protocol_error(e.into()),
            }
            if matches!(self.state, State::Closed { .. }) {
                break;
            }
        }
    }

    fn protocol_error(&mut self, err: ProtocolError) {
        tracing::debug!(%err, "LPMS protocol error");
        self.stats.protocol_errors += 1;
        self.events.push_back(Event::ProtocolError(err));
    }

    fn handle_data(&mut self, now: Instant, payload: &[u8]) {
        // Data before stream mode is leftover from the sensor's previous streaming: ignore it.
        let State::Streaming { last_data } = &mut self.state else { return };
        match decode_sensor_data(payload, self.active.outputs(), self.active.data_mode()) {
            Ok(sample) => {
                *last_data = now;
                // Data flows again: the next failure starts the backoff from the beginning.
                self.backoff = self.config.backoff_initial;
                self.stats.samples += 1;
                self.events.push_back(Event::Sample(sample));
            }
            Err(e) => self.protocol_error(e.into()),
        }
    }

    fn handle_reply(&mut self, now: Instant, reply: Reply) {
        let State::Configuring { step, .. } = self.state else { return };
        let Some(&pending) = self.steps.get(step) else { return };
        let pending_id = pending.id();
        match reply {
            Reply::Nack => {
                self.stats.nacks += 1;
                tracing::warn!(command = %pending_id, "LPMS sensor NACKed a start-up command");
                self.events.push_back(Event::DeviceError(DeviceError::Nack { command: pending_id }));
                self.state = State::Paused { until: now + self.next_backoff() };
            }
            Reply::Ack if pending_id.is_acked() => self.advance(now, step),
            Reply::Ack => {} // a late ACK of a retried mode switch
            other if other.id() == pending_id => {
                match other {
                    Reply::Config(c) => self.active = c,
                    Reply::ImuId(id) => self.imu_id = Some(id),
                    Reply::FirmwareVersion(v) => self.firmware = Some(v),
                    _ => {}
                }
                self.advance(now, step);
            }
            _ => {} // a stale reply to an earlier attempt
        }
    }

    fn advance(&mut self, now: Instant, step: usize) {
        let next = step + 1;
        match self.steps.get(next).copied() {
            Some(command) => {
                self.send(command);
                self.state =
                    State::Configuring { step: next, attempt: 1, deadline: now + self.config.reply_timeout };
            }
            None => {
                let wanted = ConfigRegister::from_settings(
                    self.config.outputs,
                    self.config.data_mode,
                    self.config.stream_hz,
                );
                let layout = |r: ConfigRegister| (r.outputs(), r.data_mode(), r.stream_hz());
                if wanted.map(layout) != Some(layout(self.active)) {
                    // LPBUS ACKs name no command, so a late ACK can be taken for the next SET; the
                    // register read back is the truth. Decode with it and say so.
                    tracing::warn!(reported = self.active.0, "LPMS config differs from the settings sent");
                    self.events.push_back(Event::DeviceError(DeviceError::ConfigNotApplied {
                        requested: wanted.map_or(0, |w| w.0),
                        reported: self.active.0,
                    }));
                }
                let info = DeviceInfo {
                    imu_id: self.imu_id.unwrap_or(u32::from(self.config.imu_id)),
                    firmware: self.firmware.unwrap_or(FirmwareVersion { major: 0, minor: 0, build: 0 }),
                    config: self.active,
                };
                self.stats.ready += 1;
                self.state = State::Streaming { last_data: now };
                self.events.push_back(Event::Ready(info));
            }
        }
    }

    fn start_configuring(&mut self, now: Instant) {
        self.send(Command::GotoCommandMode);
        self.state = State::Configuring { step: 0, attempt: 1, deadline: now + self.config.reply_timeout };
    }

    fn send(&mut self, command: Command) {
        match command.to_frame(self.config.imu_id).encode() {
            Ok(bytes) => self.transmits.push_back(bytes),
            // Requests carry at most 4 bytes; the cap cannot be hit.
            Err(e) => tracing::error!(%e, "LPMS request not encodable"),
        }
    }

    fn next_backoff(&mut self) -> Duration {
        let delay = self.backoff;
        self.backoff = (self.backoff * 2).min(self.config.backoff_max);
        delay
    }

    fn fail(&mut self, now: Instant, err: LinkError) {
        tracing::warn!(%err, "LPMS link down");
        self.stats.link_downs += 1;
        self.decoder.clear();
        self.transmits.clear();
        let delay = self.next_backoff();
        self.state = State::Closed { reopen_at: now + delay };
        self.events.push_back(Event::LinkDown(err));
    }
}

#[cfg(test)]
mod tests;
