//! The mock LPMS-B2 behind a pseudo-terminal, so the driver opens it through tokio-serial exactly
//! as it opens `/dev/rfcomm0` on the robot.
//!
//! Replug with ptys: a pty's slave path (`/dev/pts/N`) vanishes when the mock closes the master, and
//! a new pair gets a new N. So the driver is pointed at a stable symlink (`link_path`) that the mock
//! re-points atomically (symlink to a temporary name, then rename) on every replug — the same way
//! udev gives an RFCOMM device a stable name. While unplugged the symlink does not exist, so the
//! driver's reopen attempts fail with "not found" until the replug.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use amr_drivers::lpms::command::CommandId;
use thiserror::Error;
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;
use tokio::time::{Instant, MissedTickBehavior};
use tokio_serial::{SerialPort, SerialStream};

use super::device::{DeviceSettings, DeviceStats, MockDevice};
use super::motion::{ConstantYawRate, MotionSource};

/// A write to the pty that does not finish in this time is dropped (nobody is reading the slave:
/// a real Bluetooth link loses data the same way).
const WRITE_TIMEOUT: Duration = Duration::from_millis(100);
/// How long to wait before reading the master again when no one holds the slave open.
const NO_PEER_RETRY: Duration = Duration::from_millis(10);

/// How to start the mock.
#[derive(Debug, Clone, Default)]
pub struct MockImuOptions {
    /// Where the stable symlink to the current pty goes; `None` picks a fresh path in the temp dir.
    pub link_path: Option<PathBuf>,
    /// Power-up settings (stream rate, outputs, data mode, id, identity strings).
    pub device: DeviceSettings,
}

impl MockImuOptions {
    /// Options for `amr mock imu --rate <hz>`: power up streaming at `rate_hz`.
    pub fn with_rate(rate_hz: u32) -> Self {
        Self { device: DeviceSettings { stream_hz: rate_hz, ..DeviceSettings::default() }, ..Self::default() }
    }
}

/// A fault the mock injects on command (devices.md §4).
#[derive(Debug, Clone, PartialEq)]
pub enum Fault {
    /// Write these bytes to the link now, between frames.
    Garbage(Vec<u8>),
    /// Send the next `n` frames (replies or data) with a wrong LRC.
    WrongLrc(u32),
    /// Answer the next `times` requests of `command` with NACK.
    Nack {
        /// The command to refuse.
        command: CommandId,
        /// How many times.
        times: u32,
    },
    /// Send the next `n` frames cut to half their length (applied after any pending `WrongLrc`).
    Truncate(u32),
    /// Swallow the next `n` replies (not data).
    DropReplies(u32),
    /// Send nothing at all (neither replies nor data) while `true`; requests are still executed.
    Silence(bool),
}

/// Errors of the mock.
#[derive(Debug, Error)]
pub enum MockImuError {
    /// Creating the pty or the symlink failed.
    #[error("mock IMU pty: {0}")]
    Io(#[from] std::io::Error),
    /// The pty has no slave name.
    #[error("mock IMU pty has no slave path")]
    NoSlavePath,
    /// The mock task has stopped.
    #[error("mock IMU task has stopped")]
    Stopped,
}

/// Counters of the running mock.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MockImuStats {
    /// Device counters (commands seen, NACKs, data packets produced).
    pub device: DeviceStats,
    /// Data packets written to the pty completely.
    pub packets_written: u64,
    /// Writes dropped (timeout or error).
    pub writes_dropped: u64,
    /// Current pty slave path, if plugged.
    pub pty_path: Option<PathBuf>,
    /// Plug-ins so far (1 after start).
    pub plugs: u32,
}

enum Control {
    Fault(Fault, oneshot::Sender<()>),
    Unplug(oneshot::Sender<()>),
    Replug(oneshot::Sender<Result<PathBuf, MockImuError>>),
}

/// Handle to a running mock; dropping it stops the mock and removes the symlink.
#[derive(Debug)]
pub struct MockImuHandle {
    link_path: PathBuf,
    control: mpsc::Sender<Control>,
    stats: Arc<Mutex<MockImuStats>>,
    task: JoinHandle<()>,
}

impl std::fmt::Debug for Control {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Fault(x, _) => write!(f, "Fault({x:?})"),
            Self::Unplug(_) => write!(f, "Unplug"),
            Self::Replug(_) => write!(f, "Replug"),
        }
    }
}

