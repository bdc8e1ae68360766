//! The Cortex-M4 System Control Space: NVIC, SCB and SysTick, as registers and as the rules
//! that choose which exception the core takes next (ARMv7-M ARM B1.5, B3.2-B3.4; Cortex-M4
//! TRM §4). Unicorn has none of it: the board does exception entry and return itself
//! ([`crate::board`]) and asks this model which exception preempts.
//!
//! Priorities: 8-bit fields of which the STM32F4 implements the top 4 (the low bits read 0);
//! AIRCR.PRIGROUP splits them into group priority (preemption) and subpriority (order among
//! pending). Reset, NMI and HardFault have the fixed priorities -3, -2, -1. An interrupt
//! pended while it cannot be taken (disabled, PRIMASK, BASEPRI, a higher active one) stays
//! pending; a level-sensitive peripheral line that is still asserted pends again after its
//! handler returns (the board re-evaluates the lines after each slice).

/// Exception numbers.
pub mod exc {
    /// Non-maskable interrupt.
    pub const NMI: u16 = 2;
    /// HardFault.
    pub const HARD_FAULT: u16 = 3;
    /// Supervisor call.
    pub const SVCALL: u16 = 11;
    /// Pendable service request.
    pub const PENDSV: u16 = 14;
    /// SysTick.
    pub const SYSTICK: u16 = 15;
    /// External interrupt 0 (IRQ n is exception 16 + n).
    pub const IRQ0: u16 = 16;
}

/// External interrupts of the STM32F407 (RM0090 Table 61: IRQ 0..=81).
pub const IRQS: usize = 82;
const WORDS: usize = IRQS.div_ceil(32);
/// Exceptions, system and external.
const EXCEPTIONS: usize = 16 + IRQS;
/// Priority bits the STM32F4 implements (the top ones of each 8-bit field).
const PRIO_MASK: u8 = 0xF0;
/// The priority of thread mode with nothing active: below every configurable one.
pub const THREAD_PRIORITY: i16 = 256;

/// What a write to the SCS asks of the board.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Effect {
    /// Nothing beyond the register change.
    None,
    /// An exception may have become pending: the CPU should stop to take it.
    Pended,
    /// AIRCR.SYSRESETREQ: reset the system.
    SystemReset,
}

/// The SCS's state.
#[derive(Debug, Clone)]
pub struct Scs {
    enabled: [u32; WORDS],
    pending: [u32; WORDS],
    /// Active exceptions (system and external), one flag per exception number.
    active: [bool; EXCEPTIONS],
    /// The stack of active exceptions, outermost first (for nesting and RETTOBASE).
    stack: Vec<u16>,
    /// IPR: priority of each external interrupt.
    irq_priority: [u8; IRQS],
    /// SHPR1-3: priority of system exceptions 4..=15.
    sys_priority: [u8; 12],
    pend_sv: bool,
    pend_systick: bool,
    pend_nmi: bool,
    vtor: u32,
    aircr_prigroup: u32,
    scr: u32,
    ccr: u32,
    shcsr: u32,
    cpacr: u32,
    fpccr: u32,
    fpcar: u32,
    fpdscr: u32,
    systick: SysTick,
}

impl Default for Scs {
    fn default() -> Self {
        Self::new()
    }
}

/// Register offsets in the SCS page (0xE000_E000).
pub mod reg {
    /// SysTick control and status.
    pub const SYST_CSR: u32 = 0x010;
    /// SysTick reload value.
    pub const SYST_RVR: u32 = 0x014;
    /// SysTick current value.
    pub const SYST_CVR: u32 = 0x018;
    /// SysTick calibration.
    pub const SYST_CALIB: u32 = 0x01C;
    /// Interrupt set-enable 0..2.
    pub const ISER: u32 = 0x100;
    /// Interrupt clear-enable.
    pub const ICER: u32 = 0x180;
    /// Interrupt set-pending.
    pub const ISPR: u32 = 0x200;
    /// Interrupt clear-pending.
    pub const ICPR: u32 = 0x280;
    /// Interrupt active bits.
    pub const IABR: u32 = 0x300;
    /// Interrupt priorities, a byte each.
    pub const IPR: u32 = 0x400;
    /// CPUID base.
    pub const CPUID: u32 = 0xD00;
    /// Interrupt control and state.
    pub const ICSR: u32 = 0xD04;
    /// Vector table offset.
    pub const VTOR: u32 = 0xD08;
    /// Application interrupt and reset control.
    pub const AIRCR: u32 = 0xD0C;
    /// System control.
    pub const SCR: u32 = 0xD10;
    /// Configuration and control.
    pub const CCR: u32 = 0xD14;
    /// System handler priorities 1..3 (bytes for exceptions 4..=15).
    pub const SHPR: u32 = 0xD18;
    /// System handler control and state.
    pub const SHCSR: u32 = 0xD24;
    /// Coprocessor access control.
    pub const CPACR: u32 = 0xD88;
    /// Software trigger interrupt.
    pub const STIR: u32 = 0xF00;
    /// FP context control.
    pub const FPCCR: u32 = 0xF34;
    /// FP context address.
    pub const FPCAR: u32 = 0xF38;
    /// FP default status control.
    pub const FPDSCR: u32 = 0xF3C;
}

