//! The register map (RM0090 §32.9): the offsets, the bits the model acts on, the reset
//! values, and the reads and writes, the modes' hand-shakes (MCR, MSR) included.

use crate::regs::{merge, sub_word};

use super::{BUS_OFF_RECOVERY_BITS, BxCan};

/// Register offsets.
pub mod reg {
    /// Master control.
    pub const MCR: u32 = 0x000;
    /// Master status.
    pub const MSR: u32 = 0x004;
    /// Transmit status.
    pub const TSR: u32 = 0x008;
    /// Receive FIFO 0.
    pub const RF0R: u32 = 0x00C;
    /// Receive FIFO 1.
    pub const RF1R: u32 = 0x010;
    /// Interrupt enable.
    pub const IER: u32 = 0x014;
    /// Error status.
    pub const ESR: u32 = 0x018;
    /// Bit timing.
    pub const BTR: u32 = 0x01C;
    /// TX mailbox 0 identifier; mailboxes are 0x10 apart: TIxR, TDTxR, TDLxR, TDHxR.
    pub const TI0R: u32 = 0x180;
    /// RX FIFO 0 mailbox identifier; FIFO 1 at +0x10: RIxR, RDTxR, RDLxR, RDHxR.
    pub const RI0R: u32 = 0x1B0;
    /// Filter master.
    pub const FMR: u32 = 0x200;
    /// Filter mode (1: list).
    pub const FM1R: u32 = 0x204;
    /// Filter scale (1: 32-bit).
    pub const FS1R: u32 = 0x20C;
    /// Filter FIFO assignment.
    pub const FFA1R: u32 = 0x214;
    /// Filter activation.
    pub const FA1R: u32 = 0x21C;
    /// Bank 0 register 1; bank i at +8 i: FiR1, FiR2.
    pub const F0R1: u32 = 0x240;
}

/// MCR bits.
pub(super) mod mcr {
    pub const INRQ: u32 = 1;
    pub const SLEEP: u32 = 1 << 1;
    pub const TXFP: u32 = 1 << 2;
    pub const RFLM: u32 = 1 << 3;
    pub const NART: u32 = 1 << 4;
    pub const ABOM: u32 = 1 << 6;
    pub const TTCM: u32 = 1 << 7;
    pub const RESET: u32 = 1 << 15;
}

/// MSR bits.
pub(super) mod msr {
    pub const INAK: u32 = 1;
    pub const SLAK: u32 = 1 << 1;
    pub const ERRI: u32 = 1 << 2;
    pub const WKUI: u32 = 1 << 3;
    pub const SLAKI: u32 = 1 << 4;
}

/// IER bits.
pub(super) mod ier {
    pub const TMEIE: u32 = 1;
    pub const EWGIE: u32 = 1 << 8;
    pub const EPVIE: u32 = 1 << 9;
    pub const BOFIE: u32 = 1 << 10;
    pub const LECIE: u32 = 1 << 11;
    pub const ERRIE: u32 = 1 << 15;
    pub const WKUIE: u32 = 1 << 16;
    pub const SLKIE: u32 = 1 << 17;
}

pub(super) const MCR_RESET: u32 = 0x0001_0002;
pub(super) const MSR_RESET: u32 = 0x0000_0C02;
pub(super) const BTR_RESET: u32 = 0x0123_0000;
/// FMR after reset: FINIT, CAN2SB = 14 (banks 0..13 are CAN1's).
pub(super) const FMR_RESET: u32 = 0x2A1C_0E01;

impl BxCan {
    fn tsr_word(&self) -> u32 {
        let mut v = self.tsr;
        let empty: Vec<usize> = (0..3).filter(|&i| !self.mailboxes[i].pending()).collect();
        for &i in &empty {
            v |= 1 << (26 + i);
        }
        let code = match empty.first() {
            Some(&i) => i,
            // All pending: the one of lowest priority.
            None if self.mcr & mcr::TXFP != 0 => {
                (0..3).max_by_key(|&i| self.mailboxes[i].seq).unwrap_or(0)
            }
            None => (0..3)
                .max_by_key(|&i| (self.mailboxes[i].tir >> 1, i))
                .unwrap_or(0),
        };
        v | (code as u32) << 24
    }

    /// A read at `off`. `None` for an offset the model does not know.
    #[must_use]
    pub fn read(&self, off: u32, size: usize) -> Option<u32> {
        let word = off & !3;
        let v = match word {
            reg::MCR => self.mcr,
            reg::MSR => self.msr,
            reg::TSR => self.tsr_word(),
            reg::RF0R | reg::RF1R => {
                let f = &self.fifos[((word - reg::RF0R) / 4) as usize];
                f.frames.len() as u32 | u32::from(f.full) << 3 | u32::from(f.overrun) << 4
            }
            reg::IER => self.ier,
            reg::ESR => self.esr,
            reg::BTR => self.btr,
            0x180..0x1B0 => {
                let m = &self.mailboxes[((word - reg::TI0R) / 16) as usize];
                [m.tir, m.tdtr, m.tdlr, m.tdhr][((word & 0xF) / 4) as usize]
            }
            0x1B0..0x1D0 => {
                let f = &self.fifos[((word - reg::RI0R) / 16) as usize];
                f.frames
                    .front()
                    .map_or(0, |w| w[((word & 0xF) / 4) as usize])
            }
            reg::FMR..0x320 if self.filter_register(word) => self.filters.word(word - reg::FMR),
            _ => return None,
        };
        Some(sub_word(v, off, size))
    }

