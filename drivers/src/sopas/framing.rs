//! Cutting a TCP byte stream into CoLa-A and CoLa-B frames (notes §1.1, §1.2), sans-IO.
//!
//! CoLa-A: `STX text ETX`, no length, no checksum. CoLa-B: `02 02 02 02`, u32 BE payload length,
//! payload, XOR of the payload. Bytes arrive in arbitrary pieces; anything that is not a frame is
//! skipped by scanning for the next STX / magic, and a broken frame costs only its own bytes.

use serde::Serialize;

use super::error::FrameError;

/// The two SOPAS dialects.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum Dialect {
    /// ASCII, `STX … ETX`.
    ColaA,
    /// Binary, magic + length + payload + XOR.
    ColaB,
}

impl Dialect {
    /// The value of `sWN EIHstCola` selecting this dialect (notes §1.2: 0 = CoLa-A, 1 = CoLa-B).
    pub fn eih_value(self) -> u8 {
        match self {
            Self::ColaA => 0,
            Self::ColaB => 1,
        }
    }

    /// The other dialect.
    pub fn other(self) -> Self {
        match self {
            Self::ColaA => Self::ColaB,
            Self::ColaB => Self::ColaA,
        }
    }
}

pub(crate) const STX: u8 = 0x02;
pub(crate) const ETX: u8 = 0x03;
const MAGIC: [u8; 4] = [STX; 4];

/// Default cap on a frame's payload: a scan frame is ~600–4400 bytes (notes §1.2), so 16 KiB
/// bounds memory and the delay a fake length field can cause.
pub const DEFAULT_MAX_FRAME_LEN: usize = 16 * 1024;

/// One frame's payload (`sRA LMDscandata …`) and the dialect it arrived in.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    pub dialect: Dialect,
    pub payload: Vec<u8>,
}

/// XOR of all bytes: the CoLa-B checksum (notes §1.2, Wireshark `get_crc8_xor`).
pub fn xor_checksum(payload: &[u8]) -> u8 {
    payload.iter().fold(0, |acc, b| acc ^ b)
}

/// Wraps a payload into a frame of the given dialect.
pub fn encode_frame(dialect: Dialect, payload: &[u8]) -> Vec<u8> {
    match dialect {
        Dialect::ColaA => {
            let mut out = Vec::with_capacity(payload.len() + 2);
            out.push(STX);
            out.extend_from_slice(payload);
            out.push(ETX);
            out
        }
        Dialect::ColaB => {
            let len = u32::try_from(payload.len()).unwrap_or(u32::MAX);
            let mut out = Vec::with_capacity(payload.len() + 9);
            out.extend_from_slice(&MAGIC);
            out.extend_from_slice(&len.to_be_bytes());
            out.extend_from_slice(payload);
            out.push(xor_checksum(payload));
            out
        }
    }
}

/// The stream framer: feed bytes with [`Framer::push`], take frames with [`Framer::next_frame`].
/// Detects the dialect per frame, so it serves the driver and the mock alike.
#[derive(Debug, Clone)]
pub struct Framer {
    buf: Vec<u8>,
    /// Bytes before `head` are consumed; compacted lazily so a resync through a long run of
    /// bytes stays linear in their number.
    head: usize,
    max_len: usize,
    skipped_bytes: u64,
}

impl Default for Framer {
    fn default() -> Self {
        Self::new(DEFAULT_MAX_FRAME_LEN)
    }
}

impl Framer {
    /// A framer that rejects payloads longer than `max_len`.
    pub fn new(max_len: usize) -> Self {
        Self { buf: Vec::new(), head: 0, max_len, skipped_bytes: 0 }
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        if self.head > 0 && self.head >= self.buf.len() / 2 {
            self.buf.drain(..self.head);
            self.head = 0;
        }
        self.buf.extend_from_slice(bytes);
    }

    fn pending(&self) -> &[u8] {
        &self.buf[self.head.min(self.buf.len())..]
    }

    /// Forgets everything buffered (after a reconnect).
    pub fn clear(&mut self) {
        self.buf.clear();
        self.head = 0;
    }

    /// Bytes skipped so far as not belonging to any frame.
    pub fn skipped_bytes(&self) -> u64 {
        self.skipped_bytes
    }

    fn skip(&mut self, n: usize) {
        let n = n.min(self.pending().len());
        self.head += n;
        self.skipped_bytes += n as u64;
    }

    fn consume(&mut self, n: usize) {
        self.head += n.min(self.pending().len());
    }

    /// The next complete frame, an error for a broken one (its first byte is dropped and the
    /// search goes on at the next call), or `None` when more bytes are needed.
    pub fn next_frame(&mut self) -> Option<Result<Frame, FrameError>> {
        loop {
            let start = match self.pending().iter().position(|&b| b == STX) {
                Some(i) => i,
                None => {
                    let n = self.pending().len();
                    self.skip(n);
                    return None;
                }
            };
            self.skip(start);
            let second = *self.pending().get(1)?;
            if second == STX {
                match self.try_cola_b() {
                    Step::NeedMore => return None,
                    Step::Resync => {
                        self.skip(1);
                        continue;
                    }
                    Step::Done(result) => return Some(result),
                }
            }
            return self.try_cola_a();
        }
    }

