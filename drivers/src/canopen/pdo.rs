//! PDO mapping (CiA 301): mapping entries `index << 16 | sub << 8 | bits`, the standard remap
//! procedure as a list of SDO writes, packing of mapped values, and the profile-velocity mapping
//! this project uses (RPDO1 = 6040 + 60FF, TPDO1 = 6041 + 606C, TPDO2 = 6064; notes B2, B3).

use super::frame::NodeId;
use super::sdo::{ObjectAddr, SdoRequest};

/// COB-ID bit 31: the PDO is not valid (disabled) — set while remapping.
pub const COB_ID_INVALID: u32 = 1 << 31;
/// Transmission type 1: synchronous, every SYNC.
pub const TRANSMISSION_SYNC_EVERY: u8 = 1;

/// One mapped object.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct MapEntry {
    /// The object.
    pub addr: ObjectAddr,
    /// Its length in bits (8, 16 or 32 here).
    pub bits: u8,
}

impl MapEntry {
    /// An entry for `index:sub` of `bits`.
    pub const fn new(index: u16, sub: u8, bits: u8) -> Self {
        Self { addr: ObjectAddr::new(index, sub), bits }
    }

    /// The u32 stored in 0x1600+n / 0x1A00+n.
    pub fn raw(self) -> u32 {
        (u32::from(self.addr.index) << 16) | (u32::from(self.addr.sub) << 8) | u32::from(self.bits)
    }

    /// From the stored u32.
    pub fn from_raw(raw: u32) -> Self {
        Self::new((raw >> 16) as u16, (raw >> 8) as u8, raw as u8)
    }
}

/// Controlword 0x6040 (u16).
pub const CONTROLWORD: MapEntry = MapEntry::new(0x6040, 0, 16);
/// Statusword 0x6041 (u16).
pub const STATUSWORD: MapEntry = MapEntry::new(0x6041, 0, 16);
/// Target velocity 0x60FF (i32).
pub const TARGET_VELOCITY: MapEntry = MapEntry::new(0x60FF, 0, 32);
/// Velocity actual value 0x606C (i32).
pub const VELOCITY_ACTUAL: MapEntry = MapEntry::new(0x606C, 0, 32);
/// Position actual value 0x6064 (i32).
pub const POSITION_ACTUAL: MapEntry = MapEntry::new(0x6064, 0, 32);
/// Digital inputs 0x60FD (u32; CiA 402: bit 0 negative limit, 1 positive limit, 2 home, 3
/// interlock, 16–31 manufacturer-specific).
pub const DIGITAL_INPUTS: MapEntry = MapEntry::new(0x60FD, 0, 32);

/// RPDO1 of the profile-velocity set: controlword + target velocity.
pub const RPDO1_MAP: [MapEntry; 2] = [CONTROLWORD, TARGET_VELOCITY];
/// TPDO1: statusword + velocity actual.
pub const TPDO1_MAP: [MapEntry; 2] = [STATUSWORD, VELOCITY_ACTUAL];
/// TPDO2: position actual.
pub const TPDO2_MAP: [MapEntry; 1] = [POSITION_ACTUAL];
/// TPDO2 when the drive's digital inputs are watched (an e-stop wired to one): position actual and
/// digital inputs, 8 bytes.
pub const TPDO2_INPUTS_MAP: [MapEntry; 2] = [POSITION_ACTUAL, DIGITAL_INPUTS];

/// Which direction a PDO goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PdoDirection {
    /// Master → drive (0x1400 / 0x1600).
    Receive,
    /// Drive → master (0x1800 / 0x1A00).
    Transmit,
}

impl PdoDirection {
    /// The communication parameter index of PDO `n` (1-based).
    pub fn comm_index(self, n: u8) -> u16 {
        let base = match self {
            PdoDirection::Receive => 0x1400,
            PdoDirection::Transmit => 0x1800,
        };
        base + u16::from(n.saturating_sub(1))
    }

    /// The mapping parameter index of PDO `n` (1-based).
    pub fn map_index(self, n: u8) -> u16 {
        self.comm_index(n) + 0x200
    }

    /// The default COB-ID of PDO `n` (1..=4) of `node`.
    pub fn default_cob_id(self, n: u8, node: NodeId) -> u32 {
        let base: u32 = match self {
            PdoDirection::Transmit => 0x180,
            PdoDirection::Receive => 0x200,
        };
        base + 0x100 * u32::from(n.clamp(1, 4) - 1) + u32::from(node)
    }
}

/// The remap procedure (notes B2): disable (COB-ID bit 31) → transmission type → mapping count 0 →
/// entries → count → enable. The node must be in PRE-OPERATIONAL.
pub fn remap_requests(
    dir: PdoDirection,
    n: u8,
    node: NodeId,
    transmission_type: u8,
    entries: &[MapEntry],
) -> Vec<SdoRequest> {
    let comm = dir.comm_index(n);
    let map = dir.map_index(n);
    let cob = dir.default_cob_id(n, node);
    let mut reqs = vec![
        SdoRequest::Download(ObjectAddr::new(comm, 1), (cob | COB_ID_INVALID).to_le_bytes().to_vec()),
        SdoRequest::Download(ObjectAddr::new(comm, 2), vec![transmission_type]),
        SdoRequest::Download(ObjectAddr::new(map, 0), vec![0]),
    ];
    // A PDO holds at most 8 entries (sub-indices 1..=8).
    let entries = &entries[..entries.len().min(8)];
    for (sub, e) in (1u8..).zip(entries) {
        reqs.push(SdoRequest::Download(ObjectAddr::new(map, sub), e.raw().to_le_bytes().to_vec()));
    }
    reqs.push(SdoRequest::Download(ObjectAddr::new(map, 0), vec![entries.len() as u8]));
    reqs.push(SdoRequest::Download(ObjectAddr::new(comm, 1), cob.to_le_bytes().to_vec()));
    reqs
}