impl MockImuHandle {
    /// The stable path to point the driver at.
    pub fn tty_path(&self) -> &Path {
        &self.link_path
    }

    /// A snapshot of the counters.
    pub fn stats(&self) -> MockImuStats {
        self.stats.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Injects a fault; returns once the mock has applied it.
    pub async fn inject(&self, fault: Fault) -> Result<(), MockImuError> {
        let (tx, rx) = oneshot::channel();
        self.control.send(Control::Fault(fault, tx)).await.map_err(|_| MockImuError::Stopped)?;
        rx.await.map_err(|_| MockImuError::Stopped)
    }

    /// Closes the pty (the driver's port reports an error) and removes the symlink; returns once done.
    pub async fn unplug(&self) -> Result<(), MockImuError> {
        let (tx, rx) = oneshot::channel();
        self.control.send(Control::Unplug(tx)).await.map_err(|_| MockImuError::Stopped)?;
        rx.await.map_err(|_| MockImuError::Stopped)
    }

    /// Opens a new pty and re-points the symlink to it; returns the new slave path once it is there.
    pub async fn replug(&self) -> Result<PathBuf, MockImuError> {
        let (tx, rx) = oneshot::channel();
        self.control.send(Control::Replug(tx)).await.map_err(|_| MockImuError::Stopped)?;
        rx.await.map_err(|_| MockImuError::Stopped)?
    }

    /// Stops the mock and removes the symlink.
    pub fn shutdown(self) {
        drop(self);
    }
}

impl Drop for MockImuHandle {
    fn drop(&mut self) {
        self.task.abort();
        let _ = std::fs::remove_file(&self.link_path);
    }
}

/// Default symlinks are `amr-mock-imu-<pid>-<n>` in the temp dir.
const LINK_PREFIX: &str = "amr-mock-imu-";

fn default_link_path() -> PathBuf {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    let dir = std::env::temp_dir();
    if n == 0 {
        remove_stale_links(&dir);
    }
    dir.join(format!("{LINK_PREFIX}{}-{n}", std::process::id()))
}

/// Removes the default symlinks (and their temporary `.new` names) that processes no longer
/// running left in `dir`: a mock stopped by a signal (Ctrl-C on `amr sim`, a test killing it)
/// never runs its `Drop`. A link is left alone unless its process is known to be gone, which
/// needs `/proc`; without it nothing is removed. (A process in another PID namespace that shares
/// the temp dir looks gone: give such mocks their own `link_path`.)
fn remove_stale_links(dir: &Path) {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name
            .to_str()
            .and_then(|n| n.strip_prefix(LINK_PREFIX))
            .and_then(|rest| rest.split(['-', '.']).next())
            .and_then(|pid| pid.parse::<u32>().ok())
        else {
            continue;
        };
        let is_link = entry.file_type().is_ok_and(|t| t.is_symlink());
        if is_link && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// Opens a pty pair, points `link_path` at the slave and returns the master. The mock does not keep
/// the slave open: the driver is the only one holding it, as with a real tty.
fn plug(link_path: &Path) -> Result<(SerialStream, PathBuf), MockImuError> {
    let (master, slave) = SerialStream::pair().map_err(std::io::Error::from)?;
    let slave_path = PathBuf::from(slave.name().ok_or(MockImuError::NoSlavePath)?);
    drop(slave);
    let tmp = link_path.with_extension("new");
    let _ = std::fs::remove_file(&tmp);
    std::os::unix::fs::symlink(&slave_path, &tmp)?;
    std::fs::rename(&tmp, link_path)?;
    tracing::info!(link = %link_path.display(), pty = %slave_path.display(), "mock LPMS plugged in");
    Ok((master, slave_path))
}

/// Starts the mock IMU with the motion source `motion`; returns once the tty path exists.
pub async fn start_mock_imu(
    options: MockImuOptions,
    motion: Box<dyn MotionSource>,
) -> Result<MockImuHandle, MockImuError> {
    let link_path = options.link_path.clone().unwrap_or_else(default_link_path);
    let (master, pty_path) = plug(&link_path)?;
    let stats = MockImuStats { pty_path: Some(pty_path), plugs: 1, ..MockImuStats::default() };
    Ok(spawn_runner(options, motion, Some(Box::new(master)), None, link_path, stats))
}

/// Start the runner task on `master` (the pty) or `pipes` (in memory).
fn spawn_runner(
    options: MockImuOptions,
    motion: Box<dyn MotionSource>,
    master: Option<Box<dyn Port>>,
    pipes: Option<mpsc::Receiver<DuplexStream>>,
    link_path: PathBuf,
    stats: MockImuStats,
) -> MockImuHandle {
    let stats = Arc::new(Mutex::new(stats));
    let (control, control_rx) = mpsc::channel(16);
    let runner = Runner {
        device: MockDevice::new(options.device),
        motion,
        master,
        pipes,
        plugged: true,
        link_path: link_path.clone(),
        stats: stats.clone(),
        silent: false,
        started: Instant::now(),
    };
    let task = tokio::spawn(runner.run(control_rx));
    MockImuHandle { link_path, control, stats, task }
}

/// Opens in-memory connections to a mock made by [`start_mock_imu_in_memory`] (what opening the
/// tty is on a robot).
#[derive(Debug, Clone)]
pub struct ImuConnector {
    tx: mpsc::Sender<DuplexStream>,
}

impl ImuConnector {
    /// A new connection; the previous one is closed (one port, one user).
    pub async fn connect(&self) -> std::io::Result<DuplexStream> {
        let (client, server) = tokio::io::duplex(64 * 1024);
        self.tx.send(server).await.map_err(|_| std::io::Error::from(std::io::ErrorKind::NotFound))?;
        Ok(client)
    }
}

/// The mock over in-memory pipes instead of a pty (a virtual-time simulation: no file descriptor,
/// so nothing but tokio's clock decides the order of events). Unplug closes the current pipe and
/// refuses new ones until replug; the returned path is only a name.
pub fn start_mock_imu_in_memory(
    options: MockImuOptions,
    motion: Box<dyn MotionSource>,
) -> (MockImuHandle, ImuConnector) {
    let link_path = PathBuf::from("in-memory-imu");
    let (tx, rx) = mpsc::channel(4);
    let stats = MockImuStats { plugs: 1, ..MockImuStats::default() };
    (spawn_runner(options, motion, None, Some(rx), link_path, stats), ImuConnector { tx })
}

/// Starts the mock the way `amr mock imu --rate <hz>` will: a slowly turning body
/// (0.2 rad/s, 0.005 rad/s bias, 0.002 rad/s noise, seed 1).
pub async fn start_default_mock_imu(rate_hz: u32) -> Result<MockImuHandle, MockImuError> {
    start_mock_imu(MockImuOptions::with_rate(rate_hz), Box::new(ConstantYawRate::new(0.2, 0.005, 0.002, 1)))
        .await
}

/// The mock's side of the link: the pty master, or one end of an in-memory pipe.
trait Port: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send {}
impl<T: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send> Port for T {}

struct Runner {
    device: MockDevice,
    motion: Box<dyn MotionSource>,
    master: Option<Box<dyn Port>>,
    /// In-memory mode: new connections from the [`ImuConnector`]; `None` for the pty.
    pipes: Option<mpsc::Receiver<DuplexStream>>,
    /// In-memory mode: whether the "cable" is in (connections are refused while unplugged).
    plugged: bool,
    link_path: PathBuf,
    stats: Arc<Mutex<MockImuStats>>,
    silent: bool,
    started: Instant,
}

impl Runner {
    fn stats(&self) -> std::sync::MutexGuard<'_, MockImuStats> {
        self.stats.lock().unwrap_or_else(|e| e.into_inner())
    }

    async fn write(&mut self, bytes: &[u8]) -> bool {
        if self.silent || bytes.is_empty() {
            return false;
        }
        let Some(master) = self.master.as_mut() else { return false };
        let done = tokio::time::timeout(WRITE_TIMEOUT, async {
            master.write_all(bytes).await?;
            master.flush().await
        })
        .await;
        let ok = matches!(done, Ok(Ok(())));
        if !ok {
            self.stats().writes_dropped += 1;
        }
        ok
    }

    fn new_interval(&self) -> tokio::time::Interval {
        let period = self.device.stream_period();
        let mut iv = tokio::time::interval_at(Instant::now() + period, period);
        iv.set_missed_tick_behavior(MissedTickBehavior::Burst);
        iv
    }

    async fn run(mut self, mut control: mpsc::Receiver<Control>) {
        let mut buf = vec![0u8; 1024];
        let mut interval = self.new_interval();
        let mut period = self.device.stream_period();
        let mut streaming = self.device.is_streaming();
        let mut read_paused_until: Option<Instant> = None;
        loop {
            let can_read = self.master.is_some() && read_paused_until.is_none();
            let stream_now = streaming && self.master.is_some();
            // In this order (a fault or a plug, the stream's next packet, the host's bytes, the
            // pauses, a new pipe): the same order every time, so a virtual-time run is the same
            // from the same seed; the stream is never starved by a port that is always readable.
            tokio::select! {
                biased;
                ctl = control.recv() => match ctl {
                    None => return,
                    Some(c) => {
                        let was_plugged = self.master.is_some();
                        self.control(c).await;
                        if !was_plugged && self.master.is_some() {
                            // No burst of the ticks missed while unplugged.
                            interval = self.new_interval();
                        }
                    }
                },
                _ = interval.tick(), if stream_now => {
                    let motion = self.motion.motion_at(self.started.elapsed().as_secs_f64());
                    let packet = self.device.next_data_packet(&motion);
                    if self.write(&packet).await {
                        self.stats().packets_written += 1;
                    }
                    self.publish_device_stats();
                }
                read = async {
                    match self.master.as_mut() {
                        Some(m) => m.read(&mut buf).await,
                        None => std::future::pending().await,
                    }
                }, if can_read => match read {
                    Ok(n) if n > 0 => {
                        let t_s = self.started.elapsed().as_secs_f64();
                        let motion = &mut self.motion;
                        let out = self.device.handle_bytes(buf.get(..n).unwrap_or_default(), &mut || motion.motion_at(t_s));
                        self.publish_device_stats();
                        self.write(&out).await;
                    }
                    // A pipe's end closed: the driver let go of the port.
                    _ if self.pipes.is_some() => self.master = None,
                    // EIO / EOF: no one holds the slave open right now; look again shortly.
                    _ => read_paused_until = Some(Instant::now() + NO_PEER_RETRY),
                },
                () = async {
                    match read_paused_until {
                        Some(t) => tokio::time::sleep_until(t).await,
                        None => std::future::pending().await,
                    }
                } => read_paused_until = None,
                pipe = async {
                    match self.pipes.as_mut() {
                        Some(rx) => rx.recv().await,
                        None => std::future::pending().await,
                    }
                } => match pipe {
                    Some(p) if self.plugged => {
                        self.master = Some(Box::new(p));
                        self.device.reset_link();
                        interval = self.new_interval();
                    }
                    Some(refused) => drop(refused),
                    None => self.pipes = None,
                },
            }
            // Follow mode and rate changes made by commands.
            let now_streaming = self.device.is_streaming();
            let now_period = self.device.stream_period();
            if now_streaming != streaming || now_period != period {
                streaming = now_streaming;
                period = now_period;
                interval = self.new_interval();
            }
        }
    }

    fn publish_device_stats(&mut self) {
        let device = self.device.stats().clone();
        self.stats().device = device;
    }

    async fn control(&mut self, c: Control) {
        match c {
            Control::Fault(fault, done) => {
                tracing::info!(?fault, "mock LPMS fault");
                match fault {
                    Fault::Garbage(bytes) => {
                        let was_silent = std::mem::replace(&mut self.silent, false);
                        self.write(&bytes).await;
                        self.silent = was_silent;
                    }
                    Fault::WrongLrc(n) => self.device.faults_mut().corrupt_lrc += n,
                    Fault::Truncate(n) => self.device.faults_mut().truncate += n,
                    Fault::Nack { command, times } => self.device.faults_mut().nack.push((command, times)),
                    Fault::DropReplies(n) => self.device.faults_mut().drop_replies += n,
                    Fault::Silence(on) => self.silent = on,
                }
                let _ = done.send(());
            }
            Control::Unplug(done) => {
                self.master = None;
                self.plugged = false;
                if self.pipes.is_none() {
                    let _ = std::fs::remove_file(&self.link_path);
                }
                self.device.reset_link();
                self.stats().pty_path = None;
                tracing::info!(link = %self.link_path.display(), "mock LPMS unplugged");
                let _ = done.send(());
            }
            Control::Replug(done) if self.pipes.is_some() => {
                self.plugged = true;
                self.stats().plugs += 1;
                let _ = done.send(Ok(self.link_path.clone()));
            }
            Control::Replug(done) => {
                self.master = None;
                self.device.reset_link();
                let result = plug(&self.link_path).map(|(master, path)| {
                    self.master = Some(Box::new(master));
                    let mut s = self.stats();
                    s.pty_path = Some(path.clone());
                    s.plugs += 1;
                    path
                });
                let _ = done.send(result);
            }
        }
    }
}

#[cfg(test)]
mod memory_tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use std::time::Duration;