    fn try_cola_b(&mut self) -> Step {
        let buf = self.pending();
        let have = buf.len().min(4);
        if buf[..have] != MAGIC[..have] {
            return Step::Resync;
        }
        let Some(len_bytes) = buf.get(4..8) else { return Step::NeedMore };
        let mut be = [0u8; 4];
        be.copy_from_slice(len_bytes);
        let len = u32::from_be_bytes(be) as usize;
        if len == 0 {
            self.skip(1);
            return Step::Done(Err(FrameError::Empty));
        }
        if len > self.max_len {
            self.skip(1);
            return Step::Done(Err(FrameError::TooLong { len, max: self.max_len }));
        }
        let total = 8 + len + 1;
        let buf = self.pending();
        if buf.len() < total {
            return Step::NeedMore;
        }
        let payload = &buf[8..8 + len];
        let actual = xor_checksum(payload);
        let expected = buf[8 + len];
        if actual != expected {
            // Drop only the first byte: if the length field was the broken part, the frames it
            // swallowed are found again by the rescan.
            self.skip(1);
            return Step::Done(Err(FrameError::Checksum { expected, actual }));
        }
        let payload = payload.to_vec();
        self.consume(total);
        Step::Done(Ok(Frame { dialect: Dialect::ColaB, payload }))
    }

    fn try_cola_a(&mut self) -> Option<Result<Frame, FrameError>> {
        let buf = self.pending();
        let end = buf.iter().skip(1).position(|&b| b == ETX || b == STX).map(|i| i + 1);
        match end {
            Some(i) if buf[i] == ETX => {
                let payload = buf[1..i].to_vec();
                self.consume(i + 1);
                Some(Ok(Frame { dialect: Dialect::ColaA, payload }))
            }
            Some(i) => {
                self.skip(i);
                Some(Err(FrameError::Truncated { len: i }))
            }
            None if buf.len() > self.max_len + 2 => {
                let len = buf.len();
                self.skip(1);
                Some(Err(FrameError::TooLong { len, max: self.max_len }))
            }
            None => None,
        }
    }
}

enum Step {
    NeedMore,
    Resync,
    Done(Result<Frame, FrameError>),
}

#[cfg(test)]
mod tests {
    use super::*;

    fn drain(f: &mut Framer) -> Vec<Result<Frame, FrameError>> {
        let mut out = Vec::new();
        for _ in 0..10_000 {
            match f.next_frame() {
                Some(r) => out.push(r),
                None => break,
            }
        }
        out
    }

    #[test]
    fn operating_instructions_examples_frame_both_ways() {
        // OI p.2 (04_command_vectors.txt section A).
        let a = encode_frame(Dialect::ColaA, b"sRN LMDscandata");
        assert_eq!(a[0], 0x02);
        assert_eq!(*a.last().unwrap(), 0x03);
        let b = encode_frame(Dialect::ColaB, b"sRN LMDscandata");
        assert_eq!(&b[..8], &[2, 2, 2, 2, 0, 0, 0, 0x0F]);
        assert_eq!(*b.last().unwrap(), 0x05);
    }

    #[test]
    fn garbage_truncation_and_bad_checksum_cost_only_their_frames() {
        let good_a = encode_frame(Dialect::ColaA, b"sEA LMDscandata 1");
        let good_b = encode_frame(Dialect::ColaB, b"sWA EIHstCola ");
        let mut bad_b = good_b.clone();
        let last = bad_b.len() - 1;
        bad_b[last] ^= 0xFF;
        let mut stream = b"noise\x03\x02\x02zz".to_vec();
        stream.extend_from_slice(&good_a);
        stream.extend_from_slice(&good_b[..10]); // truncated B frame
        stream.extend_from_slice(&good_a[..5]); // truncated A frame
        stream.extend_from_slice(&good_a);
        stream.extend_from_slice(&bad_b);
        stream.extend_from_slice(&good_b);
        let mut f = Framer::default();
        f.push(&stream);
        let frames: Vec<Frame> = drain(&mut f).into_iter().filter_map(Result::ok).collect();
        assert_eq!(frames.len(), 3, "{frames:?}");
        assert_eq!(frames[0].payload, b"sEA LMDscandata 1");
        assert_eq!(frames[1].payload, b"sEA LMDscandata 1");
        assert_eq!(frames[2].payload, b"sWA EIHstCola ");
        assert_eq!(frames[2].dialect, Dialect::ColaB);
    }

    #[test]
    fn oversized_length_is_rejected() {
        let mut f = Framer::new(100);
        f.push(&[2, 2, 2, 2, 0, 0, 1, 0]);
        assert_eq!(f.next_frame(), Some(Err(FrameError::TooLong { len: 256, max: 100 })));
        let mut f = Framer::new(4);
        f.push(b"\x02sRN LMDscandata");
        assert!(matches!(f.next_frame(), Some(Err(FrameError::TooLong { .. }))));
    }

    #[test]
    fn long_runs_of_fake_magic_and_byte_by_byte_input_still_find_the_frame() {
        let good = encode_frame(Dialect::ColaB, b"sEA LMDscandata \x01");
        let mut f = Framer::default();
        for _ in 0..5_000 {
            f.push(&[2, 2, 2, 2, 0x7F, 0, 0, 0]);
        }
        let mut found = Vec::new();
        for b in &good {
            f.push(std::slice::from_ref(b));
            found.extend(drain(&mut f).into_iter().filter_map(Result::ok));
        }
        assert_eq!(found.len(), 1);
        assert_eq!(found[0].payload, b"sEA LMDscandata \x01");
        assert_eq!(f.skipped_bytes(), 40_000);
    }
}
