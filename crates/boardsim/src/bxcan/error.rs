//! Fault confinement: the error counters (TEC, REC) and states (warning, passive, bus-off),
//! the last error code, and the bus-off recovery (automatic with ABOM).

use super::BxCan;
use super::registers::{ier, mcr, msr};

/// Bit times of the bus-off recovery: 128 occurrences of 11 recessive bits.
pub const BUS_OFF_RECOVERY_BITS: u64 = 128 * 11;

/// The last error code (ESR.LEC).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum Lec {
    /// No error.
    None = 0,
    /// Stuff error.
    Stuff = 1,
    /// Form error.
    Form = 2,
    /// Acknowledgment error (no receiver acknowledged).
    Ack = 3,
    /// Bit recessive error.
    BitRecessive = 4,
    /// Bit dominant error.
    BitDominant = 5,
    /// CRC error.
    Crc = 6,
}

impl BxCan {
    /// TEC and REC.
    #[must_use]
    pub fn error_counters(&self) -> (u8, u8) {
        ((self.esr >> 16) as u8, (self.esr >> 24) as u8)
    }

    /// Bus-off (ESR.BOFF).
    #[must_use]
    pub fn bus_off(&self) -> bool {
        self.esr & 4 != 0
    }

    /// The frame on the wire met an error (`lec`), e.g. no acknowledgment: TEC += 8 (except
    /// an ACK error while error passive, ISO 11898-1 12.1.4.2 exception), TERR; with NART
    /// the mailbox gives up (RQCP, TERR), else it stays pending and retries. May go bus-off
    /// (TEC > 255) at `now`.
    pub fn tx_error(&mut self, mailbox: usize, lec: Lec, now: u64) {
        self.on_bus = None;
        let (tec, rec) = self.error_counters();
        let passive = tec >= 128;
        let tec = if lec == Lec::Ack && passive {
            u16::from(tec)
        } else {
            u16::from(tec) + 8
        };
        self.set_lec(lec);
        if self.mcr & mcr::NART != 0 {
            self.mailboxes[mailbox].tir &= !1;
            self.tsr |= 0b1001 << (8 * mailbox);
        } else {
            self.tsr |= 0b1000 << (8 * mailbox);
        }
        if tec > 255 {
            self.enter_bus_off(now);
        } else {
            self.set_counters(tec as u8, rec);
        }
    }

    fn enter_bus_off(&mut self, now: u64) {
        self.esr |= 4 | (255 << 16);
        self.bus_offs += 1;
        self.max_tec = 255;
        self.on_bus = None;
        if self.ier & ier::BOFIE != 0 {
            self.msr |= msr::ERRI;
        }
        self.recovery_at = (self.mcr & mcr::ABOM != 0)
            .then(|| now + BUS_OFF_RECOVERY_BITS * self.cycles_per_bit());
    }

    /// Bus-off recovery, if due at `now`: counters reset, online again.
    pub fn advance(&mut self, now: u64) {
        if let Some(at) = self.recovery_at
            && now >= at
        {
            self.recovery_at = None;
            self.esr &= !(0xFFFF_0000 | 7);
        }
    }

    /// When the bus-off recovery completes, if one is running.
    #[must_use]
    pub const fn next_event(&self) -> Option<u64> {
        self.recovery_at
    }

    pub(super) fn set_counters(&mut self, tec: u8, rec: u8) {
        self.max_tec = self.max_tec.max(tec);
        let before = self.esr & 3;
        let mut esr = (self.esr & 0xFF7C) | u32::from(tec) << 16 | u32::from(rec) << 24;
        if tec >= 96 || rec >= 96 {
            esr |= 1;
        }
        if tec >= 128 || rec >= 128 {
            esr |= 2;
        }
        let raised = esr & 3 & !before;
        if (raised & 1 != 0 && self.ier & ier::EWGIE != 0)
            || (raised & 2 != 0 && self.ier & ier::EPVIE != 0)
        {
            self.msr |= msr::ERRI;
        }
        self.esr = esr;
    }

    fn set_lec(&mut self, lec: Lec) {
        self.esr = (self.esr & !0x70) | (lec as u32) << 4;
        if lec != Lec::None && self.ier & ier::LECIE != 0 {
            self.msr |= msr::ERRI;
        }
    }
}
