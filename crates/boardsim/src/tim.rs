//! TIM2, a general-purpose timer (RM0090 §18) counting up on the APB1 timer clock: prescaler
//! and auto-reload with their preload registers, the update event (overflow or EGR.UG, URS,
//! UDIS, OPM), four compare channels, the status flags (rc_w0) and their interrupt.
//!
//! The counter is not stepped: it is a start (`cnt0` at `base` CPU cycles) and a rate (CPU
//! cycles per count = cycles per timer clock × (PSC + 1)), so a read of CNT at any cycle is
//! exact and the next event's cycle is known in advance (the board sleeps until it). Counting
//! down, centre-aligned modes, input capture, slave modes and DMA are not modelled: embassy's
//! time driver uses none of them, and a write that selects one is reported.

/// Register offsets.
pub mod reg {
    /// Control 1: CEN, UDIS, URS, OPM, DIR, CMS, ARPE.
    pub const CR1: u32 = 0x00;
    /// Control 2.
    pub const CR2: u32 = 0x04;
    /// Slave mode control.
    pub const SMCR: u32 = 0x08;
    /// DMA/interrupt enable: UIE, CC1IE..CC4IE.
    pub const DIER: u32 = 0x0C;
    /// Status: UIF, CC1IF..CC4IF (write 0 to clear).
    pub const SR: u32 = 0x10;
    /// Event generation: UG.
    pub const EGR: u32 = 0x14;
    /// Capture/compare mode 1.
    pub const CCMR1: u32 = 0x18;
    /// Capture/compare mode 2.
    pub const CCMR2: u32 = 0x1C;
    /// Capture/compare enable.
    pub const CCER: u32 = 0x20;
    /// Counter.
    pub const CNT: u32 = 0x24;
    /// Prescaler.
    pub const PSC: u32 = 0x28;
    /// Auto-reload.
    pub const ARR: u32 = 0x2C;
    /// Compare 1; CCR2..CCR4 follow.
    pub const CCR1: u32 = 0x34;
    /// DMA control.
    pub const DCR: u32 = 0x48;
    /// DMA address.
    pub const DMAR: u32 = 0x4C;
    /// Option register (TIM2: ITR1 remap).
    pub const OR: u32 = 0x50;
}

const CEN: u32 = 1;
const UDIS: u32 = 1 << 1;
const URS: u32 = 1 << 2;
const OPM: u32 = 1 << 3;
const ARPE: u32 = 1 << 7;
const UIF: u32 = 1;
/// The flags that can raise the interrupt (UIF, CC1IF..CC4IF, TIF) with their DIER enables.
const IRQ_FLAGS: u32 = 0x5F;

/// A 32-bit up-counting timer. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct Timer {
    cr1: u32,
    cr2: u32,
    smcr: u32,
    dier: u32,
    sr: u32,
    ccmr: [u32; 2],
    ccer: u32,
    /// Prescaler in use, and the value written (loaded at the next update event).
    psc: u32,
    psc_preload: u32,
    /// Auto-reload in use, and the value written (loaded at the next update with ARPE).
    arr: u32,
    arr_preload: u32,
    ccr: [u32; 4],
    dcr: u32,
    or: u32,
    /// CPU cycles per timer clock (2: 168 MHz core, 84 MHz APB1 timers).
    clock_div: u64,
    /// The counter was `cnt0` at `base` cycles.
    base: u64,
    cnt0: u32,
    /// Counts since `base` whose events `advance` has already flagged.
    seen: u64,
    /// Writes that select something the model does not do: (register offset, value).
    pub unsupported: Vec<(u32, u32)>,
    /// The cycle of the latest compare match flagged (any channel).
    pub last_compare_at: Option<u64>,
}

impl Timer {
    /// The timer after reset; `clock_div` CPU cycles per timer clock.
    #[must_use]
    pub fn new(clock_div: u64) -> Self {
        Self {
            cr1: 0,
            cr2: 0,
            smcr: 0,
            dier: 0,
            sr: 0,
            ccmr: [0; 2],
            ccer: 0,
            psc: 0,
            psc_preload: 0,
            arr: u32::MAX,
            arr_preload: u32::MAX,
            ccr: [0; 4],
            dcr: 0,
            or: 0,
            clock_div: clock_div.max(1),
            base: 0,
            cnt0: 0,
            seen: 0,
            unsupported: Vec::new(),
            last_compare_at: None,
        }
    }

    /// Changes the timer clock (the RCC prescalers changed) from `now` on.
    pub fn set_clock_div(&mut self, clock_div: u64, now: u64) {
        self.rebase(now);
        self.clock_div = clock_div.max(1);
    }

