//! The TiM5xx command set (devices.md §1, notes §2): requests the driver sends and the replies the
//! device gives, each encodable and decodable in both dialects (the mock uses the other half).

use serde::Serialize;

use super::args::{ArgReader, ArgWriter};
use super::error::{DecodeError, ErrorCode};
use super::framing::Dialect;
use super::scan::ScanTelegram;

/// Password hash of the "authorized client" level (notes §2: sick_scan_xd CMD_SET_ACCESS_MODE_X,
/// sick_tim rebootScanner).
pub const CLIENT_PASSWORD_HASH: u32 = 0xF472_4744;
/// User level 3 = authorized client (Wireshark `access_mode_user_level_vals`).
pub const CLIENT_LEVEL: u8 = 3;

/// A readable variable (`sRN <name>`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum Variable {
    ScanData,
    DeviceIdent,
    SerialNumber,
    FirmwareVersion,
    DeviceState,
    OperatingHours,
    PowerOnCount,
    LocationName,
    OutputRange,
    ScanDataConfig,
}

const VARIABLES: [(Variable, &str); 10] = [
    (Variable::ScanData, "LMDscandata"),
    (Variable::DeviceIdent, "DeviceIdent"),
    (Variable::SerialNumber, "SerialNumber"),
    (Variable::FirmwareVersion, "FirmwareVersion"),
    (Variable::DeviceState, "SCdevicestate"),
    (Variable::OperatingHours, "ODoprh"),
    (Variable::PowerOnCount, "ODpwrc"),
    (Variable::LocationName, "LocationName"),
    (Variable::OutputRange, "LMPoutputRange"),
    (Variable::ScanDataConfig, "LMDscandatacfg"),
];

impl Variable {
    /// The SOPAS variable name.
    pub fn name(self) -> &'static str {
        VARIABLES.iter().find(|(v, _)| *v == self).map_or("", |(_, n)| n)
    }

    fn from_name(name: &str) -> Option<Self> {
        VARIABLES.iter().find(|(_, n)| *n == name).map(|(v, _)| *v)
    }
}

/// One angular sector of `LMPoutputRange`: resolution and limits in 1/10000°, device frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Sector {
    pub resolution_1e4deg: u32,
    pub start_1e4deg: i32,
    pub stop_1e4deg: i32,
}

/// `LMPoutputRange` (notes §2: u16 count, then per sector u32 resolution, i32 start, i32 stop).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct OutputRange {
    pub sectors: Vec<Sector>,
}

impl OutputRange {
    /// The full −45°..225° field at a resolution (2710 = 1° for a TiM55x, D05 for TiM56x/57x).
    pub fn full_field(resolution_1e4deg: u32) -> Self {
        Self { sectors: vec![Sector { resolution_1e4deg, start_1e4deg: -450_000, stop_1e4deg: 2_250_000 }] }
    }

    fn decode(r: &mut ArgReader<'_>) -> Result<Self, DecodeError> {
        let n = r.u16("number of sectors")?;
        if n > 4 {
            return Err(DecodeError::OutOfRange { what: "number of sectors", value: n.into() });
        }
        let mut sectors = Vec::new();
        for _ in 0..n {
            sectors.push(Sector {
                resolution_1e4deg: r.u32("resolution")?,
                start_1e4deg: r.i32("start angle")?,
                stop_1e4deg: r.i32("stop angle")?,
            });
        }
        Ok(Self { sectors })
    }

    fn encode(&self, w: &mut ArgWriter) {
        w.u16(self.sectors.len() as u16);
        for s in &self.sectors {
            w.u32(s.resolution_1e4deg);
            w.i32(s.start_1e4deg);
            w.i32(s.stop_1e4deg);
        }
    }
}

/// `LMDscandatacfg` (Wireshark `dissect_sick_cola_write`): 13 bytes. The u16 fields travel as two
/// byte tokens in CoLa-A, as sick_scan_xd writes them (`01 00 1 0 0 00 00 …`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ScanDataConfig {
    pub output_channel: u16,
    pub remission: u8,
    pub resolution: u8,
    pub unit: u8,
    pub encoder: u16,
    pub position: u8,
    pub device_name: u8,
    pub comment: u8,
    pub time: u8,
    pub output_interval: u16,
}

