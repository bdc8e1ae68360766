//! The hardware state the CPU's callbacks and hooks see: the clock, the peripheral models
//! behind the MMIO map (RCC, TIM2, CAN1, IWDG, FLASH, the SCS and plain register files), their
//! interrupt lines, and what the hooks report back to the board's loop.

use std::collections::{BTreeMap, HashMap};

use super::BoardError;
use super::{CPU_HZ, HSE_HZ, UnknownRegister, irq};
use crate::bxcan::BxCan;
use crate::flash::{Flash, Timing};
use crate::iwdg::Iwdg;
use crate::nvic::{Effect, Scs};
use crate::regs::{Rcc, RegFile, base, register_files};
use crate::tim::Timer;

/// The system control space (NVIC, SysTick, SCB) in the private peripheral bus.
pub(super) const SCS: u32 = 0xE000_E000;

/// Counts of what the board did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Stats {
    /// Instructions executed.
    pub instructions: u64,
    /// Emulation slices (calls into Unicorn).
    pub slices: u64,
    /// Exceptions taken, by entry (tail-chained ones included).
    pub exceptions: u64,
    /// Exception returns.
    pub returns: u64,
    /// MMIO reads and writes.
    pub mmio: u64,
    /// Cycles spent asleep (WFE/WFI).
    pub sleep_cycles: u64,
    /// Resets by the independent watchdog.
    pub watchdog_resets: u64,
    /// Cycles the CPU waited on the flash (a fetch, read or write while it was busy).
    pub flash_stall_cycles: u64,
    /// Flash operations a reset cut short (their bytes left as before them).
    pub flash_ops_interrupted: u64,
}

/// Why the CPU is not running.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Sleep {
    Awake,
    /// WFE: until the event register is set (an exception entry does it).
    Event,
    /// WFI: until an interrupt is pending and enabled, whatever the masks.
    Interrupt,
    /// Stalled on a fetch or read from the flash until its operation ends; interrupts wait.
    Flash,
}

/// The hardware state the MMIO callbacks and hooks see.
pub(super) struct Hw {
    pub(super) now: u64,
    /// The block hook stops the CPU once `now` reaches this.
    pub(super) stop_at: u64,
    pub(super) rcc: Rcc,
    files: BTreeMap<u32, RegFile>,
    /// Blocks of unknown peripherals: written values read back.
    unknown_files: HashMap<u32, RegFile>,
    pub(super) scs: Scs,
    pub(super) tim2: Timer,
    pub(super) can1: BxCan,
    pub(super) iwdg: Iwdg,
    pub(super) flash: Flash,
    /// Byte writes still to come of a misaligned flash write Unicorn splits (dropped).
    pub(super) flash_split_bytes: usize,
    /// The harness withholds the TIM2 interrupt until the next reset (a stalled loop).
    pub(super) stall_timer: bool,
    /// The harness withholds the CAN1 RX0 interrupt until this cycle (a busy CPU).
    pub(super) hold_rx0_until: u64,
    /// AIRCR.SYSRESETREQ was written.
    pub(super) reset_requested: bool,
    /// The event register (WFE).
    pub(super) event: bool,
    pub(super) sleep: Sleep,
    /// The CPU tried to fetch EXC_RETURN: the handler returned.
    pub(super) exc_return: Option<u32>,
    /// A hint hook asked the next invalid-instruction report to be ignored (WFE, WFI).
    pub(super) hint: bool,
    /// Where the CPU resumes after a sleep (the instruction after the WFE/WFI).
    pub(super) resume_at: Option<u32>,
    pub(super) fault: Option<BoardError>,
    /// The CAN controller changed what it would send: the driver should look.
    pub(super) can_attention: bool,
    pub(super) unknown: Vec<UnknownRegister>,
    pub(super) reported: std::collections::BTreeSet<u32>,
    /// Instructions of each translated block, by start address: (size, count) per halfword
    /// of the flash (code runs from the flash or its alias at 0), else in `other_blocks`.
    /// A table, not a hash map: the block hook runs for every block, and hashing was a sixth
    /// of a run's time (perf, the built-in square).
    pub(super) blocks: Vec<(u32, u32)>,
    pub(super) other_blocks: HashMap<(u64, u32), u64>,
    pub(super) stats: Stats,
}

