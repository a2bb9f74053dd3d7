//! SDO (CiA 301): the 8-byte request/response codec, abort codes with names, a client for one
//! server (expedited and segmented upload/download, per-request timeout) and a server over any
//! object dictionary (used by the mock drives). Command specifiers and golden vectors:
//! python-canopen `sdo/constants.py`, `test/test_sdo.py` (notes B2).

use std::fmt;
use std::time::{Duration, Instant};

use super::frame::{CanFrame, Cob, NodeId};

/// An SDO abort code (u32 in bytes 4..8 of an abort frame).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct AbortCode(pub u32);

impl AbortCode {
    /// Toggle bit not alternated.
    pub const TOGGLE: Self = Self(0x0503_0000);
    /// SDO protocol timed out.
    pub const TIMEOUT: Self = Self(0x0504_0000);
    /// Command specifier not valid or unknown.
    pub const BAD_COMMAND: Self = Self(0x0504_0001);
    /// Attempt to write a read-only object.
    pub const READ_ONLY: Self = Self(0x0601_0002);
    /// Object does not exist in the object dictionary.
    pub const NO_OBJECT: Self = Self(0x0602_0000);
    /// Data type does not match, length of service parameter does not match.
    pub const LENGTH: Self = Self(0x0607_0010);
    /// Sub-index does not exist.
    pub const NO_SUBINDEX: Self = Self(0x0609_0011);
    /// Invalid value for parameter.
    pub const VALUE_RANGE: Self = Self(0x0609_0030);
    /// General error.
    pub const GENERAL: Self = Self(0x0800_0000);
    /// Data cannot be transferred because of the present device state.
    pub const DEVICE_STATE: Self = Self(0x0800_0022);

    /// The CiA 301 description (python-canopen `sdo/exceptions.py`), or "unknown abort code".
    pub fn name(self) -> &'static str {
        match self.0 {
            0x0503_0000 => "SDO toggle bit not alternated",
            0x0504_0000 => "SDO protocol timed out",
            0x0504_0001 => "Client/server command specifier not valid or unknown",
            0x0504_0002 => "Invalid block size",
            0x0504_0003 => "Invalid sequence number",
            0x0504_0004 => "CRC error",
            0x0504_0005 => "Out of memory",
            0x0601_0000 => "Unsupported access to an object",
            0x0601_0001 => "Attempt to read a write only object",
            0x0601_0002 => "Attempt to write a read only object",
            0x0602_0000 => "Object does not exist in the object dictionary",
            0x0604_0041 => "Object cannot be mapped to the PDO",
            0x0604_0042 => "The number and length of the objects to be mapped would exceed PDO length",
            0x0604_0043 => "General parameter incompatibility reason",
            0x0604_0047 => "General internal incompatibility in the device",
            0x0606_0000 => "Access failed due to a hardware error",
            0x0607_0010 => "Data type does not match, length of service parameter does not match",
            0x0607_0012 => "Data type does not match, length of service parameter too high",
            0x0607_0013 => "Data type does not match, length of service parameter too low",
            0x0609_0011 => "Sub-index does not exist",
            0x0609_0030 => "Invalid value for parameter",
            0x0609_0031 => "Value of parameter written too high",
            0x0609_0032 => "Value of parameter written too low",
            0x0609_0036 => "Maximum value is less than minimum value",
            0x060A_0023 => "Resource not available: SDO connection",
            0x0800_0000 => "General error",
            0x0800_0020 => "Data cannot be transferred or stored to the application",
            0x0800_0021 => "Data cannot be transferred or stored because of local control",
            0x0800_0022 => "Data cannot be transferred or stored because of the present device state",
            0x0800_0023 => "Object dictionary dynamic generation fails or no object dictionary present",
            0x0800_0024 => "No data available",
            _ => "unknown abort code",
        }
    }
}

impl fmt::Display for AbortCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:#010x} ({})", self.0, self.name())
    }
}

/// An object address: index and sub-index.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ObjectAddr {
    /// Index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
}

impl ObjectAddr {
    /// `index:sub`.
    pub const fn new(index: u16, sub: u8) -> Self {
        Self { index, sub }
    }

    fn put(self, buf: &mut [u8; 8]) {
        let i = self.index.to_le_bytes();
        buf[1] = i[0];
        buf[2] = i[1];
        buf[3] = self.sub;
    }

