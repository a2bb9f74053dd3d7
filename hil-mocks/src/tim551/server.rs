//! The mock's TCP server: one task accepting, one task per connection. Each connection detects its
//! dialect from its first frame, answers commands through the pure `Device` model and streams
//! `sSN LMDscandata` on the device's 15 Hz scan clock once subscribed. Faults come in through the
//! [`MockHandle`].

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use amr_drivers::sopas::{Command, Dialect, ErrorCode, Framer, Reply, encode_frame};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, DuplexStream};
use tokio::net::TcpListener;
use tokio::sync::broadcast;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;

use super::device::{Conn, Device, SideEffect, Variant};
use super::source::ScanSource;

/// Mock settings.
#[derive(Debug, Clone, PartialEq)]
pub struct MockConfig {
    pub variant: Variant,
    /// `None`: answer whatever dialect a connection speaks first. `Some(d)`: behave like a real
    /// device set to `d`, ignoring frames of the other dialect until `sWN EIHstCola` switches it.
    pub dialect: Option<Dialect>,
    pub serial: u32,
    /// 15 Hz on a TiM5xx.
    pub scan_period: Duration,
    /// Device tick at boot, to exercise the 32-bit wrap.
    pub initial_tick_us: u32,
    /// How long `sMN mSCreboot` keeps the device away (sick_tim waits 15 s for a real one).
    pub reboot_down_for: Duration,
}

impl Default for MockConfig {
    fn default() -> Self {
        Self {
            variant: Variant::Tim551,
            dialect: None,
            serial: 0x0102_3456,
            scan_period: Duration::from_nanos(1_000_000_000 / 15),
            initial_tick_us: 0,
            reboot_down_for: Duration::from_millis(500),
        }
    }
}

/// A fault the mock injects on command (devices.md §4).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Fault {
    /// Close every connection; refuse new ones (accept and close) for `refuse_for`.
    Drop { refuse_for: Duration },
    /// Stay connected but send nothing (replies and scans are swallowed) until [`Fault::Resume`].
    Stall,
    /// Undo [`Fault::Stall`] and [`Fault::SlowReplies`].
    Resume,
    /// Send these bytes before the next scan telegram.
    Garbage(Vec<u8>),
    /// Send only the first half of the next scan telegram.
    TruncateNext,
    /// Corrupt the next scan telegram (CoLa-B: checksum byte; CoLa-A: a digit becomes `G`).
    CorruptNext,
    /// Answer the next `times` requests labelled `command` (e.g. `sRN SerialNumber`) with `sFA code`.
    ErrorReply { command: String, code: ErrorCode, times: u32 },
    /// Delay every reply.
    SlowReplies(Duration),
    /// Reboot: connections drop, nothing is accepted for `down_for`, counters and tick restart.
    Reboot { down_for: Duration },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Control {
    Drop,
}

#[derive(Debug)]
struct State {
    device: Device,
    boot: Instant,
    stalled: bool,
    slow: Option<Duration>,
    garbage: Option<Vec<u8>>,
    truncate: bool,
    corrupt: bool,
    error_replies: Vec<(String, ErrorCode, u32)>,
    refuse_until: Option<Instant>,
    strict_dialect: Option<Dialect>,
    log: Vec<(u64, Dialect, String)>,
}

#[derive(Debug)]
struct Shared {
    config: MockConfig,
    source: Arc<dyn ScanSource>,
    state: Mutex<State>,
    control: broadcast::Sender<Control>,
    connections: AtomicU64,
    scans_sent: AtomicU64,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Controls a running mock and observes what it did.
#[derive(Debug, Clone)]
pub struct MockHandle {
    shared: Arc<Shared>,
}

impl MockHandle {
    /// Injects a fault.
    pub fn inject(&self, fault: Fault) {
        apply(&self.shared, fault);
    }

    /// Connections accepted so far (refused ones included).
    pub fn connections(&self) -> u64 {
        self.shared.connections.load(Ordering::Relaxed)
    }

    /// Scan telegrams written so far (streamed and polled).
    pub fn scans_sent(&self) -> u64 {
        self.shared.scans_sent.load(Ordering::Relaxed)
    }

