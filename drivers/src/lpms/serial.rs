//! The tokio shell: runs a [`Session`] over any `AsyncRead + AsyncWrite` port, opens (and reopens)
//! it through a connect function, and publishes samples and health on a channel.
//!
//! On the robot the port is a tokio-serial stream: an RFCOMM tty for the Bluetooth B2 (baud rate
//! meaningless there) or a UART at 115200 8N1 (notes A0: LpSensor `LpmsRS232.cpp`, OpenZen `3c25e5b`).

use std::future::Future;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::mpsc;

use super::data::{DataMode, OutputMask, SensorData};
use super::error::{LinkError, LpmsError};
use super::session::{DeviceInfo, Event, Session, SessionConfig};

/// Default UART rate (notes A0).
pub const DEFAULT_BAUD: u32 = 115_200;

/// Configuration of the LPMS driver.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LpmsConfig {
    /// Serial device, e.g. `/dev/rfcomm0` (or a udev symlink to it).
    pub path: String,
    /// UART baud rate (ignored by RFCOMM ttys).
    pub baud: u32,
    /// Stream rate, Hz (5, 10, 25, 50, 100, 200, 400).
    pub stream_hz: u32,
    /// Id requests are addressed to.
    pub imu_id: u16,
    /// Outputs to stream.
    pub outputs: OutputMask,
    /// Float or 16-bit data.
    pub data_mode: DataMode,
    /// Time to wait for each reply.
    pub reply_timeout: Duration,
    /// No data for this long reopens the port.
    pub data_timeout: Duration,
    /// First reopen delay.
    pub backoff_initial: Duration,
    /// Longest reopen delay.
    pub backoff_max: Duration,
}

impl Default for LpmsConfig {
    fn default() -> Self {
        let s = SessionConfig::default();
        Self {
            path: "/dev/rfcomm0".into(),
            baud: DEFAULT_BAUD,
            stream_hz: s.stream_hz,
            imu_id: s.imu_id,
            outputs: s.outputs,
            data_mode: s.data_mode,
            reply_timeout: s.reply_timeout,
            data_timeout: s.data_timeout,
            backoff_initial: s.backoff_initial,
            backoff_max: s.backoff_max,
        }
    }
}

/// A configuration value the driver cannot work with.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConfigError {
    /// The path is empty.
    #[error("lpms.path is empty")]
    EmptyPath,
    /// The rate is not one the B2 streams at (notes A3: 5, 10, 25, 50, 100, 200, 400 Hz).
    #[error("lpms.stream_hz = {0}: the LPMS-B2 streams at 5, 10, 25, 50, 100, 200 or 400 Hz")]
    StreamRate(u32),
    /// A timeout or delay is zero.
    #[error("lpms.{0} must be positive")]
    ZeroDuration(&'static str),
    /// The data timeout does not cover two sample periods, so the watchdog would fire on jitter.
    #[error("lpms.data_timeout must exceed two sample periods ({min:?})")]
    DataTimeoutTooShort {
        /// Two sample periods.
        min: Duration,
    },
    /// The first backoff delay exceeds the cap.
    #[error("lpms.backoff_initial must not exceed lpms.backoff_max")]
    BackoffOrder,
}

impl LpmsConfig {
    /// Checks the values against what the sensor and the session can do.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.path.is_empty() {
            return Err(ConfigError::EmptyPath);
        }
        if !super::data::STREAM_RATES_HZ[..7].contains(&self.stream_hz) {
            return Err(ConfigError::StreamRate(self.stream_hz));
        }
        for (name, d) in [
            ("reply_timeout", self.reply_timeout),
            ("data_timeout", self.data_timeout),
            ("backoff_initial", self.backoff_initial),
            ("backoff_max", self.backoff_max),
        ] {
            if d.is_zero() {
                return Err(ConfigError::ZeroDuration(name));
            }
        }
        let min = Duration::from_secs_f64(2.0 / f64::from(self.stream_hz));
        if self.data_timeout <= min {
            return Err(ConfigError::DataTimeoutTooShort { min });
        }
        if self.backoff_initial > self.backoff_max {
            return Err(ConfigError::BackoffOrder);
        }
        Ok(())
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
            backoff_initial: self.backoff_initial,
            backoff_max: self.backoff_max,
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
            let mut progressed = false;
            while let Some(bytes) = session.poll_transmit() {
                progressed = true;
                if let Some(p) = port.as_mut() {
                    // A dead Bluetooth link can block writes: bound them by the reply timeout.
                    let written = tokio::time::timeout(write_timeout, async {
                        p.write_all(&bytes).await?;
                        p.flush().await
                    });
                    match written.await {
                        Ok(Ok(())) => {}
                        Ok(Err(e)) => session.link_failed(now(), LinkError::io(&e)),
                        Err(_) => session.link_failed(
                            now(),
                            LinkError::Io {
                                kind: std::io::ErrorKind::TimedOut,
                                message: "write timed out".into(),
                            },
                        ),
                    }
                }
            }
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
                        // Never block the reader on a slow consumer: the serial buffer would overflow.
                        if tx.try_send(ImuMessage::Sample(ImuSample { data, received_at: now() })).is_err() {
                            dropped_samples += 1;
                            tracing::warn!(dropped_samples, "LPMS sample dropped: consumer too slow");
                        }
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
        let deadline = session.poll_timeout().map(tokio::time::Instant::from_std);
        let fallback = tokio::time::Instant::now() + Duration::from_millis(100);
        // Bytes already waiting are read before a timer is acted on: a driver task that was
        // starved for a while must not declare the sensor silent while its data sits in the buffer.
        tokio::select! {
            biased;
            read = read_some(&mut port, &mut buf), if port.is_some() => match read {
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
) -> Result<(mpsc::Receiver<ImuMessage>, tokio::task::JoinHandle<()>), ConfigError> {
    config.validate()?;
    let (tx, rx) = mpsc::channel(capacity.max(1));
    Ok((rx, tokio::spawn(run_serial(config, tx))))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_names_the_broken_value() {
        assert_eq!(LpmsConfig::default().validate(), Ok(()));
        let bad = |f: fn(&mut LpmsConfig)| {
            let mut c = LpmsConfig::default();
            f(&mut c);
            c.validate().unwrap_err()
        };
        assert_eq!(bad(|c| c.path.clear()), ConfigError::EmptyPath);
        assert_eq!(bad(|c| c.stream_hz = 800), ConfigError::StreamRate(800));
        assert_eq!(bad(|c| c.stream_hz = 99), ConfigError::StreamRate(99));
        assert_eq!(bad(|c| c.reply_timeout = Duration::ZERO), ConfigError::ZeroDuration("reply_timeout"));
        assert!(matches!(
            bad(|c| {
                c.stream_hz = 5;
                c.data_timeout = Duration::from_millis(400);
            }),
            ConfigError::DataTimeoutTooShort { .. }
        ));
        assert_eq!(bad(|c| c.backoff_initial = Duration::from_secs(9)), ConfigError::BackoffOrder);
    }
}
