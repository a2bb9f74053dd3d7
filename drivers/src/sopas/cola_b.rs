//! CoLa-B (binary) arguments (notes §1.2): fixed-width big-endian numbers, REAL as float32,
//! strings as u16 length + chars, channel names as fixed 5 chars.

use super::error::DecodeError;

/// Reads big-endian fields from the argument part of a CoLa-B payload.
#[derive(Debug, Clone)]
pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, pos: 0 }
    }

    fn take<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], DecodeError> {
        let end = self.pos + N;
        let s = self.bytes.get(self.pos..end).ok_or(DecodeError::UnexpectedEnd { what })?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        self.pos = end;
        Ok(a)
    }

    pub(crate) fn u8(&mut self, what: &'static str) -> Result<u8, DecodeError> {
        self.take::<1>(what).map(|a| a[0])
    }

    pub(crate) fn u16(&mut self, what: &'static str) -> Result<u16, DecodeError> {
        self.take(what).map(u16::from_be_bytes)
    }

    pub(crate) fn u32(&mut self, what: &'static str) -> Result<u32, DecodeError> {
        self.take(what).map(u32::from_be_bytes)
    }

    pub(crate) fn i32(&mut self, what: &'static str) -> Result<i32, DecodeError> {
        self.take(what).map(i32::from_be_bytes)
    }

    pub(crate) fn f32(&mut self, what: &'static str) -> Result<f32, DecodeError> {
        self.take(what).map(f32::from_be_bytes)
    }

    fn bytes_n(&mut self, what: &'static str, len: usize) -> Result<String, DecodeError> {
        let end = self.pos + len;
        let s = self.bytes.get(self.pos..end).ok_or(DecodeError::UnexpectedEnd { what })?;
        self.pos = end;
        String::from_utf8(s.to_vec()).map_err(|_| DecodeError::BadValue { what })
    }

    pub(crate) fn fixed(&mut self, what: &'static str, len: usize) -> Result<String, DecodeError> {
        self.bytes_n(what, len)
    }

    pub(crate) fn string(&mut self, what: &'static str) -> Result<String, DecodeError> {
        let len = self.u16(what)? as usize;
        self.bytes_n(what, len)
    }

    pub(crate) fn remaining(&self) -> usize {
        self.bytes.len().saturating_sub(self.pos)
    }
}

/// Appends big-endian CoLa-B fields.
#[derive(Debug, Clone, Default)]
pub(crate) struct Writer {
    pub(crate) out: Vec<u8>,
}

impl Writer {
    pub(crate) fn u8(&mut self, v: u8) {
        self.out.push(v);
    }

    pub(crate) fn u16(&mut self, v: u16) {
        self.out.extend_from_slice(&v.to_be_bytes());
    }

    pub(crate) fn u32(&mut self, v: u32) {
        self.out.extend_from_slice(&v.to_be_bytes());
    }

    pub(crate) fn i32(&mut self, v: i32) {
        self.out.extend_from_slice(&v.to_be_bytes());
    }

    pub(crate) fn f32(&mut self, v: f32) {
        self.out.extend_from_slice(&v.to_be_bytes());
    }

    pub(crate) fn fixed(&mut self, s: &str) {
        self.out.extend_from_slice(s.as_bytes());
    }

    pub(crate) fn string(&mut self, s: &str) {
        let len = u16::try_from(s.len()).unwrap_or(u16::MAX);
        self.u16(len);
        self.out.extend_from_slice(&s.as_bytes()[..usize::from(len)]);
    }
}