impl Hw {
    pub(super) fn new(flash_timing: Timing) -> Self {
        let rcc = Rcc::new(HSE_HZ);
        let (tim_div, pclk_div) = Self::dividers(&rcc);
        Self {
            now: 0,
            stop_at: 0,
            rcc,
            files: register_files().into_iter().collect(),
            unknown_files: HashMap::new(),
            scs: Scs::new(),
            tim2: Timer::new(tim_div),
            can1: BxCan::new(pclk_div),
            iwdg: Iwdg::new(CPU_HZ),
            flash: Flash::new(CPU_HZ, flash_timing),
            flash_split_bytes: 0,
            stall_timer: false,
            hold_rx0_until: 0,
            reset_requested: false,
            event: false,
            sleep: Sleep::Awake,
            exc_return: None,
            hint: false,
            resume_at: None,
            fault: None,
            can_attention: false,
            unknown: Vec::new(),
            reported: std::collections::BTreeSet::new(),
            blocks: vec![(0, 0); crate::flash::SIZE as usize / 2],
            other_blocks: HashMap::new(),
            stats: Stats::default(),
        }
    }

    /// CPU cycles per APB1 timer clock and per APB1 clock, from the RCC's clock tree.
    fn dividers(rcc: &Rcc) -> (u64, u64) {
        let c = rcc.clocks();
        let sys = u64::from(c.sysclk);
        (
            (sys / u64::from(c.tim_apb1.max(1))).max(1),
            (sys / u64::from(c.pclk1.max(1))).max(1),
        )
    }

    /// A read of `size` bytes at `addr`; `None` if no model knows the register.
    pub(super) fn read(&mut self, addr: u32, size: usize) -> Option<u32> {
        self.stats.mmio += 1;
        let now = self.now;
        let block = addr & !0x3FF;
        let off = addr & 0x3FF;
        match block {
            base::TIM2 => self.tim2.read(off, size, now),
            base::CAN1 => self.can1.read(off, size),
            base::IWDG => self
                .iwdg
                .read(off)
                .map(|v| crate::regs::sub_word(v, off, size)),
            base::RCC => Some(self.rcc.read(off, size)).filter(|_| self.rcc.regs.knows(off)),
            _ if (SCS..SCS + 0x1000).contains(&addr) => self.scs.read(addr - SCS, size, now),
            _ => {
                let file = self.files.get(&block)?;
                file.knows(off).then(|| file.read(off, size))
            }
        }
    }

    /// A write; `None` if no model knows the register. Stops the CPU (`stop`) when the board
    /// must look before the slice ends: an exception pended, the CAN controller has a new
    /// request, a timer's next event moved.
    pub(super) fn write(
        &mut self,
        addr: u32,
        size: usize,
        value: u32,
        stop: &mut bool,
    ) -> Option<()> {
        self.stats.mmio += 1;
        let now = self.now;
        let block = addr & !0x3FF;
        let off = addr & 0x3FF;
        match block {
            base::TIM2 => {
                self.tim2.write(off, size, value, now)?;
                *stop |= off & !3 != crate::tim::reg::SR;
            }
            base::CAN1 => {
                self.can1.write(off, size, value, now)?;
                let word = off & !3;
                if (0x180..0x1B0).contains(&word) || word == crate::bxcan::reg::TSR || word == 0 {
                    self.can_attention = true;
                    *stop = true;
                }
            }
            base::IWDG => {
                let word = crate::regs::merge(0, off, size, value);
                let was = self.iwdg.running();
                self.iwdg.write(off, word, now)?;
                // Started: its expiry is the board's next event.
                *stop |= !was && self.iwdg.running();
            }
            base::RCC => {
                if !self.rcc.regs.knows(off) {
                    return None;
                }
                self.rcc.write(off, size, value);
                let (tim_div, pclk_div) = Self::dividers(&self.rcc);
                self.tim2.set_clock_div(tim_div, now);
                self.can1.set_pclk_div(pclk_div);
            }
            _ if (SCS..SCS + 0x1000).contains(&addr) => {
                match self.scs.write(addr - SCS, size, value, now)? {
                    Effect::None => {}
                    Effect::Pended => *stop = true,
                    Effect::SystemReset => {
                        self.reset_requested = true;
                        *stop = true;
                    }
                }
            }
            _ => {
                let file = self.files.get_mut(&block)?;
                if !file.knows(off) {
                    return None;
                }
                file.write(off, size, value);
            }
        }
        Some(())
    }

