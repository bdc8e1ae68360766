//! The CiA 402 drive profile's device control: the drive states a statusword reports, the
//! drive's side of the state machine, and the controlword commands that walk it.

/// The CiA 402 drive state a statusword reports (object 0x6041, bits 0-3, 5 and 6).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum DriveState402 {
    /// Not ready to switch on (initialising).
    NotReadyToSwitchOn,
    /// Switch on disabled (after power-up, a fault reset, a quick stop).
    SwitchOnDisabled,
    /// Ready to switch on (after shutdown, 0x06).
    ReadyToSwitchOn,
    /// Switched on (after switch on, 0x07).
    SwitchedOn,
    /// Operation enabled (after enable operation, 0x0F): the drive follows its target.
    OperationEnabled,
    /// Quick stop active (after quick stop, 0x02).
    QuickStopActive,
    /// Fault reaction active.
    FaultReactionActive,
    /// Fault.
    Fault,
}

impl DriveState402 {
    /// The state of a statusword; `None` for bit patterns CiA 402 does not define.
    #[must_use]
    pub const fn from_statusword(sw: u16) -> Option<Self> {
        Some(match (sw & 0x4F, sw & 0x6F) {
            (0x00, _) => Self::NotReadyToSwitchOn,
            (0x40, _) => Self::SwitchOnDisabled,
            (_, 0x21) => Self::ReadyToSwitchOn,
            (_, 0x23) => Self::SwitchedOn,
            (_, 0x27) => Self::OperationEnabled,
            (_, 0x07) => Self::QuickStopActive,
            (0x0F, _) => Self::FaultReactionActive,
            (0x08, _) => Self::Fault,
            _ => return None,
        })
    }

    /// The state a drive goes to on `controlword` (CiA 402's device control, the drive's
    /// side), `previous` the controlword before it: a fault leaves only on a rising edge of
    /// bit 7; otherwise the profile's command table on bits 0-3, its "x" bits ignored:
    /// disable voltage (bit 1 clear: 7, 9, 10, 12), quick stop (bit 2 clear: 11 from
    /// operation enabled, 7 and 10 otherwise), shutdown (bit 0 clear: 2, 6, 8), switch on and
    /// disable operation (bit 3 clear: 3, 5), enable operation (4, and "3 + 4" from ready to
    /// switch on). Operation enabled only if `may_enable` (the drive's mode and its own
    /// conditions allow it; else switch on alone). For the simulated and scripted drives: the
    /// master only reads states ([`Self::from_statusword`]).
    #[must_use]
    pub const fn on_controlword(self, cw: u16, previous: u16, may_enable: bool) -> Self {
        use DriveState402 as S;
        if let S::Fault | S::FaultReactionActive = self {
            let rising_reset = cw & 0x80 != 0 && previous & 0x80 == 0;
            return if rising_reset && matches!(self, S::Fault) {
                S::SwitchOnDisabled
            } else {
                self
            };
        }
        if cw & 0x80 != 0 {
            // Fault reset outside a fault: no transition.
            return self;
        }
        if cw & 0x02 == 0 {
            return S::SwitchOnDisabled;
        }
        if cw & 0x04 == 0 {
            return match self {
                S::OperationEnabled | S::QuickStopActive => S::QuickStopActive,
                _ => S::SwitchOnDisabled,
            };
        }
        match (self, cw & 0x01 != 0, cw & 0x08 != 0) {
            (S::SwitchOnDisabled | S::SwitchedOn | S::OperationEnabled, false, _) => {
                S::ReadyToSwitchOn
            }
            (S::ReadyToSwitchOn | S::OperationEnabled, true, false) => S::SwitchedOn,
            (S::ReadyToSwitchOn | S::SwitchedOn, true, true) if may_enable => S::OperationEnabled,
            (S::ReadyToSwitchOn, true, true) => S::SwitchedOn,
            _ => self,
        }
    }

    /// A statusword reporting this state, as the project's simulated drives send it (bit 4,
    /// voltage enabled, and bit 9, remote, set).
    #[must_use]
    pub const fn statusword(self) -> u16 {
        match self {
            Self::NotReadyToSwitchOn => 0x0200,
            Self::SwitchOnDisabled => 0x0250,
            Self::ReadyToSwitchOn => 0x0231,
            Self::SwitchedOn => 0x0233,
            Self::OperationEnabled => 0x0237,
            Self::QuickStopActive => 0x0217,
            Self::FaultReactionActive => 0x021F,
            Self::Fault => 0x0218,
        }
    }

    /// A name for logs (CiA 402's, in capitals).
    #[must_use]
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::NotReadyToSwitchOn => "NOT_READY_TO_SWITCH_ON",
            Self::SwitchOnDisabled => "SWITCH_ON_DISABLED",
            Self::ReadyToSwitchOn => "READY_TO_SWITCH_ON",
            Self::SwitchedOn => "SWITCHED_ON",
            Self::OperationEnabled => "OPERATION_ENABLED",
            Self::QuickStopActive => "QUICK_STOP_ACTIVE",
            Self::FaultReactionActive => "FAULT_REACTION_ACTIVE",
            Self::Fault => "FAULT",
        }
    }
}