/// Cortex-M4 r0p1 (the STM32F407's core).
pub const CPUID: u32 = 0x410F_C241;

impl Scs {
    /// The SCS after reset: nothing enabled or pending, all priorities 0, VTOR 0, CCR.STKALIGN,
    /// FPCCR.ASPEN|LSPEN.
    #[must_use]
    pub fn new() -> Self {
        Self {
            enabled: [0; WORDS],
            pending: [0; WORDS],
            active: [false; EXCEPTIONS],
            stack: Vec::new(),
            irq_priority: [0; IRQS],
            sys_priority: [0; 12],
            pend_sv: false,
            pend_systick: false,
            pend_nmi: false,
            vtor: 0,
            aircr_prigroup: 0,
            scr: 0,
            ccr: 0x200,
            shcsr: 0,
            cpacr: 0,
            fpccr: 0xC000_0000,
            fpcar: 0,
            fpdscr: 0,
            systick: SysTick::default(),
        }
    }

    /// The vector table's address.
    #[must_use]
    pub const fn vtor(&self) -> u32 {
        self.vtor
    }

    /// SCR.SEVONPEND: a newly pending interrupt is a wake-up event for WFE.
    #[must_use]
    pub const fn sev_on_pend(&self) -> bool {
        self.scr & (1 << 4) != 0
    }

    /// Whether IRQ `irq` is enabled.
    #[must_use]
    pub fn irq_enabled(&self, irq: usize) -> bool {
        irq < IRQS && self.enabled[irq / 32] >> (irq % 32) & 1 == 1
    }

    /// Whether IRQ `irq` is pending.
    #[must_use]
    pub fn irq_pending(&self, irq: usize) -> bool {
        irq < IRQS && self.pending[irq / 32] >> (irq % 32) & 1 == 1
    }

    /// Whether exception `n` is active.
    #[must_use]
    pub fn is_active(&self, n: u16) -> bool {
        self.active.get(usize::from(n)).copied().unwrap_or(false)
    }

    /// Pends IRQ `irq` (a peripheral's line, or software). Returns whether it was not pending.
    pub fn pend_irq(&mut self, irq: usize) -> bool {
        if irq >= IRQS {
            return false;
        }
        let was = self.irq_pending(irq);
        self.pending[irq / 32] |= 1 << (irq % 32);
        !was
    }

    /// A level-sensitive line: pends `irq` while asserted, unless its handler is active (it
    /// pends again once the handler returns, if the line is still asserted). Returns whether
    /// this made it newly pending.
    pub fn level(&mut self, irq: usize, asserted: bool) -> bool {
        asserted && !self.is_active(exc::IRQ0 + irq as u16) && self.pend_irq(irq)
    }

    /// Pends system exception `n` (NMI, PendSV, SysTick).
    pub fn pend_system(&mut self, n: u16) {
        match n {
            exc::NMI => self.pend_nmi = true,
            exc::PENDSV => self.pend_sv = true,
            exc::SYSTICK => self.pend_systick = true,
            _ => {}
        }
    }

    /// The configured priority of exception `n` (fixed for reset, NMI and HardFault).
    #[must_use]
    pub fn priority(&self, n: u16) -> i16 {
        match n {
            exc::NMI => -2,
            exc::HARD_FAULT => -1,
            4..=15 => i16::from(self.sys_priority[usize::from(n) - 4]),
            n if n >= exc::IRQ0 => i16::from(self.irq_priority[usize::from(n - exc::IRQ0)]),
            _ => -3,
        }
    }

