//! bxCAN CAN1 (RM0090 §32): the operating modes (sleep, initialisation, normal, and the
//! hand-shake flags), three transmit mailboxes chosen by request order (TXFP) or identifier,
//! two 3-deep receive FIFOs (FMP, FULL, FOVR, locked or overwriting), the 28 filter banks in
//! their four modes with the filter match index, the error counters and states (warning,
//! passive, bus-off with automatic recovery, ABOM), time stamps (TTCM), and the four
//! interrupt lines.
//!
//! The wire is not here: the board's driver ([`crate::board`]) asks [`BxCan::offer`] for the
//! frame the controller would put on the bus, tells it when that frame started, completed or
//! failed, and hands it the frames other nodes completed ([`BxCan::receive`]) at their
//! end-of-frame time. Times are CPU cycles; bit times follow BTR and the APB1 clock.
//! Loopback and silent modes are not modelled (a write selecting them is reported).

use std::collections::VecDeque;

use embedded_can::{ExtendedId, Frame, Id, StandardId};
use firmware::CanFrame;

use crate::regs::{RegFile, merge, sub_word};

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
mod mcr {
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
mod msr {
    pub const INAK: u32 = 1;
    pub const SLAK: u32 = 1 << 1;
    pub const ERRI: u32 = 1 << 2;
    pub const WKUI: u32 = 1 << 3;
    pub const SLAKI: u32 = 1 << 4;
}

/// IER bits.
mod ier {
    pub const TMEIE: u32 = 1;
    pub const EWGIE: u32 = 1 << 8;
    pub const EPVIE: u32 = 1 << 9;
    pub const BOFIE: u32 = 1 << 10;
    pub const LECIE: u32 = 1 << 11;
    pub const ERRIE: u32 = 1 << 15;
    pub const WKUIE: u32 = 1 << 16;
    pub const SLKIE: u32 = 1 << 17;
}

const MCR_RESET: u32 = 0x0001_0002;
const MSR_RESET: u32 = 0x0000_0C02;
const BTR_RESET: u32 = 0x0123_0000;
/// FMR after reset: FINIT, CAN2SB = 14 (banks 0..13 are CAN1's).
const FMR_RESET: u32 = 0x2A1C_0E01;
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

/// What became of a frame from the bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Received {
    /// Stored in FIFO `fifo` with filter match index `fmi`.
    Stored {
        /// FIFO 0 or 1.
        fifo: usize,
        /// The filter match index.
        fmi: u8,
    },
    /// The FIFO was full: lost (FOVR set; with RFLM=0 the newest stored frame was replaced).
    Overrun {
        /// FIFO 0 or 1.
        fifo: usize,
    },
    /// No active filter accepted it.
    Filtered,
    /// Not in normal mode (initialisation, sleep or bus-off): not received.
    Offline,
}

#[derive(Debug, Clone, Copy, Default)]
struct Mailbox {
    tir: u32,
    tdtr: u32,
    tdlr: u32,
    tdhr: u32,
    /// Request order (for TXFP).
    seq: u64,
}

impl Mailbox {
    fn pending(&self) -> bool {
        self.tir & 1 != 0
    }

    fn frame(&self) -> CanFrame {
        let dlc = (self.tdtr & 0xF).min(8) as usize;
        let mut data = [0u8; 8];
        data[..4].copy_from_slice(&self.tdlr.to_le_bytes());
        data[4..].copy_from_slice(&self.tdhr.to_le_bytes());
        let id = if self.tir & 4 != 0 {
            Id::Extended(ExtendedId::new(self.tir >> 3).unwrap_or(ExtendedId::ZERO))
        } else {
            Id::Standard(StandardId::new((self.tir >> 21) as u16).unwrap_or(StandardId::ZERO))
        };
        let frame = if self.tir & 2 != 0 {
            CanFrame::new_remote(id, dlc)
        } else {
            CanFrame::new(id, &data[..dlc])
        };
        frame.unwrap_or_else(|| CanFrame::from_buffer(StandardId::ZERO, [0; 8], 0))
    }
}

