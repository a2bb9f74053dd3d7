//! The tokio shell: runs a [`Session`] over any `AsyncRead + AsyncWrite` port, opens (and reopens)
//! it through a connect function, and publishes samples and health on a channel.
//!
//! On the robot the port is a tokio-serial stream: an RFCOMM tty for the Bluetooth B2 (baud rate
//! meaningless there) or a UART at 115200 8N1 (notes A0: LpSensor `LpmsRS232.cpp`, OpenZen `3c25e5b`).

use std::future::Future;
use std::time::{Duration, Instant};

use amr_settings::value::Backoff;
use amr_settings::{DeviceSource, Violation, join, rule};
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::mpsc;

use super::data::{DataMode, OutputMask, SensorData};
use super::error::{LinkError, LpmsError};
use super::session::{DeviceInfo, Event, Session, SessionConfig};

/// Default UART rate (notes A0).
pub const DEFAULT_BAUD: u32 = 115_200;

/// UART rates the LP sensors support (LpSensor `LpmsRS232.cpp`).
pub const BAUD_RATES: [u32; 7] = [19_200, 38_400, 57_600, 115_200, 230_400, 460_800, 921_600];

/// Stream rates the LPMS-B2 delivers (notes A3): the config register has a code for 800 Hz too,
/// but the B2's timestamp counts 400 Hz ticks.
pub const B2_STREAM_RATES_HZ: [u32; 7] = [5, 10, 25, 50, 100, 200, 400];

/// The LPMS driver: `[devices.imu]` of a robot file (devices.md §3), deserialised straight into
/// this type; [`LpmsConfig::validate`] checks what the sensor and the session can do.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LpmsConfig {
    pub source: DeviceSource,
    /// Serial device: a UART, an RFCOMM tty (`/dev/rfcomm0`, or a udev symlink to it) or a pty.
    pub path: String,
    /// UART baud rate (ignored by RFCOMM ttys).
    pub baud: u32,
    /// Stream rate, Hz ([`B2_STREAM_RATES_HZ`]).
    pub stream_hz: u32,
    /// The sensor's LPBUS id (replies carry it; commands are sent to it).
    pub imu_id: u16,
    /// Outputs to stream: what the robot's actors use, not a file setting.
    #[serde(skip, default = "default_outputs")]
    pub outputs: OutputMask,
    /// Float or 16-bit data (`float | int16`).
    pub data_mode: DataMode,
    /// Time to wait for each reply.
    #[serde(rename = "reply_timeout_ms", deserialize_with = "amr_settings::value::millis")]
    pub reply_timeout: Duration,
    /// No data packet for this long while streaming reopens the port.
    #[serde(rename = "data_timeout_ms", deserialize_with = "amr_settings::value::millis")]
    pub data_timeout: Duration,
    /// Reopening the port after it fails.
    pub reconnect: Backoff,
}

fn default_outputs() -> OutputMask {
    SessionConfig::default().outputs
}

impl Default for LpmsConfig {
    fn default() -> Self {
        let s = SessionConfig::default();
        Self {
            source: DeviceSource::Real,
            path: "/dev/rfcomm0".into(),
            baud: DEFAULT_BAUD,
            stream_hz: s.stream_hz,
            imu_id: s.imu_id,
            outputs: s.outputs,
            data_mode: s.data_mode,
            reply_timeout: s.reply_timeout,
            data_timeout: s.data_timeout,
            reconnect: Backoff { initial: s.backoff_initial, max: s.backoff_max },
        }
    }
}

impl LpmsConfig {
    /// What the sensor and the session can work with; `path` is where the section stands
    /// (`devices.imu` in a robot file).
    pub fn validate(&self, path: &str) -> Result<(), Violation> {
        rule(!self.path.trim().is_empty(), join(path, "path"), "must not be empty")?;
        rule(
            BAUD_RATES.contains(&self.baud),
            join(path, "baud"),
            format!("must be one of {BAUD_RATES:?} (got {})", self.baud),
        )?;
        rule(
            B2_STREAM_RATES_HZ.contains(&self.stream_hz),
            join(path, "stream_hz"),
            format!("must be one of {B2_STREAM_RATES_HZ:?} (got {})", self.stream_hz),
        )?;
        for (key, d) in [("reply_timeout_ms", self.reply_timeout), ("data_timeout_ms", self.data_timeout)] {
            rule(!d.is_zero(), join(path, key), "must be a whole number of milliseconds > 0 (got 0)")?;
        }
        // Three sample periods, so the watchdog does not fire on jitter.
        let min_ms = 3000u64.div_ceil(u64::from(self.stream_hz));
        rule(
            self.data_timeout >= Duration::from_millis(min_ms),
            join(path, "data_timeout_ms"),
            format!(
                "must cover at least three stream periods at {} Hz ({min_ms} ms) (got {} ms)",
                self.stream_hz,
                self.data_timeout.as_millis()
            ),
        )?;
        self.reconnect.check(&join(path, "reconnect"))
    }