    /// The group (preemption) part of priority `p` under AIRCR.PRIGROUP.
    #[must_use]
    pub fn group(&self, p: i16) -> i16 {
        if p < 0 {
            return p;
        }
        let sub_bits = self.aircr_prigroup + 1;
        p & !((1i16 << sub_bits) - 1)
    }

    /// The execution priority: the highest (lowest number) of the active exceptions' group
    /// priorities, PRIMASK (0), BASEPRI (its group) and FAULTMASK (-1); [`THREAD_PRIORITY`] in
    /// thread mode with none of them.
    #[must_use]
    pub fn execution_priority(&self, primask: bool, basepri: u8, faultmask: bool) -> i16 {
        let mut p = self
            .stack
            .iter()
            .map(|&n| self.group(self.priority(n)))
            .min()
            .unwrap_or(THREAD_PRIORITY);
        let basepri = basepri & PRIO_MASK;
        if basepri != 0 {
            p = p.min(self.group(i16::from(basepri)));
        }
        if primask {
            p = p.min(0);
        }
        if faultmask {
            p = p.min(-1);
        }
        p
    }

    /// The pending exception the core would take given its masks: the enabled pending one of
    /// highest priority (group, then subpriority, then lowest number), if its group priority
    /// is higher than the execution priority.
    #[must_use]
    pub fn next(&self, primask: bool, basepri: u8, faultmask: bool) -> Option<u16> {
        let best = self.highest_pending()?;
        let execution = self.execution_priority(primask, basepri, faultmask);
        (self.group(self.priority(best)) < execution).then_some(best)
    }

    /// The highest-priority pending exception that is enabled, whatever the masks.
    #[must_use]
    pub fn highest_pending(&self) -> Option<u16> {
        let mut best: Option<(i16, u16)> = None;
        let mut consider = |n: u16, p: i16| {
            if best.is_none_or(|(bp, _)| p < bp) {
                best = Some((p, n));
            }
        };
        if self.pend_nmi {
            consider(exc::NMI, -2);
        }
        if self.pend_sv {
            consider(exc::PENDSV, self.priority(exc::PENDSV));
        }
        if self.pend_systick {
            consider(exc::SYSTICK, self.priority(exc::SYSTICK));
        }
        for w in 0..WORDS {
            let mut ready = self.pending[w] & self.enabled[w];
            while ready != 0 {
                let bit = ready.trailing_zeros() as usize;
                ready &= ready - 1;
                let n = exc::IRQ0 + (w * 32 + bit) as u16;
                consider(n, self.priority(n));
            }
        }
        best.map(|(_, n)| n)
    }

    /// Exception entry: `n` stops pending and becomes active (innermost).
    pub fn activate(&mut self, n: u16) {
        match n {
            exc::NMI => self.pend_nmi = false,
            exc::PENDSV => self.pend_sv = false,
            exc::SYSTICK => self.pend_systick = false,
            n if n >= exc::IRQ0 => {
                let irq = usize::from(n - exc::IRQ0);
                self.pending[irq / 32] &= !(1 << (irq % 32));
            }
            _ => {}
        }
        self.active[usize::from(n)] = true;
        self.stack.push(n);
    }

    /// Exception return from the innermost active exception; which one it was.
    pub fn deactivate(&mut self) -> Option<u16> {
        let n = self.stack.pop()?;
        self.active[usize::from(n)] = false;
        Some(n)
    }

    /// The innermost active exception (IPSR), 0 in thread mode.
    #[must_use]
    pub fn current(&self) -> u16 {
        self.stack.last().copied().unwrap_or(0)
    }

    /// Active exceptions, innermost last.
    #[must_use]
    pub fn active_stack(&self) -> &[u16] {
        &self.stack
    }

    /// SysTick: advances it to `now` (processor cycles); pends the SysTick exception if it
    /// wrapped with TICKINT set.
    pub fn advance(&mut self, now: u64) {
        if self.systick.advance(now) {
            self.pend_systick = true;
        }
    }

    /// When SysTick next reaches zero, in cycles, if it counts.
    #[must_use]
    pub fn next_event(&self) -> Option<u64> {
        self.systick.next_wrap()
    }

