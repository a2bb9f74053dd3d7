//! CDR, the encoding of ROS 2 messages on the wire and in rosbag2 files (message encoding `cdr`).
//!
//! What is implemented (OMG "Common Object Request Broker Architecture (CORBA) 3.4, Part 2",
//! §9.3 "CDR Transfer Syntax", as used by ROS 2's rmw implementations through Fast-CDR/cycloneDDS;
//! the encapsulation header is OMG DDS-XTypes 1.3 §7.6.3.1.2 / DDS-RTPS 2.5 §10.2):
//!
//! - a 4-byte encapsulation header: two bytes of representation identifier, two bytes of options.
//!   `00 01` is plain CDR little endian (`CDR_LE`), `00 00` plain CDR big endian (`CDR_BE`); the
//!   options are ignored on read and written as `00 00`. Other identifiers (parameter lists,
//!   XCDR2) are refused with [`CdrError::Encapsulation`].
//! - every primitive aligned to its own size (1, 2, 4 or 8 bytes; `float64` on 8: XCDR version 1),
//!   counted from the end of the header, padding bytes zero;
//! - `string`: `u32` length including the terminating NUL, the bytes, the NUL;
//! - `T[]` (sequence): `u32` element count, then the elements; `T[N]`: the N elements alone.
//!
//! One implementation for the writer ([`CdrWriter`]: always little endian) and the reader
//! ([`CdrReader`]: either byte order). The reader never panics and never allocates more than the
//! input could hold: a count is checked against the bytes left before anything is reserved.

/// Why bytes are not a CDR message of the expected type.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CdrError {
    #[error("shorter than the 4-byte CDR encapsulation header ({0} bytes)")]
    NoHeader(usize),
    #[error(
        "encapsulation {0:02x} {1:02x} is not plain CDR (00 00 big endian, 00 01 little endian); parameter lists and XCDR2 are not read"
    )]
    Encapsulation(u8, u8),
    #[error("ends at byte {at} of the payload; {need} more bytes were needed")]
    Eof { at: usize, need: usize },
    #[error("a string at byte {at} is not NUL-terminated UTF-8")]
    BadString { at: usize },
    #[error("a sequence at byte {at} claims {count} elements, more than the {left} bytes left hold")]
    TooLong { at: usize, count: u32, left: usize },
    #[error("{0}")]
    Invalid(String),
}

/// Little-endian plain CDR (`CDR_LE`): representation identifier `00 01`, options `00 00`.
pub const HEADER_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Writes one message, little endian.
#[derive(Debug, Clone)]
pub struct CdrWriter {
    buf: Vec<u8>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    #[must_use]
    pub fn new() -> Self {
        let mut buf = Vec::with_capacity(256);
        buf.extend_from_slice(&HEADER_LE);
        CdrWriter { buf }
    }

