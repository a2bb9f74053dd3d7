//! socketcand (CAN over TCP) in raw mode: the `< … >` element codec, used by both sides, and a
//! client transport. Wire format (devices.md §2, python-can `socketcand.py`): server `< hi >`;
//! client `< open CH >` → `< ok >`, `< rawmode >` → `< ok >`; server frames
//! `< frame ID SECS.USECS DATAHEX >`; client `< send ID LEN B0 B1 … >` (hex, no zero padding).
//! Standard ids are exactly 3 hex digits, extended ids 8.

use std::fmt::Write as _;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::CanTransport;
use crate::canopen::error::TransportError;
use crate::canopen::frame::CanFrame;

/// Longest element kept while looking for its `>` (longer ones are garbage and dropped).
pub const MAX_ELEMENT_LEN: usize = 256;

/// One element of the protocol.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Element {
    /// `< hi >`: the server's greeting.
    Hi,
    /// `< ok >`.
    Ok,
    /// `< error … >`.
    Error(String),
    /// `< open CHANNEL >`.
    Open(String),
    /// `< rawmode >`.
    Rawmode,
    /// `< frame ID SECS.USECS DATA >` from the server.
    Frame {
        /// The frame.
        frame: CanFrame,
        /// Timestamp seconds.
        secs: u64,
        /// Timestamp microseconds.
        usecs: u32,
    },
    /// `< send ID LEN B… >` from the client.
    Send(CanFrame),
    /// Anything else that is well-formed (`< echo >`, `< bcmmode >`, …).
    Other(String),
}

/// Why an element could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ElementError {
    /// A `frame` or `send` element with a bad field.
    #[error("bad socketcand element `{0}`")]
    Bad(String),
    /// Bytes outside `< … >`, or an element too long.
    #[error("socketcand garbage of {0} bytes dropped")]
    Garbage(usize),
}

fn parse_id(s: &str) -> Option<(u32, bool)> {
    if s.is_empty() || s.len() > 8 || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    let id = u32::from_str_radix(s, 16).ok()?;
    Some((id, s.len() != 3))
}

fn parse_hex_u8(s: &str) -> Option<u8> {
    if s.is_empty() || s.len() > 2 || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    u8::from_str_radix(s, 16).ok()
}

/// Decode the inside of one element (between `<` and `>`).
pub fn parse_element(body: &str) -> Result<Element, ElementError> {
    let bad = || ElementError::Bad(body.chars().take(64).collect());
    let mut tokens = body.split_ascii_whitespace();
    let Some(cmd) = tokens.next() else { return Err(bad()) };
    let rest: Vec<&str> = tokens.collect();
    match (cmd, rest.as_slice()) {
        ("hi", []) => Ok(Element::Hi),
        ("ok", []) => Ok(Element::Ok),
        ("rawmode", []) => Ok(Element::Rawmode),
        ("open", [ch]) => Ok(Element::Open((*ch).to_owned())),
        ("error", r) => Ok(Element::Error(r.join(" "))),
        ("frame", [id, stamp, data @ ..]) => {
            let (id, ext) = parse_id(id).ok_or_else(bad)?;
            let (s, us) = stamp.split_once('.').ok_or_else(bad)?;
            let secs = s.parse::<u64>().map_err(|_| bad())?;
            let usecs = us.parse::<u32>().map_err(|_| bad())?;
            let hex = match data {
                [] => "",
                [h] => h,
                _ => return Err(bad()),
            };
            if hex.len() % 2 != 0 || hex.len() > 16 {
                return Err(bad());
            }
            let bytes: Option<Vec<u8>> =
                (0..hex.len() / 2).map(|i| parse_hex_u8(hex.get(2 * i..2 * i + 2)?)).collect();
            let frame = CanFrame::with_id(id, ext, &bytes.ok_or_else(bad)?).map_err(|_| bad())?;
            Ok(Element::Frame { frame, secs, usecs })
        }
        ("send", [id, len, data @ ..]) => {
            let (id, ext) = parse_id(id).ok_or_else(bad)?;
            let len = parse_hex_u8(len).ok_or_else(bad)?;
            if usize::from(len) != data.len() {
                return Err(bad());
            }
            let bytes: Option<Vec<u8>> = data.iter().map(|b| parse_hex_u8(b)).collect();
            let frame = CanFrame::with_id(id, ext, &bytes.ok_or_else(bad)?).map_err(|_| bad())?;
            Ok(Element::Send(frame))
        }
        ("frame" | "send", _) => Err(bad()),
        _ => Ok(Element::Other(body.trim().to_owned())),
    }
}

