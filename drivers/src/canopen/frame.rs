//! The classic CAN 2.0 frame and the CiA 301 predefined connection set (which COB-ID is which
//! service), so every other module matches on [`Cob`] instead of on raw identifiers.

use thiserror::Error;

/// Largest 11-bit identifier.
pub const MAX_STANDARD_ID: u32 = 0x7FF;
/// Largest 29-bit identifier.
pub const MAX_EXTENDED_ID: u32 = 0x1FFF_FFFF;

/// A frame could not be built from its parts.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum FrameError {
    /// More than 8 data bytes.
    #[error("CAN frame with {0} data bytes (at most 8)")]
    TooLong(usize),
    /// An identifier out of range for its format.
    #[error("CAN identifier {id:#x} out of range (extended: {extended})")]
    BadId {
        /// The identifier.
        id: u32,
        /// Whether it was meant as a 29-bit identifier.
        extended: bool,
    },
}

/// One classic CAN data frame (no FD, no remote frames: CANopen here uses neither).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct CanFrame {
    id: u32,
    extended: bool,
    len: u8,
    data: [u8; 8],
}

impl CanFrame {
    /// A frame with an 11-bit identifier.
    pub fn new(id: u16, data: &[u8]) -> Result<Self, FrameError> {
        Self::with_id(u32::from(id), false, data)
    }

    /// A frame with an 11-bit (`extended == false`) or 29-bit identifier.
    pub fn with_id(id: u32, extended: bool, data: &[u8]) -> Result<Self, FrameError> {
        let max = if extended { MAX_EXTENDED_ID } else { MAX_STANDARD_ID };
        if id > max {
            return Err(FrameError::BadId { id, extended });
        }
        if data.len() > 8 {
            return Err(FrameError::TooLong(data.len()));
        }
        let mut buf = [0u8; 8];
        buf[..data.len()].copy_from_slice(data);
        // len <= 8 checked above.
        Ok(Self { id, extended, len: data.len() as u8, data: buf })
    }

    /// The identifier (11 or 29 bits).
    pub fn id(&self) -> u32 {
        self.id
    }

    /// Whether the identifier is a 29-bit one.
    pub fn is_extended(&self) -> bool {
        self.extended
    }

    /// The data bytes (0..=8).
    pub fn data(&self) -> &[u8] {
        &self.data[..usize::from(self.len)]
    }

    /// The data padded with zeros to 8 bytes (SDO decoders read fixed offsets; some devices send
    /// DLC < 8, notes B2).
    pub(crate) fn data8(&self) -> [u8; 8] {
        self.data
    }

    /// The service this frame belongs to in the predefined connection set.
    pub fn cob(&self) -> Cob {
        if self.extended { Cob::Other(self.id) } else { Cob::from_id(self.id) }
    }
}

/// A CANopen node id, 1..=127.
pub type NodeId = u8;

/// The CiA 301 predefined connection set (notes B2): function code in bits 7..10, node in 0..6.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Cob {
    /// NMT command, 0x000.
    Nmt,
    /// SYNC, 0x080.
    Sync,
    /// Emergency of a node, 0x080 + id.
    Emcy(NodeId),
    /// TIME, 0x100.
    Time,
    /// Transmit PDO `n` (1..=4) of a node (drive → master), 0x180/0x280/0x380/0x480 + id.
    Tpdo(u8, NodeId),
    /// Receive PDO `n` (1..=4) of a node (master → drive), 0x200/0x300/0x400/0x500 + id.
    Rpdo(u8, NodeId),
    /// SDO response of a node's server, 0x580 + id.
    SdoResponse(NodeId),
    /// SDO request to a node's server, 0x600 + id.
    SdoRequest(NodeId),
    /// Heartbeat or boot-up of a node, 0x700 + id.
    Heartbeat(NodeId),
    /// Anything else.
    Other(u32),
}