impl ScanDataConfig {
    /// The value sick_scan_xd writes to a TiM5xx (start-up log, 04_command_vectors.txt B).
    pub const SICK_SCAN_XD: Self = Self {
        output_channel: 0x0100,
        remission: 1,
        resolution: 0,
        unit: 0,
        encoder: 0,
        position: 0,
        device_name: 0,
        comment: 0,
        time: 1,
        output_interval: 1,
    };

    fn u16_as_bytes(r: &mut ArgReader<'_>, what: &'static str) -> Result<u16, DecodeError> {
        Ok(u16::from_be_bytes([r.u8(what)?, r.u8(what)?]))
    }

    fn decode(r: &mut ArgReader<'_>) -> Result<Self, DecodeError> {
        Ok(Self {
            output_channel: Self::u16_as_bytes(r, "output channel")?,
            remission: r.u8("remission")?,
            resolution: r.u8("resolution")?,
            unit: r.u8("unit")?,
            encoder: Self::u16_as_bytes(r, "encoder")?,
            position: r.u8("position")?,
            device_name: r.u8("device name")?,
            comment: r.u8("comment")?,
            time: r.u8("time")?,
            output_interval: Self::u16_as_bytes(r, "output interval")?,
        })
    }

    fn encode(&self, w: &mut ArgWriter) {
        let [a, b] = self.output_channel.to_be_bytes();
        w.u8(a);
        w.u8(b);
        w.u8(self.remission);
        w.u8(self.resolution);
        w.u8(self.unit);
        let [a, b] = self.encoder.to_be_bytes();
        w.u8(a);
        w.u8(b);
        for v in [self.position, self.device_name, self.comment, self.time] {
            w.u8(v);
        }
        let [a, b] = self.output_interval.to_be_bytes();
        w.u8(a);
        w.u8(b);
    }
}

/// A request to the device.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub enum Command {
    /// `sMN SetAccessMode <level> <hash>` → `sAN SetAccessMode 0|1`.
    SetAccessMode { level: u8, password_hash: u32 },
    /// `sRI <index>` (sick_tim sends `sRI 0` for the device identity).
    ReadByIndex(u16),
    /// `sRN <variable>`.
    Read(Variable),
    /// `sWN LMPoutputRange …`.
    WriteOutputRange(OutputRange),
    /// `sWN LMDscandatacfg …`.
    WriteScanDataConfig(ScanDataConfig),
    /// `sWN EIHstCola 0|1`.
    SetDialect(Dialect),
    /// `sEN LMDscandata 1|0`.
    ScanDataEvents(bool),
    /// `sMN Run`: leave configuration mode.
    Run,
    /// `sMN LMCstartmeas`.
    StartMeasurement,
    /// `sMN LMCstopmeas`.
    StopMeasurement,
    /// `sMN mSCreboot`.
    Reboot,
    /// `sMN mEEwriteall`.
    WriteEeprom,
}

fn bool_u8(r: &mut ArgReader<'_>, what: &'static str) -> Result<bool, DecodeError> {
    match r.u8(what)? {
        0 => Ok(false),
        1 => Ok(true),
        v => Err(DecodeError::OutOfRange { what, value: v.into() }),
    }
}

fn dialect_u8(r: &mut ArgReader<'_>) -> Result<Dialect, DecodeError> {
    Ok(if bool_u8(r, "EIHstCola")? { Dialect::ColaB } else { Dialect::ColaA })
}

/// Command type and name from a payload, plus the argument bytes.
struct Header<'a> {
    kind: &'a str,
    name: &'a str,
    args: &'a [u8],
}

