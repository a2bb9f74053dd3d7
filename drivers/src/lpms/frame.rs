//! LPBUS framing: `3A | id u16 | cmd u16 | len u16 | data | lrc u16 | 0D 0A`, little-endian.
//!
//! LRC = (id + cmd + len + Σ data bytes) mod 2¹⁶ (research notes Part A1: OpenMAT
//! `LpSensor/LpmsBBluetoothLinux.cpp` `sendModbusData`, `LpmsB2.java`, OpenZen `Modbus.cpp` `lrcLp`).
//! The decoder resynchronises on garbage the way OpenZen's `parsePacketWithCrapInfront` test expects:
//! drop one byte and look for the next 0x3A.

use bytes::{Buf, BytesMut};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// First byte of every frame.
pub const START: u8 = 0x3A;
/// Last two bytes of every frame.
pub const END: [u8; 2] = [0x0D, 0x0A];
/// Header bytes before the payload: start, id, cmd, len.
pub const HEADER_LEN: usize = 7;
/// Bytes of a frame that carry no payload: header, LRC, CR LF.
pub const OVERHEAD_LEN: usize = HEADER_LEN + 4;
/// Longest payload accepted. The B2's longest reply is ~108 bytes (notes A3); a garbage `len` must not
/// make the decoder wait for kilobytes.
pub const MAX_PAYLOAD_LEN: usize = 512;

/// One LPBUS frame: sensor id (the "address"), command id (the "function") and payload.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Frame {
    /// Sensor id: the device's IMU id in replies, the addressed id in requests.
    pub id: u16,
    /// Command (function) id.
    pub cmd: u16,
    /// Payload bytes.
    pub data: Vec<u8>,
}

/// Why a candidate frame was discarded (the decoder has already skipped past its 0x3A).
#[derive(Debug, Clone, PartialEq, Eq, Error, Serialize, Deserialize)]
pub enum FrameError {
    /// The length field exceeds [`MAX_PAYLOAD_LEN`].
    #[error("LPBUS frame length {len} exceeds the cap of {MAX_PAYLOAD_LEN}")]
    TooLong {
        /// The length field.
        len: usize,
    },
    /// The checksum does not match the frame's contents.
    #[error("LPBUS LRC mismatch: computed {computed:#06x}, received {received:#06x}")]
    BadLrc {
        /// LRC computed over id, cmd, len and data.
        computed: u16,
        /// LRC carried by the frame.
        received: u16,
    },
    /// The frame does not end in CR LF.
    #[error("LPBUS frame does not end in CR LF")]
    BadEnd,
}

/// Error of [`Frame::encode`].
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("LPBUS payload of {len} bytes exceeds the cap of {MAX_PAYLOAD_LEN}")]
pub struct PayloadTooLong {
    /// The payload length.
    pub len: usize,
}

/// LRC of a frame: the 16-bit sum of id, cmd, len and every data byte (notes A1).
pub fn lrc(id: u16, cmd: u16, data: &[u8]) -> u16 {
    // The length fits u16 for every frame we encode or accept (both capped at MAX_PAYLOAD_LEN);
    // truncation for longer slices only changes a checksum nobody will send.
    let len = (data.len() & 0xFFFF) as u16;
    data.iter().fold(id.wrapping_add(cmd).wrapping_add(len), |acc, &b| acc.wrapping_add(u16::from(b)))
}

impl Frame {
    /// A frame from its parts.
    pub fn new(id: u16, cmd: u16, data: Vec<u8>) -> Self {
        Self { id, cmd, data }
    }

    /// Appends the wire form of this frame to `out`.
    pub fn encode_into(&self, out: &mut Vec<u8>) -> Result<(), PayloadTooLong> {
        let len = self.data.len();
        if len > MAX_PAYLOAD_LEN {
            return Err(PayloadTooLong { len });
        }
        out.reserve(OVERHEAD_LEN + len);
        out.push(START);
        out.extend_from_slice(&self.id.to_le_bytes());
        out.extend_from_slice(&self.cmd.to_le_bytes());
        out.extend_from_slice(&(len as u16).to_le_bytes());
        out.extend_from_slice(&self.data);
        out.extend_from_slice(&lrc(self.id, self.cmd, &self.data).to_le_bytes());
        out.extend_from_slice(&END);
        Ok(())
    }

    /// The wire form of this frame.
    pub fn encode(&self) -> Result<Vec<u8>, PayloadTooLong> {
        let mut out = Vec::new();
        self.encode_into(&mut out)?;
        Ok(out)
    }
}

/// Counters of what the decoder threw away.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DecoderStats {
    /// Complete frames returned.
    pub frames: u64,
    /// Bytes skipped while looking for a start byte or after a bad candidate.
    pub skipped_bytes: u64,
    /// Candidates discarded for a bad LRC, end or length.
    pub bad_frames: u64,
}

/// Incremental LPBUS frame decoder: feed bytes in any pieces, take frames out.
#[derive(Debug, Default)]
pub struct FrameDecoder {
    buf: BytesMut,
    stats: DecoderStats,
}

impl FrameDecoder {
    /// An empty decoder.
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// Forgets buffered bytes (after a reconnect the old stream is meaningless).
    pub fn clear(&mut self) {
        self.buf.clear();
    }

