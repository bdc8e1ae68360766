//! The independent watchdog (RM0090 §21): a 12-bit down-counter on the LSI (32 kHz) through a
//! prescaler of 4 to 256, started by writing 0xCCCC to KR and reloaded with 0xAAAA; when it
//! reaches 0 the chip resets. PR and RLR are writable only after 0x5555 (any other key locks
//! them again); once started, nothing but a reset stops it.
//!
//! The counter is kept as the cycle of its last reload: it expires (RLR + 1) × prescaler LSI
//! periods later. A new PR or RLR takes effect at once (the chip's PVU/RVU update delay of a
//! few LSI periods is not modelled; SR reads 0).

/// Register offsets.
pub mod reg {
    /// Key.
    pub const KR: u32 = 0x00;
    /// Prescaler.
    pub const PR: u32 = 0x04;
    /// Reload.
    pub const RLR: u32 = 0x08;
    /// Status.
    pub const SR: u32 = 0x0C;
}

/// Keys written to KR.
pub mod key {
    /// Unlock PR and RLR.
    pub const UNLOCK: u32 = 0x5555;
    /// Start the watchdog.
    pub const START: u32 = 0xCCCC;
    /// Reload the counter (feed it).
    pub const RELOAD: u32 = 0xAAAA;
}

/// The LSI's nominal frequency on the STM32F4 (RM0090 §7.2.5; embassy-stm32 assumes it too).
pub const LSI_HZ: u64 = 32_000;

/// The watchdog. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct Iwdg {
    unlocked: bool,
    pr: u32,
    rlr: u32,
    /// Started: the cycle of the last reload.
    reloaded_at: Option<u64>,
    /// CPU cycles per LSI period.
    cycles_per_lsi: u64,
}

impl Iwdg {
    /// After reset (stopped, PR 0: /4, RLR 0xFFF), for a CPU of `cpu_hz`.
    #[must_use]
    pub const fn new(cpu_hz: u64) -> Self {
        Self {
            unlocked: false,
            pr: 0,
            rlr: 0xFFF,
            reloaded_at: None,
            cycles_per_lsi: cpu_hz / LSI_HZ,
        }
    }

    /// Started.
    #[must_use]
    pub const fn running(&self) -> bool {
        self.reloaded_at.is_some()
    }

    /// The watchdog's period: (RLR + 1) × 4 · 2^PR LSI periods, in CPU cycles.
    #[must_use]
    pub const fn period(&self) -> u64 {
        let prescaler = 4u64 << (if self.pr > 6 { 6 } else { self.pr });
        (self.rlr as u64 + 1) * prescaler * self.cycles_per_lsi
    }

    /// The cycle at which it resets the chip, if started.
    #[must_use]
    pub fn expiry(&self) -> Option<u64> {
        self.reloaded_at.map(|at| at + self.period())
    }

    /// A read; `None` for an offset the model does not know.
    #[must_use]
    pub fn read(&self, off: u32) -> Option<u32> {
        match off & !3 {
            reg::KR | reg::SR => Some(0),
            reg::PR => Some(self.pr),
            reg::RLR => Some(self.rlr),
            _ => None,
        }
    }

    /// A write at `now` (cycles); `None` for an offset the model does not know.
    pub fn write(&mut self, off: u32, value: u32, now: u64) -> Option<()> {
        match off & !3 {
            reg::KR => {
                // Any key but the unlocking one protects PR and RLR again.
                self.unlocked = value & 0xFFFF == key::UNLOCK;
                match value & 0xFFFF {
                    key::START => self.reloaded_at = Some(now),
                    key::RELOAD if self.running() => self.reloaded_at = Some(now),
                    _ => {}
                }
            }
            reg::PR if self.unlocked => self.pr = value & 7,
            reg::RLR if self.unlocked => self.rlr = value & 0xFFF,
            reg::PR | reg::RLR | reg::SR => {}
            _ => return None,
        }
        Some(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CPU: u64 = 168_000_000;

    #[test]
    fn it_expires_after_its_period_unless_reloaded() {
        let mut w = Iwdg::new(CPU);
        assert_eq!(w.expiry(), None, "stopped after reset");
        // embassy's IndependentWatchdog::new(_, 50 ms): unlock, PR 0 (/4), RLR 399.
        w.write(reg::KR, key::UNLOCK, 0);
        w.write(reg::PR, 0, 0);
        w.write(reg::RLR, 399, 0);
        assert_eq!(w.read(reg::RLR), Some(399));
        w.write(reg::KR, key::START, 1000);
        // 400 x 4 LSI periods of 5250 cycles: 50 ms.
        assert_eq!(w.expiry(), Some(1000 + CPU / 20));
        w.write(reg::KR, key::RELOAD, 5000);
        assert_eq!(w.expiry(), Some(5000 + CPU / 20));
    }

    #[test]
    fn pr_and_rlr_are_locked_without_the_key_and_reload_does_not_start_it() {
        let mut w = Iwdg::new(CPU);
        w.write(reg::RLR, 10, 0);
        assert_eq!(w.read(reg::RLR), Some(0xFFF), "locked");
        w.write(reg::KR, key::RELOAD, 0);
        assert!(!w.running(), "0xAAAA does not start it");
        w.write(reg::KR, key::UNLOCK, 0);
        w.write(reg::KR, 0x1234, 0);
        w.write(reg::PR, 6, 0);
        assert_eq!(w.read(reg::PR), Some(0), "another key locks again");
        assert_eq!(w.read(0x10), None);
    }
}