    /// Records an access to a register no model knows (once per address); the access then
    /// behaves as memory.
    pub(super) fn unknown_access(&mut self, addr: u32, write: bool, pc: u32) -> &mut RegFile {
        if self.reported.insert(addr & !3) {
            self.unknown.push(UnknownRegister {
                addr,
                peripheral: peripheral_name(addr),
                write,
                pc,
            });
        }
        self.unknown_files
            .entry(addr & !0x3FF)
            .or_insert_with(|| RegFile::new("unknown", 0x400, &[], &[]))
    }

    /// The next cycle at which a peripheral needs the CPU's attention.
    pub(super) fn next_event(&self) -> Option<u64> {
        [
            self.tim2.next_event(self.now),
            self.can1.next_event(),
            self.scs.next_event(),
            self.iwdg.expiry(),
            self.flash.op().map(|op| op.end),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Brings the peripherals to `now` and pends the asserted interrupt lines.
    pub(super) fn sync_lines(&mut self) {
        let now = self.now;
        self.tim2.advance(now);
        self.can1.advance(now);
        self.scs.advance(now);
        let [tx, rx0, rx1, sce] = self.can1.irq_lines();
        let lines = [
            (irq::CAN1_TX, tx),
            (irq::CAN1_RX0, rx0 && now >= self.hold_rx0_until),
            (irq::CAN1_RX1, rx1),
            (irq::CAN1_SCE, sce),
            (irq::TIM2, self.tim2.irq() && !self.stall_timer),
            (irq::FLASH, self.flash.irq()),
        ];
        for (line, asserted) in lines {
            if self.scs.level(line, asserted) && self.scs.sev_on_pend() {
                self.event = true;
            }
        }
    }
}

/// The name of the peripheral at `addr` (RM0090 memory map), for reports.
fn peripheral_name(addr: u32) -> &'static str {
    match addr & !0x3FF {
        0x4000_0000 => "TIM2",
        0x4000_0400 => "TIM3",
        0x4000_0800 => "TIM4",
        0x4000_0C00 => "TIM5",
        0x4000_2800 => "RTC",
        0x4000_2C00 => "WWDG",
        0x4000_3000 => "IWDG",
        0x4000_4400 => "USART2",
        0x4000_4800 => "USART3",
        0x4000_6400 => "CAN1",
        0x4000_6800 => "CAN2",
        0x4000_7000 => "PWR",
        0x4001_1000 => "USART1",
        0x4001_3800 => "SYSCFG",
        0x4001_3C00 => "EXTI",
        0x4002_3800 => "RCC",
        0x4002_3C00 => "FLASH",
        0x4002_6000 => "DMA1",
        0x4002_6400 => "DMA2",
        a if (0x4002_0000..0x4002_2400).contains(&a) => "GPIO",
        0xE000_0000 => "ITM",
        0xE000_1000 => "DWT",
        0xE000_E000 | 0xE000_EC00 | 0xE000_ED00 | 0xE000_EE00 | 0xE000_EF00 => "SCS",
        0xE004_2000 => "DBGMCU",
        _ => "?",
    }
}