    /// Pad with zeros to a multiple of `n` bytes of payload (the header does not count).
    fn align(&mut self, n: usize) {
        let pos = self.buf.len() - HEADER_LE.len();
        let pad = (n - pos % n) % n;
        self.buf.resize(self.buf.len() + pad, 0);
    }

    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }

    pub fn i8(&mut self, v: i8) {
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f32(&mut self, v: f32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A sequence's element count. Counts past `u32::MAX` cannot be written in CDR: saturated (the
    /// caller never has that many).
    pub fn len(&mut self, n: usize) {
        self.u32(u32::try_from(n).unwrap_or(u32::MAX));
    }

    pub fn string(&mut self, s: &str) {
        // A NUL inside would end the string early for a C reader: cut there.
        let s = s.split('\0').next().unwrap_or_default();
        self.len(s.len() + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }

    pub fn f32s(&mut self, v: &[f32]) {
        self.len(v.len());
        for x in v {
            self.f32(*x);
        }
    }

    pub fn i8s(&mut self, v: &[i8]) {
        self.len(v.len());
        for x in v {
            self.i8(*x);
        }
    }

    /// The message with its header.
    #[must_use]
    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

/// Reads one message, either byte order.
#[derive(Debug, Clone)]
pub struct CdrReader<'a> {
    /// The payload after the encapsulation header.
    b: &'a [u8],
    pos: usize,
    big_endian: bool,
}

impl<'a> CdrReader<'a> {
    /// Check the encapsulation header.
    pub fn new(bytes: &'a [u8]) -> Result<Self, CdrError> {
        let (Some(head), Some(b)) = (bytes.get(..4), bytes.get(4..)) else {
            return Err(CdrError::NoHeader(bytes.len()));
        };
        let big_endian = match (head[0], head[1]) {
            (0x00, 0x00) => true,
            (0x00, 0x01) => false,
            (a, b) => return Err(CdrError::Encapsulation(a, b)),
        };
        Ok(CdrReader { b, pos: 0, big_endian })
    }

    #[must_use]
    pub fn is_big_endian(&self) -> bool {
        self.big_endian
    }

    /// Payload bytes not yet read.
    #[must_use]
    pub fn left(&self) -> usize {
        self.b.len().saturating_sub(self.pos)
    }

    fn align(&mut self, n: usize) -> Result<(), CdrError> {
        let pad = (n - self.pos % n) % n;
        self.take(pad).map(|_| ())
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], CdrError> {
        let end = self.pos.checked_add(n).filter(|e| *e <= self.b.len());
        match end {
            Some(end) => {
                let s = &self.b[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(CdrError::Eof { at: self.pos, need: n - self.left().min(n) }),
        }
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], CdrError> {
        self.align(N)?;
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }

    pub fn u8(&mut self) -> Result<u8, CdrError> {
        Ok(self.array::<1>()?[0])
    }

    pub fn i8(&mut self) -> Result<i8, CdrError> {
        Ok(i8::from_ne_bytes(self.array::<1>()?))
    }

    pub fn u32(&mut self) -> Result<u32, CdrError> {
        let a = self.array::<4>()?;
        Ok(if self.big_endian { u32::from_be_bytes(a) } else { u32::from_le_bytes(a) })
    }

    pub fn i32(&mut self) -> Result<i32, CdrError> {
        let a = self.array::<4>()?;
        Ok(if self.big_endian { i32::from_be_bytes(a) } else { i32::from_le_bytes(a) })
    }

    pub fn f32(&mut self) -> Result<f32, CdrError> {
        let a = self.array::<4>()?;
        Ok(if self.big_endian { f32::from_be_bytes(a) } else { f32::from_le_bytes(a) })
    }

    pub fn f64(&mut self) -> Result<f64, CdrError> {
        let a = self.array::<8>()?;
        Ok(if self.big_endian { f64::from_be_bytes(a) } else { f64::from_le_bytes(a) })
    }

    /// A sequence's element count, checked against what is left (each element at least
    /// `min_size` bytes), so that a damaged count never reserves gigabytes.
    pub fn len(&mut self, min_size: usize) -> Result<usize, CdrError> {
        let at = self.pos;
        let count = self.u32()?;
        let n = usize::try_from(count).unwrap_or(usize::MAX);
        if n.saturating_mul(min_size.max(1)) > self.left() {
            return Err(CdrError::TooLong { at, count, left: self.left() });
        }
        Ok(n)
    }

    pub fn string(&mut self) -> Result<String, CdrError> {
        let at = self.pos;
        let n = self.len(1)?;
        if n == 0 {
            // Not what a conforming writer sends for "", but unambiguous.
            return Ok(String::new());
        }
        let bytes = self.take(n)?;
        match bytes.split_last() {
            Some((0, text)) => {
                std::str::from_utf8(text).map(str::to_owned).map_err(|_| CdrError::BadString { at })
            }
            _ => Err(CdrError::BadString { at }),
        }
    }

    pub fn f32s(&mut self) -> Result<Vec<f32>, CdrError> {
        let n = self.len(4)?;
        (0..n).map(|_| self.f32()).collect()
    }

    pub fn i8s(&mut self) -> Result<Vec<i8>, CdrError> {
        let n = self.len(1)?;
        Ok(self.take(n)?.iter().map(|b| i8::from_ne_bytes([*b])).collect())
    }

    pub fn f64_array<const N: usize>(&mut self) -> Result<[f64; N], CdrError> {
        let mut a = [0.0; N];
        for x in &mut a {
            *x = self.f64()?;
        }
        Ok(a)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
    use super::*;

    #[test]
    fn alignment_counts_from_the_end_of_the_header() {
        let mut w = CdrWriter::new();
        w.u8(7);
        w.f64(1.5);
        w.string("ab");
        w.i8(-1);
        w.f32(2.0);
        let b = w.finish();
        // header, u8, 7 pad, f64 at payload offset 8, string length at 16, "ab\0" at 20..23,
        // i8 at 23, f32 at 24.
        assert_eq!(&b[..4], &[0, 1, 0, 0]);
        assert_eq!(b[4], 7);
        assert_eq!(&b[5..12], &[0; 7]);
        assert_eq!(&b[12..20], &1.5f64.to_le_bytes());
        assert_eq!(&b[20..24], &3u32.to_le_bytes());
        assert_eq!(&b[24..27], b"ab\0");
        assert_eq!(b[27], 0xff);
        assert_eq!(&b[28..32], &2.0f32.to_le_bytes());
        assert_eq!(b.len(), 32);
        let mut r = CdrReader::new(&b).unwrap();
        assert_eq!(r.u8().unwrap(), 7);
        assert_eq!(r.f64().unwrap(), 1.5);
        assert_eq!(r.string().unwrap(), "ab");
        assert_eq!(r.i8().unwrap(), -1);
        assert_eq!(r.f32().unwrap(), 2.0);
        assert_eq!(r.left(), 0);
    }

    #[test]
    fn big_endian_reads_and_other_encapsulations_are_refused() {
        let mut b = vec![0x00, 0x00, 0x00, 0x00];
        b.extend_from_slice(&5u32.to_be_bytes());
        b.extend_from_slice(&[0; 4]);
        b.extend_from_slice(&(-2.25f64).to_be_bytes());
        let mut r = CdrReader::new(&b).unwrap();
        assert!(r.is_big_endian());
        assert_eq!(r.u32().unwrap(), 5);
        assert_eq!(r.f64().unwrap(), -2.25);
        for enc in [[0x00, 0x03], [0x00, 0x07], [0x00, 0x02], [0x01, 0x01]] {
            let e = CdrReader::new(&[enc[0], enc[1], 0, 0, 1, 2, 3, 4]).unwrap_err();
            assert_eq!(e, CdrError::Encapsulation(enc[0], enc[1]));
            assert!(e.to_string().contains("not plain CDR"), "{e}");
        }
        assert_eq!(CdrReader::new(&[0, 1]).unwrap_err(), CdrError::NoHeader(2));
    }

    #[test]
    fn damaged_counts_and_strings_are_errors() {
        let mut w = CdrWriter::new();
        w.u32(u32::MAX);
        let b = w.finish();
        assert!(matches!(CdrReader::new(&b).unwrap().f32s(), Err(CdrError::TooLong { .. })));
        assert!(matches!(CdrReader::new(&b).unwrap().string(), Err(CdrError::TooLong { .. })));
        let mut w = CdrWriter::new();
        w.u32(2);
        w.u8(b'a');
        w.u8(b'b');
        let b = w.finish();
        assert!(matches!(CdrReader::new(&b).unwrap().string(), Err(CdrError::BadString { at: 0 })));
        assert!(matches!(CdrReader::new(&b[..6]).unwrap().u32(), Err(CdrError::Eof { at: 0, need: 2 })));
    }
}