    fn running(&self) -> bool {
        self.cr1 & CEN != 0
    }

    /// CPU cycles per count.
    fn cycles_per_count(&self) -> u64 {
        self.clock_div * (u64::from(self.psc) + 1)
    }

    /// Counts since `base`.
    fn counts(&self, now: u64) -> u64 {
        if self.running() {
            now.saturating_sub(self.base) / self.cycles_per_count()
        } else {
            0
        }
    }

    fn modulus(&self) -> u64 {
        u64::from(self.arr) + 1
    }

    /// The counter after `k` counts from `cnt0`.
    fn cnt_after(&self, k: u64) -> u32 {
        ((u64::from(self.cnt0) + k) % self.modulus()) as u32
    }

    /// The count k > `after` (since `base`) at which the counter first equals `value`
    /// (0 for the overflow).
    fn first_count_at(&self, value: u32, after: u64) -> Option<u64> {
        let m = self.modulus();
        if u64::from(value) >= m {
            return None;
        }
        let start = u64::from(self.cnt0) + after + 1;
        let k = start + (u64::from(value) + m - start % m) % m;
        Some(k - u64::from(self.cnt0))
    }

    /// Flags the events up to `now`: the update at each overflow (loading the preloaded
    /// PSC and ARR, which restarts the arithmetic there), compare matches.
    pub fn advance(&mut self, now: u64) {
        if !self.running() {
            return;
        }
        loop {
            let k = self.counts(now);
            if k <= self.seen {
                return;
            }
            let update = self
                .first_count_at(0, self.seen)
                .filter(|&at| at <= k && self.cr1 & UDIS == 0);
            // Compares up to the update (after it, the new PSC and ARR count).
            let end = update.unwrap_or(k);
            for i in 0..4 {
                if let Some(at) = self
                    .first_count_at(self.ccr[i], self.seen)
                    .filter(|&at| at <= end)
                {
                    self.sr |= 1 << (i + 1);
                    let at_cycle = self.base + at * self.cycles_per_count();
                    self.last_compare_at = self.last_compare_at.max(Some(at_cycle));
                }
            }
            match update {
                Some(at) => {
                    // The update: flags, preloads, and the counting restarts there.
                    let at_cycle = self.base + at * self.cycles_per_count();
                    self.sr |= UIF;
                    self.psc = self.psc_preload;
                    if self.cr1 & ARPE != 0 {
                        self.arr = self.arr_preload;
                    }
                    if self.cr1 & OPM != 0 {
                        self.cr1 &= !CEN;
                    }
                    self.base = at_cycle;
                    self.cnt0 = 0;
                    self.seen = 0;
                }
                None => {
                    self.seen = k;
                    return;
                }
            }
        }
    }

    /// The first cycle after `now` at which an enabled interrupt flag would be set.
    #[must_use]
    pub fn next_event(&self, now: u64) -> Option<u64> {
        if !self.running() {
            return None;
        }
        let seen = self.counts(now).max(self.seen);
        let mut best: Option<u64> = None;
        if self.dier & 1 != 0 && self.cr1 & UDIS == 0 {
            best = self.first_count_at(0, seen);
        }
        for i in 0..4 {
            if self.dier & (1 << (i + 1)) != 0
                && let Some(at) = self.first_count_at(self.ccr[i], seen)
            {
                // A compare after the next update follows the new PSC/ARR: waking at the
                // update is early, never late.
                best = Some(best.map_or(at, |b| b.min(at)));
            }
        }
        best.map(|k| self.base + k * self.cycles_per_count())
    }

    /// The interrupt line: a flag set with its enable.
    #[must_use]
    pub fn irq(&self) -> bool {
        self.sr & self.dier & IRQ_FLAGS != 0
    }

    /// Restarts the arithmetic at `now` from the current counter value.
    fn rebase(&mut self, now: u64) {
        self.advance(now);
        let k = self.counts(now);
        self.cnt0 = self.cnt_after(k);
        self.base = if self.running() {
            // Keep the fraction of a count already elapsed.
            self.base + k * self.cycles_per_count()
        } else {
            now
        };
        self.seen = 0;
    }

    /// The counter at `now`, without flagging the events on the way (a read of CNT does:
    /// after an update, only it counts with the new PSC and ARR).
    #[must_use]
    pub fn cnt(&self, now: u64) -> u32 {
        self.cnt_after(self.counts(now))
    }

