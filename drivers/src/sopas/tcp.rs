//! The tokio shell: runs a [`Session`] over `tokio::net::TcpStream`, reconnects when it asks, and
//! publishes scans with host timestamps, health and errors on a channel. All protocol decisions
//! live in the session; this file only moves bytes and waits.

use std::time::Duration;

use std::future::Future;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;

use amr_settings::value::Backoff;
use amr_settings::{DeviceSource, Violation, join, rule};
use serde::Deserialize;

use super::error::{LinkError, SopasError};
use super::session::{DeviceInfo, DialectChoice, Event, Mode, Profile, Session, SessionConfig, StampedScan};

/// One LiDAR connection: `[devices.lidar]` of a robot file (devices.md §1), deserialised straight
/// into this type; [`LidarConfig::validate`] checks the rules across its fields.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LidarConfig {
    pub source: DeviceSource,
    pub host: String,
    /// 2112 on a TiM5xx (notes §1.3).
    pub port: u16,
    /// `auto`, `A` (CoLa-A, ASCII) or `B` (CoLa-B, binary).
    pub dialect: DialectChoice,
    /// The start-up sequence: `minimal` (the ROS `sick_tim` driver's) or `full` (`sick_scan_xd`'s).
    pub startup: Profile,
    /// Streaming on a robot; polling is for tests and diagnostics, not a file setting.
    #[serde(skip, default = "streaming")]
    pub mode: Mode,
    /// How long to wait for the reply to one command.
    #[serde(rename = "reply_timeout_ms", deserialize_with = "amr_settings::value::millis")]
    pub reply_timeout: Duration,
    /// No scan for this long while streaming → reconnect and run the start-up again.
    #[serde(rename = "scan_timeout_ms", deserialize_with = "amr_settings::value::millis")]
    pub scan_timeout: Duration,
    pub reconnect: Backoff,
    /// sick_tim and sick_scan_xd both give a connect 5 s; not a file setting.
    #[serde(skip, default = "connect_timeout")]
    pub connect_timeout: Duration,
}

fn streaming() -> Mode {
    Mode::Streaming
}

fn connect_timeout() -> Duration {
    Duration::from_secs(5)
}

impl Default for LidarConfig {
    fn default() -> Self {
        let s = SessionConfig::default();
        Self {
            source: DeviceSource::Real,
            host: "192.168.0.1".into(),
            port: 2112,
            dialect: s.dialect,
            startup: s.profile,
            mode: s.mode,
            reply_timeout: s.reply_timeout,
            scan_timeout: s.scan_timeout,
            reconnect: Backoff { initial: s.backoff_initial, max: s.backoff_max },
            connect_timeout: connect_timeout(),
        }
    }
}

impl LidarConfig {
    /// The section's rules; `path` is where it stands (`devices.lidar`).
    pub fn validate(&self, path: &str) -> Result<(), Violation> {
        rule(!self.host.trim().is_empty(), join(path, "host"), "must not be empty")?;
        rule(self.port != 0, join(path, "port"), "must be a TCP port in 1..=65535 (got 0)")?;
        rule(
            self.scan_timeout >= Duration::from_millis(200),
            join(path, "scan_timeout_ms"),
            format!(
                "must be at least 200 ms (three scan periods at 15 Hz) (got {} ms)",
                self.scan_timeout.as_millis()
            ),
        )?;
        self.reconnect.check(&join(path, "reconnect"))
    }

    fn session_config(&self) -> SessionConfig {
        SessionConfig {
            profile: self.startup,
            dialect: self.dialect,
            mode: self.mode,
            reply_timeout: self.reply_timeout,
            scan_timeout: self.scan_timeout,
            backoff_initial: self.reconnect.initial,
            backoff_max: self.reconnect.max,
            ..SessionConfig::default()
        }
    }
}

/// Connection health, `Starting | Ok | Degraded | Lost` (docs/architecture.md, "The robot's actor
/// tree").
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Health {
    /// Connected, start-up running.
    Starting,
    /// Start-up done.
    Ok(DeviceInfo),
    /// Connection lost; reconnecting after `retry_in`.
    Lost { retry_in: Duration },
}

/// What the shell publishes.
#[derive(Debug, Clone, PartialEq)]
pub enum LidarMessage {
    Scan(Box<StampedScan>),
    Health(Health),
    /// A device error (`sFA`) or a broken frame / timeout / link, kept in its layer.
    Error(SopasError),
}

/// Runs the connection over TCP until the receiver is dropped.
pub async fn run_tcp(config: LidarConfig, tx: mpsc::Sender<LidarMessage>) {
    let connect = |addr: String| async move {
        let s = TcpStream::connect(&addr).await?;
        let _ = s.set_nodelay(true);
        Ok(s)
    };
    run_stream(config, connect, tx).await;
}