impl Cob {
    /// Classify an 11-bit identifier.
    pub fn from_id(id: u32) -> Self {
        let node = (id & 0x7F) as u8;
        match (id >> 7, node) {
            (0, 0) => Cob::Nmt,
            (1, 0) => Cob::Sync,
            (1, n) => Cob::Emcy(n),
            (2, 0) => Cob::Time,
            (3, n) if n != 0 => Cob::Tpdo(1, n),
            (4, n) if n != 0 => Cob::Rpdo(1, n),
            (5, n) if n != 0 => Cob::Tpdo(2, n),
            (6, n) if n != 0 => Cob::Rpdo(2, n),
            (7, n) if n != 0 => Cob::Tpdo(3, n),
            (8, n) if n != 0 => Cob::Rpdo(3, n),
            (9, n) if n != 0 => Cob::Tpdo(4, n),
            (10, n) if n != 0 => Cob::Rpdo(4, n),
            (11, n) if n != 0 => Cob::SdoResponse(n),
            (12, n) if n != 0 => Cob::SdoRequest(n),
            (14, n) if n != 0 => Cob::Heartbeat(n),
            _ => Cob::Other(id),
        }
    }

    /// The 11-bit identifier (for `Other`, the value it holds, masked to 11 bits).
    pub fn id(self) -> u16 {
        let (f, n): (u16, u8) = match self {
            Cob::Nmt => (0, 0),
            Cob::Sync => (1, 0),
            Cob::Emcy(n) => (1, n),
            Cob::Time => (2, 0),
            Cob::Tpdo(k, n) => (1 + 2 * u16::from(k.clamp(1, 4)), n),
            Cob::Rpdo(k, n) => (2 + 2 * u16::from(k.clamp(1, 4)), n),
            Cob::SdoResponse(n) => (11, n),
            Cob::SdoRequest(n) => (12, n),
            Cob::Heartbeat(n) => (14, n),
            Cob::Other(id) => return (id & MAX_STANDARD_ID) as u16,
        };
        (f << 7) | u16::from(n & 0x7F)
    }

    /// A frame of this service with `data` (at most 8 bytes, else truncated: callers pass fixed sizes).
    pub fn frame(self, data: &[u8]) -> CanFrame {
        let n = data.len().min(8);
        CanFrame::new(self.id(), &data[..n]).unwrap_or(CanFrame {
            id: 0,
            extended: false,
            len: 0,
            data: [0; 8],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canopen_cob_ids_of_the_predefined_set() {
        assert_eq!(Cob::from_id(0x000), Cob::Nmt);
        assert_eq!(Cob::from_id(0x080), Cob::Sync);
        assert_eq!(Cob::from_id(0x081), Cob::Emcy(1));
        assert_eq!(Cob::from_id(0x182), Cob::Tpdo(1, 2));
        assert_eq!(Cob::from_id(0x282), Cob::Tpdo(2, 2));
        assert_eq!(Cob::from_id(0x201), Cob::Rpdo(1, 1));
        assert_eq!(Cob::from_id(0x581), Cob::SdoResponse(1));
        assert_eq!(Cob::from_id(0x601), Cob::SdoRequest(1));
        assert_eq!(Cob::from_id(0x77F), Cob::Heartbeat(127));
        assert_eq!(Cob::from_id(0x700), Cob::Other(0x700));
        for id in 0..=MAX_STANDARD_ID {
            let cob = Cob::from_id(id);
            assert_eq!(u32::from(cob.id()), id, "{cob:?}");
        }
    }

    #[test]
    fn canopen_frame_rejects_bad_parts() {
        assert_eq!(CanFrame::new(0x800, &[]), Err(FrameError::BadId { id: 0x800, extended: false }));
        assert_eq!(CanFrame::new(1, &[0; 9]), Err(FrameError::TooLong(9)));
        let f = CanFrame::with_id(0x1234_5678, true, &[1, 2]).unwrap();
        assert_eq!((f.id(), f.is_extended(), f.data()), (0x1234_5678, true, &[1u8, 2][..]));
        assert_eq!(f.cob(), Cob::Other(0x1234_5678));
    }
}