    /// A read of `size` bytes at offset `off` of the SCS page, at time `now` (cycles).
    /// `None` for an offset the model does not know.
    pub fn read(&mut self, off: u32, size: usize, now: u64) -> Option<u32> {
        let word = off & !3;
        let bank = |regs: &[u32; WORDS], base: u32| regs.get(((word - base) / 4) as usize).copied();
        let v = match word {
            reg::SYST_CSR..=reg::SYST_CALIB => self.systick.read(word, now),
            0x004 => 2, // ICTR: 96 interrupt lines
            0x008 => 0, // ACTLR
            reg::ISER..0x10C | reg::ICER..0x18C => bank(&self.enabled, word & !0x80)?,
            reg::ISPR..0x20C | reg::ICPR..0x28C => bank(&self.pending, word & !0x80)?,
            reg::IABR..0x30C => {
                let base = (word - reg::IABR) * 8;
                (0..32).fold(0, |v, b| {
                    v | u32::from(self.active.get(16 + (base + b) as usize) == Some(&true)) << b
                })
            }
            reg::IPR..0x454 => {
                let i = (word - reg::IPR) as usize;
                u32::from_le_bytes(std::array::from_fn(|k| {
                    self.irq_priority.get(i + k).copied().unwrap_or(0)
                }))
            }
            reg::CPUID => CPUID,
            reg::ICSR => self.icsr(),
            reg::VTOR => self.vtor,
            reg::AIRCR => 0xFA05_0000 | self.aircr_prigroup << 8,
            reg::SCR => self.scr,
            reg::CCR => self.ccr,
            reg::SHPR..0xD24 => {
                let i = (word - reg::SHPR) as usize;
                u32::from_le_bytes(std::array::from_fn(|k| self.sys_priority[i + k]))
            }
            reg::SHCSR => self.shcsr,
            0xD28..=0xD3C => 0, // CFSR, HFSR, DFSR, MMFAR, BFAR, AFSR: no faults recorded
            reg::CPACR => self.cpacr,
            reg::FPCCR => self.fpccr,
            reg::FPCAR => self.fpcar,
            reg::FPDSCR => self.fpdscr,
            // The CoreSight ID registers at the end of the page.
            0xFD0..=0xFFC => 0,
            _ => return None,
        };
        Some(crate::regs::sub_word(v, off, size))
    }

    /// ICSR: VECTACTIVE, RETTOBASE, VECTPENDING, ISRPENDING, PENDSTSET, PENDSVSET, NMIPENDSET.
    fn icsr(&self) -> u32 {
        let active = u32::from(self.current());
        let rettobase = u32::from(self.stack.len() <= 1) << 11;
        let pending = u32::from(self.highest_pending().unwrap_or(0)) << 12;
        let isr = u32::from(self.pending.iter().zip(&self.enabled).any(|(p, _)| *p != 0)) << 22;
        active
            | rettobase
            | pending
            | isr
            | u32::from(self.pend_systick) << 26
            | u32::from(self.pend_sv) << 28
            | u32::from(self.pend_nmi) << 31
    }