    /// The session part of this configuration.
    pub fn session_config(&self) -> SessionConfig {
        SessionConfig {
            imu_id: self.imu_id,
            stream_hz: self.stream_hz,
            outputs: self.outputs,
            data_mode: self.data_mode,
            reply_timeout: self.reply_timeout,
            data_timeout: self.data_timeout,
            backoff_initial: self.reconnect.initial,
            backoff_max: self.reconnect.max,
            ..SessionConfig::default()
        }
    }
}

/// Opens a serial port 8N1, no flow control, as a tokio stream.
pub fn open_serial(path: &str, baud: u32) -> std::io::Result<tokio_serial::SerialStream> {
    use tokio_serial::SerialPortBuilderExt;
    tokio_serial::new(path, baud)
        .data_bits(tokio_serial::DataBits::Eight)
        .parity(tokio_serial::Parity::None)
        .stop_bits(tokio_serial::StopBits::One)
        .flow_control(tokio_serial::FlowControl::None)
        .open_native_async()
        .map_err(std::io::Error::from)
}

/// A decoded sample with the host time it was read.
#[derive(Debug, Clone, PartialEq)]
pub struct ImuSample {
    /// The data packet.
    pub data: SensorData,
    /// Host time the bytes completing it were read.
    pub received_at: Instant,
}

/// Link health as the shell sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Health {
    /// Opening the port.
    Connecting,
    /// Port open, start-up sequence running.
    Configuring,
    /// Data flowing.
    Streaming,
    /// Port closed after a failure; reopening after the backoff.
    Lost,
}

/// What the shell publishes.
#[derive(Debug, Clone, PartialEq)]
pub enum ImuMessage {
    /// One sample.
    Sample(ImuSample),
    /// Start-up finished.
    Ready(DeviceInfo),
    /// Health changed.
    Health(Health),
    /// An error: NACK (device), link loss, or a dropped frame (protocol).
    Error(LpmsError),
}

fn now() -> Instant {
    tokio::time::Instant::now().into_std()
}

async fn read_some<T: AsyncRead + Unpin>(port: &mut Option<T>, buf: &mut [u8]) -> std::io::Result<usize> {
    match port {
        Some(p) => p.read(buf).await,
        None => std::future::pending().await,
    }
}

/// Runs the driver until the receiver of `tx` is dropped. `connect` opens the port each time the
/// session asks for it (at start and after every failure, with backoff).
pub async fn run<C, F, T>(config: SessionConfig, mut connect: C, tx: mpsc::Sender<ImuMessage>)
where
    C: FnMut() -> F,
    F: Future<Output = std::io::Result<T>>,
    T: AsyncRead + AsyncWrite + Unpin,
{
    let write_timeout = config.reply_timeout;
    let mut session = Session::new(config, now());
    let mut port: Option<T> = None;
    let mut buf = vec![0u8; 4096];
    let mut dropped_samples: u64 = 0;
    loop {
        // Drain the session's output until it is quiet.
        loop {
            let mut progressed = transmit(&mut session, &mut port, write_timeout).await;
            while let Some(event) = session.poll_event() {
                progressed = true;
                let msg = match event {
                    Event::OpenLink => {
                        let _ = tx.send(ImuMessage::Health(Health::Connecting)).await;
                        match connect().await {
                            Ok(p) => {
                                port = Some(p);
                                session.link_up(now());
                                ImuMessage::Health(Health::Configuring)
                            }
                            Err(e) => {
                                session.link_failed(now(), LinkError::io(&e));
                                continue;
                            }
                        }
                    }
                    Event::LinkDown(e) => {
                        port = None;
                        let _ = tx.send(ImuMessage::Error(e.into())).await;
                        ImuMessage::Health(Health::Lost)
                    }
                    Event::Ready(info) => {
                        let _ = tx.send(ImuMessage::Ready(info)).await;
                        ImuMessage::Health(Health::Streaming)
                    }
                    Event::Sample(data) => {
                        offer_sample(&tx, ImuSample { data, received_at: now() }, &mut dropped_samples);
                        continue;
                    }
                    Event::DeviceError(e) => ImuMessage::Error(e.into()),
                    Event::ProtocolError(e) => ImuMessage::Error(e.into()),
                };
                if tx.send(msg).await.is_err() {
                    return;
                }
            }
            if !progressed {
                break;
            }
        }
        if tx.is_closed() {
            return;
        }
        wait(&mut session, &mut port, &mut buf).await;
    }
}

