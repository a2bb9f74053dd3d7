//! Emergency messages (0x080 + id, `<u16 code, u8 error register, 5 bytes>`; python-canopen
//! `emcy.py`). Code 0x0000 is "error reset / no error", not an error (ros_canopen #396, notes B2).

use super::frame::{CanFrame, Cob, NodeId};

/// One EMCY message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Emcy {
    /// Error code (CiA 301/402 classes: 0x2xxx current, 0x3xxx voltage, 0x4xxx temperature,
    /// 0x8xxx monitoring, 0xFFxx device specific).
    pub code: u16,
    /// Error register 0x1001.
    pub register: u8,
    /// Manufacturer-specific bytes.
    pub data: [u8; 5],
}

/// Communication error: heartbeat or node-guarding event (CiA 301).
pub const EMCY_HEARTBEAT: u16 = 0x8130;
/// Communication: recovered from bus-off (CiA 301; c-open PR #34).
pub const EMCY_BUS_OFF_RECOVERED: u16 = 0x8140;

impl Emcy {
    /// Whether this is an error reset (code 0x0000) rather than an error.
    pub fn is_reset(&self) -> bool {
        self.code == 0
    }

    /// Decode the EMCY of `frame`; `None` if it is not an EMCY or is shorter than 3 bytes.
    pub fn decode(frame: &CanFrame) -> Option<(NodeId, Self)> {
        let Cob::Emcy(node) = frame.cob() else { return None };
        if frame.data().len() < 3 {
            return None;
        }
        let d = frame.data8();
        Some((
            node,
            Emcy {
                code: u16::from_le_bytes([d[0], d[1]]),
                register: d[2],
                data: [d[3], d[4], d[5], d[6], d[7]],
            },
        ))
    }

    /// The EMCY frame of `node`.
    pub fn frame(&self, node: NodeId) -> CanFrame {
        let c = self.code.to_le_bytes();
        let d = self.data;
        Cob::Emcy(node).frame(&[c[0], c[1], self.register, d[0], d[1], d[2], d[3], d[4]])
    }

    /// A short name of the error class, for logs.
    pub fn class_name(&self) -> &'static str {
        match self.code >> 12 {
            _ if self.code == 0 => "error reset",
            0x1 => "generic",
            0x2 => "current",
            0x3 => "voltage",
            0x4 => "temperature",
            0x5 => "device hardware",
            0x6 => "device software",
            0x7 => "additional modules",
            0x8 => "monitoring/communication",
            0x9 => "external",
            0xF => "additional functions / device specific",
            _ => "unknown",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canopen_emcy_golden_and_reset() {
        // Overcurrent 0x2310, error register 0x03 (generic + current).
        let f = Cob::Emcy(1).frame(&[0x10, 0x23, 0x03, 1, 2, 3, 4, 5]);
        let (node, e) = Emcy::decode(&f).unwrap();
        assert_eq!((node, e.code, e.register, e.data), (1, 0x2310, 0x03, [1, 2, 3, 4, 5]));
        assert!(!e.is_reset());
        assert_eq!(e.class_name(), "current");
        assert_eq!(e.frame(1), f);
        let reset = Emcy::decode(&Cob::Emcy(2).frame(&[0, 0, 0, 0, 0, 0, 0, 0])).unwrap().1;
        assert!(reset.is_reset());
        assert_eq!(Emcy::decode(&Cob::Emcy(2).frame(&[0, 0])), None);
        assert_eq!(Emcy::decode(&Cob::Sync.frame(&[])), None);
    }
}