    /// A write of `size` bytes at offset `off` of the SCS page, at time `now` (cycles).
    /// `None` for an offset the model does not know.
    pub fn write(&mut self, off: u32, size: usize, value: u32, now: u64) -> Option<Effect> {
        let word = off & !3;
        let v = crate::regs::merge(0, off, size, value);
        let idx = |base: u32| ((word - base) / 4) as usize;
        let mut effect = Effect::None;
        match word {
            reg::SYST_CSR..=reg::SYST_CALIB => self.systick.write(word, v, now),
            reg::ISER..0x10C => self.enabled[idx(reg::ISER)] |= v,
            reg::ICER..0x18C => self.enabled[idx(reg::ICER)] &= !v,
            reg::ISPR..0x20C => {
                self.pending[idx(reg::ISPR)] |= v;
                effect = Effect::Pended;
            }
            reg::ICPR..0x28C => self.pending[idx(reg::ICPR)] &= !v,
            reg::IABR..0x30C => {} // read-only
            reg::IPR..0x454 => {
                let i = (off - reg::IPR) as usize;
                for k in 0..size.min(4) {
                    if let Some(p) = self.irq_priority.get_mut(i + k) {
                        *p = (value >> (8 * k)) as u8 & PRIO_MASK;
                    }
                }
            }
            reg::CPUID => {}
            reg::ICSR => {
                if v & 1 << 31 != 0 {
                    self.pend_nmi = true;
                }
                if v & 1 << 28 != 0 {
                    self.pend_sv = true;
                }
                if v & 1 << 27 != 0 {
                    self.pend_sv = false;
                }
                if v & 1 << 26 != 0 {
                    self.pend_systick = true;
                }
                if v & 1 << 25 != 0 {
                    self.pend_systick = false;
                }
                effect = Effect::Pended;
            }
            reg::VTOR => self.vtor = v & 0xFFFF_FF80,
            reg::AIRCR => {
                // Writes need VECTKEY 0x05FA.
                if v >> 16 == 0x05FA {
                    self.aircr_prigroup = (v >> 8) & 7;
                    if v & 1 << 2 != 0 {
                        effect = Effect::SystemReset;
                    }
                }
            }
            reg::SCR => self.scr = v & 0x16,
            reg::CCR => self.ccr = (v & 0x31B) | 0x200,
            reg::SHPR..0xD24 => {
                let i = (off - reg::SHPR) as usize;
                for k in 0..size.min(4) {
                    if let Some(p) = self.sys_priority.get_mut(i + k) {
                        *p = (value >> (8 * k)) as u8 & PRIO_MASK;
                    }
                }
            }
            reg::SHCSR => self.shcsr = v & 0x0007_0000,
            0xD28..=0xD3C => {} // fault status: write-1-to-clear, none recorded
            reg::CPACR => self.cpacr = v & 0x00F0_0000,
            reg::STIR => {
                self.pend_irq((v & 0x1FF) as usize);
                effect = Effect::Pended;
            }
            reg::FPCCR => self.fpccr = v & 0xC000_0000,
            reg::FPCAR => self.fpcar = v & !7,
            reg::FPDSCR => self.fpdscr = v & 0x07C0_0000,
            _ => return None,
        }
        Some(effect)
    }
}

/// The SysTick timer (ARMv7-M B3.3): a 24-bit down-counter on the processor clock
/// (CLKSOURCE 1) or on HCLK/8. On each tick it counts down, or reloads RVR if it is at 0;
/// reaching 0 sets COUNTFLAG and, with TICKINT, pends the exception.
///
/// Kept as a start: `cvr` at `base` cycles; the value and the zero crossings after it are
/// computed from the ticks since then (`c0` = `cvr`, period RVR + 1): value(t) = c0 - t up to
/// c0, then RVR - ((t - c0 - 1) mod period); zeros at c0 (if c0 > 0) and c0 + k · period.
#[derive(Debug, Clone, Default)]
struct SysTick {
    csr: u32,
    rvr: u32,
    cvr: u32,
    base: u64,
    /// COUNTFLAG: it reached 0 since the last read of CSR.
    counted: bool,
    /// Zero crossings since `base` already seen by `advance`.
    reported: u64,
}

impl SysTick {
    fn enabled(&self) -> bool {
        self.csr & 1 == 1
    }

    fn divider(&self) -> u64 {
        if self.csr & 4 != 0 { 1 } else { 8 }
    }

    fn ticks(&self, now: u64) -> u64 {
        now.saturating_sub(self.base) / self.divider()
    }

    fn period(&self) -> u64 {
        u64::from(self.rvr) + 1
    }

    /// Zero crossings in (base, now].
    fn zeros(&self, now: u64) -> u64 {
        if !self.enabled() {
            return self.reported;
        }
        let (t, c0) = (self.ticks(now), u64::from(self.cvr));
        if t < c0 {
            return 0;
        }
        u64::from(c0 > 0) + (t - c0) / self.period()
    }

    fn value(&self, now: u64) -> u32 {
        if !self.enabled() {
            return self.cvr;
        }
        let (t, c0) = (self.ticks(now), u64::from(self.cvr));
        if t <= c0 {
            return (c0 - t) as u32;
        }
        (u64::from(self.rvr) - (t - c0 - 1) % self.period()) as u32
    }

    fn advance(&mut self, now: u64) -> bool {
        let zeros = self.zeros(now);
        if zeros > self.reported {
            self.reported = zeros;
            self.counted = true;
            return self.csr & 2 != 0;
        }
        false
    }