/// Write what the session has to send (dropped while the port is closed); whether there was any.
async fn transmit<T: AsyncWrite + Unpin>(
    session: &mut Session,
    port: &mut Option<T>,
    timeout: Duration,
) -> bool {
    let mut any = false;
    while let Some(bytes) = session.poll_transmit() {
        any = true;
        if let Some(p) = port.as_mut() {
            // A dead Bluetooth link can block writes: bound them by the reply timeout.
            let written = tokio::time::timeout(timeout, async {
                p.write_all(&bytes).await?;
                p.flush().await
            });
            match written.await {
                Ok(Ok(())) => {}
                Ok(Err(e)) => session.link_failed(now(), LinkError::io(&e)),
                Err(_) => session.link_failed(
                    now(),
                    LinkError::Io { kind: std::io::ErrorKind::TimedOut, message: "write timed out".into() },
                ),
            }
        }
    }
    any
}

/// A sample to the consumer, never blocking the reader on a slow one (the serial buffer would
/// overflow): dropped and counted when the channel is full.
fn offer_sample(tx: &mpsc::Sender<ImuMessage>, sample: ImuSample, dropped_samples: &mut u64) {
    if tx.try_send(ImuMessage::Sample(sample)).is_err() {
        *dropped_samples += 1;
        tracing::warn!(dropped_samples = *dropped_samples, "LPMS sample dropped: consumer too slow");
    }
}

/// Wait for bytes from the port or the session's next timer (at most 100 ms) and hand either to
/// the session.
async fn wait<T: AsyncRead + Unpin>(session: &mut Session, port: &mut Option<T>, buf: &mut [u8]) {
    let deadline = session.poll_timeout().map(tokio::time::Instant::from_std);
    let fallback = tokio::time::Instant::now() + Duration::from_millis(100);
    // Bytes already waiting are read before a timer is acted on: a driver task that was
    // starved for a while must not declare the sensor silent while its data sits in the buffer.
    tokio::select! {
        biased;
        read = read_some(port, buf), if port.is_some() => match read {
            Ok(0) => session.link_failed(now(), LinkError::Io {
                kind: std::io::ErrorKind::UnexpectedEof,
                message: "port closed".into(),
            }),
            Ok(n) => {
                session.handle_bytes(now(), buf.get(..n).unwrap_or_default());
                // Timers still run when bytes never stop coming (e.g. a flood of garbage).
                session.handle_timeout(now());
            }
            Err(e) => session.link_failed(now(), LinkError::io(&e)),
        },
        () = tokio::time::sleep_until(deadline.unwrap_or(fallback)) => session.handle_timeout(now()),
    }
}

/// Runs the driver on the serial port of `config`, reopening it whenever it disappears.
pub async fn run_serial(config: LpmsConfig, tx: mpsc::Sender<ImuMessage>) {
    let session = config.session_config();
    let (path, baud) = (config.path, config.baud);
    run(session, || std::future::ready(open_serial(&path, baud)), tx).await;
}

/// Validates `config` and spawns [`run_serial`] on the current runtime; the task ends when the
/// receiver is dropped.
pub fn spawn_serial(
    config: LpmsConfig,
    capacity: usize,
) -> Result<(mpsc::Receiver<ImuMessage>, tokio::task::JoinHandle<()>), Violation> {
    config.validate("lpms")?;
    let (tx, rx) = mpsc::channel(capacity.max(1));
    Ok((rx, tokio::spawn(run_serial(config, tx))))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_names_the_broken_value() {
        assert_eq!(LpmsConfig::default().validate("imu"), Ok(()));
        let bad = |f: fn(&mut LpmsConfig)| {
            let mut c = LpmsConfig::default();
            f(&mut c);
            let v = c.validate("imu").unwrap_err();
            format!("{}: {}", v.key, v.rule)
        };
        assert_eq!(bad(|c| c.path.clear()), "imu.path: must not be empty");
        assert_eq!(
            bad(|c| c.stream_hz = 800),
            "imu.stream_hz: must be one of [5, 10, 25, 50, 100, 200, 400] (got 800)"
        );
        assert_eq!(
            bad(|c| c.stream_hz = 99),
            "imu.stream_hz: must be one of [5, 10, 25, 50, 100, 200, 400] (got 99)"
        );
        assert_eq!(
            bad(|c| c.baud = 9600),
            "imu.baud: must be one of [19200, 38400, 57600, 115200, 230400, 460800, 921600] (got 9600)"
        );
        assert_eq!(
            bad(|c| c.reply_timeout = Duration::ZERO),
            "imu.reply_timeout_ms: must be a whole number of milliseconds > 0 (got 0)"
        );
        assert_eq!(
            bad(|c| {
                c.stream_hz = 5;
                c.data_timeout = Duration::from_millis(400);
            }),
            "imu.data_timeout_ms: must cover at least three stream periods at 5 Hz (600 ms) (got 400 ms)"
        );
        assert_eq!(
            bad(|c| c.reconnect.initial = Duration::from_secs(9)),
            "imu.reconnect.initial_ms: must not exceed imu.reconnect.max_ms (9000 ms > 500 ms)"
        );
    }
}