    /// Every request received: (connection number, dialect, label such as `sRN SerialNumber`).
    pub fn command_log(&self) -> Vec<(u64, Dialect, String)> {
        self.shared.lock().log.clone()
    }
}

fn apply(shared: &Shared, fault: Fault) {
    let now = Instant::now();
    let mut s = shared.lock();
    match fault {
        Fault::Drop { refuse_for } => {
            s.refuse_until = Some(now + refuse_for);
            let _ = shared.control.send(Control::Drop);
        }
        Fault::Stall => s.stalled = true,
        Fault::Resume => {
            s.stalled = false;
            s.slow = None;
        }
        Fault::Garbage(bytes) => s.garbage = Some(bytes),
        Fault::TruncateNext => s.truncate = true,
        Fault::CorruptNext => s.corrupt = true,
        Fault::ErrorReply { command, code, times } => s.error_replies.push((command, code, times)),
        Fault::SlowReplies(d) => s.slow = Some(d),
        Fault::Reboot { down_for } => {
            tracing::info!(down_ms = down_for.as_millis() as u64, "mock TiM5xx rebooting");
            s.refuse_until = Some(now + down_for);
            s.boot = now + down_for;
            s.device = Device::new(shared.config.variant, shared.config.serial);
            s.strict_dialect = shared.config.dialect;
            let _ = shared.control.send(Control::Drop);
        }
    }
}

/// A running mock TiM5xx.
#[derive(Debug)]
pub struct Tim551Mock {
    pub local_addr: SocketAddr,
    pub handle: MockHandle,
    task: JoinHandle<()>,
}

impl Tim551Mock {
    /// Binds `addr` (e.g. `127.0.0.1:0`) and starts serving.
    pub async fn spawn(addr: &str, config: MockConfig, source: Arc<dyn ScanSource>) -> std::io::Result<Self> {
        let listener = TcpListener::bind(addr).await?;
        let local_addr = listener.local_addr()?;
        let shared = Self::shared(config, source);
        let task = tokio::spawn(accept_loop(listener, shared.clone()));
        tracing::info!(%local_addr, "mock TiM5xx listening");
        Ok(Self { local_addr, handle: MockHandle { shared }, task })
    }

    /// A mock reached through in-memory pipes instead of TCP (a virtual-time simulation: no socket,
    /// so nothing but tokio's clock decides the order of events). Connect with the returned
    /// [`MemoryConnector`].
    pub fn spawn_in_memory(config: MockConfig, source: Arc<dyn ScanSource>) -> (Self, MemoryConnector) {
        let shared = Self::shared(config, source);
        let (tx, rx) = mpsc::channel(4);
        let task = tokio::spawn(accept_memory(rx, shared.clone()));
        let local_addr = SocketAddr::from(([0, 0, 0, 0], 0));
        (Self { local_addr, handle: MockHandle { shared }, task }, MemoryConnector { tx })
    }

    fn shared(config: MockConfig, source: Arc<dyn ScanSource>) -> Arc<Shared> {
        let (control, _) = broadcast::channel(16);
        let state = State {
            device: Device::new(config.variant, config.serial),
            boot: Instant::now(),
            stalled: false,
            slow: None,
            garbage: None,
            truncate: false,
            corrupt: false,
            error_replies: Vec::new(),
            refuse_until: None,
            strict_dialect: config.dialect,
            log: Vec::new(),
        };
        Arc::new(Shared {
            config,
            source,
            state: Mutex::new(state),
            control,
            connections: AtomicU64::new(0),
            scans_sent: AtomicU64::new(0),
        })
    }