fn split_header(payload: &[u8]) -> Result<Header<'_>, DecodeError> {
    let kind = payload.get(..3).and_then(|k| std::str::from_utf8(k).ok()).ok_or(DecodeError::BadHeader)?;
    if kind == "sFA" {
        return Ok(Header { kind, name: "", args: &payload[3..] });
    }
    if payload.get(3) != Some(&b' ') {
        return Err(DecodeError::BadHeader);
    }
    let rest = &payload[4..];
    let end = rest.iter().position(|&b| b == b' ').unwrap_or(rest.len());
    let name = std::str::from_utf8(&rest[..end]).map_err(|_| DecodeError::BadHeader)?;
    if name.is_empty() || !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
        return Err(DecodeError::BadHeader);
    }
    let args = rest.get(end + 1..).unwrap_or(&[]);
    Ok(Header { kind, name, args })
}

/// `kind name` + arguments. CoLa-A tokens carry their own leading space; CoLa-B puts one space
/// before binary arguments, and replies keep it even without arguments (notes §1.2).
fn build(
    dialect: Dialect,
    kind: &str,
    name: &str,
    is_reply: bool,
    fill: impl FnOnce(&mut ArgWriter),
) -> Vec<u8> {
    let mut w = ArgWriter::new(dialect);
    fill(&mut w);
    let args = w.into_bytes();
    let mut out = format!("{kind} {name}").into_bytes();
    match dialect {
        Dialect::ColaA => out.extend_from_slice(&args),
        Dialect::ColaB => {
            if is_reply || !args.is_empty() {
                out.push(b' ');
            }
            out.extend_from_slice(&args);
        }
    }
    out
}

impl Command {
    /// `sRN LMPoutputRange`-style label for logs and error reports.
    pub fn label(&self) -> String {
        let (kind, name) = self.kind_name();
        format!("{kind} {name}")
    }

    fn kind_name(&self) -> (&'static str, String) {
        match self {
            Self::SetAccessMode { .. } => ("sMN", "SetAccessMode".into()),
            Self::ReadByIndex(i) => ("sRI", i.to_string()),
            Self::Read(v) => ("sRN", v.name().into()),
            Self::WriteOutputRange(_) => ("sWN", "LMPoutputRange".into()),
            Self::WriteScanDataConfig(_) => ("sWN", "LMDscandatacfg".into()),
            Self::SetDialect(_) => ("sWN", "EIHstCola".into()),
            Self::ScanDataEvents(_) => ("sEN", "LMDscandata".into()),
            Self::Run => ("sMN", "Run".into()),
            Self::StartMeasurement => ("sMN", "LMCstartmeas".into()),
            Self::StopMeasurement => ("sMN", "LMCstopmeas".into()),
            Self::Reboot => ("sMN", "mSCreboot".into()),
            Self::WriteEeprom => ("sMN", "mEEwriteall".into()),
        }
    }

    /// The frame payload of this request.
    pub fn encode(&self, dialect: Dialect) -> Vec<u8> {
        let (kind, name) = self.kind_name();
        build(dialect, kind, &name, false, |w| match self {
            Self::SetAccessMode { level, password_hash } => {
                w.u8(*level);
                w.u32(*password_hash);
            }
            Self::WriteOutputRange(r) => r.encode(w),
            Self::WriteScanDataConfig(c) => c.encode(w),
            Self::SetDialect(d) => w.u8(d.eih_value()),
            Self::ScanDataEvents(on) => w.u8(u8::from(*on)),
            _ => {}
        })
    }