/// Statusword bit 3: a fault (or its reaction) is active.
pub const STATUSWORD_FAULT: u16 = 1 << 3;

/// Controlword commands (object 0x6040) of the CiA 402 state machine.
pub mod controlword {
    /// Shutdown: to ready to switch on (no torque).
    pub const SHUTDOWN: u16 = 0x06;
    /// Switch on: to switched on.
    pub const SWITCH_ON: u16 = 0x07;
    /// Enable operation: to operation enabled.
    pub const ENABLE_OPERATION: u16 = 0x0F;
    /// Quick stop (bit 2 clear): to quick stop active, then switch on disabled.
    pub const QUICK_STOP: u16 = 0x02;
    /// Disable voltage (bit 1 clear): to switch on disabled, from any powered state.
    pub const DISABLE_VOLTAGE: u16 = 0x00;
    /// Fault reset: its rising edge (bit 7) leaves fault for switch on disabled.
    pub const FAULT_RESET: u16 = 0x80;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statusword_states_follow_cia402() {
        use DriveState402 as S;
        for (sw, state) in [
            (0x0000, S::NotReadyToSwitchOn),
            (0x0250, S::SwitchOnDisabled),
            (0x0231, S::ReadyToSwitchOn),
            (0x0233, S::SwitchedOn),
            (0x0637, S::OperationEnabled),
            (0x0217, S::QuickStopActive),
            (0x021F, S::FaultReactionActive),
            (0x0218, S::Fault),
        ] {
            assert_eq!(DriveState402::from_statusword(sw), Some(state), "{sw:#06x}");
        }
        assert_eq!(DriveState402::from_statusword(0x0001), None);
    }

    #[test]
    fn the_drive_side_machine_follows_cia402s_transitions() {
        use DriveState402 as S;
        let walk = |cws: &[u16], may_enable: bool| {
            let (mut s, mut prev) = (S::SwitchOnDisabled, 0);
            for &cw in cws {
                s = s.on_controlword(cw, prev, may_enable);
                prev = cw;
            }
            s
        };
        assert_eq!(walk(&[0x06, 0x07, 0x0F], true), S::OperationEnabled);
        assert_eq!(walk(&[0x06, 0x07, 0x0F], false), S::SwitchedOn);
        assert_eq!(
            walk(&[0x07, 0x0F], true),
            S::SwitchOnDisabled,
            "no skipping"
        );
        assert_eq!(walk(&[0x06, 0x07, 0x0F, 0x02], true), S::QuickStopActive);
        assert_eq!(
            walk(&[0x06, 0x07, 0x0F, 0x02, 0x00], true),
            S::SwitchOnDisabled
        );
        assert_eq!(walk(&[0x06, 0x07, 0x0F, 0x06], true), S::ReadyToSwitchOn);
        assert_eq!(walk(&[0x06, 0x07, 0x0F, 0x07], true), S::SwitchedOn);
        // Switch on + enable operation from ready to switch on: "3 + 4" (switch on alone
        // where the drive may not enable).
        assert_eq!(walk(&[0x06, 0x0F], true), S::OperationEnabled);
        assert_eq!(walk(&[0x06, 0x0F], false), S::SwitchedOn);
        // The command table's "x" bits are ignored: 0x0E is shutdown, 0x0B quick stop,
        // 0x0D disable voltage; bits 4-6 and 8-15 are the mode's and the maker's.
        assert_eq!(walk(&[0x0E], true), S::ReadyToSwitchOn);
        assert_eq!(walk(&[0x06, 0x07, 0x0F, 0x0B], true), S::QuickStopActive);
        assert_eq!(walk(&[0x06, 0x07, 0x0F, 0x0D], true), S::SwitchOnDisabled);
        assert_eq!(walk(&[0x06, 0x07, 0x7F0F], true), S::OperationEnabled);
        // A fault leaves on the rising edge of bit 7 only.
        assert_eq!(S::Fault.on_controlword(0x80, 0x80, true), S::Fault);
        assert_eq!(S::Fault.on_controlword(0x06, 0x80, true), S::Fault);
        assert_eq!(
            S::Fault.on_controlword(0x80, 0x06, true),
            S::SwitchOnDisabled
        );
        for s in [
            S::NotReadyToSwitchOn,
            S::SwitchOnDisabled,
            S::ReadyToSwitchOn,
            S::SwitchedOn,
            S::OperationEnabled,
            S::QuickStopActive,
            S::FaultReactionActive,
            S::Fault,
        ] {
            assert_eq!(S::from_statusword(s.statusword()), Some(s));
        }
    }
}
