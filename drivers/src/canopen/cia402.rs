//! CiA 402 drive profile: the statusword decoded into the eight states (python-canopen
//! `p402.py` `State402.SW_MASK`, ros2_canopen `state.cpp`), the controlword commands, the
//! device-side transition table (used by the mock drives and tested here), and the master-side
//! choice of the next controlword on the way to a goal (notes B3).

/// The eight states of the CiA 402 power state machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum State402 {
    /// Not ready to switch on (initialising).
    NotReadyToSwitchOn,
    /// Switch on disabled.
    SwitchOnDisabled,
    /// Ready to switch on.
    ReadyToSwitchOn,
    /// Switched on (power stage on, no torque command).
    SwitchedOn,
    /// Operation enabled: follows the target.
    OperationEnabled,
    /// Quick stop active.
    QuickStopActive,
    /// Fault reaction active.
    FaultReactionActive,
    /// Fault.
    Fault,
}

/// (state, mask, value) of the statusword decode table (notes B3).
const SW_TABLE: [(State402, u16, u16); 8] = [
    (State402::NotReadyToSwitchOn, 0x4F, 0x00),
    (State402::SwitchOnDisabled, 0x4F, 0x40),
    (State402::ReadyToSwitchOn, 0x6F, 0x21),
    (State402::SwitchedOn, 0x6F, 0x23),
    (State402::OperationEnabled, 0x6F, 0x27),
    (State402::QuickStopActive, 0x6F, 0x07),
    (State402::FaultReactionActive, 0x4F, 0x0F),
    (State402::Fault, 0x4F, 0x08),
];

/// Statusword bit 4: voltage enabled.
pub const SW_VOLTAGE_ENABLED: u16 = 1 << 4;
/// Statusword bit 9: remote (controlword honoured).
pub const SW_REMOTE: u16 = 1 << 9;
/// Statusword bit 10: target reached.
pub const SW_TARGET_REACHED: u16 = 1 << 10;
/// Statusword bit 12 in profile velocity: speed is zero.
pub const SW_PV_SPEED_ZERO: u16 = 1 << 12;

impl State402 {
    /// Decode a statusword; `None` for a bit pattern no state has.
    pub fn from_statusword(sw: u16) -> Option<Self> {
        SW_TABLE.iter().find(|(_, mask, value)| sw & mask == *value).map(|(s, _, _)| *s)
    }

    /// The state bits of a statusword for this state (the table's value).
    pub fn statusword_bits(self) -> u16 {
        SW_TABLE.iter().find(|(s, _, _)| *s == self).map_or(0, |(_, _, v)| *v)
    }

    /// Whether this is one of the two fault states.
    pub fn is_fault(self) -> bool {
        matches!(self, State402::Fault | State402::FaultReactionActive)
    }
}

/// Controlword 0x6040 commands (notes B3, python-canopen `TRANSITIONTABLE`).
pub mod controlword {
    /// Shutdown (transitions 2, 6, 8).
    pub const SHUTDOWN: u16 = 0x0006;
    /// Switch on (3) / disable operation (5).
    pub const SWITCH_ON: u16 = 0x0007;
    /// Enable operation (4, 16).
    pub const ENABLE_OPERATION: u16 = 0x000F;
    /// Disable voltage (7, 9, 10, 12).
    pub const DISABLE_VOLTAGE: u16 = 0x0000;
    /// Quick stop (7, 10, 11): bit 2 is active low.
    pub const QUICK_STOP: u16 = 0x0002;
    /// Fault reset bit 7 (15), acts on a rising edge.
    pub const FAULT_RESET: u16 = 0x0080;
    /// Halt bit 8: in profile velocity, ramp to zero and stay enabled.
    pub const HALT: u16 = 0x0100;
}

/// A controlword decoded into the command it means (bits 0, 1, 2, 3 and 7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Command402 {
    /// xxxx x110.
    Shutdown,
    /// xxxx 0111.
    SwitchOn,
    /// xxxx 1111.
    EnableOperation,
    /// xxxx xx0x.
    DisableVoltage,
    /// xxxx x01x.
    QuickStop,
}

impl Command402 {
    /// Decode bits 0..3 (fault reset, bit 7, is edge-triggered and handled apart).
    pub fn from_controlword(cw: u16) -> Self {
        if cw & 0x02 == 0 {
            Command402::DisableVoltage
        } else if cw & 0x04 == 0 {
            Command402::QuickStop
        } else if cw & 0x01 == 0 {
            Command402::Shutdown
        } else if cw & 0x08 == 0 {
            Command402::SwitchOn
        } else {
            Command402::EnableOperation
        }
    }
}

