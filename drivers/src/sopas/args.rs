//! One argument reader/writer for both dialects, so every command and the scan telegram are
//! described once and encode/decode identically in CoLa-A and CoLa-B.

use super::error::DecodeError;
use super::framing::Dialect;
use super::{cola_a, cola_b};

/// Reads typed arguments in either dialect.
#[derive(Debug, Clone)]
pub(crate) enum ArgReader<'a> {
    A(cola_a::Reader<'a>),
    B(cola_b::Reader<'a>),
}

macro_rules! dispatch_read {
    ($($name:ident -> $t:ty),*) => {$(
        pub(crate) fn $name(&mut self, what: &'static str) -> Result<$t, DecodeError> {
            match self {
                Self::A(r) => r.$name(what),
                Self::B(r) => r.$name(what),
            }
        }
    )*};
}

impl<'a> ArgReader<'a> {
    pub(crate) fn new(dialect: Dialect, args: &'a [u8]) -> Self {
        match dialect {
            Dialect::ColaA => Self::A(cola_a::Reader::new(args)),
            Dialect::ColaB => Self::B(cola_b::Reader::new(args)),
        }
    }

    dispatch_read!(u8 -> u8, u16 -> u16, u32 -> u32, i32 -> i32, f32 -> f32, string -> String);

    pub(crate) fn fixed(&mut self, what: &'static str, len: usize) -> Result<String, DecodeError> {
        match self {
            Self::A(r) => r.fixed(what, len),
            Self::B(r) => r.fixed(what, len),
        }
    }

    /// A "present" flag (u16 0/1 in the scan telegram).
    pub(crate) fn flag16(&mut self, what: &'static str) -> Result<bool, DecodeError> {
        match self.u16(what)? {
            0 => Ok(false),
            1 => Ok(true),
            v => Err(DecodeError::OutOfRange { what, value: v.into() }),
        }
    }

    /// Errors unless every byte was consumed.
    pub(crate) fn finish(&self) -> Result<(), DecodeError> {
        let n = match self {
            Self::A(r) => r.remaining(),
            Self::B(r) => r.remaining(),
        };
        if n == 0 { Ok(()) } else { Err(DecodeError::TrailingData { n }) }
    }
}

/// Writes typed arguments in either dialect.
#[derive(Debug, Clone)]
pub(crate) enum ArgWriter {
    A(cola_a::Writer),
    B(cola_b::Writer),
}

macro_rules! dispatch_write {
    ($($name:ident($t:ty)),*) => {$(
        pub(crate) fn $name(&mut self, v: $t) {
            match self {
                Self::A(w) => w.$name(v),
                Self::B(w) => w.$name(v),
            }
        }
    )*};
}

impl ArgWriter {
    pub(crate) fn new(dialect: Dialect) -> Self {
        match dialect {
            Dialect::ColaA => Self::A(cola_a::Writer::default()),
            Dialect::ColaB => Self::B(cola_b::Writer::default()),
        }
    }

    dispatch_write!(u8(u8), u16(u16), u32(u32), i32(i32), f32(f32), fixed(&str), string(&str));

    pub(crate) fn flag16(&mut self, v: bool) {
        self.u16(u16::from(v));
    }

    pub(crate) fn into_bytes(self) -> Vec<u8> {
        match self {
            Self::A(w) => w.out,
            Self::B(w) => w.out,
        }
    }
}