    fn of(buf: &[u8; 8]) -> Self {
        Self { index: u16::from_le_bytes([buf[1], buf[2]]), sub: buf[3] }
    }
}

impl fmt::Display for ObjectAddr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:#06x}:{:02x}", self.index, self.sub)
    }
}

/// An abort frame body: `80 idx sub code`.
pub fn abort_bytes(addr: ObjectAddr, code: AbortCode) -> [u8; 8] {
    let mut b = [0u8; 8];
    b[0] = 0x80;
    addr.put(&mut b);
    b[4..].copy_from_slice(&code.0.to_le_bytes());
    b
}

/// An expedited download request (1..=4 bytes): cs = 0x20 | (4 − n) << 2 | 0x03.
pub fn expedited_download(addr: ObjectAddr, data: &[u8]) -> Option<[u8; 8]> {
    if data.is_empty() || data.len() > 4 {
        return None;
    }
    let mut b = [0u8; 8];
    b[0] = 0x20 | (((4 - data.len()) as u8) << 2) | 0x03;
    addr.put(&mut b);
    b[4..4 + data.len()].copy_from_slice(data);
    Some(b)
}

/// An upload request: `40 idx sub 00 00 00 00`.
pub fn upload_request(addr: ObjectAddr) -> [u8; 8] {
    let mut b = [0u8; 8];
    b[0] = 0x40;
    addr.put(&mut b);
    b
}

/// What a finished client request produced.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SdoResult {
    /// The download was confirmed.
    Written,
    /// The uploaded bytes.
    Read(Vec<u8>),
}

/// Why a client request failed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SdoFailure {
    /// The server aborted with this code (the device answered "no").
    Aborted(AbortCode),
    /// The client aborted: an unexpected or malformed response (sent abort with this code).
    Protocol(AbortCode),
    /// No response within the request timeout (the client sent abort 0x05040000).
    Timeout,
}

/// One SDO request from the client.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SdoRequest {
    /// Read an object.
    Upload(ObjectAddr),
    /// Write an object (expedited if 1..=4 bytes, segmented otherwise).
    Download(ObjectAddr, Vec<u8>),
}

impl SdoRequest {
    /// The object addressed.
    pub fn addr(&self) -> ObjectAddr {
        match self {
            SdoRequest::Upload(a) | SdoRequest::Download(a, _) => *a,
        }
    }
}

#[derive(Debug, Clone)]
enum Transfer {
    Idle,
    /// Waiting for the initiate response.
    Initiate {
        req: SdoRequest,
    },
    /// Segmented download: `sent` bytes are confirmed, the segment with `toggle` is in flight.
    DownSegment {
        addr: ObjectAddr,
        data: Vec<u8>,
        sent: usize,
        toggle: bool,
        last_len: usize,
    },
    /// Segmented upload: received so far, waiting for the segment with `toggle`.
    UpSegment {
        addr: ObjectAddr,
        data: Vec<u8>,
        size: Option<usize>,
        toggle: bool,
    },
}

/// Most bytes a segmented upload may collect (guards against a server that never sets "last").
const MAX_SEGMENTED_BYTES: usize = 4096;

/// What the client wants done after a response or a timeout.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SdoStep {
    /// Send this request frame body and keep waiting.
    Send([u8; 8]),
    /// The request finished; if `abort` is set, send it to the server first.
    Done { result: Result<SdoResult, SdoFailure>, abort: Option<[u8; 8]> },
}

/// The SDO client for one server node: one request at a time.
#[derive(Debug, Clone)]
pub struct SdoClient {
    node: NodeId,
    timeout: Duration,
    transfer: Transfer,
    deadline: Option<Instant>,
}

impl SdoClient {
    /// A client for `node` with a per-request (and per-segment) timeout.
    pub fn new(node: NodeId, timeout: Duration) -> Self {
        Self { node, timeout, transfer: Transfer::Idle, deadline: None }
    }

    /// Whether no request is in flight.
    pub fn is_idle(&self) -> bool {
        matches!(self.transfer, Transfer::Idle)
    }

    /// Drop any transfer in flight (the node rebooted).
    pub fn cancel(&mut self) {
        self.transfer = Transfer::Idle;
        self.deadline = None;
    }

    /// The request frame to a body.
    pub fn frame(&self, body: [u8; 8]) -> CanFrame {
        Cob::SdoRequest(self.node).frame(&body)
    }