    /// Decodes a request (device side).
    pub fn decode(dialect: Dialect, payload: &[u8]) -> Result<Self, DecodeError> {
        let h = split_header(payload)?;
        let mut r = ArgReader::new(dialect, h.args);
        let unknown = || DecodeError::UnknownCommand { kind: h.kind.into(), name: h.name.into() };
        let cmd = match (h.kind, h.name) {
            ("sMN", "SetAccessMode") => {
                Self::SetAccessMode { level: r.u8("user level")?, password_hash: r.u32("password hash")? }
            }
            ("sRI", index) => Self::ReadByIndex(index.parse().map_err(|_| unknown())?),
            ("sRN", name) => Self::Read(Variable::from_name(name).ok_or_else(unknown)?),
            ("sWN", "LMPoutputRange") => Self::WriteOutputRange(OutputRange::decode(&mut r)?),
            ("sWN", "LMDscandatacfg") => Self::WriteScanDataConfig(ScanDataConfig::decode(&mut r)?),
            ("sWN", "EIHstCola") => Self::SetDialect(dialect_u8(&mut r)?),
            ("sEN", "LMDscandata") => Self::ScanDataEvents(bool_u8(&mut r, "event switch")?),
            ("sMN", "Run") => Self::Run,
            ("sMN", "LMCstartmeas") => Self::StartMeasurement,
            ("sMN", "LMCstopmeas") => Self::StopMeasurement,
            ("sMN", "mSCreboot") => Self::Reboot,
            ("sMN", "mEEwriteall") => Self::WriteEeprom,
            _ => return Err(unknown()),
        };
        r.finish()?;
        Ok(cmd)
    }
}

/// A telegram from the device.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub enum Reply {
    /// `sFA <code>`: the device refused the last command.
    Error(ErrorCode),
    /// `sAN SetAccessMode 1|0`.
    AccessMode {
        granted: bool,
    },
    /// `sRA <index> <name> <version>`, the answer to `sRI 0` (`sRA 0 6 TiM561 E V2.51-21.08.15`).
    IndexIdent {
        index: u16,
        name: String,
        version: String,
    },
    /// `sRA LMDscandata …` (poll) or `sSN LMDscandata …` (`event` = true, streamed).
    ScanData {
        event: bool,
        telegram: Box<ScanTelegram>,
    },
    /// `sEA LMDscandata 1|0`.
    ScanDataEvents {
        enabled: bool,
    },
    /// `sRA DeviceIdent <name> <version>`.
    DeviceIdent {
        name: String,
        version: String,
    },
    SerialNumber(String),
    FirmwareVersion(String),
    /// `SCdevicestate`: 0 busy, 1 ready, 2 error (sick_tim_common.cpp).
    DeviceState(u8),
    OperatingHours(u32),
    PowerOnCount(u32),
    LocationName(String),
    OutputRange(OutputRange),
    ScanDataConfig(ScanDataConfig),
    /// `sWA <variable>`: a write was accepted.
    WriteAck(String),
    /// `sAN Run 1|0`.
    Run {
        ok: bool,
    },
    /// `sAN LMCstartmeas <status>` (0 = no error).
    StartMeasurement {
        status: u8,
    },
    /// `sAN LMCstopmeas <status>`.
    StopMeasurement {
        status: u8,
    },
    /// `sAN mSCreboot`.
    Reboot,
    /// `sAN mEEwriteall 1|0`.
    EepromWritten {
        ok: bool,
    },
}

impl Reply {
    /// The name a reply answers (`LMDscandata`, `0` for `sRI 0`), empty for `sFA`.
    pub fn name(&self) -> String {
        self.kind_name().1
    }

    fn kind_name(&self) -> (&'static str, String) {
        let n = |s: &str| s.to_string();
        match self {
            Self::Error(_) => ("sFA", String::new()),
            Self::AccessMode { .. } => ("sAN", n("SetAccessMode")),
            Self::IndexIdent { index, .. } => ("sRA", index.to_string()),
            Self::ScanData { event: true, .. } => ("sSN", n("LMDscandata")),
            Self::ScanData { event: false, .. } => ("sRA", n("LMDscandata")),
            Self::ScanDataEvents { .. } => ("sEA", n("LMDscandata")),
            Self::DeviceIdent { .. } => ("sRA", n("DeviceIdent")),
            Self::SerialNumber(_) => ("sRA", n("SerialNumber")),
            Self::FirmwareVersion(_) => ("sRA", n("FirmwareVersion")),
            Self::DeviceState(_) => ("sRA", n("SCdevicestate")),
            Self::OperatingHours(_) => ("sRA", n("ODoprh")),
            Self::PowerOnCount(_) => ("sRA", n("ODpwrc")),
            Self::LocationName(_) => ("sRA", n("LocationName")),
            Self::OutputRange(_) => ("sRA", n("LMPoutputRange")),
            Self::ScanDataConfig(_) => ("sRA", n("LMDscandatacfg")),
            Self::WriteAck(name) => ("sWA", name.clone()),
            Self::Run { .. } => ("sAN", n("Run")),
            Self::StartMeasurement { .. } => ("sAN", n("LMCstartmeas")),
            Self::StopMeasurement { .. } => ("sAN", n("LMCstopmeas")),
            Self::Reboot => ("sAN", n("mSCreboot")),
            Self::EepromWritten { .. } => ("sAN", n("mEEwriteall")),
        }
    }

