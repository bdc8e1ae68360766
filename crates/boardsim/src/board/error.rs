//! Why the board stopped ([`BoardError`]), and the registers no model knows
//! ([`UnknownRegister`]), reported once each.

/// Why the board stopped running.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BoardError {
    /// An access outside every mapped region.
    Unmapped {
        /// "read", "write" or "fetch".
        access: &'static str,
        /// The address.
        addr: u32,
        /// The instruction's address.
        pc: u32,
    },
    /// An instruction Unicorn does not execute.
    InvalidInstruction {
        /// Its address.
        pc: u32,
    },
    /// A branch to an EXC_RETURN value the board does not handle (or outside a handler).
    BadExceptionReturn {
        /// The value.
        value: u32,
        /// Where the handler returned from.
        pc: u32,
    },
    /// Thread mode on the process stack (CONTROL.SPSEL): not modelled.
    ProcessStack {
        /// Where.
        pc: u32,
    },
    /// Any other emulation error.
    Emulation {
        /// Unicorn's error.
        error: String,
        /// Where.
        pc: u32,
    },
}

impl std::fmt::Display for BoardError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Unmapped { access, addr, pc } => write!(
                f,
                "{access} of unmapped address {addr:#010x} at pc {pc:#010x}"
            ),
            Self::InvalidInstruction { pc } => write!(f, "invalid instruction at pc {pc:#010x}"),
            Self::BadExceptionReturn { value, pc } => write!(
                f,
                "exception return to {value:#010x} at pc {pc:#010x} is not one the board handles"
            ),
            Self::ProcessStack { pc } => write!(
                f,
                "thread mode on the process stack (CONTROL.SPSEL) at pc {pc:#010x}: not modelled"
            ),
            Self::Emulation { error, pc } => write!(f, "emulation error {error} at pc {pc:#010x}"),
        }
    }
}

impl std::error::Error for BoardError {}

/// A register the models do not know, reported once.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownRegister {
    /// Its address.
    pub addr: u32,
    /// The peripheral it lies in, if the board knows its name.
    pub peripheral: &'static str,
    /// Written (else read).
    pub write: bool,
    /// The instruction's address (of the block it ran in: Unicorn's PC in an MMIO callback).
    pub pc: u32,
}

impl std::fmt::Display for UnknownRegister {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} of a register the models do not know: {:#010x} ({}) at pc {:#010x}",
            if self.write { "write" } else { "read" },
            self.addr,
            self.peripheral,
            self.pc
        )
    }
}