    /// The bound port.
    pub fn port(&self) -> u16 {
        self.local_addr.port()
    }
}

impl Drop for Tim551Mock {
    fn drop(&mut self) {
        self.task.abort();
        let _ = self.handle.shared.control.send(Control::Drop);
    }
}

async fn accept_loop(listener: TcpListener, shared: Arc<Shared>) {
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(x) => x,
            Err(e) => {
                // E.g. out of file descriptors: back off instead of spinning on the error.
                tracing::warn!(error = %e, "mock accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let id = shared.connections.fetch_add(1, Ordering::Relaxed);
        let refused = shared.lock().refuse_until.is_some_and(|t| Instant::now() < t);
        if refused {
            tracing::debug!(%peer, "mock refusing connection (down)");
            drop(stream);
            continue;
        }
        let _ = stream.set_nodelay(true);
        let control = shared.control.subscribe();
        tokio::spawn(serve(id, stream, shared.clone(), control));
    }
}

/// Opens in-memory connections to a mock made by [`Tim551Mock::spawn_in_memory`].
#[derive(Debug, Clone)]
pub struct MemoryConnector {
    tx: mpsc::Sender<DuplexStream>,
}

impl MemoryConnector {
    /// A new connection (refused like a TCP connect when the mock is gone).
    pub async fn connect(&self) -> std::io::Result<DuplexStream> {
        let (client, server) = tokio::io::duplex(64 * 1024);
        self.tx
            .send(server)
            .await
            .map_err(|_| std::io::Error::from(std::io::ErrorKind::ConnectionRefused))?;
        Ok(client)
    }
}

async fn accept_memory(mut rx: mpsc::Receiver<DuplexStream>, shared: Arc<Shared>) {
    // Bounded by the connector: one pass per connection.
    while let Some(stream) = rx.recv().await {
        let id = shared.connections.fetch_add(1, Ordering::Relaxed);
        if shared.lock().refuse_until.is_some_and(|t| Instant::now() < t) {
            drop(stream);
            continue;
        }
        let control = shared.control.subscribe();
        tokio::spawn(serve(id, stream, shared.clone(), control));
    }
}

struct ConnState {
    id: u64,
    dialect: Option<Dialect>,
    conn: Conn,
    next_scan: u64,
    telegram_counter: u16,
}

async fn serve<S: AsyncRead + AsyncWrite + Unpin>(
    id: u64,
    mut stream: S,
    shared: Arc<Shared>,
    mut control: broadcast::Receiver<Control>,
) {
    let mut framer = Framer::default();
    let mut c = ConnState { id, dialect: None, conn: Conn::default(), next_scan: 0, telegram_counter: 0 };
    let mut buf = vec![0u8; 4096];
    loop {
        let next_scan_at = if c.conn.streaming { Some(scan_time(&shared, c.next_scan)) } else { None };
        let sleep = async {
            match next_scan_at {
                Some(t) => tokio::time::sleep_until(t).await,
                None => std::future::pending().await,
            }
        };
        // In this order (a fault's drop, the scan that is due, the host's bytes): the same order
        // every time, so a virtual-time run is the same from the same seed.
        tokio::select! {
            biased;
            msg = control.recv() => match msg {
                Ok(Control::Drop) | Err(broadcast::error::RecvError::Closed) => return,
                Err(broadcast::error::RecvError::Lagged(_)) => {}
            },
            () = sleep => {
                if send_scan(&shared, &mut c, &mut stream, true).await.is_err() {
                    return;
                }
            }
            r = stream.read(&mut buf) => {
                let n = match r {
                    Ok(0) | Err(_) => return,
                    Ok(n) => n,
                };
                framer.push(&buf[..n]);
                while let Some(frame) = framer.next_frame() {
                    let Ok(frame) = frame else { continue };
                    if handle_frame(&shared, &mut c, &mut stream, frame.dialect, &frame.payload).await.is_err() {
                        return;
                    }
                }
            }
        }
    }
}

/// When scan `index` (counted from boot) ends.
fn scan_time(shared: &Shared, index: u64) -> Instant {
    let boot = shared.lock().boot;
    boot + shared.config.scan_period.saturating_mul(u32::try_from(index).unwrap_or(u32::MAX))
}

/// The number of the last scan completed at `now`.
fn current_scan(shared: &Shared, now: Instant) -> u64 {
    let boot = shared.lock().boot;
    let period = shared.config.scan_period.as_nanos().max(1);
    (now.saturating_duration_since(boot).as_nanos() / period) as u64
}

async fn handle_frame(
    shared: &Shared,
    c: &mut ConnState,
    stream: &mut (impl AsyncWrite + Unpin),
    dialect: Dialect,
    payload: &[u8],
) -> std::io::Result<()> {
    if shared.lock().strict_dialect.is_some_and(|d| d != dialect) {
        tracing::debug!(?dialect, "mock ignores a frame in the other dialect");
        return Ok(());
    }
    let reply_dialect = *c.dialect.get_or_insert(dialect);
    let (reply, effect) = match Command::decode(dialect, payload) {
        Err(e) => {
            tracing::debug!(error = %e, "mock got an undecodable request");
            let code = if payload.starts_with(b"sRN ") || payload.starts_with(b"sWN ") {
                ErrorCode::VariableUnknownIndex
            } else {
                ErrorCode::UnknownColaCommand
            };
            (Reply::Error(code), SideEffect::None)
        }
        Ok(cmd) => {
            let now = Instant::now();
            let index = current_scan(shared, now);
            let mut s = shared.lock();
            s.log.push((c.id, dialect, cmd.label()));
            let forced = s.error_replies.iter_mut().find(|(label, _, n)| *n > 0 && *label == cmd.label());
            if let Some((_, code, n)) = forced {
                *n -= 1;
                (Reply::Error(*code), SideEffect::None)
            } else {
                let boot = s.boot;
                let counter = c.telegram_counter;
                let poll = |d: &Device| {
                    d.telegram(
                        shared.source.as_ref(),
                        index,
                        shared.config.scan_period,
                        now.saturating_duration_since(boot),
                        counter,
                        shared.config.initial_tick_us,
                    )
                };
                let was_streaming = c.conn.streaming;
                let mut device = s.device.clone();
                let out = device.answer(&mut c.conn, &cmd, poll);
                s.device = device;
                if matches!(out.0, Reply::ScanData { .. }) {
                    c.telegram_counter = c.telegram_counter.wrapping_add(1);
                    shared.scans_sent.fetch_add(1, Ordering::Relaxed);
                }
                if c.conn.streaming && !was_streaming {
                    c.next_scan = index + 1;
                }
                out
            }
        }
    };
    let (slow, stalled) = {
        let s = shared.lock();
        (s.slow, s.stalled)
    };
    if let Some(d) = slow {
        tokio::time::sleep(d).await;
    }
    if !stalled {
        let bytes = match reply.encode(reply_dialect) {
            Ok(p) => encode_frame(reply_dialect, &p),
            Err(e) => {
                tracing::warn!(error = %e, "mock could not encode its reply");
                return Ok(());
            }
        };
        stream.write_all(&bytes).await?;
    }
    match effect {
        SideEffect::None => {}
        SideEffect::SwitchDialect(d) => {
            c.dialect = Some(d);
            let mut s = shared.lock();
            if s.strict_dialect.is_some() {
                s.strict_dialect = Some(d);
            }
        }
        SideEffect::Reboot => apply(shared, Fault::Reboot { down_for: shared.config.reboot_down_for }),
    }
    Ok(())
}

/// Sends scan `c.next_scan` (applying one-shot faults) and advances; catches up without skipping.
async fn send_scan(
    shared: &Shared,
    c: &mut ConnState,
    stream: &mut (impl AsyncWrite + Unpin),
    event: bool,
) -> std::io::Result<()> {
    let dialect = c.dialect.unwrap_or(Dialect::ColaB);
    let now = Instant::now();
    let (telegram, garbage, truncate, corrupt, stalled) = {
        let mut s = shared.lock();
        let sent = now.saturating_duration_since(s.boot);
        let t = s.device.telegram(
            shared.source.as_ref(),
            c.next_scan,
            shared.config.scan_period,
            sent,
            c.telegram_counter,
            shared.config.initial_tick_us,
        );
        let stalled = s.stalled;
        if stalled {
            (t, None, false, false, true)
        } else {
            (t, s.garbage.take(), std::mem::take(&mut s.truncate), std::mem::take(&mut s.corrupt), false)
        }
    };
    c.next_scan += 1;
    c.telegram_counter = c.telegram_counter.wrapping_add(1);
    if stalled {
        return Ok(());
    }
    let reply = Reply::ScanData { event, telegram: Box::new(telegram) };
    let mut bytes = match reply.encode(dialect) {
        Ok(p) => encode_frame(dialect, &p),
        Err(e) => {
            tracing::warn!(error = %e, "mock could not encode a scan");
            return Ok(());
        }
    };
    if corrupt {
        corrupt_frame(dialect, &mut bytes);
    }
    if truncate {
        bytes.truncate(bytes.len() / 2);
    }
    if let Some(g) = garbage {
        stream.write_all(&g).await?;
    }
    stream.write_all(&bytes).await?;
    shared.scans_sent.fetch_add(1, Ordering::Relaxed);
    Ok(())
}

fn corrupt_frame(dialect: Dialect, bytes: &mut [u8]) {
    match dialect {
        Dialect::ColaB => {
            if let Some(last) = bytes.last_mut() {
                *last ^= 0x5A;
            }
        }
        Dialect::ColaA => {
            let mid = bytes.len() / 2;
            if let Some(i) = bytes[mid..].iter().position(u8::is_ascii_hexdigit) {
                bytes[mid + i] = b'G';
            }
        }
    }
}

#[cfg(test)]
mod memory_tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use std::sync::Arc;
    use std::time::Duration;

    use amr_drivers::sopas::tcp::{LidarConfig, LidarMessage, spawn_stream};

    use super::{MockConfig, Tim551Mock};
    use crate::tim551::RectRoom;

    /// The real SOPAS shell against the mock over in-memory pipes, in paused time: 10 simulated
    /// seconds at 15 Hz give 150 scans, whatever the machine's load, and the same run twice gives
    /// the same stamps.
    #[tokio::test(start_paused = true)]
    async fn the_shell_streams_from_the_in_memory_mock_in_virtual_time() {
        let mut runs = Vec::new();
        for _ in 0..2 {
            let (mock, connector) =
                Tim551Mock::spawn_in_memory(MockConfig::default(), Arc::new(RectRoom::default()));
            let connect = move |_addr: String| {
                let c = connector.clone();
                async move { c.connect().await }
            };
            let (task, mut rx) = spawn_stream(LidarConfig::default(), connect, 64);
            let start = tokio::time::Instant::now();
            let mut stamps = Vec::new();
            while start.elapsed() < Duration::from_secs(10) {
                if let Some(LidarMessage::Scan(s)) = rx.recv().await {
                    stamps.push(s.received.duration_since(start.into_std()).as_micros());
                }
            }
            task.abort();
            assert_eq!(mock.handle.connections(), 1);
            runs.push(stamps);
        }
        assert!((148..=151).contains(&runs[0].len()), "{} scans", runs[0].len());
        assert_eq!(runs[0], runs[1]);
    }
}