    /// The cycle of the next zero crossing, if it would pend the exception.
    fn next_wrap(&self) -> Option<u64> {
        if !self.enabled() || self.csr & 2 == 0 {
            return None;
        }
        let c0 = u64::from(self.cvr);
        let j = self.reported + 1;
        let tick = if c0 > 0 {
            c0 + (j - 1) * self.period()
        } else {
            j * self.period()
        };
        Some(self.base + tick * self.divider())
    }

    fn read(&mut self, word: u32, now: u64) -> u32 {
        self.advance(now);
        match word {
            reg::SYST_CSR => {
                let v = self.csr | u32::from(self.counted) << 16;
                self.counted = false;
                v
            }
            reg::SYST_RVR => self.rvr,
            reg::SYST_CVR => self.value(now),
            // CALIB: no reference clock, TENMS unknown.
            _ => 0xC000_0000,
        }
    }

    fn write(&mut self, word: u32, v: u32, now: u64) {
        self.advance(now);
        // Restart the formulas from now's value (RVR changes apply at the next reload, as the
        // formulas read it then; a write changes it for the future only).
        self.cvr = self.value(now);
        self.base = now;
        self.reported = 0;
        match word {
            reg::SYST_CSR => self.csr = v & 7,
            reg::SYST_RVR => self.rvr = v & 0x00FF_FFFF,
            // Any write clears the counter and COUNTFLAG.
            reg::SYST_CVR => {
                self.cvr = 0;
                self.counted = false;
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn irq(n: u16) -> u16 {
        exc::IRQ0 + n
    }

    #[test]
    fn an_interrupt_pended_while_masked_stays_pending_until_unmasked() {
        let mut s = Scs::new();
        s.write(reg::ISER, 4, 1 << 20, 0);
        s.write(reg::ISPR, 4, 1 << 20, 0);
        // PRIMASK set: not taken, still pending.
        assert_eq!(s.next(true, 0, false), None);
        assert!(s.irq_pending(20));
        assert_eq!(s.next(false, 0, false), Some(irq(20)));
    }

    #[test]
    fn a_disabled_interrupt_pends_but_is_not_taken_until_enabled() {
        let mut s = Scs::new();
        s.pend_irq(28);
        assert_eq!(s.next(false, 0, false), None);
        assert_eq!(s.read(reg::ISPR, 4, 0), Some(1 << 28));
        s.write(reg::ISER, 4, 1 << 28, 0);
        assert_eq!(s.next(false, 0, false), Some(irq(28)));
        s.write(reg::ICPR, 4, 1 << 28, 0);
        assert_eq!(s.next(false, 0, false), None);
    }

    #[test]
    fn priorities_choose_and_preempt_by_group() {
        let mut s = Scs::new();
        s.write(reg::ISER, 4, (1 << 19) | (1 << 20) | (1 << 28), 0);
        // IPR bytes: IRQ 19 at 0x20, IRQ 20 at 0x10; only the top 4 bits are kept.
        s.write(reg::IPR + 19, 1, 0x2F, 0);
        s.write(reg::IPR + 20, 1, 0x10, 0);
        assert_eq!(s.read(reg::IPR + 16, 4, 0), Some(0x2000_0000));
        assert_eq!(s.read(reg::IPR + 20, 4, 0), Some(0x10));
        s.pend_irq(19);
        s.pend_irq(20);
        // The higher priority (lower number) first.
        assert_eq!(s.next(false, 0, false), Some(irq(20)));
        s.activate(irq(20));
        // IRQ 19 (0x20) cannot preempt 0x10; IRQ 28 at priority 0 can.
        assert_eq!(s.next(false, 0, false), None);
        s.pend_irq(28);
        assert_eq!(s.next(false, 0, false), Some(irq(28)));
        // BASEPRI 0x10 masks priority 0x10 and lower, not 0.
        assert_eq!(s.execution_priority(false, 0x10, false), 0x10);
        // Equal priority: the lower exception number wins.
        let mut t = Scs::new();
        t.write(reg::ISER, 4, (1 << 5) | (1 << 3), 0);
        t.pend_irq(5);
        t.pend_irq(3);
        assert_eq!(t.next(false, 0, false), Some(irq(3)));
    }

    #[test]
    fn subpriority_orders_pending_but_does_not_preempt() {
        let mut s = Scs::new();
        // PRIGROUP 5: group = bits 7:6, subpriority = bits 5:0.
        s.write(reg::AIRCR, 4, 0x05FA_0000 | 5 << 8, 0);
        s.write(reg::ISER, 4, 0b11, 0);
        s.write(reg::IPR, 1, 0x40, 0);
        s.write(reg::IPR + 1, 1, 0x60, 0);
        s.activate(irq(1));
        s.pend_irq(0);
        // 0x40 and 0x60 are the same group (0x40): no preemption.
        assert_eq!(s.next(false, 0, false), None);
        assert_eq!(s.deactivate(), Some(irq(1)));
        assert_eq!(s.next(false, 0, false), Some(irq(0)));
        // A write without VECTKEY changes nothing.
        s.write(reg::AIRCR, 4, 0x0000_0300, 0);
        assert_eq!(s.read(reg::AIRCR, 4, 0), Some(0xFA05_0500));
    }

    #[test]
    fn a_level_line_does_not_repend_while_its_handler_is_active() {
        let mut s = Scs::new();
        s.write(reg::ISER, 4, 1 << 20, 0);
        assert!(s.level(20, true));
        s.activate(irq(20));
        assert!(
            !s.level(20, true),
            "active: the line is seen after the return"
        );
        assert_eq!(s.deactivate(), Some(irq(20)));
        assert!(s.level(20, true));
        assert!(!s.level(21, false));
    }

    #[test]
    fn icsr_reports_active_pending_and_sets_pendsv() {
        let mut s = Scs::new();
        s.write(reg::ISER, 4, 1 << 28, 0);
        s.pend_irq(28);
        let icsr = s.read(reg::ICSR, 4, 0).unwrap();
        assert_eq!((icsr >> 12) & 0x1FF, u32::from(irq(28)), "VECTPENDING");
        s.activate(irq(28));
        let icsr = s.read(reg::ICSR, 4, 0).unwrap();
        assert_eq!(icsr & 0x1FF, u32::from(irq(28)), "VECTACTIVE");
        assert_eq!(icsr >> 11 & 1, 1, "RETTOBASE");
        assert_eq!(s.write(reg::ICSR, 4, 1 << 28, 0), Some(Effect::Pended));
        assert_eq!(s.highest_pending(), Some(exc::PENDSV));
        assert_eq!(
            s.write(reg::AIRCR, 4, 0x05FA_0004, 0),
            Some(Effect::SystemReset)
        );
    }

    #[test]
    fn systick_counts_down_reloads_and_pends() {
        let mut s = Scs::new();
        s.write(reg::SYST_RVR, 4, 99, 0);
        s.write(reg::SYST_CVR, 4, 0, 0);
        // Processor clock, TICKINT, ENABLE at cycle 1000: loads 99 at the first tick.
        s.write(reg::SYST_CSR, 4, 0b111, 1000);
        assert_eq!(s.read(reg::SYST_CVR, 4, 1001), Some(99));
        assert_eq!(s.read(reg::SYST_CVR, 4, 1051), Some(49));
        assert_eq!(s.next_event(), Some(1001 + 99));
        s.advance(1001 + 98);
        assert_eq!(s.highest_pending(), None);
        s.advance(1001 + 99);
        assert_eq!(s.highest_pending(), Some(exc::SYSTICK));
        // COUNTFLAG reads 1 once.
        assert_eq!(s.read(reg::SYST_CSR, 4, 1101).map(|v| v >> 16), Some(1));
        assert_eq!(s.read(reg::SYST_CSR, 4, 1102).map(|v| v >> 16), Some(0));
        // Reloaded: 99 on the tick after 0, a period of 100.
        assert_eq!(s.read(reg::SYST_CVR, 4, 1101), Some(99));
        assert_eq!(s.next_event(), Some(1001 + 199));
    }

    #[test]
    fn unknown_offsets_are_reported() {
        let mut s = Scs::new();
        assert_eq!(s.read(0x500, 4, 0), None);
        assert_eq!(s.write(0x600, 4, 1, 0), None);
        assert_eq!(s.read(reg::CPUID, 4, 0), Some(CPUID));
        assert_eq!(s.read(reg::CCR, 4, 0), Some(0x200));
    }
}