/// The device side: the state after controlword `cw` (previous controlword `prev_cw`, for the
/// fault-reset edge) in `state`. Automatic transitions (0, 1, 13, 14) are the device's own.
pub fn device_transition(state: State402, prev_cw: u16, cw: u16) -> State402 {
    use Command402 as C;
    use State402 as S;
    let reset_edge = cw & controlword::FAULT_RESET != 0 && prev_cw & controlword::FAULT_RESET == 0;
    if state == S::Fault {
        // Transition 15 only on the 0 → 1 edge of bit 7.
        return if reset_edge { S::SwitchOnDisabled } else { S::Fault };
    }
    if cw & controlword::FAULT_RESET != 0 {
        // While bit 7 is set outside Fault, the other bits are ignored (CiA 402).
        return state;
    }
    match (state, C::from_controlword(cw)) {
        (S::SwitchOnDisabled, C::Shutdown) => S::ReadyToSwitchOn, // 2
        (S::ReadyToSwitchOn, C::SwitchOn | C::EnableOperation) => S::SwitchedOn, // 3
        (S::ReadyToSwitchOn, C::DisableVoltage | C::QuickStop) => S::SwitchOnDisabled, // 7
        (S::SwitchedOn, C::EnableOperation) => S::OperationEnabled, // 4
        (S::SwitchedOn, C::Shutdown) => S::ReadyToSwitchOn,       // 6
        (S::SwitchedOn, C::DisableVoltage | C::QuickStop) => S::SwitchOnDisabled, // 10
        (S::OperationEnabled, C::SwitchOn) => S::SwitchedOn,      // 5
        (S::OperationEnabled, C::Shutdown) => S::ReadyToSwitchOn, // 8
        (S::OperationEnabled, C::DisableVoltage) => S::SwitchOnDisabled, // 9
        (S::OperationEnabled, C::QuickStop) => S::QuickStopActive, // 11
        (S::QuickStopActive, C::DisableVoltage) => S::SwitchOnDisabled, // 12
        (S::QuickStopActive, C::EnableOperation) => S::OperationEnabled, // 16
        (s, _) => s,
    }
}

/// Where the master wants a drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Goal {
    /// Operation enabled, following the target velocity.
    Enabled,
    /// Switch on disabled (no torque).
    Disabled,
    /// Quick stop: from Operation enabled into Quick stop active, and stay.
    QuickStop,
}

