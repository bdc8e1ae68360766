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
//!
//! The parts, one service each: `registers` (the register map: reads, writes, the modes),
//! `mailbox` (the transmit mailboxes and the receive FIFOs), `filter` (the filter banks),
//! `error` (the error counters and states, bus-off and its recovery).

use crate::regs::RegFile;

mod error;
mod filter;
mod mailbox;
mod registers;

pub use error::{BUS_OFF_RECOVERY_BITS, Lec};
pub use mailbox::Received;
pub use registers::reg;

use mailbox::{Fifo, Mailbox};
use registers::{BTR_RESET, FMR_RESET, MCR_RESET, MSR_RESET, ier, msr};

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
}

#[cfg(test)]
mod tests;
