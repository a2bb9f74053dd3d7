//! Reading a recording back, complete or cut short: messages are read in file order up to the
//! first record that is not whole (a crash leaves the chunks flushed before it), never panicking.

use std::path::Path;

use mcap::read::Options;

/// One message of a recording.
#[derive(Debug, Clone)]
pub struct Recorded {
    pub topic: String,
    pub schema: String,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub data: Vec<u8>,
}

/// What was read.
#[derive(Debug, Clone, Default)]
pub struct Recording {
    pub messages: Vec<Recorded>,
    /// Why the file is not whole (cut short by a crash, or damaged), if it is not.
    pub stopped: Option<String>,
}

/// Why a recording could not be read at all.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("not an MCAP file: {0}")]
    Mcap(#[from] mcap::McapError),
}

/// The MCAP magic, at both ends of a complete file (<https://mcap.dev/spec#magic>).
const MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";

/// The longest prefix of `bytes` made of the magic and whole top-level records (opcode u8, length
/// u64 LE, body; <https://mcap.dev/spec#records>). mcap 0.26's reader overflows (a panic in a
/// debug build) on a record length near `u64::MAX`; cut before it sees one.
fn whole_records(bytes: &[u8]) -> &[u8] {
    let mut at = MAGIC.len().min(bytes.len());
    while let Some(header) = bytes.get(at..at + 9) {
        let mut len = [0u8; 8];
        len.copy_from_slice(&header[1..]);
        let end = u64::try_from(at + 9).ok().and_then(|a| a.checked_add(u64::from_le_bytes(len)));
        match end.and_then(|e| usize::try_from(e).ok()) {
            Some(e) if e <= bytes.len() => at = e,
            _ => break,
        }
    }
    &bytes[..at]
}

/// Read every message of `bytes`.
pub fn read_bytes(bytes: &[u8]) -> Result<Recording, ReadError> {
    let mut out = Recording::default();
    if !bytes.ends_with(MAGIC) || bytes.len() < 2 * MAGIC.len() {
        out.stopped = Some(format!("no end magic: the file was cut short at byte {}", bytes.len()));
    }
    // IgnoreEndMagic: a crashed recorder wrote no footer; read what is there.
    let stream = mcap::MessageStream::new_with_options(whole_records(bytes), Options::IgnoreEndMagic.into())?;
    for m in stream {
        match m {
            Ok(m) => out.messages.push(Recorded {
                topic: m.channel.topic.clone(),
                schema: m.channel.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default(),
                log_time_ns: m.log_time,
                publish_time_ns: m.publish_time,
                data: m.data.into_owned(),
            }),
            Err(e) => {
                out.stopped.get_or_insert_with(|| e.to_string());
                break;
            }
        }
    }
    Ok(out)
}

/// Read every message of the file at `path`.
pub fn read_file(path: &Path) -> Result<Recording, ReadError> {
    let bytes =
        std::fs::read(path).map_err(|source| ReadError::Io { path: path.display().to_string(), source })?;
    read_bytes(&bytes)
}
