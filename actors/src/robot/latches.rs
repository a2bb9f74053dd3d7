//! The e-stop latch in memory ([`EStopLatch`]: which sources hold it) and the robot's latched
//! stops on disk, so that a restart of `amr robot` (a crash, `kill -9`, a power cycle of its
//! computer) is not a reset (ISO 13850: an e-stop is cleared only by a deliberate reset).
//!
//! The file holds which e-stop sources hold the latch, whether a fault is latched, and a count
//! reserved above every stop count used so far (an arm must carry the count, so it must never go
//! back; a reservation a thousand ahead keeps the file from being written on every disarm). The
//! safety actor writes it, atomically (a temporary file, fsynced, renamed over the old one, the
//! directory fsynced), whenever one of these changes and before it reports the new state up the
//! link. A missing file is a robot that
//! never latched anything; a file that cannot be read or parsed counts as a latched local e-stop,
//! cleared only by a reset on the robot (which writes a good file).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};

/// Where an e-stop came from. A reset clears only the sources at its own place (ISO 13850: a
/// reset is a manual action where the stop was initiated): the server's or an operator's reset
/// over the network clears a network e-stop, never one pressed on the robot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EStopSource {
    /// Over the link (the server's `estop`, an operator's `amr estop`).
    Network = 1,
    /// On the robot's computer (SIGUSR1 to `amr robot`, the in-process control).
    Local = 2,
    /// The e-stop chain on a drive's digital input.
    Input = 4,
}

/// The e-stop latch: which sources hold it. It lives in the ports, not in the safety actor, so
/// that it survives the actor's restart and an e-stop that arrives while no safety actor runs is
/// not lost.
#[derive(Debug, Default)]
pub struct EStopLatch {
    sources: AtomicU8,
    /// The drive input reads pressed now (a local reset cannot clear it until it is released).
    input_pressed: AtomicBool,
}

impl EStopLatch {
    /// A latch held by `sources` ([`EStopSource`] bits), as restored from the file.
    #[must_use]
    pub(crate) fn holding(sources: u8) -> Self {
        EStopLatch { sources: AtomicU8::new(sources), input_pressed: AtomicBool::new(false) }
    }

    /// Latch from `source`.
    pub fn set(&self, source: EStopSource) {
        self.sources.fetch_or(source as u8, Ordering::SeqCst);
    }

    /// The sources that hold it ([`EStopSource`] bits).
    #[must_use]
    pub fn sources(&self) -> u8 {
        self.sources.load(Ordering::SeqCst)
    }

    /// Whether any source holds it.
    #[must_use]
    pub fn is_set(&self) -> bool {
        self.sources.load(Ordering::SeqCst) != 0
    }

    /// The e-stop input's state now (set by the drive actor on every change).
    pub fn input(&self, pressed: bool) {
        self.input_pressed.store(pressed, Ordering::SeqCst);
        if pressed {
            self.set(EStopSource::Input);
        }
    }

    /// A reset from the network (`local` false) or on the robot (`local` true): clears the sources
    /// of its place (a pressed input stays); true if nothing holds the latch any more.
    pub fn reset(&self, local: bool) -> bool {
        let mut mask = if local { EStopSource::Local as u8 } else { EStopSource::Network as u8 };
        if local && !self.input_pressed.load(Ordering::SeqCst) {
            mask |= EStopSource::Input as u8;
        }
        self.sources.fetch_and(!mask, Ordering::SeqCst) & !mask == 0
    }
}

/// What is latched.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Latched {
    /// The e-stop sources that hold the latch ([`EStopSource`] bits).
    pub estop: u8,
    pub fault: bool,
    /// The stop counter's reservation: above every count used so far (a restart starts above it).
    pub stops: u64,
}

/// Why the file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum LatchFileError {
    #[error("{path}: cannot read the robot's safety state: {error}")]
    Read { path: PathBuf, error: std::io::Error },
    #[error("{path}: not a safety state file ({why})")]
    Corrupt { path: PathBuf, why: String },
    #[error("{path}: cannot write the robot's safety state: {error}")]
    Write { path: PathBuf, error: std::io::Error },
}

/// The robot's safety state file.
#[derive(Debug, Clone)]
pub struct LatchFile {
    path: PathBuf,
}

const HEADER: &str = "# amr robot: latched stops. Written by the robot; cleared only by a reset.";
const SOURCES: [(EStopSource, &str); 3] =
    [(EStopSource::Network, "network"), (EStopSource::Local, "local"), (EStopSource::Input, "input")];

impl LatchFile {
    #[must_use]
    pub fn new(path: impl Into<PathBuf>) -> Self {
        LatchFile { path: path.into() }
    }