    use amr_drivers::lpms::serial::{ImuMessage, LpmsConfig, run};

    use super::{ConstantYawRate, MockImuOptions, start_mock_imu_in_memory};

    /// The real LPBUS shell against the in-memory mock in paused time: 100 Hz for 5 simulated
    /// seconds, an unplug the shell recovers from, the same samples twice.
    #[tokio::test(start_paused = true)]
    async fn the_shell_streams_from_the_in_memory_mock_and_survives_an_unplug() {
        let mut runs = Vec::new();
        for _ in 0..2 {
            let (mock, connector) = start_mock_imu_in_memory(
                MockImuOptions::with_rate(100),
                Box::new(ConstantYawRate::new(0.2, 0.0, 0.0, 1)),
            );
            let (tx, mut rx) = tokio::sync::mpsc::channel(256);
            let config = LpmsConfig { stream_hz: 100, ..LpmsConfig::default() };
            let task = tokio::spawn(run(
                config.session_config(),
                move || {
                    let c = connector.clone();
                    async move { c.connect().await }
                },
                tx,
            ));
            let start = tokio::time::Instant::now();
            let mut samples = Vec::new();
            let mut unplugged = false;
            while start.elapsed() < Duration::from_secs(5) {
                if !unplugged && start.elapsed() > Duration::from_secs(2) {
                    mock.unplug().await.unwrap();
                    tokio::time::sleep(Duration::from_millis(500)).await;
                    mock.replug().await.unwrap();
                    unplugged = true;
                }
                if let Ok(Some(ImuMessage::Sample(s))) =
                    tokio::time::timeout(Duration::from_millis(50), rx.recv()).await
                {
                    samples.push((
                        s.received_at.duration_since(start.into_std()).as_micros(),
                        s.data.timestamp_ticks,
                    ));
                }
            }
            task.abort();
            runs.push(samples);
        }
        // About 4.3 s of streaming at 100 Hz (the unplug and the reconnection cost the rest).
        assert!((380..=470).contains(&runs[0].len()), "{} samples", runs[0].len());
        assert!(runs[0].iter().any(|(t, _)| *t > 3_000_000), "streaming again after the replug");
        assert_eq!(runs[0], runs[1]);
    }
}

#[cfg(test)]
mod link_tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::{LINK_PREFIX, remove_stale_links};

    /// Links left by a process that is gone are removed; this process's, another file of the same
    /// name pattern that is not a link, and unrelated links are kept.
    #[test]
    fn links_of_processes_that_are_gone_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let gone = child.id();
        child.wait().unwrap();
        let me = std::process::id();
        let link = |name: String| {
            let path = dir.path().join(name);
            std::os::unix::fs::symlink("/dev/null", &path).unwrap();
            path
        };
        let stale = link(format!("{LINK_PREFIX}{gone}-0"));
        let stale_tmp = link(format!("{LINK_PREFIX}{gone}-1.new"));
        let mine = link(format!("{LINK_PREFIX}{me}-0"));
        let other = link("serial0".to_owned());
        let not_a_link = dir.path().join(format!("{LINK_PREFIX}{gone}-2"));
        std::fs::write(&not_a_link, b"").unwrap();
        remove_stale_links(dir.path());
        assert!(!stale.exists() && stale.symlink_metadata().is_err());
        assert!(stale_tmp.symlink_metadata().is_err());
        assert!(mine.symlink_metadata().is_ok());
        assert!(other.symlink_metadata().is_ok());
        assert!(not_a_link.exists());
    }
}