#[derive(Debug, Clone, Default)]
struct Fifo {
    /// RIxR, RDTxR, RDLxR, RDHxR of each stored frame, oldest first.
    frames: VecDeque<[u32; 4]>,
    full: bool,
    overrun: bool,
}

/// The controller. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct BxCan {
    mcr: u32,
    msr: u32,
    /// TSR's per-mailbox flags: RQCP, TXOK, ALST, TERR (bits 0..3, 8..11, 16..19).
    tsr: u32,
    ier: u32,
    esr: u32,
    btr: u32,
    mailboxes: [Mailbox; 3],
    seq: u64,
    fifos: [Fifo; 2],
    filters: RegFile,
    /// The mailbox whose frame is on the wire.
    on_bus: Option<usize>,
    /// Bus-off: recovered at this cycle (automatic with ABOM, or once initialisation is left).
    recovery_at: Option<u64>,
    /// CPU cycles per APB1 clock (4: 168 MHz core, 42 MHz APB1).
    pclk_div: u64,
    /// Writes that select something the model does not do: (offset, value).
    pub unsupported: Vec<(u32, u32)>,
    /// Frames lost to a full FIFO, per FIFO.
    pub overruns: [u64; 2],
    /// Times the controller went bus-off.
    pub bus_offs: u64,
    /// The highest transmit error count reached (255 at bus-off).
    pub max_tec: u8,
}

impl Default for BxCan {
    fn default() -> Self {
        Self::new(4)
    }
}

/// The identifier as the filters and RIxR see it, 32-bit layout.
fn id_word(frame: &CanFrame) -> u32 {
    let rtr = u32::from(frame.is_remote_frame()) << 1;
    match frame.id() {
        Id::Standard(id) => u32::from(id.as_raw()) << 21 | rtr,
        Id::Extended(id) => id.as_raw() << 3 | 1 << 2 | rtr,
    }
}

/// The identifier in the 16-bit filter layout: STID, RTR, IDE, EXID[17:15].
fn id_half(frame: &CanFrame) -> u32 {
    let rtr = u32::from(frame.is_remote_frame()) << 4;
    match frame.id() {
        Id::Standard(id) => u32::from(id.as_raw()) << 5 | rtr,
        Id::Extended(id) => {
            let id = id.as_raw();
            (id >> 18) << 5 | rtr | 1 << 3 | ((id >> 15) & 7)
        }
    }
}

impl BxCan {
    /// The controller after reset (sleep mode); `pclk_div` CPU cycles per APB1 clock.
    #[must_use]
    pub fn new(pclk_div: u64) -> Self {
        Self {
            mcr: MCR_RESET,
            msr: MSR_RESET,
            tsr: 0,
            ier: 0,
            esr: 0,
            btr: BTR_RESET,
            mailboxes: [Mailbox::default(); 3],
            seq: 0,
            fifos: [Fifo::default(), Fifo::default()],
            filters: RegFile::new("CAN1 filters", 0x120, &[], &[(0, FMR_RESET)]),
            on_bus: None,
            recovery_at: None,
            pclk_div: pclk_div.max(1),
            unsupported: Vec::new(),
            overruns: [0; 2],
            bus_offs: 0,
            max_tec: 0,
        }
    }

    /// Changes the APB1 clock (RCC prescalers).
    pub fn set_pclk_div(&mut self, pclk_div: u64) {
        self.pclk_div = pclk_div.max(1);
    }

    /// CPU cycles per bit: (BRP + 1) × (1 + TS1 + 1 + TS2 + 1) APB1 clocks.
    #[must_use]
    pub fn cycles_per_bit(&self) -> u64 {
        let brp = u64::from(self.btr & 0x3FF) + 1;
        let ts1 = u64::from((self.btr >> 16) & 0xF) + 1;
        let ts2 = u64::from((self.btr >> 20) & 0x7) + 1;
        brp * (1 + ts1 + ts2) * self.pclk_div
    }

    /// Normal mode: neither initialisation nor sleep, and not bus-off.
    #[must_use]
    pub fn online(&self) -> bool {
        self.msr & (msr::INAK | msr::SLAK) == 0 && self.esr & 4 == 0
    }

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

