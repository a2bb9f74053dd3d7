//! Where encoded messages go: an MCAP file (chunked, flushed by a policy so that a killed process
//! leaves a file readable up to its last flush) and/or the live Foxglove server.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use crate::encode::Out;

/// Why recording failed.
#[derive(Debug, thiserror::Error)]
pub enum SinkError {
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
}

/// When the open chunk is closed and written out (MCAP spec: a chunk is the unit a reader recovers;
/// <https://mcap.dev/spec#chunk-op0x06>). Whichever comes first.
#[derive(Debug, Clone, Copy)]
pub struct FlushPolicy {
    /// Messages in the open chunk.
    pub max_messages: usize,
    /// Log time since the last flush, ns (the fleet clock: virtual time in a virtual-time run).
    pub max_interval_ns: u64,
    /// Compress each chunk with LZ4 (MCAP compression `lz4`: the LZ4 frame format), as rosbag2
    /// compresses its chunks; every MCAP reader decompresses it.
    pub lz4: bool,
}

impl Default for FlushPolicy {
    /// About a second of data, never more than 2000 messages, LZ4-compressed.
    fn default() -> Self {
        FlushPolicy { max_messages: 2000, max_interval_ns: 1_000_000_000, lz4: true }
    }
}

/// Counts of what was written.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct WriteStats {
    pub messages: u64,
    /// Chunks closed by the flush policy (the writer also closes one at its size target).
    pub flushes: u64,
    pub per_topic: BTreeMap<String, u64>,
}

/// What a file's channels carry.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Format {
    /// Foxglove's and our JSON schemas (schema encoding `jsonschema`, message encoding `json`).
    #[default]
    Foxglove,
    /// rosbag2's profile `ros2`: `ros2msg` schemas, CDR messages, QoS per channel
    /// ([`crate::ros2`]).
    Ros2,
}

/// An MCAP file being written.
pub struct McapFile {
    writer: mcap::Writer<BufWriter<File>>,
    format: Format,
    channels: BTreeMap<String, u16>,
    sequence: u32,
    policy: FlushPolicy,
    in_chunk: usize,
    last_flush_ns: Option<u64>,
    stats: WriteStats,
}

impl std::fmt::Debug for McapFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("McapFile").field("stats", &self.stats).finish_non_exhaustive()
    }
}

impl McapFile {
    /// Create (truncate) `path`. Chunks are written whole (`disable_seeking`: the writer keeps the
    /// open chunk in memory and never goes back to patch a header), LZ4-compressed if the policy
    /// says so (see the crate docs for the sizes), with message indexes and a summary when finished.
    pub fn create(path: &Path, policy: FlushPolicy) -> Result<Self, SinkError> {
        Self::create_as(path, policy, Format::Foxglove)
    }

    /// Create (truncate) `path` for channels of `format`. A ROS 2 file has the profile `ros2` and
    /// a metadata record `rosbag2` without `serialized_metadata`, which rosbag2 reads as metadata
    /// version 8, the version of the QoS form written ([`crate::ros2`]).
    pub fn create_as(path: &Path, policy: FlushPolicy, format: Format) -> Result<Self, SinkError> {
        let file = File::create(path)
            .map_err(|source| SinkError::Io { path: path.display().to_string(), source })?;
        let writer = mcap::WriteOptions::new()
            .compression(policy.lz4.then_some(mcap::Compression::Lz4))
            .profile(match format {
                Format::Foxglove => "",
                Format::Ros2 => "ros2",
            })
            .library(concat!("amr-record ", env!("CARGO_PKG_VERSION")))
            .disable_seeking(true)
            .create(BufWriter::new(file))?;
        let mut writer = writer;
        if format == Format::Ros2 {
            let record = BTreeMap::from([("writer".to_owned(), "amr-record".to_owned())]);
            writer.write_metadata(&mcap::records::Metadata { name: "rosbag2".into(), metadata: record })?;
        }
        Ok(McapFile {
            writer,
            format,
            channels: BTreeMap::new(),
            sequence: 0,
            policy,
            in_chunk: 0,
            last_flush_ns: None,
            stats: WriteStats::default(),
        })
    }

    /// Key-value metadata (MCAP Metadata record), e.g. the configuration and seed.
    pub fn metadata(&mut self, name: &str, values: BTreeMap<String, String>) -> Result<(), SinkError> {
        self.writer.write_metadata(&mcap::records::Metadata { name: name.to_owned(), metadata: values })?;
        Ok(())
    }

    fn channel(&mut self, out: &Out) -> Result<u16, SinkError> {
        if let Some(id) = self.channels.get(&out.topic) {
            return Ok(*id);
        }
        let id = match self.format {
            Format::Foxglove => {
                let text = crate::encode::schema_text(out.schema);
                let schema = self.writer.add_schema(out.schema, "jsonschema", text.as_bytes())?;
                self.writer.add_channel(schema, &out.topic, "json", &BTreeMap::new())?
            }
            Format::Ros2 => {
                let text = crate::ros2::schema_text(out.schema);
                let schema = self.writer.add_schema(out.schema, "ros2msg", text.as_bytes())?;
                let metadata = crate::ros2::channel_metadata(&out.topic);
                self.writer.add_channel(schema, &out.topic, "cdr", &metadata)?
            }
        };
        self.channels.insert(out.topic.clone(), id);
        Ok(id)
    }

    /// Write one message; close the chunk when the policy says so.
    pub fn write(&mut self, out: &Out) -> Result<(), SinkError> {
        let channel_id = self.channel(out)?;
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.sequence,
            log_time: out.log_time_ns,
            publish_time: out.publish_time_ns,
        };
        self.writer.write_to_known_channel(&header, &out.data)?;
        self.stats.messages += 1;
        *self.stats.per_topic.entry(out.topic.clone()).or_default() += 1;
        self.in_chunk += 1;
        let since = *self.last_flush_ns.get_or_insert(out.log_time_ns);
        if self.in_chunk >= self.policy.max_messages
            || out.log_time_ns.saturating_sub(since) >= self.policy.max_interval_ns
        {
            self.flush()?;
            self.last_flush_ns = Some(out.log_time_ns);
        }
        Ok(())
    }

    /// Close the open chunk if it is older than the policy's interval at log time `now_ns`.
    pub fn flush_if_due(&mut self, now_ns: u64) -> Result<(), SinkError> {
        let since = self.last_flush_ns.unwrap_or(0);
        if self.in_chunk > 0 && now_ns.saturating_sub(since) >= self.policy.max_interval_ns {
            self.flush()?;
            self.last_flush_ns = Some(now_ns);
        }
        Ok(())
    }

    /// Close the open chunk and hand everything to the operating system.
    pub fn flush(&mut self) -> Result<(), SinkError> {
        if self.in_chunk > 0 {
            self.writer.flush()?;
            self.stats.flushes += 1;
            self.in_chunk = 0;
        }
        Ok(())
    }

    /// Write the summary and the footer: a complete, indexed file.
    pub fn finish(mut self) -> Result<WriteStats, SinkError> {
        self.writer.finish()?;
        Ok(self.stats)
    }

    #[must_use]
    pub fn stats(&self) -> &WriteStats {
        &self.stats
    }
}