    /// The frame payload of this reply (device side).
    pub fn encode(&self, dialect: Dialect) -> Result<Vec<u8>, DecodeError> {
        if let Self::Error(code) = self {
            // Binary: `sFA` + u16 BE, no space; ASCII: `sFA <hex>` (notes §2.1).
            let mut out = b"sFA".to_vec();
            match dialect {
                Dialect::ColaA => out.extend_from_slice(format!(" {:X}", code.code()).as_bytes()),
                Dialect::ColaB => out.extend_from_slice(&code.code().to_be_bytes()),
            }
            return Ok(out);
        }
        let (kind, name) = self.kind_name();
        let mut result = Ok(());
        let out = build(dialect, kind, &name, true, |w| match self {
            Self::AccessMode { granted }
            | Self::Run { ok: granted }
            | Self::EepromWritten { ok: granted } => w.u8(u8::from(*granted)),
            Self::IndexIdent { name, version, .. } | Self::DeviceIdent { name, version } => {
                w.string(name);
                w.string(version);
            }
            Self::ScanData { telegram, .. } => result = telegram.encode(w),
            Self::ScanDataEvents { enabled } => w.u8(u8::from(*enabled)),
            Self::SerialNumber(s) | Self::FirmwareVersion(s) | Self::LocationName(s) => w.string(s),
            Self::DeviceState(s) => w.u8(*s),
            Self::OperatingHours(v) | Self::PowerOnCount(v) => w.u32(*v),
            Self::OutputRange(r) => r.encode(w),
            Self::ScanDataConfig(c) => c.encode(w),
            Self::StartMeasurement { status } | Self::StopMeasurement { status } => w.u8(*status),
            Self::WriteAck(_) | Self::Reboot | Self::Error(_) => {}
        });
        result.map(|()| out)
    }

    /// Decodes a device telegram.
    pub fn decode(dialect: Dialect, payload: &[u8]) -> Result<Self, DecodeError> {
        let h = split_header(payload)?;
        let mut r = ArgReader::new(dialect, h.args);
        let unknown = || DecodeError::UnknownCommand { kind: h.kind.into(), name: h.name.into() };
        let reply = match (h.kind, h.name) {
            ("sFA", _) => Self::Error(ErrorCode::from_code(r.u16("sFA code")?)),
            ("sAN", "SetAccessMode") => Self::AccessMode { granted: bool_u8(&mut r, "access granted")? },
            ("sRA" | "sSN", "LMDscandata") => {
                let telegram = Box::new(ScanTelegram::decode(&mut r)?);
                Self::ScanData { event: h.kind == "sSN", telegram }
            }
            ("sRA", name) if name.bytes().all(|b| b.is_ascii_digit()) => Self::IndexIdent {
                index: name.parse().map_err(|_| unknown())?,
                name: r.string("device name")?,
                version: r.string("device version")?,
            },
            ("sEA", "LMDscandata") => Self::ScanDataEvents { enabled: bool_u8(&mut r, "event switch")? },
            ("sRA", "DeviceIdent") => {
                Self::DeviceIdent { name: r.string("device name")?, version: r.string("device version")? }
            }
            ("sRA", "SerialNumber") => Self::SerialNumber(r.string("serial number")?),
            ("sRA", "FirmwareVersion") => Self::FirmwareVersion(r.string("firmware version")?),
            ("sRA", "SCdevicestate") => Self::DeviceState(r.u8("device state")?),
            ("sRA", "ODoprh") => Self::OperatingHours(r.u32("operating hours")?),
            ("sRA", "ODpwrc") => Self::PowerOnCount(r.u32("power-on count")?),
            ("sRA", "LocationName") => Self::LocationName(r.string("location name")?),
            ("sRA", "LMPoutputRange") => Self::OutputRange(OutputRange::decode(&mut r)?),
            ("sRA", "LMDscandatacfg") => Self::ScanDataConfig(ScanDataConfig::decode(&mut r)?),
            ("sWA", name) => Self::WriteAck(name.to_string()),
            ("sAN", "Run") => Self::Run { ok: bool_u8(&mut r, "run result")? },
            ("sAN", "LMCstartmeas") => Self::StartMeasurement { status: r.u8("start status")? },
            ("sAN", "LMCstopmeas") => Self::StopMeasurement { status: r.u8("stop status")? },
            ("sAN", "mSCreboot") => Self::Reboot,
            ("sAN", "mEEwriteall") => Self::EepromWritten { ok: bool_u8(&mut r, "eeprom result")? },
            _ => return Err(unknown()),
        };
        r.finish()?;
        Ok(reply)
    }

