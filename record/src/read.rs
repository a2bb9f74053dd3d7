//! Reading a recording back, complete or cut short: messages are read in file order up to the
//! first record that is not whole (a crash leaves the chunks flushed before it), never panicking.

use std::collections::BTreeMap;
use std::path::Path;

use mcap::read::Options;

/// One message of a recording.
#[derive(Debug, Clone)]
pub struct Recorded {
    pub topic: String,
    pub schema: String,
    /// The channel's message encoding (`json` for ours, `cdr` in a ROS 2 bag).
    pub encoding: String,
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

fn u64_at(b: &[u8], at: usize) -> Option<u64> {
    let mut v = [0u8; 8];
    v.copy_from_slice(b.get(at..at.checked_add(8)?)?);
    Some(u64::from_le_bytes(v))
}

fn u32_at(b: &[u8], at: usize) -> Option<u32> {
    let mut v = [0u8; 4];
    v.copy_from_slice(b.get(at..at.checked_add(4)?)?);
    Some(u32::from_le_bytes(v))
}

/// The end of the record at `at` in `b` (opcode u8, length u64 LE, body;
/// <https://mcap.dev/spec#records>) if it is whole.
fn record_end(b: &[u8], at: usize) -> Option<usize> {
    let len = usize::try_from(u64_at(b, at.checked_add(1)?)?).ok()?;
    let end = at.checked_add(9)?.checked_add(len)?;
    (end <= b.len()).then_some(end)
}

/// Largest chunk (uncompressed) a reader takes: chunks here hold about a second of data (well under
/// 1 MB); a chunk claiming more is damaged, or a decompression bomb.
const MAX_CHUNK_BYTES: u64 = 64 << 20;

/// A chunk, uncompressed or LZ4, whose records are all whole (<https://mcap.dev/spec#chunk-op0x06>:
/// start u64, end u64, uncompressed size u64, crc u32, compression string, records u64-prefixed).
fn chunk_ok(body: &[u8]) -> bool {
    let check = || -> Option<bool> {
        let uncompressed = u64_at(body, 16)?;
        let compression_len = usize::try_from(u32_at(body, 28)?).ok()?;
        let compression = body.get(32..32usize.checked_add(compression_len)?)?;
        let at = 32 + compression_len;
        let len = usize::try_from(u64_at(body, at)?).ok()?;
        let stored = body.get(at + 8..(at + 8).checked_add(len)?)?;
        let inflated;
        let records = match compression {
            b"" => stored,
            b"lz4" if uncompressed <= MAX_CHUNK_BYTES => {
                let mut out = Vec::with_capacity(usize::try_from(uncompressed).ok()?);
                let mut frames = std::io::Read::take(lz4::Decoder::new(stored).ok()?, uncompressed + 1);
                std::io::Read::read_to_end(&mut frames, &mut out).ok()?;
                if out.len() as u64 != uncompressed {
                    return Some(false);
                }
                inflated = out;
                &inflated[..]
            }
            // zstd, or a chunk too big to take: not readable by this build.
            _ => return Some(false),
        };
        let mut at = 0;
        while at < records.len() {
            at = record_end(records, at)?;
        }
        Some(true)
    };
    check().unwrap_or(false)
}

/// A chunk's compression name (after start, end, uncompressed size and crc), if readable.
fn chunk_compression(body: &[u8]) -> Option<&[u8]> {
    let len = usize::try_from(u32_at(body, 28)?).ok()?;
    body.get(32..32usize.checked_add(len)?)
}

/// The longest prefix of `bytes` made of the magic and whole top-level records, every chunk's
/// records whole too. mcap 0.26's reader overflows (a panic in a debug build) on a record length
/// near `u64::MAX`, at the top level and inside a chunk: cut before it sees one.
fn whole_records(bytes: &[u8]) -> &[u8] {
    const CHUNK: u8 = 0x06;
    let mut at = MAGIC.len().min(bytes.len());
    while let Some(end) = record_end(bytes, at) {
        if bytes[at] == CHUNK && !chunk_ok(&bytes[at + 9..end]) {
            break;
        }
        at = end;
    }
    &bytes[..at]
}

/// Read every message of `bytes`.
pub fn read_bytes(bytes: &[u8]) -> Result<Recording, ReadError> {
    read_bytes_where(bytes, |_| true)
}

/// Read every message of `bytes`, keeping the data of the topics `keep` takes only (the others
/// come with empty `data`: their topic, type and times are still there). A bag's images need not
/// be copied to read its scans.
pub fn read_bytes_where(bytes: &[u8], keep: impl Fn(&str) -> bool) -> Result<Recording, ReadError> {
    let mut out = Recording::default();
    if !bytes.ends_with(MAGIC) || bytes.len() < 2 * MAGIC.len() {
        out.stopped = Some(format!("no end magic: the file was cut short at byte {}", bytes.len()));
    }
    // IgnoreEndMagic: a crashed recorder wrote no footer; read what is there.
    let whole = whole_records(bytes);
    // mcap's reader is not ours: should it still panic on some bytes, that is a damaged file.
    let read = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| -> Result<Recording, ReadError> {
        let mut out = Recording::default();
        let stream = mcap::MessageStream::new_with_options(whole, Options::IgnoreEndMagic.into())?;
        for m in stream {
            match m {
                Ok(m) => out.messages.push(Recorded {
                    topic: m.channel.topic.clone(),
                    schema: m.channel.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default(),
                    encoding: m.channel.message_encoding.clone(),
                    log_time_ns: m.log_time,
                    publish_time_ns: m.publish_time,
                    data: if keep(&m.channel.topic) { m.data.into_owned() } else { Vec::new() },
                }),
                Err(e) => {
                    out.stopped = Some(e.to_string());
                    break;
                }
            }
        }
        Ok(out)
    }));
    match read {
        Ok(Ok(r)) => {
            out.messages = r.messages;
            out.stopped = out.stopped.or(r.stopped);
        }
        Ok(Err(e)) => return Err(e),
        Err(_) => out.stopped = Some("the MCAP reader failed on damaged data".into()),
    }
    if whole.len() + MAGIC.len() < bytes.len() && out.stopped.is_none() {
        out.stopped = Some(format!("damaged record at byte {}", whole.len()));
    }
    // Not damaged but not readable here: say so (rosbag2's `zstd_*` presets write such chunks).
    let zstd = bytes.get(whole.len()) == Some(&0x06)
        && bytes.get(whole.len() + 9..).is_some_and(|chunk| chunk_compression(chunk) == Some(b"zstd"));
    if zstd {
        out.stopped = Some(format!(
            "a zstd-compressed chunk at byte {}: this build reads uncompressed and LZ4 chunks only \
             (decompress the file first, e.g. with the mcap command-line tool)",
            whole.len()
        ));
    }
    Ok(out)
}

/// The metadata records of `bytes` by name (e.g. `amr`: the command, configuration and seed the
/// recorder was given), from the top level of the data section: a file cut short has them too.
#[must_use]
pub fn metadata(bytes: &[u8]) -> BTreeMap<String, BTreeMap<String, String>> {
    const METADATA: u8 = 0x0C;
    let whole = whole_records(bytes);
    let mut out = BTreeMap::new();
    let mut at = MAGIC.len().min(whole.len());
    while let Some(end) = record_end(whole, at) {
        if whole[at] == METADATA
            && let Ok(Ok(mcap::records::Record::Metadata(m))) = std::panic::catch_unwind(|| {
                mcap::parse_record(METADATA, &whole[at + 9..end]).map(mcap::records::Record::into_owned)
            })
        {
            out.insert(m.name, m.metadata);
        }
        at = end;
    }
    out
}

/// Read every message of the file at `path`.
pub fn read_file(path: &Path) -> Result<Recording, ReadError> {
    let bytes =
        std::fs::read(path).map_err(|source| ReadError::Io { path: path.display().to_string(), source })?;
    read_bytes(&bytes)
}
