//! How far the formation got in its plan, kept across restarts of the server (in memory for a
//! server restarted within one process, in a file for `amr server`), so that a new formation
//! resumes where the job was and never later: on a plan of laps every lap passes the same places,
//! and the point nearest V alone cannot tell which lap the job is in.
//!
//! The record names the plan it belongs to (its length and end pose), so a record of another plan
//! is ignored. It is written every second of plan progress (atomically: a temporary file, fsynced,
//! renamed) and removed when the plan finishes.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

use amr_core::plan::Reference;

/// Plan progress written at most this often, s of plan time.
const WRITE_EVERY_S: f64 = 1.0;

/// Where the plan's progress is kept.
#[derive(Debug, Default)]
pub struct PlanProgress {
    file: Option<PathBuf>,
    /// The plan's identity and the progress, s.
    memory: Mutex<Option<(String, f64)>>,
    /// The progress last written to the file.
    written: Mutex<Option<f64>>,
}

/// Why the progress file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ProgressError {
    #[error("{path}: cannot read the plan's progress: {error} (remove it to start the plan afresh)")]
    Read { path: PathBuf, error: std::io::Error },
    #[error("{path}: not a plan progress file ({why}; remove it to start the plan afresh)")]
    Corrupt { path: PathBuf, why: String },
}

/// The identity of `plan`: its length and where it ends.
#[must_use]
pub fn plan_id(plan: &[Reference]) -> String {
    let end = plan.last().map(|r| r.pose).unwrap_or_default();
    format!("{} {:.3} {:.3} {:.3}", plan.len(), end.x, end.y, end.theta)
}

impl PlanProgress {
    /// Progress kept in memory only (a server restarted within one process finds it).
    #[must_use]
    pub fn in_memory() -> Self {
        PlanProgress::default()
    }

    /// Progress kept in `path` too, starting from what it holds.
    pub fn file(path: &Path) -> Result<Self, ProgressError> {
        let memory = match std::fs::read_to_string(path) {
            Ok(text) => {
                Some(parse(&text).map_err(|why| ProgressError::Corrupt { path: path.to_owned(), why })?)
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(error) => return Err(ProgressError::Read { path: path.to_owned(), error }),
        };
        let written = memory.as_ref().map(|(_, s)| *s);
        Ok(PlanProgress {
            file: Some(path.to_owned()),
            memory: Mutex::new(memory),
            written: Mutex::new(written),
        })
    }

    /// The progress recorded for plan `id`, s.
    #[must_use]
    pub fn load(&self, id: &str) -> Option<f64> {
        let m = self.memory.lock().unwrap_or_else(PoisonError::into_inner);
        m.as_ref().filter(|(i, _)| i == id).map(|(_, s)| *s)
    }

    /// The formation is `plan_s` into plan `id`.
    pub fn note(&self, id: &str, plan_s: f64) {
        *self.memory.lock().unwrap_or_else(PoisonError::into_inner) = Some((id.to_owned(), plan_s));
        let Some(path) = &self.file else { return };
        let mut written = self.written.lock().unwrap_or_else(PoisonError::into_inner);
        if written.is_some_and(|w| (plan_s - w).abs() < WRITE_EVERY_S) {
            return;
        }
        match store(path, &format!("plan = \"{id}\"\nplan_s = {plan_s}\n")) {
            Ok(()) => *written = Some(plan_s),
            Err(e) => tracing::error!(file = %path.display(), error = %e, "cannot write the plan's progress"),
        }
    }

    /// The plan finished: nothing to resume.
    pub fn clear(&self) {
        *self.memory.lock().unwrap_or_else(PoisonError::into_inner) = None;
        *self.written.lock().unwrap_or_else(PoisonError::into_inner) = None;
        if let Some(path) = &self.file
            && let Err(e) = std::fs::remove_file(path)
            && e.kind() != std::io::ErrorKind::NotFound
        {
            tracing::error!(file = %path.display(), error = %e, "cannot remove the plan's progress");
        }
    }
}

fn parse(text: &str) -> Result<(String, f64), String> {
    let (mut id, mut plan_s) = (None, None);
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
        match line.split_once('=').map(|(k, v)| (k.trim(), v.trim())) {
            Some(("plan", v)) => {
                id = v.strip_prefix('"').and_then(|v| v.strip_suffix('"')).map(str::to_owned)
            }
            Some(("plan_s", v)) => plan_s = v.parse::<f64>().ok().filter(|s| s.is_finite() && *s >= 0.0),
            _ => return Err(format!("unexpected line `{line}`")),
        }
    }
    match (id, plan_s) {
        (Some(id), Some(s)) => Ok((id, s)),
        _ => Err("plan or plan_s missing or not valid".into()),
    }
}

fn store(path: &Path, text: &str) -> std::io::Result<()> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir)?;
    let mut name = path.file_name().map(std::ffi::OsStr::to_os_string).unwrap_or_default();
    name.push(".tmp");
    let tmp = dir.join(name);
    {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(text.as_bytes())?;
        f.sync_all()?;
    }
    std::fs::rename(&tmp, path)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    #[test]
    fn progress_survives_in_its_file_for_its_own_plan_only_and_goes_when_the_plan_finishes() {
        let dir = std::env::temp_dir().join(format!("amr-progress-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let path = dir.join("server.progress");
        let p = PlanProgress::file(&path).unwrap();
        assert_eq!(p.load("a"), None);
        p.note("a", 0.5);
        p.note("a", 12.25);
        let again = PlanProgress::file(&path).unwrap();
        assert_eq!(again.load("a"), Some(12.25), "on disk");
        assert_eq!(again.load("b"), None, "another plan's record is not used");
        p.note("a", 12.75);
        assert_eq!(p.load("a"), Some(12.75), "in memory at once");
        assert_eq!(PlanProgress::file(&path).unwrap().load("a"), Some(12.25), "on disk every second");
        p.clear();
        assert_eq!(p.load("a"), None);
        assert_eq!(PlanProgress::file(&path).unwrap().load("a"), None);
        std::fs::write(&path, "plan = \"a\"\nplan_s = -3\n").unwrap();
        let e = PlanProgress::file(&path).unwrap_err().to_string();
        assert!(e.contains("server.progress") && e.contains("remove it"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