    /// Whether this reply answers `cmd` (by name; `sFA` answers anything).
    pub fn answers(&self, cmd: &Command) -> bool {
        let (kind, name) = self.kind_name();
        let (ckind, cname) = cmd.kind_name();
        let expected_kind = match ckind {
            "sRN" | "sRI" => "sRA",
            "sWN" => "sWA",
            "sMN" => "sAN",
            "sEN" => "sEA",
            _ => "",
        };
        kind == "sFA" || (kind == expected_kind && (name == cname || ckind == "sRI"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ascii_requests_have_no_trailing_space_and_binary_replies_keep_it() {
        assert_eq!(Command::Read(Variable::ScanData).encode(Dialect::ColaA), b"sRN LMDscandata");
        assert_eq!(Command::ScanDataEvents(true).encode(Dialect::ColaA), b"sEN LMDscandata 1");
        assert_eq!(Reply::WriteAck("EIHstCola".into()).encode(Dialect::ColaB).unwrap(), b"sWA EIHstCola ");
        assert_eq!(Reply::WriteAck("EIHstCola".into()).encode(Dialect::ColaA).unwrap(), b"sWA EIHstCola");
    }

    #[test]
    fn sfa_in_both_dialects() {
        assert_eq!(
            Reply::decode(Dialect::ColaB, b"sFA\x00\x08").unwrap(),
            Reply::Error(ErrorCode::BufferUnderflow)
        );
        assert_eq!(
            Reply::decode(Dialect::ColaA, b"sFA A").unwrap(),
            Reply::Error(ErrorCode::VariableWriteAccessDenied)
        );
        assert_eq!(Reply::Error(ErrorCode::BufferUnderflow).encode(Dialect::ColaB).unwrap(), b"sFA\x00\x08");
    }

    #[test]
    fn real_tim561_ascii_identity_replies_decode() {
        // 04_command_vectors.txt section C (sick_scan#4).
        assert_eq!(
            Reply::decode(Dialect::ColaA, b"sRA 0 6 TiM561 E V2.51-21.08.15").unwrap(),
            Reply::IndexIdent { index: 0, name: "TiM561".into(), version: "V2.51-21.08.15".into() }
        );
        assert_eq!(
            Reply::decode(Dialect::ColaA, b"sRA SerialNumber 8 16160456").unwrap(),
            Reply::SerialNumber("16160456".into())
        );
        assert_eq!(
            Reply::decode(Dialect::ColaA, b"sAN SetAccessMode 0").unwrap(),
            Reply::AccessMode { granted: false }
        );
    }

    #[test]
    fn trailing_bytes_are_rejected() {
        assert!(Reply::decode(Dialect::ColaB, b"sRA SCdevicestate \x00\x01").is_err());
        assert!(Reply::decode(Dialect::ColaA, b"sEA LMDscandata 1 7").is_err());
    }
}