    /// The mailbox the controller transmits next and its frame: in request order with
    /// TXFP, else the lowest identifier (then the lowest mailbox number). `None` unless
    /// online, or while a frame is on the wire.
    #[must_use]
    pub fn offer(&self) -> Option<(usize, CanFrame)> {
        if !self.online() || self.on_bus.is_some() {
            return None;
        }
        let pending = (0..3).filter(|&i| self.mailboxes[i].pending());
        let next = if self.mcr & mcr::TXFP != 0 {
            pending.min_by_key(|&i| self.mailboxes[i].seq)
        } else {
            pending.min_by_key(|&i| (self.mailboxes[i].tir >> 1, i))
        }?;
        Some((next, self.mailboxes[next].frame()))
    }

    /// The offered frame of `mailbox` started on the wire at `sof` (cycles): it can no
    /// longer be aborted; with TTCM its time stamp is taken.
    pub fn started(&mut self, mailbox: usize, sof: u64) {
        self.on_bus = Some(mailbox);
        if self.mcr & mcr::TTCM != 0 {
            let stamp = self.stamp(sof);
            let m = &mut self.mailboxes[mailbox];
            m.tdtr = (m.tdtr & 0xFFFF) | stamp << 16;
        }
    }

    /// The frame on the wire completed and was acknowledged: RQCP and TXOK, the mailbox
    /// empties, TEC counts down.
    pub fn transmitted(&mut self, mailbox: usize) {
        self.on_bus = None;
        self.mailboxes[mailbox].tir &= !1;
        self.tsr |= 0b11 << (8 * mailbox);
        let (tec, rec) = self.error_counters();
        self.set_counters(tec.saturating_sub(1), rec);
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

    /// The frame on the wire lost arbitration: ALST; it stays pending (retried).
    pub fn lost_arbitration(&mut self, mailbox: usize) {
        self.on_bus = None;
        self.tsr |= 0b100 << (8 * mailbox);
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

    fn set_counters(&mut self, tec: u8, rec: u8) {
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

    /// The 16-bit bit-time counter at `at` (the TTCM time stamp).
    fn stamp(&self, at: u64) -> u32 {
        ((at / self.cycles_per_bit()) & 0xFFFF) as u32
    }

    /// A frame another node completed at `eof` (cycles), whose SOF was at `sof`: filtered
    /// into a FIFO, with REC counting down.
    pub fn receive(&mut self, frame: &CanFrame, sof: u64) -> Received {
        if !self.online() {
            return Received::Offline;
        }
        let (tec, rec) = self.error_counters();
        self.set_counters(tec, rec.saturating_sub(1));
        let Some((fifo, fmi)) = self.filter(frame) else {
            return Received::Filtered;
        };
        let mut data = [0u8; 8];
        data[..frame.dlc()].copy_from_slice(frame.data());
        let time = if self.mcr & mcr::TTCM != 0 {
            self.stamp(sof)
        } else {
            0
        };
        let words = [
            id_word(frame),
            frame.dlc() as u32 | u32::from(fmi) << 8 | time << 16,
            u32::from_le_bytes([data[0], data[1], data[2], data[3]]),
            u32::from_le_bytes([data[4], data[5], data[6], data[7]]),
        ];
        let locked = self.mcr & mcr::RFLM != 0;
        let f = &mut self.fifos[fifo];
        if f.frames.len() == 3 {
            f.overrun = true;
            self.overruns[fifo] += 1;
            if !locked && let Some(newest) = f.frames.back_mut() {
                *newest = words;
            }
            return Received::Overrun { fifo };
        }
        f.frames.push_back(words);
        if f.frames.len() == 3 {
            f.full = true;
        }
        Received::Stored { fifo, fmi }
    }

    /// The filter that accepts `frame`, among CAN1's banks (below FMR.CAN2SB): its FIFO and
    /// match index. Priority (RM0090 §32.7.4): 32-bit over 16-bit, list over mask, then the
    /// lower filter number. Filter numbers count per FIFO, in bank order, active or not.
    #[must_use]
    pub fn filter(&self, frame: &CanFrame) -> Option<(usize, u8)> {
        let f = |off| self.filters.word(off - reg::FMR);
        if f(reg::FMR) & 1 != 0 {
            // Filter initialisation mode: reception is deactivated.
            return None;
        }
        let can2sb = ((f(reg::FMR) >> 8) & 0x3F).min(28);
        let (fm1r, fs1r, ffa1r, fa1r) = (f(reg::FM1R), f(reg::FS1R), f(reg::FFA1R), f(reg::FA1R));
        let (w32, w16) = (id_word(frame), id_half(frame));
        let mut numbers = [0u32; 2];
        // (rank: 16-bit?, mask?, number), FIFO, number.
        let mut best: Option<((bool, bool, u32), usize, u32)> = None;
        for bank in 0..can2sb {
            let fifo = ((ffa1r >> bank) & 1) as usize;
            let list = (fm1r >> bank) & 1 == 1;
            let scale32 = (fs1r >> bank) & 1 == 1;
            let r1 = f(reg::F0R1 + 8 * bank);
            let r2 = f(reg::F0R1 + 4 + 8 * bank);
            let count = match (scale32, list) {
                (true, false) => 1,
                (true, true) | (false, false) => 2,
                (false, true) => 4,
            };
            if (fa1r >> bank) & 1 == 1 {
                let hit = match (scale32, list) {
                    (true, false) => (((w32 ^ r1) & r2 & !1) == 0).then_some(0),
                    (true, true) => [r1, r2].iter().position(|&r| (w32 ^ r) & !1 == 0),
                    (false, false) => [r1, r2]
                        .iter()
                        .position(|&r| ((w16 ^ r) & (r >> 16) & 0xFFFF) == 0),
                    (false, true) => [r1 & 0xFFFF, r1 >> 16, r2 & 0xFFFF, r2 >> 16]
                        .iter()
                        .position(|&r| r == w16),
                };
                if let Some(j) = hit {
                    let number = numbers[fifo] + j as u32;
                    let rank = (!scale32, !list, number);
                    if best.is_none_or(|(b, _, _)| rank < b) {
                        best = Some((rank, fifo, number));
                    }
                }
            }
            numbers[fifo] += count;
        }
        best.map(|(_, fifo, number)| (fifo, number.min(255) as u8))
    }

    /// The interrupt lines: TX (IRQ 19), RX0 (20), RX1 (21), SCE (22).
    #[must_use]
    pub fn irq_lines(&self) -> [bool; 4] {
        let rx = |i: usize| {
            let f = &self.fifos[i];
            let shift = 1 + 3 * i;
            let fmpie = self.ier >> shift & 1 == 1;
            let ffie = self.ier >> (shift + 1) & 1 == 1;
            let fovie = self.ier >> (shift + 2) & 1 == 1;
            (fmpie && !f.frames.is_empty()) || (ffie && f.full) || (fovie && f.overrun)
        };
        let tx = self.ier & ier::TMEIE != 0 && self.tsr & 0x0001_0101 != 0;
        let sce = (self.ier & ier::ERRIE != 0 && self.msr & msr::ERRI != 0)
            || (self.ier & ier::WKUIE != 0 && self.msr & msr::WKUI != 0)
            || (self.ier & ier::SLKIE != 0 && self.msr & msr::SLAKI != 0);
        [tx, rx(0), rx(1), sce]
    }

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

#[cfg(test)]
mod tests {
    use super::*;

    fn std_frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
    }

    /// The controller as embassy-stm32 configures it for the board: initialisation, bank 0
    /// accepting every standard id into FIFO 0, 1 Mbit/s, TXFP, then normal mode.
    fn board_can() -> BxCan {
        let mut c = BxCan::new(4);
        c.write(reg::MCR, 4, mcr::INRQ, 0);
        assert_eq!(
            c.read(reg::MSR, 4).unwrap() & 3,
            msr::INAK,
            "initialisation"
        );
        c.write(reg::IER, 4, 0x8F13, 0);
        c.write(reg::FMR, 4, FMR_RESET, 0);
        c.write(reg::FA1R, 4, 1, 0);
        c.write(reg::FS1R, 4, 1, 0);
        c.write(reg::F0R1, 4, 0, 0);
        c.write(reg::F0R1 + 4, 4, 0x4, 0);
        c.write(reg::FMR, 4, FMR_RESET & !1, 0);
        c.write(reg::BTR, 4, 2 | 9 << 16 | 2 << 20, 0);
        c.write(reg::MCR, 4, mcr::TXFP | mcr::TTCM, 0);
        assert!(c.online());
        c
    }

    fn request(c: &mut BxCan, mailbox: u32, id: u16, data: &[u8]) {
        let base = reg::TI0R + 16 * mailbox;
        let mut bytes = [0u8; 8];
        bytes[..data.len()].copy_from_slice(data);
        c.write(base + 4, 4, data.len() as u32, 0);
        c.write(
            base + 8,
            4,
            u32::from_le_bytes(bytes[..4].try_into().unwrap()),
            0,
        );
        c.write(
            base + 12,
            4,
            u32::from_le_bytes(bytes[4..].try_into().unwrap()),
            0,
        );
        c.write(base, 4, u32::from(id) << 21 | 1, 0);
    }

    #[test]
    fn reset_values_are_rm0090s() {
        let c = BxCan::new(4);
        assert_eq!(c.read(reg::MCR, 4), Some(MCR_RESET));
        assert_eq!(c.read(reg::MSR, 4), Some(MSR_RESET));
        assert_eq!(c.read(reg::TSR, 4), Some(0x1C00_0000));
        assert_eq!(c.read(reg::BTR, 4), Some(BTR_RESET));
        assert_eq!(c.read(reg::FMR, 4), Some(FMR_RESET));
        assert_eq!((c.read(reg::FMR, 4).unwrap() >> 8) & 0x3F, 14, "CAN2SB");
        assert!(!c.online(), "sleep after reset");
    }

    #[test]
    fn init_and_sleep_handshakes_follow_mcr() {
        let mut c = BxCan::new(4);
        c.write(reg::MCR, 4, mcr::INRQ, 0);
        assert_eq!(c.read(reg::MSR, 4).unwrap() & 3, msr::INAK);
        c.write(reg::MCR, 4, mcr::SLEEP, 0);
        let msr = c.read(reg::MSR, 4).unwrap();
        assert_eq!(msr & 3, msr::SLAK);
        assert_ne!(msr & msr::SLAKI, 0, "SLAKI on entering sleep");
        c.write(reg::MSR, 4, msr::SLAKI, 0);
        assert_eq!(c.read(reg::MSR, 4).unwrap() & msr::SLAKI, 0, "rc_w1");
        c.write(reg::MCR, 4, 0, 0);
        assert!(c.online());
        // BTR is write-protected outside initialisation.
        c.write(reg::BTR, 4, 0, 0);
        assert_eq!(c.read(reg::BTR, 4), Some(BTR_RESET));
    }

    #[test]
    fn txfp_sends_in_request_order_and_tsr_reports_it() {
        let mut c = board_can();
        request(&mut c, 0, 0x300, &[1]);
        request(&mut c, 2, 0x100, &[2]);
        request(&mut c, 1, 0x200, &[3]);
        let tsr = c.read(reg::TSR, 4).unwrap();
        assert_eq!(tsr >> 26 & 7, 0, "no empty mailbox");
        assert_eq!(
            tsr >> 24 & 3,
            1,
            "CODE: the lowest-priority (last requested) mailbox"
        );
        let (m, f) = c.offer().unwrap();
        assert_eq!((m, f.data()), (0, &[1][..]), "request order, not id");
        c.started(m, 0);
        assert_eq!(c.offer(), None, "one frame on the wire at a time");
        c.transmitted(m);
        let tsr = c.read(reg::TSR, 4).unwrap();
        assert_eq!(tsr & 3, 3, "RQCP0 and TXOK0");
        assert_eq!(tsr >> 26 & 7, 1, "TME0");
        assert_eq!(tsr >> 24 & 3, 0, "CODE: the free mailbox");
        assert_eq!(c.irq_lines(), [true, false, false, false]);
        c.write(reg::TSR, 4, 1, 0);
        assert_eq!(c.read(reg::TSR, 4).unwrap() & 0xF, 0);
        assert_eq!(c.offer().unwrap().0, 2);
        // Without TXFP: the lowest identifier first.
        c.write(reg::MCR, 4, 0, 0);
        request(&mut c, 0, 0x050, &[]);
        assert_eq!(c.offer().unwrap().0, 0);
    }

    #[test]
    fn a_pending_mailbox_is_write_protected_and_abort_empties_it() {
        let mut c = board_can();
        request(&mut c, 0, 0x200, &[1, 2]);
        c.write(reg::TI0R + 8, 4, 0xFFFF_FFFF, 0);
        assert_eq!(c.offer().unwrap().1.data(), &[1, 2]);
        c.write(reg::TSR, 4, 1 << 7, 0);
        assert_eq!(c.offer(), None);
        assert_eq!(c.read(reg::TSR, 4).unwrap() & 0xF, 1, "RQCP without TXOK");
    }

    #[test]
    fn fifo_holds_three_then_overruns_and_fmp_counts() {
        let mut c = board_can();
        for i in 0..3u8 {
            assert_eq!(
                c.receive(&std_frame(0x201, &[i]), 0),
                Received::Stored { fifo: 0, fmi: 0 }
            );
        }
        let rf0r = c.read(reg::RF0R, 4).unwrap();
        assert_eq!((rf0r & 3, rf0r >> 3 & 1), (3, 1), "FMP 3, FULL");
        assert_eq!(
            c.receive(&std_frame(0x202, &[9]), 0),
            Received::Overrun { fifo: 0 }
        );
        assert_eq!(c.read(reg::RF0R, 4).unwrap() >> 4 & 1, 1, "FOVR");
        // RFLM = 0: the newest was overwritten by the new frame.
        c.write(reg::RF0R, 4, 1 << 5, 0);
        c.write(reg::RF0R, 4, 1 << 5, 0);
        assert_eq!(c.read(reg::RI0R, 4), Some(0x202 << 21));
        assert_eq!(c.read(reg::RI0R + 8, 4), Some(9));
        assert_eq!(c.read(reg::RI0R + 4, 4).unwrap() & 0xF, 1, "DLC");
        c.write(reg::RF0R, 4, 1 << 4, 0);
        assert_eq!(
            c.read(reg::RF0R, 4).unwrap(),
            1,
            "FOVR cleared by writing 1"
        );
        assert_eq!(c.overruns, [1, 0]);
        // FMPIE0 with a frame: RX0 line.
        assert!(c.irq_lines()[1]);
    }

    #[test]
    fn filters_match_in_all_four_modes_with_priority_and_fmi() {
        let mut c = board_can();
        c.write(reg::FMR, 4, FMR_RESET, 0);
        // Bank 0: 32-bit mask accepting 0x200..=0x20F into FIFO 0 (number 0).
        // Bank 1: 16-bit list of 0x201, 0x300, 0x301, 0x302 into FIFO 1 (numbers 0..3).
        // Bank 2: 32-bit list 0x205 and 0x206 into FIFO 1 (numbers 4, 5).
        // Bank 3: 16-bit masks, FIFO 0 (numbers 1, 2): exactly 0x400; 0x500..=0x5FF.
        c.write(reg::FS1R, 4, 0b0101, 0);
        c.write(reg::FM1R, 4, 0b0110, 0);
        c.write(reg::FFA1R, 4, 0b0110, 0);
        c.write(reg::F0R1, 4, 0x200 << 21, 0);
        c.write(reg::F0R1 + 4, 4, 0x7F0 << 21 | 0b110, 0);
        c.write(reg::F0R1 + 8, 4, 0x300 << 5 << 16 | 0x201 << 5, 0);
        c.write(reg::F0R1 + 12, 4, 0x302 << 5 << 16 | 0x301 << 5, 0);
        c.write(reg::F0R1 + 16, 4, 0x205 << 21, 0);
        c.write(reg::F0R1 + 20, 4, 0x206 << 21, 0);
        c.write(reg::F0R1 + 24, 4, 0xFFF8 << 16 | 0x400 << 5, 0);
        c.write(reg::F0R1 + 28, 4, 0xE018 << 16 | 0x500 << 5, 0);
        c.write(reg::FA1R, 4, 0b1111, 0);
        c.write(reg::FMR, 4, FMR_RESET & !1, 0);
        let at = |id| c.filter(&std_frame(id, &[]));
        // 0x201: bank 0 (32-bit mask) and bank 1 (16-bit list): 32-bit wins.
        assert_eq!(at(0x201), Some((0, 0)));
        // 0x205: bank 0 (32-bit mask) and bank 2 (32-bit list): the list wins.
        assert_eq!(at(0x205), Some((1, 4)));
        assert_eq!(at(0x206), Some((1, 5)));
        assert_eq!(at(0x301), Some((1, 2)));
        assert_eq!(at(0x302), Some((1, 3)));
        assert_eq!(at(0x400), Some((0, 1)));
        assert_eq!(at(0x4F1), None);
        assert_eq!(at(0x5AB), Some((0, 2)));
        assert_eq!(at(0x600), None);
        // An extended id never matches bank 0's IDE=0 mask.
        let ext = CanFrame::new(ExtendedId::new(0x200 << 18).unwrap(), &[]).unwrap();
        assert_eq!(c.filter(&ext), None);
        // In filter initialisation mode nothing is received.
        c.write(reg::FMR, 4, FMR_RESET, 0);
        assert_eq!(c.receive(&std_frame(0x201, &[]), 0), Received::Filtered);
    }

    #[test]
    fn no_ack_makes_the_sender_error_passive_and_bit_errors_bus_off_with_abom_recovery() {
        let mut c = board_can();
        c.write(reg::MCR, 4, mcr::INRQ, 0);
        c.write(reg::IER, 4, ier::ERRIE | ier::BOFIE | ier::EPVIE, 0);
        c.write(reg::MCR, 4, mcr::TXFP | mcr::ABOM, 0);
        request(&mut c, 0, 0x200, &[1]);
        for _ in 0..40 {
            let (m, _) = c.offer().unwrap();
            c.started(m, 0);
            c.tx_error(m, Lec::Ack, 0);
        }
        // 16 ACK errors reach 128 (error passive); ACK errors then no longer count.
        assert_eq!(c.error_counters().0, 128);
        assert_eq!(c.read(reg::ESR, 4).unwrap() & 7, 0b011, "EWGF and EPVF");
        assert_eq!(c.read(reg::ESR, 4).unwrap() >> 4 & 7, Lec::Ack as u32);
        assert!(c.irq_lines()[3], "SCE: ERRI with EPVIE");
        for _ in 0..16 {
            let (m, _) = c.offer().unwrap();
            c.started(m, 0);
            c.tx_error(m, Lec::BitDominant, 1000);
        }
        assert!(c.bus_off());
        assert_eq!(c.offer(), None);
        assert_eq!(c.receive(&std_frame(0x201, &[]), 0), Received::Offline);
        let due = 1000 + BUS_OFF_RECOVERY_BITS * c.cycles_per_bit();
        assert_eq!(c.next_event(), Some(due));
        c.advance(due - 1);
        assert!(c.bus_off());
        c.advance(due);
        assert!(!c.bus_off() && c.online());
        assert_eq!(c.error_counters(), (0, 0));
        // The mailbox is still pending (NART = 0): it is sent after the recovery.
        assert_eq!(c.offer().map(|(m, _)| m), Some(0));
    }

    #[test]
    fn the_boards_bit_time_is_one_microsecond() {
        let c = board_can();
        // 168 MHz core, 42 MHz APB1: 3 x 14 quanta of 4 cycles.
        assert_eq!(c.cycles_per_bit(), 168);
    }
}