fn fmt_id(frame: &CanFrame) -> String {
    if frame.is_extended() { format!("{:08X}", frame.id()) } else { format!("{:03X}", frame.id()) }
}

/// `< frame ID SECS.USECS DATA >` (server → client).
pub fn encode_frame(frame: &CanFrame, secs: u64, usecs: u32) -> String {
    let mut hex = String::with_capacity(16);
    for b in frame.data() {
        let _ = write!(hex, "{b:02X}");
    }
    format!("< frame {} {secs}.{usecs:06} {hex} >", fmt_id(frame))
}

/// `< send ID LEN B0 … >` (client → server), numbers in hex without padding.
pub fn encode_send(frame: &CanFrame) -> String {
    let mut s = format!("< send {} {:X} ", fmt_id(frame), frame.data().len());
    for b in frame.data() {
        let _ = write!(s, "{b:X} ");
    }
    s.push('>');
    s
}

/// Splits a byte stream into elements; never panics, drops garbage.
#[derive(Debug, Default, Clone)]
pub struct ElementDecoder {
    buf: Vec<u8>,
}

impl ElementDecoder {
    /// An empty decoder.
    pub fn new() -> Self {
        Self::default()
    }

    /// Append received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// The next element, `None` when more bytes are needed. Each call consumes input or returns None.
    pub fn next_element(&mut self) -> Option<Result<Element, ElementError>> {
        let start = self.buf.iter().position(|&b| b == b'<');
        match start {
            None => {
                let n = self.buf.iter().filter(|b| !b.is_ascii_whitespace()).count();
                self.buf.clear();
                return (n > 0).then_some(Err(ElementError::Garbage(n)));
            }
            Some(s) if s > 0 => {
                let n = self.buf[..s].iter().filter(|b| !b.is_ascii_whitespace()).count();
                self.buf.drain(..s);
                if n > 0 {
                    return Some(Err(ElementError::Garbage(n)));
                }
            }
            Some(_) => {}
        }
        // buf[0] == b'<'
        let Some(end) = self.buf.iter().position(|&b| b == b'>') else {
            if self.buf.len() > MAX_ELEMENT_LEN {
                let n = self.buf.len();
                self.buf.clear();
                return Some(Err(ElementError::Garbage(n)));
            }
            return None;
        };
        let element: Vec<u8> = self.buf.drain(..=end).collect();
        if element.len() > MAX_ELEMENT_LEN {
            return Some(Err(ElementError::Garbage(element.len())));
        }
        let body = String::from_utf8_lossy(&element[1..element.len() - 1]);
        // A nested '<' means the previous element was cut: restart at the inner one.
        if let Some(inner) = body.rfind('<') {
            let inner_body = body[inner + 1..].to_owned();
            return Some(parse_element(&inner_body));
        }
        Some(parse_element(&body))
    }
}

/// A socketcand client in raw mode on one channel.
#[derive(Debug)]
pub struct SocketcandClient {
    stream: TcpStream,
    decoder: ElementDecoder,
    buf: Vec<u8>,
}

impl SocketcandClient {
    /// Connect, wait for `< hi >`, open `channel` and switch to raw mode, each step within `timeout`.
    pub async fn connect(addr: &str, channel: &str, timeout: Duration) -> Result<Self, TransportError> {
        let stream = tokio::time::timeout(timeout, TcpStream::connect(addr))
            .await
            .map_err(|_| TransportError::Socketcand(format!("connect to {addr} timed out")))?
            .map_err(|e| TransportError::io(&e))?;
        let _ = stream.set_nodelay(true);
        let mut client = Self { stream, decoder: ElementDecoder::new(), buf: vec![0; 4096] };
        client.expect(Element::Hi, timeout).await?;
        client.write(&format!("< open {channel} >")).await?;
        client.expect(Element::Ok, timeout).await?;
        client.write("< rawmode >").await?;
        client.expect(Element::Ok, timeout).await?;
        Ok(client)
    }

    async fn write(&mut self, s: &str) -> Result<(), TransportError> {
        self.stream.write_all(s.as_bytes()).await.map_err(|e| TransportError::io(&e))
    }