    fn filter_register(&self, word: u32) -> bool {
        matches!(
            word,
            reg::FMR | reg::FM1R | reg::FS1R | reg::FFA1R | reg::FA1R
        ) || (reg::F0R1..0x320).contains(&word)
    }

    /// A write at `off` at `now` (cycles). `None` for an offset the model does not know.
    pub fn write(&mut self, off: u32, size: usize, value: u32, now: u64) -> Option<()> {
        let word = off & !3;
        let v = merge(self.read(word, 4)?, off, size, value);
        // Bits of a sub-word write outside its bytes are the register's own: for the
        // write-1 registers, only the bytes written act.
        let w1 = merge(0, off, size, value);
        match word {
            reg::MCR => self.write_mcr(v, now),
            reg::MSR => self.msr &= !(w1 & (msr::ERRI | msr::WKUI | msr::SLAKI)),
            reg::TSR => {
                for i in 0..3 {
                    if w1 >> (8 * i) & 1 != 0 {
                        self.tsr &= !(0xF << (8 * i));
                    }
                    if w1 >> (8 * i + 7) & 1 != 0
                        && self.mailboxes[i].pending()
                        && self.on_bus != Some(i)
                    {
                        // Aborted: RQCP, no TXOK.
                        self.mailboxes[i].tir &= !1;
                        self.tsr = (self.tsr & !(0xF << (8 * i))) | 1 << (8 * i);
                    }
                }
            }
            reg::RF0R | reg::RF1R => {
                let f = &mut self.fifos[((word - reg::RF0R) / 4) as usize];
                if w1 & 1 << 3 != 0 {
                    f.full = false;
                }
                if w1 & 1 << 4 != 0 {
                    f.overrun = false;
                }
                if w1 & 1 << 5 != 0 && f.frames.pop_front().is_some() {
                    f.full = false;
                }
            }
            reg::IER => self.ier = v & 0x0003_8F7F,
            reg::ESR => self.esr = (self.esr & !0x70) | (v & 0x70),
            reg::BTR => {
                // Writable in initialisation mode only.
                if self.msr & msr::INAK != 0 {
                    if v & (3 << 30) != 0 {
                        self.unsupported.push((word, v));
                    }
                    self.btr = v & 0xC37F_03FF;
                }
            }
            0x180..0x1B0 => {
                let i = ((word - reg::TI0R) / 16) as usize;
                // A pending mailbox is write-protected.
                if !self.mailboxes[i].pending() {
                    let m = &mut self.mailboxes[i];
                    match (word & 0xF) / 4 {
                        0 => {
                            m.tir = v;
                            if v & 1 != 0 {
                                self.seq += 1;
                                m.seq = self.seq;
                            }
                        }
                        1 => m.tdtr = v & 0xFFFF_010F,
                        2 => m.tdlr = v,
                        _ => m.tdhr = v,
                    }
                }
            }
            0x1B0..0x1D0 => {} // read-only
            reg::FMR..0x320 if self.filter_register(word) => {
                self.filters.set_word(word - reg::FMR, v);
            }
            _ => return None,
        }
        Some(())
    }

    fn write_mcr(&mut self, v: u32, now: u64) {
        if v & mcr::RESET != 0 {
            // Software master reset: back to the reset state (sleep mode).
            let (pclk_div, unsupported, overruns, bus_offs, max_tec) = (
                self.pclk_div,
                std::mem::take(&mut self.unsupported),
                self.overruns,
                self.bus_offs,
                self.max_tec,
            );
            *self = Self::new(pclk_div);
            self.unsupported = unsupported;
            (self.overruns, self.bus_offs, self.max_tec) = (overruns, bus_offs, max_tec);
            return;
        }
        self.mcr = v & 0x0001_80FF;
        let was_sleeping = self.msr & msr::SLAK != 0;
        if v & mcr::INRQ != 0 {
            self.msr = (self.msr & !msr::SLAK) | msr::INAK;
        } else if v & mcr::SLEEP != 0 {
            self.msr = (self.msr & !msr::INAK) | msr::SLAK;
            if !was_sleeping {
                self.msr |= msr::SLAKI;
            }
        } else {
            // Normal mode once 11 recessive bits are seen: the bus is idle at once here.
            self.msr &= !(msr::INAK | msr::SLAK);
            if self.bus_off() && self.recovery_at.is_none() {
                // Leaving initialisation starts the recovery of a bus-off without ABOM.
                self.recovery_at = Some(now + BUS_OFF_RECOVERY_BITS * self.cycles_per_bit());
            }
        }
    }
}