/// Runs the connection over any byte stream `connect(address)` opens (TCP on a robot; an
/// in-memory pipe in a virtual-time simulation), until the receiver is dropped.
pub async fn run_stream<S, F, Fut>(config: LidarConfig, mut connect: F, tx: mpsc::Sender<LidarMessage>)
where
    S: AsyncRead + AsyncWrite + Unpin + Send,
    F: FnMut(String) -> Fut,
    Fut: Future<Output = std::io::Result<S>>,
{
    let mut session = Session::new(config.session_config(), Instant::now().into_std());
    let mut stream: Option<S> = None;
    let mut buf = vec![0u8; 8192];
    loop {
        if stream.is_none()
            && session.needs_connection(Instant::now().into_std())
            && !open(&config, &mut connect, &mut session, &mut stream, &tx).await
        {
            return;
        }
        if let Some(s) = stream.as_mut() {
            transmit(&mut session, s, config.reply_timeout).await;
        }
        while let Some(event) = session.poll_event() {
            let Some(msg) = message(event, &mut stream) else { continue };
            if tx.send(msg).await.is_err() {
                return;
            }
        }
        let deadline = session.poll_timeout().map(Instant::from_std);
        let sleep = async {
            match deadline {
                Some(d) => tokio::time::sleep_until(d).await,
                None => std::future::pending().await,
            }
        };
        // In a fixed order, so that a run on a paused clock is the same every time: bytes
        // already waiting before a timer (a task that was starved must not call the device silent
        // while its data sits in the buffer), and the timers run after every read too, so a
        // device that never stops sending cannot starve them.
        match stream.as_mut() {
            Some(s) => {
                tokio::select! {
                    biased;
                    r = s.read(&mut buf) => {
                        let now = Instant::now().into_std();
                        match r {
                            Ok(0) => {
                                stream = None;
                                session.handle_disconnected(now, LinkError::Closed);
                            }
                            Ok(n) => {
                                session.handle_bytes(now, &buf[..n]);
                                session.handle_timeout(now);
                            }
                            Err(e) => {
                                stream = None;
                                session.handle_disconnected(now, LinkError::Io(e.to_string()));
                            }
                        }
                    }
                    () = sleep => session.handle_timeout(Instant::now().into_std()),
                    () = tx.closed() => return,
                }
            }
            None => {
                tokio::select! {
                    biased;
                    () = sleep => session.handle_timeout(Instant::now().into_std()),
                    () = tx.closed() => return,
                }
            }
        }
    }
}

/// Open the connection (at most `connect_timeout`) and tell the session how it went; `false`
/// when the receiver is gone.
async fn open<S, F, Fut>(
    config: &LidarConfig,
    connect: &mut F,
    session: &mut Session,
    stream: &mut Option<S>,
    tx: &mpsc::Sender<LidarMessage>,
) -> bool
where
    F: FnMut(String) -> Fut,
    Fut: Future<Output = std::io::Result<S>>,
{
    let addr = format!("{}:{}", config.host, config.port);
    match tokio::time::timeout(config.connect_timeout, connect(addr.clone())).await {
        Ok(Ok(s)) => {
            tracing::info!(%addr, "sopas connected");
            *stream = Some(s);
            session.handle_connected(Instant::now().into_std());
            return tx.send(LidarMessage::Health(Health::Starting)).await.is_ok();
        }
        Ok(Err(e)) => session.handle_connect_failed(
            Instant::now().into_std(),
            LinkError::Connect { addr, msg: e.to_string() },
        ),
        Err(_) => session.handle_connect_failed(
            Instant::now().into_std(),
            LinkError::Connect { addr, msg: "timed out".into() },
        ),
    }
    true
}

/// Write what the session has to send. Bounded: a device that stops reading must not wedge the
/// shell; a failed or stalled write drops the connection.
async fn transmit<S: AsyncWrite + Unpin>(session: &mut Session, s: &mut S, timeout: Duration) {
    while let Some(bytes) = session.poll_transmit() {
        let failed = match tokio::time::timeout(timeout, s.write_all(&bytes)).await {
            Ok(Ok(())) => None,
            Ok(Err(e)) => Some(e.to_string()),
            Err(_) => Some("write timed out".to_string()),
        };
        if let Some(msg) = failed {
            session.handle_disconnected(Instant::now().into_std(), LinkError::Io(msg));
            break;
        }
    }
}

/// What the application is told of a session event (`None`: only logged); a reconnect drops the
/// stream.
fn message<S>(event: Event, stream: &mut Option<S>) -> Option<LidarMessage> {
    Some(match event {
        Event::Scan(scan) => LidarMessage::Scan(scan),
        Event::Ready(info) => LidarMessage::Health(Health::Ok(info)),
        Event::DeviceError(e) => LidarMessage::Error(e.into()),
        Event::ProtocolError(e) => LidarMessage::Error(e.into()),
        Event::LoginRefused => {
            tracing::warn!("sopas login refused (sAN SetAccessMode 0); continuing without it");
            return None;
        }
        Event::DialectDetected(dialect) => {
            tracing::info!(?dialect, "sopas dialect detected");
            return None;
        }
        Event::Reconnect { reason, delay } => {
            tracing::warn!(?reason, "sopas dropping the connection");
            *stream = None;
            LidarMessage::Health(Health::Lost { retry_in: delay })
        }
    })
}

/// Spawns [`run_stream`] and returns its handle with the receiving end of the channel.
pub fn spawn_stream<S, F, Fut>(
    config: LidarConfig,
    connect: F,
    capacity: usize,
) -> (JoinHandle<()>, mpsc::Receiver<LidarMessage>)
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    F: FnMut(String) -> Fut + Send + 'static,
    Fut: Future<Output = std::io::Result<S>> + Send + 'static,
{
    let (tx, rx) = mpsc::channel(capacity.max(1));
    (tokio::spawn(run_stream(config, connect, tx)), rx)
}

/// Spawns [`run_tcp`] and returns its handle with the receiving end of the channel.
pub fn spawn_tcp(config: LidarConfig, capacity: usize) -> (JoinHandle<()>, mpsc::Receiver<LidarMessage>) {
    let (tx, rx) = mpsc::channel(capacity.max(1));
    (tokio::spawn(run_tcp(config, tx)), rx)
}