    #[must_use]
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// What the file says (nothing latched if there is no file).
    pub fn load(&self) -> Result<Latched, LatchFileError> {
        let text = match std::fs::read(&self.path) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Latched::default()),
            Err(error) => return Err(LatchFileError::Read { path: self.path.clone(), error }),
        };
        let corrupt = |why: String| LatchFileError::Corrupt { path: self.path.clone(), why };
        let text = String::from_utf8(text).map_err(|_| corrupt("not UTF-8".into()))?;
        parse(&text).map_err(corrupt)
    }

    /// Write `l`, atomically and durably.
    pub fn store(&self, l: Latched) -> Result<(), LatchFileError> {
        let err = |error| LatchFileError::Write { path: self.path.clone(), error };
        let dir = match self.path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&dir).map_err(err)?;
        let mut name = self.path.file_name().map(std::ffi::OsStr::to_os_string).unwrap_or_default();
        name.push(".tmp");
        let tmp = dir.join(name);
        {
            let mut f = std::fs::File::create(&tmp).map_err(err)?;
            f.write_all(render(l).as_bytes()).map_err(err)?;
            f.sync_all().map_err(err)?;
        }
        std::fs::rename(&tmp, &self.path).map_err(err)?;
        // The rename itself is durable only once the directory is.
        std::fs::File::open(&dir).and_then(|d| d.sync_all()).map_err(err)?;
        Ok(())
    }
}

fn render(l: Latched) -> String {
    let estop: Vec<String> =
        SOURCES.iter().filter(|(s, _)| l.estop & (*s as u8) != 0).map(|(_, n)| format!("\"{n}\"")).collect();
    format!(
        "{HEADER}\nversion = 1\nestop = [{}]\nfault = {}\nstops = {}\n",
        estop.join(", "),
        l.fault,
        l.stops
    )
}

fn parse(text: &str) -> Result<Latched, String> {
    let mut version = None;
    let (mut estop, mut fault, mut stops) = (None, None, None);
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let (key, value) = line.split_once('=').ok_or_else(|| format!("line {}: no `=`", i + 1))?;
        let value = value.trim();
        match key.trim() {
            "version" => version = Some(value.to_owned()),
            "estop" => {
                let inner = value
                    .strip_prefix('[')
                    .and_then(|v| v.strip_suffix(']'))
                    .ok_or_else(|| format!("line {}: estop is not a list", i + 1))?;
                let mut bits = 0u8;
                for item in inner.split(',').map(str::trim).filter(|s| !s.is_empty()) {
                    let name = item.trim_matches('"');
                    let (s, _) = SOURCES
                        .iter()
                        .find(|(_, n)| *n == name)
                        .ok_or_else(|| format!("line {}: unknown e-stop source `{name}`", i + 1))?;
                    bits |= *s as u8;
                }
                estop = Some(bits);
            }
            "fault" => {
                fault =
                    Some(value.parse::<bool>().map_err(|_| format!("line {}: fault is not a bool", i + 1))?);
            }
            "stops" => {
                stops =
                    Some(value.parse::<u64>().map_err(|_| format!("line {}: stops is not a count", i + 1))?);
            }
            other => return Err(format!("line {}: unknown key `{other}`", i + 1)),
        }
    }
    if version.as_deref() != Some("1") {
        return Err(format!("version {}, expected 1", version.as_deref().unwrap_or("missing")));
    }
    match (estop, fault, stops) {
        (Some(estop), Some(fault), Some(stops)) => Ok(Latched { estop, fault, stops }),
        _ => Err("estop, fault or stops missing".into()),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;
    use proptest::prelude::*;

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("amr-latch-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn a_latch_survives_a_store_and_load_and_no_file_is_nothing_latched() {
        let d = dir("roundtrip");
        let f = LatchFile::new(d.join("sub/robot-a.safety"));
        assert_eq!(f.load().unwrap(), Latched::default());
        let l =
            Latched { estop: EStopSource::Network as u8 | EStopSource::Input as u8, fault: true, stops: 17 };
        f.store(l).unwrap();
        assert_eq!(f.load().unwrap(), l);
        assert!(!d.join("sub/robot-a.safety.tmp").exists(), "the temporary file was renamed");
        f.store(Latched { stops: 18, ..Latched::default() }).unwrap();
        assert_eq!(f.load().unwrap(), Latched { stops: 18, ..Latched::default() });
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_damaged_file_is_an_error_that_names_the_file() {
        let d = dir("corrupt");
        std::fs::create_dir_all(&d).unwrap();
        let f = LatchFile::new(d.join("robot-a.safety"));
        for text in [
            &b""[..],
            b"version = 1\nestop = []\nfault = false\n",
            b"version = 2\nestop = []\nfault = false\nstops = 1\n",
            b"version = 1\nestop = [\"nowhere\"]\nfault = false\nstops = 1\n",
            b"version = 1\nestop = []\nfault = maybe\nstops = 1\n",
            b"\xff\xfe",
            // A write cut short.
            b"# amr robot\nversion = 1\nestop = [\"network\"]\nfau",
        ] {
            std::fs::write(f.path(), text).unwrap();
            let e = f.load().unwrap_err().to_string();
            assert!(e.contains("robot-a.safety"), "{e}");
        }
        let _ = std::fs::remove_dir_all(&d);
    }

    proptest! {
        #[test]
        fn any_latch_round_trips_and_no_text_panics(estop in 0u8..8, fault: bool, stops: u64, junk in ".{0,200}") {
            let l = Latched { estop, fault, stops };
            prop_assert_eq!(parse(&render(l)), Ok(l));
            let _ = parse(&junk);
        }
    }
}