    /// Start a request at `now`; returns the first frame body to send.
    pub fn start(&mut self, now: Instant, req: SdoRequest) -> [u8; 8] {
        let body = match &req {
            SdoRequest::Upload(addr) => upload_request(*addr),
            SdoRequest::Download(addr, data) => match expedited_download(*addr, data) {
                Some(b) => b,
                None => {
                    // Segmented initiate with size indicated: cs 0x21, size u32 LE.
                    let mut b = [0u8; 8];
                    b[0] = 0x21;
                    addr.put(&mut b);
                    b[4..].copy_from_slice(&(data.len() as u32).to_le_bytes());
                    b
                }
            },
        };
        self.transfer = Transfer::Initiate { req };
        self.deadline = Some(now + self.timeout);
        body
    }

    /// When the request in flight times out.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.deadline
    }

    /// Check the timeout at `now`.
    pub fn handle_timeout(&mut self, now: Instant) -> Option<SdoStep> {
        let deadline = self.deadline?;
        if now < deadline {
            return None;
        }
        let addr = self.addr()?;
        self.cancel();
        Some(SdoStep::Done {
            result: Err(SdoFailure::Timeout),
            abort: Some(abort_bytes(addr, AbortCode::TIMEOUT)),
        })
    }

    fn addr(&self) -> Option<ObjectAddr> {
        match &self.transfer {
            Transfer::Idle => None,
            Transfer::Initiate { req } => Some(req.addr()),
            Transfer::DownSegment { addr, .. } | Transfer::UpSegment { addr, .. } => Some(*addr),
        }
    }

    fn fail(&mut self, addr: ObjectAddr, code: AbortCode) -> SdoStep {
        self.cancel();
        SdoStep::Done { result: Err(SdoFailure::Protocol(code)), abort: Some(abort_bytes(addr, code)) }
    }

    fn done(&mut self, result: SdoResult) -> SdoStep {
        self.cancel();
        SdoStep::Done { result: Ok(result), abort: None }
    }

    /// A response body from the server (frames of `0x580 + node`, any DLC) at `now`.
    pub fn handle_response(&mut self, now: Instant, data: &[u8]) -> Option<SdoStep> {
        let addr = self.addr()?;
        let mut r = [0u8; 8];
        let n = data.len().min(8);
        r[..n].copy_from_slice(&data[..n]);
        if n == 0 {
            return Some(self.fail(addr, AbortCode::BAD_COMMAND));
        }
        if r[0] == 0x80 {
            if ObjectAddr::of(&r) != addr && matches!(self.transfer, Transfer::Initiate { .. }) {
                tracing::debug!(%addr, got = %ObjectAddr::of(&r), "stale SDO abort ignored");
                return None;
            }
            self.cancel();
            let code = AbortCode(u32::from_le_bytes([r[4], r[5], r[6], r[7]]));
            return Some(SdoStep::Done { result: Err(SdoFailure::Aborted(code)), abort: None });
        }
        // A stale initiate response (to a request abandoned after a timeout or a node reset)
        // names another object: ignore it and keep waiting for ours.
        if matches!(self.transfer, Transfer::Initiate { .. })
            && r[0] & 0xE0 != 0
            && ObjectAddr::of(&r) != addr
        {
            tracing::debug!(%addr, got = %ObjectAddr::of(&r), "stale SDO response ignored");
            return None;
        }
        self.deadline = Some(now + self.timeout);
        let transfer = std::mem::replace(&mut self.transfer, Transfer::Idle);
        match transfer {
            Transfer::Idle => None,
            Transfer::Initiate { req: SdoRequest::Download(_, data) } => {
                if r[0] != 0x60 || ObjectAddr::of(&r) != addr {
                    return Some(self.fail(addr, AbortCode::BAD_COMMAND));
                }
                if data.len() <= 4 && !data.is_empty() {
                    return Some(self.done(SdoResult::Written));
                }
                Some(self.next_down_segment(addr, data, 0, false))
            }
            Transfer::Initiate { req: SdoRequest::Upload(_) } => {
                if r[0] & 0xE0 != 0x40 || ObjectAddr::of(&r) != addr {
                    return Some(self.fail(addr, AbortCode::BAD_COMMAND));
                }
                let expedited = r[0] & 0x02 != 0;
                let size_indicated = r[0] & 0x01 != 0;
                if expedited {
                    let len = if size_indicated { 4 - usize::from((r[0] >> 2) & 0x03) } else { 4 };
                    return Some(self.done(SdoResult::Read(r[4..4 + len].to_vec())));
                }
                let size = size_indicated.then(|| u32::from_le_bytes([r[4], r[5], r[6], r[7]]) as usize);
                if size.is_some_and(|s| s > MAX_SEGMENTED_BYTES) {
                    return Some(self.fail(addr, AbortCode(0x0504_0005)));
                }
                self.transfer = Transfer::UpSegment { addr, data: Vec::new(), size, toggle: false };
                Some(SdoStep::Send(Self::upload_segment_request(false)))
            }
            Transfer::DownSegment { addr, data, sent, toggle, last_len } => {
                // Download segment response: 0x20 | t << 4.
                if r[0] & 0xE0 != 0x20 {
                    return Some(self.fail(addr, AbortCode::BAD_COMMAND));
                }
                if (r[0] & 0x10 != 0) != toggle {
                    return Some(self.fail(addr, AbortCode::TOGGLE));
                }
                let sent = sent + last_len;
                if sent >= data.len() {
                    return Some(self.done(SdoResult::Written));
                }
                Some(self.next_down_segment(addr, data, sent, !toggle))
            }
            Transfer::UpSegment { addr, mut data, size, toggle } => {
                // Upload segment response: 0x00 | t << 4 | n << 1 | c.
                if r[0] & 0xE0 != 0x00 {
                    return Some(self.fail(addr, AbortCode::BAD_COMMAND));
                }
                if (r[0] & 0x10 != 0) != toggle {
                    return Some(self.fail(addr, AbortCode::TOGGLE));
                }
                let len = 7 - usize::from((r[0] >> 1) & 0x07);
                data.extend_from_slice(&r[1..1 + len]);
                if data.len() > MAX_SEGMENTED_BYTES {
                    return Some(self.fail(addr, AbortCode(0x0504_0005)));
                }
                if r[0] & 0x01 != 0 {
                    if size.is_some_and(|s| s != data.len()) {
                        return Some(self.fail(addr, AbortCode::LENGTH));
                    }
                    return Some(self.done(SdoResult::Read(data)));
                }
                self.transfer = Transfer::UpSegment { addr, data, size, toggle: !toggle };
                Some(SdoStep::Send(Self::upload_segment_request(!toggle)))
            }
        }
    }

    fn upload_segment_request(toggle: bool) -> [u8; 8] {
        let mut b = [0u8; 8];
        b[0] = 0x60 | if toggle { 0x10 } else { 0 };
        b
    }

    fn next_down_segment(&mut self, addr: ObjectAddr, data: Vec<u8>, sent: usize, toggle: bool) -> SdoStep {
        let chunk = &data[sent..data.len().min(sent + 7)];
        let last = sent + chunk.len() >= data.len();
        let mut b = [0u8; 8];
        b[0] = (if toggle { 0x10 } else { 0 }) | (((7 - chunk.len()) as u8) << 1) | u8::from(last);
        b[1..1 + chunk.len()].copy_from_slice(chunk);
        let last_len = chunk.len();
        self.transfer = Transfer::DownSegment { addr, data, sent, toggle, last_len };
        SdoStep::Send(b)
    }
}