    /// Bytes buffered but not yet decoded.
    pub fn buffered_len(&self) -> usize {
        self.buf.len()
    }

    /// What has been decoded and discarded so far.
    pub fn stats(&self) -> DecoderStats {
        self.stats
    }

    /// The next frame: `None` when more bytes are needed, `Some(Err)` when a candidate frame was
    /// discarded (call again: the decoder has moved on by one byte), `Some(Ok)` for a good frame.
    pub fn next_frame(&mut self) -> Option<Result<Frame, FrameError>> {
        // Skip to the next start byte.
        let skip = self.buf.iter().position(|&b| b == START).unwrap_or(self.buf.len());
        if skip > 0 {
            self.buf.advance(skip);
            self.stats.skipped_bytes += skip as u64;
        }
        if self.buf.len() < HEADER_LEN {
            return None;
        }
        let id = u16::from_le_bytes([self.buf[1], self.buf[2]]);
        let cmd = u16::from_le_bytes([self.buf[3], self.buf[4]]);
        let len = usize::from(u16::from_le_bytes([self.buf[5], self.buf[6]]));
        if len > MAX_PAYLOAD_LEN {
            return Some(Err(self.reject(FrameError::TooLong { len })));
        }
        let total = OVERHEAD_LEN + len;
        if self.buf.len() < total {
            return None;
        }
        let data = &self.buf[HEADER_LEN..HEADER_LEN + len];
        let computed = lrc(id, cmd, data);
        let received = u16::from_le_bytes([self.buf[HEADER_LEN + len], self.buf[HEADER_LEN + len + 1]]);
        if computed != received {
            return Some(Err(self.reject(FrameError::BadLrc { computed, received })));
        }
        if self.buf[HEADER_LEN + len + 2..total] != END {
            return Some(Err(self.reject(FrameError::BadEnd)));
        }
        let frame = Frame { id, cmd, data: data.to_vec() };
        self.buf.advance(total);
        self.stats.frames += 1;
        Some(Ok(frame))
    }

    /// Drops the start byte of a bad candidate so the search resumes inside it.
    fn reject(&mut self, err: FrameError) -> FrameError {
        self.buf.advance(1);
        self.stats.skipped_bytes += 1;
        self.stats.bad_frames += 1;
        err
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode_all(bytes: &[u8]) -> (Vec<Frame>, Vec<FrameError>) {
        let mut d = FrameDecoder::new();
        d.push(bytes);
        let (mut ok, mut bad) = (Vec::new(), Vec::new());
        while let Some(r) = d.next_frame() {
            match r {
                Ok(f) => ok.push(f),
                Err(e) => bad.push(e),
            }
        }
        (ok, bad)
    }

    #[test]
    fn encodes_the_openzen_frame() {
        let f = Frame::new(10, 11, vec![1, 2, 3, 4]);
        assert_eq!(f.encode().unwrap(), [0x3A, 10, 0, 11, 0, 4, 0, 1, 2, 3, 4, 0x23, 0, 0x0D, 0x0A]);
    }

    #[test]
    fn a_frame_with_a_bad_lrc_is_reported_and_the_next_one_decodes() {
        let mut bytes = Frame::new(1, 4, vec![7]).encode().unwrap();
        bytes[8] ^= 0xFF;
        bytes.extend(Frame::new(1, 0, vec![]).encode().unwrap());
        let (ok, bad) = decode_all(&bytes);
        assert_eq!(ok, vec![Frame::new(1, 0, vec![])]);
        assert!(matches!(bad.as_slice(), [FrameError::BadLrc { .. }]));
    }

    #[test]
    fn a_bad_end_is_rejected() {
        let mut bytes = Frame::new(1, 4, vec![7]).encode().unwrap();
        let n = bytes.len();
        bytes[n - 1] = 0;
        let (ok, bad) = decode_all(&bytes);
        assert!(ok.is_empty());
        assert_eq!(bad, vec![FrameError::BadEnd]);
    }

    #[test]
    fn an_oversized_length_is_rejected_without_waiting() {
        let mut bytes = vec![0x3A, 1, 0, 9, 0, 0x01, 0x02];
        bytes.extend(Frame::new(1, 7, vec![]).encode().unwrap());
        let (ok, bad) = decode_all(&bytes);
        assert_eq!(bad, vec![FrameError::TooLong { len: 0x0201 }]);
        assert_eq!(ok, vec![Frame::new(1, 7, vec![])]);
    }

    #[test]
    fn a_frame_in_single_bytes_decodes_once_complete() {
        let bytes = Frame::new(3, 47, vec![1, 0, 0, 0]).encode().unwrap();
        let mut d = FrameDecoder::new();
        for (i, b) in bytes.iter().enumerate() {
            d.push(&[*b]);
            let got = d.next_frame();
            if i + 1 < bytes.len() {
                assert!(got.is_none(), "frame before byte {i}");
            } else {
                assert_eq!(got, Some(Ok(Frame::new(3, 47, vec![1, 0, 0, 0]))));
            }
        }
        assert_eq!(d.buffered_len(), 0);
    }

    #[test]
    fn encode_refuses_an_oversized_payload() {
        let f = Frame::new(1, 9, vec![0; MAX_PAYLOAD_LEN + 1]);
        assert_eq!(f.encode(), Err(PayloadTooLong { len: MAX_PAYLOAD_LEN + 1 }));
    }
}
