//! NMT commands (0x000, `[cs, node]`) and the NMT states a node reports in its heartbeat
//! (0x700 + id, one byte). Values: CiA 301 via python-canopen `nmt.py` (notes B2).

use super::frame::{CanFrame, Cob, NodeId};

/// An NMT command specifier.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NmtCommand {
    /// 0x01: go to OPERATIONAL.
    Start,
    /// 0x02: go to STOPPED.
    Stop,
    /// 0x80: go to PRE-OPERATIONAL.
    EnterPreOperational,
    /// 0x81: reset the application (boot-up follows).
    ResetNode,
    /// 0x82: reset communication (boot-up follows).
    ResetCommunication,
}

impl NmtCommand {
    /// The command specifier byte.
    pub fn cs(self) -> u8 {
        match self {
            NmtCommand::Start => 0x01,
            NmtCommand::Stop => 0x02,
            NmtCommand::EnterPreOperational => 0x80,
            NmtCommand::ResetNode => 0x81,
            NmtCommand::ResetCommunication => 0x82,
        }
    }

    /// From the command specifier byte.
    pub fn from_cs(cs: u8) -> Option<Self> {
        Some(match cs {
            0x01 => NmtCommand::Start,
            0x02 => NmtCommand::Stop,
            0x80 => NmtCommand::EnterPreOperational,
            0x81 => NmtCommand::ResetNode,
            0x82 => NmtCommand::ResetCommunication,
            _ => return None,
        })
    }

    /// The NMT frame addressed to `node` (0 = all nodes).
    pub fn frame(self, node: NodeId) -> CanFrame {
        Cob::Nmt.frame(&[self.cs(), node])
    }

    /// Decode an NMT frame into (command, addressed node).
    pub fn decode(frame: &CanFrame) -> Option<(Self, NodeId)> {
        match (frame.cob(), frame.data()) {
            (Cob::Nmt, [cs, node]) => Some((Self::from_cs(*cs)?, *node)),
            _ => None,
        }
    }
}

/// The NMT state a node reports (heartbeat byte, bit 7 = toggle of node guarding, ignored).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NmtState {
    /// 0x00: boot-up message, sent once after a reset.
    BootUp,
    /// 0x04.
    Stopped,
    /// 0x05.
    Operational,
    /// 0x7F.
    PreOperational,
}

impl NmtState {
    /// The heartbeat byte.
    pub fn byte(self) -> u8 {
        match self {
            NmtState::BootUp => 0x00,
            NmtState::Stopped => 0x04,
            NmtState::Operational => 0x05,
            NmtState::PreOperational => 0x7F,
        }
    }

    /// From the heartbeat byte.
    pub fn from_byte(b: u8) -> Option<Self> {
        Some(match b & 0x7F {
            0x00 => NmtState::BootUp,
            0x04 => NmtState::Stopped,
            0x05 => NmtState::Operational,
            0x7F => NmtState::PreOperational,
            _ => return None,
        })
    }

    /// The heartbeat frame of `node` in this state.
    pub fn heartbeat(self, node: NodeId) -> CanFrame {
        Cob::Heartbeat(node).frame(&[self.byte()])
    }

    /// Decode a heartbeat or boot-up frame into (node, state).
    pub fn decode(frame: &CanFrame) -> Option<(NodeId, Self)> {
        match (frame.cob(), frame.data()) {
            (Cob::Heartbeat(n), [b]) => Some((n, Self::from_byte(*b)?)),
            _ => None,
        }
    }
}

/// The SYNC frame (0x080, no data; the counter variant is not used here).
pub fn sync_frame() -> CanFrame {
    Cob::Sync.frame(&[])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canopen_nmt_golden_frames() {
        // notes B2: NMT 0x000 [cs, node].
        let f = NmtCommand::Start.frame(1);
        assert_eq!((f.id(), f.data()), (0x000, &[0x01, 0x01][..]));
        let f = NmtCommand::EnterPreOperational.frame(0);
        assert_eq!(f.data(), &[0x80, 0x00]);
        assert_eq!(NmtCommand::decode(&NmtCommand::ResetNode.frame(2)), Some((NmtCommand::ResetNode, 2)));
        assert_eq!(NmtCommand::decode(&Cob::Nmt.frame(&[0x03, 1])), None);
        // heartbeat 0x700 + id: 00 boot-up, 04 stopped, 05 operational, 7F pre-op.
        let f = NmtState::BootUp.heartbeat(2);
        assert_eq!((f.id(), f.data()), (0x702, &[0x00][..]));
        assert_eq!(NmtState::decode(&Cob::Heartbeat(1).frame(&[0x05])), Some((1, NmtState::Operational)));
        assert_eq!(NmtState::decode(&Cob::Heartbeat(1).frame(&[0x7F])), Some((1, NmtState::PreOperational)));
        assert_eq!(NmtState::decode(&Cob::Heartbeat(1).frame(&[0x04])), Some((1, NmtState::Stopped)));
        assert_eq!(NmtState::decode(&Cob::Heartbeat(1).frame(&[0x33])), None);
        assert_eq!(sync_frame().id(), 0x080);
    }
}