/// An object dictionary as an SDO server sees it: reads and writes by address, refusing with an
/// abort code.
pub trait ObjectDictionary {
    /// The value's bytes (little-endian, as on the wire).
    fn read(&mut self, addr: ObjectAddr) -> Result<Vec<u8>, AbortCode>;
    /// Store the value's bytes.
    fn write(&mut self, addr: ObjectAddr, data: &[u8]) -> Result<(), AbortCode>;
}

#[derive(Debug, Clone, Default)]
enum ServerTransfer {
    #[default]
    Idle,
    Download {
        addr: ObjectAddr,
        data: Vec<u8>,
        size: Option<usize>,
        toggle: bool,
    },
    Upload {
        addr: ObjectAddr,
        data: Vec<u8>,
        offset: usize,
        toggle: bool,
    },
}

/// The SDO server of one node (expedited and segmented; no block transfer).
#[derive(Debug, Clone, Default)]
pub struct SdoServer {
    transfer: ServerTransfer,
}

impl SdoServer {
    /// A server with no transfer in progress.
    pub fn new() -> Self {
        Self::default()
    }

    /// Handle one request body; returns the response body (`None` for a client abort).
    pub fn handle_request(&mut self, data: &[u8], od: &mut dyn ObjectDictionary) -> Option<[u8; 8]> {
        let mut r = [0u8; 8];
        let n = data.len().min(8);
        r[..n].copy_from_slice(&data[..n]);
        let addr = ObjectAddr::of(&r);
        let transfer = std::mem::take(&mut self.transfer);
        match (r[0] >> 5, transfer) {
            (4, _) => None, // client abort
            (1, _) => {
                // Download initiate.
                let expedited = r[0] & 0x02 != 0;
                if expedited {
                    let len = if r[0] & 0x01 != 0 { 4 - usize::from((r[0] >> 2) & 0x03) } else { 4 };
                    return Some(match od.write(addr, &r[4..4 + len]) {
                        Ok(()) => Self::ok_download(addr),
                        Err(code) => abort_bytes(addr, code),
                    });
                }
                let size = (r[0] & 0x01 != 0).then(|| u32::from_le_bytes([r[4], r[5], r[6], r[7]]) as usize);
                if size.is_some_and(|s| s > MAX_SEGMENTED_BYTES) {
                    return Some(abort_bytes(addr, AbortCode(0x0504_0005)));
                }
                self.transfer = ServerTransfer::Download { addr, data: Vec::new(), size, toggle: false };
                Some(Self::ok_download(addr))
            }
            (0, ServerTransfer::Download { addr, mut data, size, toggle }) => {
                if (r[0] & 0x10 != 0) != toggle {
                    return Some(abort_bytes(addr, AbortCode::TOGGLE));
                }
                let len = 7 - usize::from((r[0] >> 1) & 0x07);
                data.extend_from_slice(&r[1..1 + len]);
                let reply = [0x20 | if toggle { 0x10 } else { 0 }, 0, 0, 0, 0, 0, 0, 0];
                if r[0] & 0x01 == 0 {
                    if data.len() > MAX_SEGMENTED_BYTES {
                        return Some(abort_bytes(addr, AbortCode(0x0504_0005)));
                    }
                    self.transfer = ServerTransfer::Download { addr, data, size, toggle: !toggle };
                    return Some(reply);
                }
                if size.is_some_and(|s| s != data.len()) {
                    return Some(abort_bytes(addr, AbortCode::LENGTH));
                }
                Some(match od.write(addr, &data) {
                    Ok(()) => reply,
                    Err(code) => abort_bytes(addr, code),
                })
            }
            (2, _) => {
                // Upload initiate.
                let value = match od.read(addr) {
                    Ok(v) => v,
                    Err(code) => return Some(abort_bytes(addr, code)),
                };
                let mut b = [0u8; 8];
                addr.put(&mut b);
                if !value.is_empty() && value.len() <= 4 {
                    b[0] = 0x43 | (((4 - value.len()) as u8) << 2);
                    b[4..4 + value.len()].copy_from_slice(&value);
                } else {
                    b[0] = 0x41;
                    b[4..].copy_from_slice(&(value.len() as u32).to_le_bytes());
                    self.transfer = ServerTransfer::Upload { addr, data: value, offset: 0, toggle: false };
                }
                Some(b)
            }
            (3, ServerTransfer::Upload { addr, data, offset, toggle }) => {
                if (r[0] & 0x10 != 0) != toggle {
                    return Some(abort_bytes(addr, AbortCode::TOGGLE));
                }
                let end = data.len().min(offset + 7);
                let chunk = &data[offset..end];
                let last = end >= data.len();
                let mut b = [0u8; 8];
                b[0] = (if toggle { 0x10 } else { 0 }) | (((7 - chunk.len()) as u8) << 1) | u8::from(last);
                b[1..1 + chunk.len()].copy_from_slice(chunk);
                if !last {
                    self.transfer = ServerTransfer::Upload { addr, data, offset: end, toggle: !toggle };
                }
                Some(b)
            }
            _ => Some(abort_bytes(addr, AbortCode::BAD_COMMAND)),
        }
    }

    fn ok_download(addr: ObjectAddr) -> [u8; 8] {
        let mut b = [0u8; 8];
        b[0] = 0x60;
        addr.put(&mut b);
        b
    }
}

#[cfg(test)]
mod tests;
