//! CoLa-A (ASCII) argument tokens (notes §1.1, SICK TI §5.1): space-separated tokens, unsigned
//! values in upper-case hex, signed values decimal with `+`/`-` or two's-complement hex as the
//! TiM sends them, REAL as the 8-hex-digit bit pattern, strings as hex length + space + chars.

use super::error::DecodeError;

/// Reads tokens from the argument part of a CoLa-A payload.
#[derive(Debug, Clone)]
pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, pos: 0 }
    }

    /// The next space-delimited token (one or more separating spaces are skipped).
    fn token(&mut self, what: &'static str) -> Result<&'a [u8], DecodeError> {
        while self.bytes.get(self.pos) == Some(&b' ') {
            self.pos += 1;
        }
        let start = self.pos;
        while let Some(&b) = self.bytes.get(self.pos) {
            if b == b' ' {
                break;
            }
            self.pos += 1;
        }
        if start == self.pos {
            return Err(DecodeError::UnexpectedEnd { what });
        }
        Ok(&self.bytes[start..self.pos])
    }

    /// A number token: decimal when signed (`+12`, `-3`), hex otherwise.
    fn number(&mut self, what: &'static str) -> Result<i64, DecodeError> {
        let tok = self.token(what)?;
        let text = std::str::from_utf8(tok).map_err(|_| DecodeError::BadValue { what })?;
        let bad = || DecodeError::BadValue { what };
        match tok[0] {
            b'+' | b'-' => text.parse::<i64>().map_err(|_| bad()),
            _ if tok.len() <= 16 => u64::from_str_radix(text, 16)
                .map_err(|_| bad())
                .and_then(|v| i64::try_from(v).map_err(|_| bad())),
            _ => Err(bad()),
        }
    }

    fn unsigned(&mut self, what: &'static str, max: u64) -> Result<u64, DecodeError> {
        let v = self.number(what)?;
        u64::try_from(v).ok().filter(|v| *v <= max).ok_or(DecodeError::OutOfRange { what, value: v })
    }

    pub(crate) fn u8(&mut self, what: &'static str) -> Result<u8, DecodeError> {
        self.unsigned(what, u8::MAX.into()).map(|v| v as u8)
    }

    pub(crate) fn u16(&mut self, what: &'static str) -> Result<u16, DecodeError> {
        self.unsigned(what, u16::MAX.into()).map(|v| v as u16)
    }

    pub(crate) fn u32(&mut self, what: &'static str) -> Result<u32, DecodeError> {
        self.unsigned(what, u32::MAX.into()).map(|v| v as u32)
    }

    /// INT32: decimal with sign, or two's-complement hex (`FFF92230` = −450000, notes §1.1).
    pub(crate) fn i32(&mut self, what: &'static str) -> Result<i32, DecodeError> {
        let tok_start = self.pos;
        let v = self.number(what)?;
        let signed = self.bytes[tok_start..self.pos].iter().any(|&b| b == b'+' || b == b'-');
        if signed {
            i32::try_from(v).map_err(|_| DecodeError::OutOfRange { what, value: v })
        } else {
            u32::try_from(v).map(|u| u as i32).map_err(|_| DecodeError::OutOfRange { what, value: v })
        }
    }

    /// REAL: the IEEE-754 bit pattern as hex (`3F800000` = 1.0).
    pub(crate) fn f32(&mut self, what: &'static str) -> Result<f32, DecodeError> {
        self.u32(what).map(f32::from_bits)
    }

    /// A fixed-width name such as `DIST1`.
    pub(crate) fn fixed(&mut self, what: &'static str, len: usize) -> Result<String, DecodeError> {
        let tok = self.token(what)?;
        if tok.len() != len {
            return Err(DecodeError::BadValue { what });
        }
        String::from_utf8(tok.to_vec()).map_err(|_| DecodeError::BadValue { what })
    }

    /// A length-prefixed string: hex length, one space, exactly that many bytes (which may be
    /// spaces: `B not defined`). Decoded by length, never by splitting.
    pub(crate) fn string(&mut self, what: &'static str) -> Result<String, DecodeError> {
        let len = self.u16(what)? as usize;
        if len == 0 {
            return Ok(String::new());
        }
        if self.bytes.get(self.pos) != Some(&b' ') {
            return Err(DecodeError::UnexpectedEnd { what });
        }
        let start = self.pos + 1;
        let end = start + len;
        let chars = self.bytes.get(start..end).ok_or(DecodeError::UnexpectedEnd { what })?;
        self.pos = end;
        String::from_utf8(chars.to_vec()).map_err(|_| DecodeError::BadValue { what })
    }

    /// Bytes not consumed, ignoring spaces and a trailing line end.
    pub(crate) fn remaining(&self) -> usize {
        self.bytes[self.pos.min(self.bytes.len())..]
            .iter()
            .filter(|b| !matches!(b, b' ' | b'\r' | b'\n'))
            .count()
    }
}

/// Appends CoLa-A argument tokens, each preceded by one space.
#[derive(Debug, Clone, Default)]
pub(crate) struct Writer {
    pub(crate) out: Vec<u8>,
}

impl Writer {
    fn hex(&mut self, v: u64) {
        self.out.extend_from_slice(format!(" {v:X}").as_bytes());
    }

    pub(crate) fn u8(&mut self, v: u8) {
        self.hex(v.into());
    }

    pub(crate) fn u16(&mut self, v: u16) {
        self.hex(v.into());
    }

    pub(crate) fn u32(&mut self, v: u32) {
        self.hex(v.into());
    }

    /// INT32 as two's-complement hex, the form the TiM uses (`FFF92230`).
    pub(crate) fn i32(&mut self, v: i32) {
        self.hex((v as u32).into());
    }

    pub(crate) fn f32(&mut self, v: f32) {
        self.out.extend_from_slice(format!(" {:08X}", v.to_bits()).as_bytes());
    }

    pub(crate) fn fixed(&mut self, s: &str) {
        self.out.push(b' ');
        self.out.extend_from_slice(s.as_bytes());
    }

    pub(crate) fn string(&mut self, s: &str) {
        self.hex(s.len() as u64);
        if !s.is_empty() {
            self.out.push(b' ');
            self.out.extend_from_slice(s.as_bytes());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strings_with_spaces_decode_by_length() {
        let mut r = Reader::new(b" 1 B not defined 0 7 Daniyal");
        assert_eq!(r.u16("present").unwrap(), 1);
        assert_eq!(r.string("name").unwrap(), "not defined");
        assert_eq!(r.u16("x").unwrap(), 0);
        assert_eq!(r.string("name").unwrap(), "Daniyal");
        assert_eq!(r.remaining(), 0);
    }

    #[test]
    fn numbers_in_both_notations() {
        let mut r = Reader::new(b"FFF92230 -450000 +12 3F800000 1FF");
        assert_eq!(r.i32("a").unwrap(), -450_000);
        assert_eq!(r.i32("a").unwrap(), -450_000);
        assert_eq!(r.u8("b").unwrap(), 12);
        assert_eq!(r.f32("c").unwrap(), 1.0);
        assert!(matches!(r.u8("d"), Err(DecodeError::OutOfRange { .. })));
        assert!(matches!(r.u8("e"), Err(DecodeError::UnexpectedEnd { .. })));
    }

    #[test]
    fn string_longer_than_payload_is_an_error() {
        let mut r = Reader::new(b" 10 short");
        assert!(r.string("s").is_err());
    }
}