    /// A read of the register at `off` (word access; sub-word reads take their bytes).
    /// `None` for an offset the model does not know.
    pub fn read(&mut self, off: u32, size: usize, now: u64) -> Option<u32> {
        self.advance(now);
        let v = match off & !3 {
            reg::CR1 => self.cr1,
            reg::CR2 => self.cr2,
            reg::SMCR => self.smcr,
            reg::DIER => self.dier,
            reg::SR => self.sr,
            reg::EGR => 0,
            reg::CCMR1 => self.ccmr[0],
            reg::CCMR2 => self.ccmr[1],
            reg::CCER => self.ccer,
            reg::CNT => self.cnt(now),
            reg::PSC => self.psc_preload,
            reg::ARR => self.arr_preload,
            o @ reg::CCR1..=0x40 => self.ccr[((o - reg::CCR1) / 4) as usize],
            reg::DCR => self.dcr,
            reg::DMAR => 0,
            reg::OR => self.or,
            _ => return None,
        };
        Some(crate::regs::sub_word(v, off, size))
    }

    /// A write at `off`. `None` for an offset the model does not know.
    pub fn write(&mut self, off: u32, size: usize, value: u32, now: u64) -> Option<()> {
        let word = off & !3;
        let old = self.read(word, 4, now)?;
        let v = crate::regs::merge(old, off, size, value);
        self.rebase(now);
        match word {
            reg::CR1 => {
                if v & 0x70 != 0 {
                    // DIR (down) or CMS (centre-aligned).
                    self.unsupported.push((word, v));
                }
                self.cr1 = v & 0x3FF;
            }
            reg::CR2 => self.cr2 = v,
            reg::SMCR => {
                if v & 7 != 0 {
                    self.unsupported.push((word, v));
                }
                self.smcr = v;
            }
            reg::DIER => self.dier = v & 0x5F5F,
            // rc_w0: writing 0 clears a flag, 1 leaves it.
            reg::SR => self.sr &= v,
            reg::EGR => {
                if v & 1 != 0 {
                    // UG: reinitialise the counter and load the preloads; UIF unless URS.
                    self.cnt0 = 0;
                    self.psc = self.psc_preload;
                    self.arr = self.arr_preload;
                    if self.cr1 & URS == 0 && self.cr1 & UDIS == 0 {
                        self.sr |= UIF;
                    }
                }
                // CCxG: the compare flags.
                self.sr |= v & 0x1E;
            }
            reg::CCMR1 => self.ccmr[0] = v,
            reg::CCMR2 => self.ccmr[1] = v,
            reg::CCER => self.ccer = v,
            reg::CNT => self.cnt0 = v,
            reg::PSC => self.psc_preload = v & 0xFFFF,
            reg::ARR => {
                self.arr_preload = v;
                if self.cr1 & ARPE == 0 {
                    self.arr = v;
                }
            }
            o @ reg::CCR1..=0x40 => self.ccr[((o - reg::CCR1) / 4) as usize] = v,
            reg::DCR => self.dcr = v,
            reg::DMAR => {}
            reg::OR => self.or = v,
            _ => return None,
        }
        if self.cnt0 > self.arr {
            // Past the reload value (ARR lowered): a 32-bit counter would count to 2^32 and
            // wrap; the model wraps at the next count instead.
            self.unsupported.push((word, v));
            self.cnt0 = (u64::from(self.cnt0) % self.modulus()) as u32;
        }
        Some(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// embassy-stm32's gp16 time driver set-up: PSC 83 on the 84 MHz timer clock (1 MHz),
    /// ARR 0xFFFF, URS around UG, CCR1 half way, UIE and CC1IE, CEN.
    fn embassy_tim2() -> Timer {
        let mut t = Timer::new(2);
        t.write(reg::CR1, 4, 0, 0);
        t.write(reg::CNT, 4, 0, 0);
        t.write(reg::PSC, 4, 83, 0);
        t.write(reg::ARR, 4, 0xFFFF, 0);
        t.write(reg::CR1, 4, URS, 0);
        t.write(reg::EGR, 4, 1, 0);
        t.write(reg::CR1, 4, 0, 0);
        t.write(reg::CCR1, 4, 0x8000, 0);
        t.write(reg::DIER, 4, 0b11, 0);
        t.write(reg::CR1, 4, CEN, 0);
        t
    }

    #[test]
    fn embassy_setup_counts_microseconds_without_a_spurious_update() {
        let mut t = embassy_tim2();
        assert_eq!(t.read(reg::SR, 4, 0), Some(0), "URS: UG set no UIF");
        // 168 CPU cycles per µs.
        assert_eq!(t.cnt(168 * 1000), 1000);
        assert_eq!(t.cnt(168 * 1000 + 167), 1000);
        assert_eq!(t.next_event(0), Some(168 * 0x8000), "CC1 half way");
        assert!(!t.irq());
        t.advance(168 * 0x8000);
        assert!(t.irq());
        assert_eq!(t.read(reg::SR, 4, 168 * 0x8000), Some(0b10));
        // The ISR writes !SR (rc_w0): clears what it saw.
        t.write(reg::SR, 4, !0b10, 168 * 0x8000);
        assert!(!t.irq());
        assert_eq!(
            t.next_event(168 * 0x8000),
            Some(168 * 0x1_0000),
            "the overflow"
        );
        t.advance(168 * 0x1_0000);
        // UIF, and the compares of CCR2..4 (0) at the wrap: flags are set enabled or not.
        assert_eq!(t.read(reg::SR, 4, 168 * 0x1_0000), Some(0b11101));
        assert_eq!(t.cnt(168 * 0x1_0000), 0);
        assert_eq!(t.cnt(168 * 0x1_0005), 5);
    }

    #[test]
    fn a_compare_channel_enabled_later_fires_at_its_count() {
        let mut t = embassy_tim2();
        let now = 168 * 100;
        // An alarm 250 µs ahead on CCR2 with CC2IE.
        t.write(reg::CCR1 + 4, 4, 350, now);
        t.write(reg::DIER, 4, 0b111, now);
        assert_eq!(t.next_event(now), Some(168 * 350));
        t.advance(168 * 349);
        assert!(!t.irq());
        t.advance(168 * 350);
        assert_eq!(
            t.read(reg::SR, 4, 168 * 350).map(|s| s & 0b100),
            Some(0b100)
        );
    }

    #[test]
    fn the_prescaler_takes_effect_at_the_update_event() {
        let mut t = Timer::new(1);
        t.write(reg::ARR, 4, 9, 0);
        t.write(reg::CR1, 4, CEN, 0);
        assert_eq!(t.read(reg::CNT, 4, 5).unwrap(), 5);
        // PSC 1 (÷2) written mid-period: still ÷1 until the overflow at 10.
        t.write(reg::PSC, 4, 1, 5);
        assert_eq!(t.read(reg::CNT, 4, 9).unwrap(), 9);
        t.advance(10);
        assert_eq!(t.read(reg::SR, 4, 10).map(|s| s & 1), Some(1));
        assert_eq!(t.read(reg::CNT, 4, 10).unwrap(), 0);
        assert_eq!(t.read(reg::CNT, 4, 14).unwrap(), 2, "÷2 after the update");
        // ARPE: ARR written now applies at the next update.
        t.write(reg::CR1, 4, CEN | ARPE, 14);
        t.write(reg::ARR, 4, 3, 14);
        assert_eq!(t.read(reg::CNT, 4, 28).unwrap(), 9);
        assert_eq!(t.read(reg::CNT, 4, 30).unwrap(), 0);
        assert_eq!(t.read(reg::CNT, 4, 36).unwrap(), 3);
        assert_eq!(
            t.read(reg::CNT, 4, 38).unwrap(),
            0,
            "period of 4 counts now"
        );
    }

    #[test]
    fn one_pulse_mode_stops_at_the_update_and_udis_suppresses_it() {
        let mut t = Timer::new(1);
        t.write(reg::ARR, 4, 4, 0);
        t.write(reg::CR1, 4, CEN | OPM, 0);
        t.advance(100);
        assert_eq!(t.read(reg::CR1, 4, 100).map(|c| c & CEN), Some(0));
        assert_eq!(t.cnt(100), 0);
        let mut u = Timer::new(1);
        u.write(reg::ARR, 4, 4, 0);
        u.write(reg::DIER, 4, 1, 0);
        u.write(reg::CR1, 4, CEN | UDIS, 0);
        assert_eq!(u.next_event(0), None);
        u.advance(100);
        assert_eq!(u.read(reg::SR, 4, 100).map(|s| s & 1), Some(0));
        // UG without URS sets UIF (unless UDIS).
        u.write(reg::CR1, 4, CEN, 100);
        u.write(reg::EGR, 4, 1, 100);
        assert_eq!(u.read(reg::SR, 4, 100).map(|s| s & 1), Some(1));
        assert!(u.irq());
    }

    #[test]
    fn unknown_offsets_and_unsupported_modes_are_reported() {
        let mut t = Timer::new(1);
        assert_eq!(t.read(0x60, 4, 0), None);
        t.write(reg::CR1, 4, 1 << 4, 0);
        assert_eq!(t.unsupported, vec![(reg::CR1, 1 << 4)]);
    }
}
