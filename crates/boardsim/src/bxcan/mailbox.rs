//! The transmit mailboxes (chosen by request order or identifier) and the two 3-deep receive
//! FIFOs (FMP, FULL, FOVR; locked or overwriting), with the TTCM time stamps.

use std::collections::VecDeque;

use embedded_can::{ExtendedId, Frame, Id, StandardId};
use firmware::CanFrame;

use super::BxCan;
use super::filter::id_word;
use super::registers::mcr;

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

/// A transmit mailbox: TIxR, TDTxR, TDLxR, TDHxR.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Mailbox {
    pub(super) tir: u32,
    pub(super) tdtr: u32,
    pub(super) tdlr: u32,
    pub(super) tdhr: u32,
    /// Request order (for TXFP).
    pub(super) seq: u64,
}

impl Mailbox {
    pub(super) fn pending(&self) -> bool {
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

/// A receive FIFO.
#[derive(Debug, Clone, Default)]
pub(super) struct Fifo {
    /// RIxR, RDTxR, RDLxR, RDHxR of each stored frame, oldest first.
    pub(super) frames: VecDeque<[u32; 4]>,
    pub(super) full: bool,
    pub(super) overrun: bool,
}

impl BxCan {
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

    /// The frame on the wire lost arbitration: ALST; it stays pending (retried).
    pub fn lost_arbitration(&mut self, mailbox: usize) {
        self.on_bus = None;
        self.tsr |= 0b100 << (8 * mailbox);
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
}