/// Pack values (low bits of each, little-endian) into a PDO payload; `None` if the mapping is
/// not byte-aligned, longer than 8 bytes, or the counts differ.
pub fn pack(entries: &[MapEntry], values: &[u64]) -> Option<Vec<u8>> {
    if entries.len() != values.len() {
        return None;
    }
    let mut out = Vec::with_capacity(8);
    for (e, v) in entries.iter().zip(values) {
        let bytes = usize::from(e.bits / 8);
        if e.bits % 8 != 0 || bytes == 0 || bytes > 8 {
            return None;
        }
        out.extend_from_slice(&v.to_le_bytes()[..bytes]);
    }
    (out.len() <= 8).then_some(out)
}

/// Unpack a PDO payload into one value per entry (zero-extended); `None` if it is too short or
/// the mapping is not byte-aligned.
pub fn unpack(entries: &[MapEntry], data: &[u8]) -> Option<Vec<u64>> {
    let mut at = 0usize;
    let mut out = Vec::with_capacity(entries.len());
    for e in entries {
        let bytes = usize::from(e.bits / 8);
        if e.bits % 8 != 0 || bytes == 0 || bytes > 8 {
            return None;
        }
        let chunk = data.get(at..at + bytes)?;
        let mut buf = [0u8; 8];
        buf[..bytes].copy_from_slice(chunk);
        out.push(u64::from_le_bytes(buf));
        at += bytes;
    }
    Some(out)
}

/// RPDO1 payload: controlword, target velocity (drive units).
pub fn encode_rpdo1(controlword: u16, target_velocity: i32) -> [u8; 6] {
    let c = controlword.to_le_bytes();
    let v = target_velocity.to_le_bytes();
    [c[0], c[1], v[0], v[1], v[2], v[3]]
}

/// TPDO1 payload → (statusword, velocity actual).
pub fn decode_tpdo1(data: &[u8]) -> Option<(u16, i32)> {
    match data {
        [s0, s1, v0, v1, v2, v3, ..] => {
            Some((u16::from_le_bytes([*s0, *s1]), i32::from_le_bytes([*v0, *v1, *v2, *v3])))
        }
        _ => None,
    }
}

/// TPDO2 payload → position actual (counts) and, when mapped, the digital inputs.
pub fn decode_tpdo2(data: &[u8]) -> Option<(i32, Option<u32>)> {
    match data {
        [p0, p1, p2, p3, i0, i1, i2, i3, ..] => {
            Some((i32::from_le_bytes([*p0, *p1, *p2, *p3]), Some(u32::from_le_bytes([*i0, *i1, *i2, *i3]))))
        }
        [p0, p1, p2, p3, ..] => Some((i32::from_le_bytes([*p0, *p1, *p2, *p3]), None)),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canopen_pdo_remap_procedure_order() {
        let reqs = remap_requests(PdoDirection::Receive, 1, 2, TRANSMISSION_SYNC_EVERY, &RPDO1_MAP);
        let expected = vec![
            SdoRequest::Download(ObjectAddr::new(0x1400, 1), 0x8000_0202u32.to_le_bytes().to_vec()),
            SdoRequest::Download(ObjectAddr::new(0x1400, 2), vec![1]),
            SdoRequest::Download(ObjectAddr::new(0x1600, 0), vec![0]),
            SdoRequest::Download(ObjectAddr::new(0x1600, 1), 0x6040_0010u32.to_le_bytes().to_vec()),
            SdoRequest::Download(ObjectAddr::new(0x1600, 2), 0x60FF_0020u32.to_le_bytes().to_vec()),
            SdoRequest::Download(ObjectAddr::new(0x1600, 0), vec![2]),
            SdoRequest::Download(ObjectAddr::new(0x1400, 1), 0x0000_0202u32.to_le_bytes().to_vec()),
        ];
        assert_eq!(reqs, expected);
        assert_eq!(PdoDirection::Transmit.default_cob_id(2, 1), 0x281);
        assert_eq!(PdoDirection::Transmit.map_index(2), 0x1A01);
    }

    #[test]
    fn canopen_pdo_pack_unpack() {
        let p = pack(&TPDO1_MAP, &[0x0627, (-1000i32) as u32 as u64]).unwrap();
        assert_eq!(decode_tpdo1(&p), Some((0x0627, -1000)));
        assert_eq!(unpack(&TPDO1_MAP, &p), Some(vec![0x0627, 0xFFFF_FC18]));
        assert_eq!(unpack(&TPDO1_MAP, &p[..5]), None);
        assert_eq!(encode_rpdo1(0x0F, 5), [0x0F, 0, 5, 0, 0, 0]);
        assert_eq!(pack(&[MapEntry::new(1, 0, 12)], &[0]), None);
        assert_eq!(MapEntry::from_raw(0x6064_0020), POSITION_ACTUAL);
    }
}