    async fn next(&mut self) -> Result<Element, TransportError> {
        // Bounded: each pass either returns or reads more bytes (or fails).
        loop {
            while let Some(r) = self.decoder.next_element() {
                match r {
                    Ok(e) => return Ok(e),
                    Err(err) => tracing::debug!(%err, "socketcand: dropped"),
                }
            }
            // `read` is cancel-safe: bytes read are in the decoder before the next await.
            let n = self.stream.read(&mut self.buf).await.map_err(|e| TransportError::io(&e))?;
            if n == 0 {
                return Err(TransportError::Closed);
            }
            self.decoder.push(&self.buf[..n]);
        }
    }

    async fn expect(&mut self, want: Element, timeout: Duration) -> Result<(), TransportError> {
        let got = tokio::time::timeout(timeout, self.next())
            .await
            .map_err(|_| TransportError::Socketcand(format!("no {want:?} within {timeout:?}")))??;
        if got == want {
            Ok(())
        } else {
            Err(TransportError::Socketcand(format!("expected {want:?}, got {got:?}")))
        }
    }
}

impl CanTransport for SocketcandClient {
    async fn send(&mut self, frame: CanFrame) -> Result<(), TransportError> {
        let line = encode_send(&frame);
        self.write(&line).await
    }

    async fn recv(&mut self) -> Result<CanFrame, TransportError> {
        // Bounded by the stream: every element consumed moves on; non-frame elements are skipped.
        loop {
            match self.next().await? {
                Element::Frame { frame, .. } => return Ok(frame),
                Element::Error(e) => return Err(TransportError::Socketcand(e)),
                other => tracing::debug!(?other, "socketcand: ignored"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canopen_socketcand_golden_elements() {
        let f = CanFrame::new(0x601, &[0x2F, 0x60, 0x60, 0, 3, 0, 0, 0]).unwrap();
        // devices.md §2: data bytes in hex without zero padding.
        assert_eq!(encode_send(&f), "< send 601 8 2F 60 60 0 3 0 0 0 >");
        assert_eq!(parse_element(" send 601 8 2f 60 60 0 3 0 0 0 "), Ok(Element::Send(f)));
        let g = CanFrame::new(0x181, &[0x37, 0x02]).unwrap();
        assert_eq!(encode_frame(&g, 12, 345), "< frame 181 12.000345 3702 >");
        assert_eq!(
            parse_element(" frame 181 12.000345 3702 "),
            Ok(Element::Frame { frame: g, secs: 12, usecs: 345 })
        );
        let sync = CanFrame::new(0x080, &[]).unwrap();
        assert_eq!(encode_frame(&sync, 1, 0), "< frame 080 1.000000  >");
        assert_eq!(
            parse_element(" frame 080 1.000000  "),
            Ok(Element::Frame { frame: sync, secs: 1, usecs: 0 })
        );
        let ext = CanFrame::with_id(0x0000_0123, true, &[1]).unwrap();
        assert_eq!(encode_send(&ext), "< send 00000123 1 1 >");
        assert_eq!(parse_element(" send 00000123 1 1 "), Ok(Element::Send(ext)));
        assert_eq!(parse_element(" hi "), Ok(Element::Hi));
        assert_eq!(parse_element(" open can0 "), Ok(Element::Open("can0".into())));
        assert!(parse_element(" send 601 2 1 ").is_err(), "length mismatch");
        assert!(parse_element(" send 601 1 100 ").is_err(), "byte out of range");
        assert!(parse_element(" frame 800 1.0 00 ").is_err(), "standard id out of range");
    }

    #[test]
    fn canopen_socketcand_decoder_splits_and_resyncs() {
        let mut d = ElementDecoder::new();
        d.push(b"< hi >< ok ><");
        assert_eq!(d.next_element(), Some(Ok(Element::Hi)));
        assert_eq!(d.next_element(), Some(Ok(Element::Ok)));
        assert_eq!(d.next_element(), None);
        d.push(b" rawmode >junk< frame 701 0.1 05 >");
        assert_eq!(d.next_element(), Some(Ok(Element::Rawmode)));
        assert_eq!(d.next_element(), Some(Err(ElementError::Garbage(4))));
        let hb = CanFrame::new(0x701, &[5]).unwrap();
        assert_eq!(d.next_element(), Some(Ok(Element::Frame { frame: hb, secs: 0, usecs: 1 })));
        d.push(&[b'<'; 300]);
        assert!(matches!(d.next_element(), Some(Err(ElementError::Garbage(_)))));
        assert_eq!(d.next_element(), None);
    }
}
