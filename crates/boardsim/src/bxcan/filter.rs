//! The 28 filter banks (RM0090 §32.7.4) in their four modes (16- or 32-bit, mask or list),
//! with the filter match index.

use embedded_can::{Frame, Id};
use firmware::CanFrame;

use super::BxCan;
use super::registers::reg;

/// The identifier as the filters and RIxR see it, 32-bit layout.
pub(super) fn id_word(frame: &CanFrame) -> u32 {
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
}