/// The master side: the controlword to send in `state` to move one step towards `goal`
/// (typical enable: SOD →0x06→ RTSO →0x07→ SO →0x0F→ OE). In Fault this is 0x0000, which also
/// prepares the rising edge of a later fault reset.
pub fn next_controlword(state: State402, goal: Goal) -> u16 {
    use State402 as S;
    use controlword as cw;
    match goal {
        Goal::Disabled => cw::DISABLE_VOLTAGE,
        Goal::QuickStop => match state {
            S::OperationEnabled | S::QuickStopActive => cw::QUICK_STOP,
            _ => cw::DISABLE_VOLTAGE,
        },
        Goal::Enabled => match state {
            S::SwitchOnDisabled => cw::SHUTDOWN,
            S::ReadyToSwitchOn => cw::SWITCH_ON,
            S::SwitchedOn | S::OperationEnabled => cw::ENABLE_OPERATION,
            // Leave quick stop through Switch on disabled (python-canopen #167: drives differ on 16).
            S::QuickStopActive => cw::DISABLE_VOLTAGE,
            S::NotReadyToSwitchOn | S::FaultReactionActive | S::Fault => cw::DISABLE_VOLTAGE,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::controlword as cw;
    use super::*;

    const ALL: [State402; 8] = [
        State402::NotReadyToSwitchOn,
        State402::SwitchOnDisabled,
        State402::ReadyToSwitchOn,
        State402::SwitchedOn,
        State402::OperationEnabled,
        State402::QuickStopActive,
        State402::FaultReactionActive,
        State402::Fault,
    ];

    #[test]
    fn canopen_cia402_statusword_decodes_each_state() {
        for s in ALL {
            assert_eq!(State402::from_statusword(s.statusword_bits()), Some(s));
            // Bits outside every mask do not change the state.
            assert_eq!(State402::from_statusword(s.statusword_bits() | 0xFF90), Some(s));
        }
        // Real statuswords: 0x0250 SOD, 0x0231 RTSO, 0x0233 SO, 0x0237 OE, 0x0217 QSA, 0x0218 Fault.
        assert_eq!(State402::from_statusword(0x0250), Some(State402::SwitchOnDisabled));
        assert_eq!(State402::from_statusword(0x0231), Some(State402::ReadyToSwitchOn));
        assert_eq!(State402::from_statusword(0x0233), Some(State402::SwitchedOn));
        assert_eq!(State402::from_statusword(0x0237), Some(State402::OperationEnabled));
        assert_eq!(State402::from_statusword(0x0217), Some(State402::QuickStopActive));
        assert_eq!(State402::from_statusword(0x0218), Some(State402::Fault));
        assert_eq!(State402::from_statusword(0x0001), None);
    }

    #[test]
    fn canopen_cia402_transition_table() {
        use State402 as S;
        // (from, controlword, to, transition number) — CiA 402 via the notes B3.
        let table = [
            (S::SwitchOnDisabled, cw::SHUTDOWN, S::ReadyToSwitchOn), // 2
            (S::ReadyToSwitchOn, cw::SWITCH_ON, S::SwitchedOn),      // 3
            (S::SwitchedOn, cw::ENABLE_OPERATION, S::OperationEnabled), // 4
            (S::OperationEnabled, cw::SWITCH_ON, S::SwitchedOn),     // 5
            (S::SwitchedOn, cw::SHUTDOWN, S::ReadyToSwitchOn),       // 6
            (S::ReadyToSwitchOn, cw::DISABLE_VOLTAGE, S::SwitchOnDisabled), // 7
            (S::ReadyToSwitchOn, cw::QUICK_STOP, S::SwitchOnDisabled), // 7
            (S::OperationEnabled, cw::SHUTDOWN, S::ReadyToSwitchOn), // 8
            (S::OperationEnabled, cw::DISABLE_VOLTAGE, S::SwitchOnDisabled), // 9
            (S::SwitchedOn, cw::DISABLE_VOLTAGE, S::SwitchOnDisabled), // 10
            (S::SwitchedOn, cw::QUICK_STOP, S::SwitchOnDisabled),    // 10
            (S::OperationEnabled, cw::QUICK_STOP, S::QuickStopActive), // 11
            (S::QuickStopActive, cw::DISABLE_VOLTAGE, S::SwitchOnDisabled), // 12
            (S::QuickStopActive, cw::ENABLE_OPERATION, S::OperationEnabled), // 16
            // Not allowed: stays.
            (S::SwitchOnDisabled, cw::ENABLE_OPERATION, S::SwitchOnDisabled),
            (S::SwitchOnDisabled, cw::SWITCH_ON, S::SwitchOnDisabled),
            (S::ReadyToSwitchOn, cw::SHUTDOWN, S::ReadyToSwitchOn),
            (S::Fault, cw::ENABLE_OPERATION, S::Fault),
            (S::Fault, cw::SHUTDOWN, S::Fault),
        ];
        for (from, c, to) in table {
            assert_eq!(device_transition(from, 0, c), to, "{from:?} + {c:#06x}");
        }
        // Halt does not change the state.
        assert_eq!(
            device_transition(S::OperationEnabled, cw::ENABLE_OPERATION, cw::ENABLE_OPERATION | cw::HALT),
            S::OperationEnabled
        );
    }

    #[test]
    fn canopen_cia402_fault_reset_needs_rising_edge() {
        use State402 as S;
        assert_eq!(
            device_transition(S::Fault, cw::FAULT_RESET, cw::FAULT_RESET),
            S::Fault,
            "held high: no edge"
        );
        assert_eq!(device_transition(S::Fault, cw::SHUTDOWN, cw::FAULT_RESET), S::SwitchOnDisabled); // 15
        assert_eq!(
            device_transition(S::Fault, 0, cw::FAULT_RESET | cw::ENABLE_OPERATION),
            S::SwitchOnDisabled
        );
    }

    #[test]
    fn canopen_cia402_master_walks_to_enabled() {
        let mut s = State402::SwitchOnDisabled;
        let mut prev = 0;
        let mut seen = vec![s];
        for _ in 0..5 {
            let c = next_controlword(s, Goal::Enabled);
            s = device_transition(s, prev, c);
            prev = c;
            seen.push(s);
        }
        assert_eq!(
            &seen[..4],
            &[
                State402::SwitchOnDisabled,
                State402::ReadyToSwitchOn,
                State402::SwitchedOn,
                State402::OperationEnabled
            ]
        );
        assert_eq!(s, State402::OperationEnabled);
        assert_eq!(next_controlword(State402::OperationEnabled, Goal::QuickStop), cw::QUICK_STOP);
        assert_eq!(next_controlword(State402::Fault, Goal::Enabled), cw::DISABLE_VOLTAGE);
    }
}
