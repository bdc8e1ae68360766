//! The board: the image in Unicorn's Cortex-M4, the STM32F407's memory map, the peripheral
//! models behind MMIO callbacks, and the loop that runs it in virtual time.
//!
//! Virtual time is instructions at 168 MHz (one cycle each, plus 12 cycles per exception
//! entry and 10 per return, the M4's latencies): a block hook adds each translated block's
//! instruction count before it runs and stops the CPU at the next event (a timer compare, a
//! CAN frame, a sleep's end), so every run of the same inputs takes the same path.
//!
//! Unicorn has no NVIC: after each slice the board evaluates the peripherals' interrupt lines,
//! asks the SCS model which exception preempts, and does the entry itself (the 8- or 26-word
//! frame, 8-byte alignment, EXC_RETURN, IPSR, the vector). The handler's return to EXC_RETURN
//! faults in Unicorn 2.1 (its IPSR write does not rebuild the translation flags), and the
//! board does the return: unstacking, tail-chaining into the next pending exception.
//! WFE and WFI stop the CPU and the board sleeps to the next event; SEV, exception entry and
//! return set the event register.

use std::collections::{BTreeMap, HashMap};

use firmware::CanFrame;
use unicorn_engine::unicorn_const::{Arch, ArmCpuModel, HookType, MemType, Mode, Prot};
use unicorn_engine::{RegisterARM, Unicorn};

use crate::bxcan::{BxCan, Lec, Received};
use crate::elf::{CPSIE_I, Image, SEV, WFE, WFI};
use crate::iwdg::Iwdg;
use crate::nvic::{Effect, Scs, exc};
use crate::regs::{Rcc, RegFile, base, register_files};
use crate::rtt::{LogLine, Rtt};
use crate::tim::Timer;

/// Virtual time's rate: instructions (cycles) per second.
pub const CPU_HZ: u64 = 168_000_000;
/// The type C board's crystal.
pub const HSE_HZ: u32 = 12_000_000;
/// Cycles of an exception entry (Cortex-M4 TRM §3.3: 12-cycle latency).
const ENTRY_CYCLES: u64 = 12;
/// Cycles of an exception return.
const RETURN_CYCLES: u64 = 10;
/// The longest slice the CPU runs without the board looking at its peripherals.
const MAX_SLICE: u64 = 20_000;

/// The interrupt lines of the modelled peripherals (RM0090 Table 61).
pub mod irq {
    /// CAN1 TX.
    pub const CAN1_TX: usize = 19;
    /// CAN1 RX0.
    pub const CAN1_RX0: usize = 20;
    /// CAN1 RX1.
    pub const CAN1_RX1: usize = 21;
    /// CAN1 SCE.
    pub const CAN1_SCE: usize = 22;
    /// TIM2.
    pub const TIM2: usize = 28;
}

/// Memory regions: (base, size, permissions, name).
const MEMORY: [(u32, u32, u32, &str); 5] = [
    (0x0000_0000, 0x10_0000, 5, "boot alias of the flash"),
    (0x0800_0000, 0x10_0000, 5, "flash"),
    (0x1000_0000, 0x1_0000, 3, "CCM RAM"),
    (0x1FFF_0000, 0x1_0000, 1, "system memory"),
    (0x2000_0000, 0x2_0000, 3, "SRAM"),
];
/// Peripheral regions mapped to the models: APB1, APB2, AHB1, AHB2, and the Cortex-M4's
/// private peripheral bus.
const MMIO: [(u32, u32); 5] = [
    (0x4000_0000, 0x8000),
    (0x4001_0000, 0x8000),
    (0x4002_0000, 0x6_0000),
    (0x5000_0000, 0x6_1000),
    (0xE000_0000, 0x10_0000),
];
const SCS: u32 = 0xE000_E000;
const SRAM: (u32, usize) = (0x2000_0000, 0x2_0000);
const CCM: (u32, usize) = (0x1000_0000, 0x1_0000);
/// The flash's size (a power of two).
const FLASH_SIZE: u32 = 0x10_0000;
/// The factory flash-size register (KiB) in system memory.
const FLASH_SIZE_REG: u32 = 0x1FFF_7A22;

/// Why the board stopped running.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BoardError {
    /// An access outside every mapped region.
    Unmapped {
        /// "read", "write" or "fetch".
        access: &'static str,
        /// The address.
        addr: u32,
        /// The instruction's address.
        pc: u32,
    },
    /// An instruction Unicorn does not execute.
    InvalidInstruction {
        /// Its address.
        pc: u32,
    },
    /// A branch to an EXC_RETURN value the board does not handle (or outside a handler).
    BadExceptionReturn {
        /// The value.
        value: u32,
        /// Where the handler returned from.
        pc: u32,
    },
    /// Thread mode on the process stack (CONTROL.SPSEL): not modelled.
    ProcessStack {
        /// Where.
        pc: u32,
    },
    /// Any other emulation error.
    Emulation {
        /// Unicorn's error.
        error: String,
        /// Where.
        pc: u32,
    },
}

impl std::fmt::Display for BoardError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Unmapped { access, addr, pc } => write!(
                f,
                "{access} of unmapped address {addr:#010x} at pc {pc:#010x}"
            ),
            Self::InvalidInstruction { pc } => write!(f, "invalid instruction at pc {pc:#010x}"),
            Self::BadExceptionReturn { value, pc } => write!(
                f,
                "exception return to {value:#010x} at pc {pc:#010x} is not one the board handles"
            ),
            Self::ProcessStack { pc } => write!(
                f,
                "thread mode on the process stack (CONTROL.SPSEL) at pc {pc:#010x}: not modelled"
            ),
            Self::Emulation { error, pc } => write!(f, "emulation error {error} at pc {pc:#010x}"),
        }
    }
}

impl std::error::Error for BoardError {}

/// A register the models do not know, reported once.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownRegister {
    /// Its address.
    pub addr: u32,
    /// The peripheral it lies in, if the board knows its name.
    pub peripheral: &'static str,
    /// Written (else read).
    pub write: bool,
    /// The instruction's address (of the block it ran in: Unicorn's PC in an MMIO callback).
    pub pc: u32,
}

impl std::fmt::Display for UnknownRegister {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} of a register the models do not know: {:#010x} ({}) at pc {:#010x}",
            if self.write { "write" } else { "read" },
            self.addr,
            self.peripheral,
            self.pc
        )
    }
}

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
}

/// Why the CPU is not running.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Sleep {
    Awake,
    /// WFE: until the event register is set (an exception entry does it).
    Event,
    /// WFI: until an interrupt is pending and enabled, whatever the masks.
    Interrupt,
}

/// The hardware state the MMIO callbacks and hooks see.
struct Hw {
    now: u64,
    /// The block hook stops the CPU once `now` reaches this.
    stop_at: u64,
    rcc: Rcc,
    files: BTreeMap<u32, RegFile>,
    /// Blocks of unknown peripherals: written values read back.
    unknown_files: HashMap<u32, RegFile>,
    scs: Scs,
    tim2: Timer,
    can1: BxCan,
    iwdg: Iwdg,
    /// The harness withholds the TIM2 interrupt until the next reset (a stalled loop).
    stall_timer: bool,
    /// The harness withholds the CAN1 RX0 interrupt until this cycle (a busy CPU).
    hold_rx0_until: u64,
    /// AIRCR.SYSRESETREQ was written.
    reset_requested: bool,
    /// The event register (WFE).
    event: bool,
    sleep: Sleep,
    /// The CPU tried to fetch EXC_RETURN: the handler returned.
    exc_return: Option<u32>,
    /// A hint hook asked the next invalid-instruction report to be ignored (WFE, WFI).
    hint: bool,
    /// Where the CPU resumes after a sleep (the instruction after the WFE/WFI).
    resume_at: Option<u32>,
    fault: Option<BoardError>,
    /// The CAN controller changed what it would send: the driver should look.
    can_attention: bool,
    unknown: Vec<UnknownRegister>,
    reported: std::collections::BTreeSet<u32>,
    /// Instructions of each translated block, by start address: (size, count) per halfword
    /// of the flash (code runs from the flash or its alias at 0), else in `other_blocks`.
    /// A table, not a hash map: the block hook runs for every block, and hashing was a sixth
    /// of a run's time (perf, the built-in square).
    blocks: Vec<(u32, u32)>,
    other_blocks: HashMap<(u64, u32), u64>,
    stats: Stats,
}

impl Hw {
    fn new() -> Self {
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
            blocks: vec![(0, 0); FLASH_SIZE as usize / 2],
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
    fn read(&mut self, addr: u32, size: usize) -> Option<u32> {
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
    fn write(&mut self, addr: u32, size: usize, value: u32, stop: &mut bool) -> Option<()> {
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
    fn unknown_access(&mut self, addr: u32, write: bool, pc: u32) -> &mut RegFile {
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
    fn next_event(&self) -> Option<u64> {
        [
            self.tim2.next_event(self.now),
            self.can1.next_event(),
            self.scs.next_event(),
            self.iwdg.expiry(),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Brings the peripherals to `now` and pends the asserted interrupt lines.
    fn sync_lines(&mut self) {
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

/// Instructions in a Thumb-2 block: 32-bit encodings start with 0b11101, 0b11110, 0b11111.
fn thumb_instructions(code: &[u8]) -> u64 {
    let mut i = 0;
    let mut n = 0;
    while i + 1 < code.len() {
        let half = u16::from_le_bytes([code[i], code[i + 1]]);
        i += if half >> 11 >= 0b11101 { 4 } else { 2 };
        n += 1;
    }
    n
}

/// The emulated board. See the [module documentation](self).
pub struct Board {
    uc: Unicorn<'static, Hw>,
    image: Image,
    rtt: Option<Rtt>,
    /// Where the CPU resumes (Thumb bit set).
    pc: u32,
    /// Log lines not yet taken.
    lines: Vec<LogLine>,
    /// The mailbox whose frame the driver put on the bus, if any.
    on_bus: Option<usize>,
}

impl std::fmt::Debug for Board {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Board")
            .field("image", &self.image.path)
            .field("pc", &self.pc)
            .finish_non_exhaustive()
    }
}

fn uc_err(e: unicorn_engine::uc_error, pc: u32) -> BoardError {
    BoardError::Emulation {
        error: format!("{e:?}"),
        pc,
    }
}

impl Board {
    /// The board with `image` flashed, out of reset.
    ///
    /// # Errors
    /// The emulator could not be set up, or the image does not fit the memory map.
    pub fn new(image: Image) -> anyhow::Result<Self> {
        let rtt = match image.symbol("_SEGGER_RTT") {
            Some(control) => Some(Rtt::new(control, &image.bytes)?),
            None => None,
        };
        let uc = Self::cpu(&image, &[])?;
        let mut board = Self {
            uc,
            image,
            rtt,
            pc: 0,
            lines: Vec::new(),
            on_bus: None,
        };
        board.reset_cpu()?;
        Ok(board)
    }

    /// A Cortex-M4 with the memory map, the image and `ram` (base, bytes) loaded, and the
    /// hooks installed.
    fn cpu(image: &Image, ram: &[(u32, Vec<u8>)]) -> anyhow::Result<Unicorn<'static, Hw>> {
        fn e(what: &'static str) -> impl Fn(unicorn_engine::uc_error) -> anyhow::Error {
            move |err| anyhow::anyhow!("{what}: {err:?}")
        }
        let mut uc = Unicorn::new_with_data(Arch::ARM, Mode::THUMB | Mode::MCLASS, Hw::new())
            .map_err(e("Unicorn"))?;
        uc.ctl_set_cpu_model(ArmCpuModel::CORTEX_M4 as i32)
            .map_err(e("the Cortex-M4 model"))?;
        for (at, size, prot, _) in MEMORY {
            uc.mem_map(u64::from(at), u64::from(size), Prot(prot))
                .map_err(e("memory map"))?;
        }
        for (addr, bytes) in &image.segments {
            let in_flash = (0x0800_0000..0x0810_0000).contains(addr);
            uc.mem_write(u64::from(*addr), bytes).map_err(|err| {
                anyhow::anyhow!(
                    "{}: a segment of {} bytes at {addr:#010x} is outside the memory map ({err:?})",
                    image.path.display(),
                    bytes.len()
                )
            })?;
            if in_flash {
                uc.mem_write(u64::from(addr - 0x0800_0000), bytes)
                    .map_err(e("boot alias"))?;
            }
        }
        uc.mem_write(u64::from(FLASH_SIZE_REG), &1024u16.to_le_bytes())
            .map_err(e("flash size register"))?;
        for (addr, bytes) in ram {
            uc.mem_write(u64::from(*addr), bytes).map_err(e("RAM"))?;
        }
        for (at, size) in MMIO {
            let read = move |uc: &mut Unicorn<'_, Hw>, off: u64, size: usize| -> u64 {
                let addr = at + off as u32;
                if let Some(v) = uc.get_data_mut().read(addr, size) {
                    return u64::from(v);
                }
                let pc = uc.reg_read(RegisterARM::PC).unwrap_or(0) as u32;
                let file = uc.get_data_mut().unknown_access(addr, false, pc);
                u64::from(file.read(addr & 0x3FF, size))
            };
            let write = move |uc: &mut Unicorn<'_, Hw>, off: u64, size: usize, value: u64| {
                let addr = at + off as u32;
                let mut stop = false;
                if uc
                    .get_data_mut()
                    .write(addr, size, value as u32, &mut stop)
                    .is_none()
                {
                    let pc = uc.reg_read(RegisterARM::PC).unwrap_or(0) as u32;
                    let file = uc.get_data_mut().unknown_access(addr, true, pc);
                    file.write(addr & 0x3FF, size, value as u32);
                }
                if stop {
                    // Stopping inside the access would leave the PC on the accessing
                    // instruction (it would run again): the block hook stops at the next block.
                    uc.get_data_mut().stop_at = 0;
                }
            };
            uc.mmio_map(u64::from(at), u64::from(size), Some(read), Some(write))
                .map_err(e("MMIO map"))?;
        }
        // Virtual time: each block's instructions, as it starts. A stop requested here
        // happens before the block runs (it is counted when it does).
        uc.add_block_hook(1, 0, |uc, addr, size| {
            if uc.get_data().now >= uc.get_data().stop_at {
                let _ = uc.emu_stop();
                return;
            }
            // The flash and its boot alias share one table.
            let slot = (addr & u64::from(FLASH_SIZE - 1)) as usize / 2;
            let in_flash = addr < u64::from(FLASH_SIZE)
                || (0x0800_0000..0x0800_0000 + u64::from(FLASH_SIZE)).contains(&addr);
            let cached = if in_flash {
                let (sz, n) = uc.get_data().blocks[slot];
                (sz == size && n > 0).then_some(u64::from(n))
            } else {
                uc.get_data().other_blocks.get(&(addr, size)).copied()
            };
            let n = cached.unwrap_or_else(|| {
                let mut code = vec![0u8; size as usize];
                let _ = uc.mem_read(addr, &mut code);
                let n = thumb_instructions(&code);
                let hw = uc.get_data_mut();
                if in_flash {
                    hw.blocks[slot] = (size, n as u32);
                } else {
                    hw.other_blocks.insert((addr, size), n);
                }
                n
            });
            let hw = uc.get_data_mut();
            hw.now += n;
            hw.stats.instructions += n;
        })
        .map_err(e("block hook"))?;
        let unmapped = HookType(
            HookType::MEM_READ_UNMAPPED.0
                | HookType::MEM_WRITE_UNMAPPED.0
                | HookType::MEM_FETCH_UNMAPPED.0
                | HookType::MEM_WRITE_PROT.0
                | HookType::MEM_FETCH_PROT.0,
        );
        uc.add_mem_hook(unmapped, 1, 0, |uc, kind, addr, _size, _value| {
            let pc = uc.reg_read(RegisterARM::PC).unwrap_or(0) as u32;
            let hw = uc.get_data_mut();
            let addr = addr as u32;
            if kind == MemType::FETCH_UNMAPPED && addr >= 0xFFFF_FF00 {
                hw.exc_return = Some(addr | 1);
                return false;
            }
            let access = match kind {
                MemType::FETCH_UNMAPPED | MemType::FETCH_PROT => "fetch",
                MemType::WRITE_UNMAPPED | MemType::WRITE_PROT => "write",
                _ => "read",
            };
            hw.fault
                .get_or_insert(BoardError::Unmapped { access, addr, pc });
            false
        })
        .map_err(e("unmapped-access hook"))?;
        // WFE and WFI raise EXCP_YIELD/EXCP_HLT, which Unicorn 2.1 reports as an invalid
        // instruction unless a hook claims it: the hint hooks below mark the one they expect.
        uc.add_insn_invalid_hook(|uc| std::mem::take(&mut uc.get_data_mut().hint))
            .map_err(e("invalid-instruction hook"))?;
        for (&hint, addrs) in &image.hints {
            for &a in addrs {
                let a = u64::from(a);
                let hooked = match hint {
                    // A code hook runs before its instruction, and a stop from it happens
                    // there: the sleep resumes after the WFE/WFI (`resume_at`), as the chip
                    // does once woken.
                    WFE => uc.add_code_hook(a, a, |uc, addr, _| {
                        let hw = uc.get_data_mut();
                        hw.hint = true;
                        if hw.event {
                            hw.event = false;
                        } else {
                            hw.sleep = Sleep::Event;
                            hw.resume_at = Some(addr as u32 + 2);
                            let _ = uc.emu_stop();
                        }
                    }),
                    WFI => uc.add_code_hook(a, a, |uc, addr, _| {
                        let hw = uc.get_data_mut();
                        hw.hint = true;
                        hw.sleep = Sleep::Interrupt;
                        hw.resume_at = Some(addr as u32 + 2);
                        let _ = uc.emu_stop();
                    }),
                    SEV => uc.add_code_hook(a, a, |uc, _, _| uc.get_data_mut().event = true),
                    CPSIE_I => uc.add_code_hook(a, a, |uc, _, _| {
                        // Unmasking may let a pending interrupt in: stop if one is.
                        if uc.get_data().scs.highest_pending().is_some() {
                            uc.get_data_mut().stop_at = 0;
                        }
                    }),
                    _ => continue,
                };
                hooked.map_err(e("hint hook"))?;
            }
        }
        Ok(uc)
    }

    /// Reset: the CPU's registers from the vector table, the peripherals to their reset
    /// values; RAM keeps its contents (as on the chip).
    fn reset_cpu(&mut self) -> anyhow::Result<()> {
        let mut vectors = [0u8; 8];
        self.uc
            .mem_read(0, &mut vectors)
            .map_err(|e| anyhow::anyhow!("vector table: {e:?}"))?;
        let sp = u32::from_le_bytes([vectors[0], vectors[1], vectors[2], vectors[3]]);
        let pc = u32::from_le_bytes([vectors[4], vectors[5], vectors[6], vectors[7]]);
        self.uc
            .reg_write(RegisterARM::MSP, u64::from(sp))
            .map_err(|e| anyhow::anyhow!("SP: {e:?}"))?;
        self.uc
            .reg_write(RegisterARM::LR, 0xFFFF_FFFF)
            .map_err(|e| anyhow::anyhow!("LR: {e:?}"))?;
        self.pc = pc | 1;
        Ok(())
    }

    /// A system reset (AIRCR.SYSRESETREQ, the watchdog): a fresh CPU and peripherals, the
    /// RAM as it was, the time and the counters going on.
    ///
    /// # Errors
    /// The emulator could not be set up again.
    pub fn reset(&mut self) -> anyhow::Result<()> {
        let mut ram = Vec::new();
        for (at, size) in [SRAM, CCM] {
            let bytes = self
                .uc
                .mem_read_as_vec(u64::from(at), size)
                .map_err(|e| anyhow::anyhow!("RAM: {e:?}"))?;
            ram.push((at, bytes));
        }
        let old = self.uc.get_data();
        let (now, stats) = (old.now, old.stats);
        let (unknown, reported) = (old.unknown.clone(), old.reported.clone());
        self.uc = Self::cpu(&self.image, &ram)?;
        let hw = self.uc.get_data_mut();
        hw.now = now;
        hw.stats = stats;
        hw.unknown = unknown;
        hw.reported = reported;
        self.on_bus = None;
        if let Some(rtt) = self.rtt.as_mut() {
            rtt.reset();
        }
        self.reset_cpu()
    }

    /// A system reset whose cause RCC_CSR then reports with `csr_flags` (RM0090 §7.3.21):
    /// the watchdog (IWDGRSTF and PINRSTF) or AIRCR.SYSRESETREQ (SFTRSTF and PINRSTF).
    fn system_reset(&mut self, csr_flags: u32) -> Result<(), BoardError> {
        let pc = self.pc;
        self.reset().map_err(|e| BoardError::Emulation {
            error: format!("reset: {e}"),
            pc,
        })?;
        let hw = self.uc.get_data_mut();
        hw.rcc.regs.set_word(crate::regs::rcc::CSR, csr_flags);
        Ok(())
    }

    /// Withholds the TIM2 interrupt from now until the next reset: the control loop, which
    /// waits on its timer, stalls (a test of the watchdog).
    pub fn stall_timer(&mut self) {
        self.uc.get_data_mut().stall_timer = true;
    }

    /// Withholds CAN1's RX0 interrupt until cycle `until`, as a CPU busy elsewhere with the
    /// interrupt masked would: the frames that arrive meanwhile wait in FIFO 0 (3 deep) for
    /// the loop's next drain, and the FIFO overruns.
    pub fn hold_can_rx(&mut self, until: u64) {
        self.uc.get_data_mut().hold_rx0_until = until;
    }

    /// Virtual time, cycles since reset.
    #[must_use]
    pub fn now(&self) -> u64 {
        self.uc.get_data().now
    }

    /// What the board did so far.
    #[must_use]
    pub fn stats(&self) -> Stats {
        self.uc.get_data().stats
    }

    /// The registers no model knows that the firmware touched, each once.
    #[must_use]
    pub fn unknown_registers(&self) -> &[UnknownRegister] {
        &self.uc.get_data().unknown
    }

    /// The RCC model (its clock tree).
    #[must_use]
    pub fn rcc(&self) -> &Rcc {
        &self.uc.get_data().rcc
    }

    /// The TIM2 model.
    #[must_use]
    pub fn tim2(&self) -> &Timer {
        &self.uc.get_data().tim2
    }

    /// The CAN1 model.
    #[must_use]
    pub fn can1(&self) -> &BxCan {
        &self.uc.get_data().can1
    }

    /// The log lines drained since the last call.
    pub fn take_lines(&mut self) -> Vec<LogLine> {
        std::mem::take(&mut self.lines)
    }

    /// The image.
    #[must_use]
    pub const fn image(&self) -> &Image {
        &self.image
    }

    fn reg(&self, r: RegisterARM) -> u32 {
        self.uc.reg_read(r).unwrap_or(0) as u32
    }

    fn set_reg(&mut self, r: RegisterARM, v: u32) -> Result<(), BoardError> {
        self.uc
            .reg_write(r, u64::from(v))
            .map_err(|e| uc_err(e, self.pc))
    }

    fn read_words(&self, addr: u32, n: usize) -> Result<Vec<u32>, BoardError> {
        let mut bytes = vec![0u8; 4 * n];
        self.uc
            .mem_read(u64::from(addr), &mut bytes)
            .map_err(|_| BoardError::Unmapped {
                access: "read",
                addr,
                pc: self.pc,
            })?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    fn write_words(&mut self, addr: u32, words: &[u32]) -> Result<(), BoardError> {
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        self.uc
            .mem_write(u64::from(addr), &bytes)
            .map_err(|_| BoardError::Unmapped {
                access: "write",
                addr,
                pc: self.pc,
            })
    }

    const STACKED: [RegisterARM; 6] = [
        RegisterARM::R0,
        RegisterARM::R1,
        RegisterARM::R2,
        RegisterARM::R3,
        RegisterARM::R12,
        RegisterARM::LR,
    ];

    /// Exception entry (ARMv7-M B1.5.6): pushes the frame on the main stack, sets LR to
    /// EXC_RETURN, IPSR, clears the IT bits and CONTROL.FPCA, and branches to the vector.
    fn enter(&mut self, n: u16) -> Result<(), BoardError> {
        let control = self.reg(RegisterARM::CONTROL);
        let handler = self.reg(RegisterARM::IPSR) & 0x1FF != 0;
        if !handler && control & 2 != 0 {
            return Err(BoardError::ProcessStack { pc: self.pc });
        }
        let fp = control & 4 != 0;
        let xpsr = self.reg(RegisterARM::XPSR);
        let sp = self.reg(RegisterARM::MSP);
        let size = if fp { 0x68 } else { 0x20 };
        let realign = (sp - size) & 4 != 0;
        let frame_sp = (sp - size) & !7;
        let mut frame: Vec<u32> = Self::STACKED.iter().map(|&r| self.reg(r)).collect();
        frame.push(self.pc & !1);
        frame.push((xpsr & !(1 << 9)) | u32::from(realign) << 9 | 1 << 24);
        if fp {
            for i in 0..16 {
                frame.push(self.reg(s_reg(i)));
            }
            frame.push(self.reg(RegisterARM::FPSCR));
            frame.push(0);
        }
        self.write_words(frame_sp, &frame)?;
        self.set_reg(RegisterARM::MSP, frame_sp)?;
        let exc_return = match (handler, fp) {
            (true, false) => 0xFFFF_FFF1,
            (false, false) => 0xFFFF_FFF9,
            (true, true) => 0xFFFF_FFE1,
            (false, true) => 0xFFFF_FFE9,
        };
        self.set_reg(RegisterARM::LR, exc_return)?;
        self.set_reg(RegisterARM::CONTROL, control & !4)?;
        // IPSR = n; EPSR: T, no IT state; the flags are kept.
        self.set_reg(
            RegisterARM::XPSR_NZCVQG,
            (xpsr & 0xF80F_0000) | 1 << 24 | u32::from(n),
        )?;
        let vtor = self.uc.get_data().scs.vtor();
        let vector = self.read_words(vtor + 4 * u32::from(n), 1)?[0];
        self.pc = vector | 1;
        let hw = self.uc.get_data_mut();
        hw.scs.activate(n);
        hw.event = true;
        hw.sleep = Sleep::Awake;
        hw.now += ENTRY_CYCLES;
        hw.stats.exceptions += 1;
        Ok(())
    }

    /// Exception return to `value` (EXC_RETURN): unstacks the frame (8 or 26 words, the
    /// alignment word), restores xPSR (IPSR, IT, flags) and CONTROL.FPCA.
    fn exception_return(&mut self, value: u32) -> Result<(), BoardError> {
        let pc = self.reg(RegisterARM::PC);
        let value = value | 1;
        let ok = matches!(value, 0xFFFF_FFF1 | 0xFFFF_FFF9 | 0xFFFF_FFE1 | 0xFFFF_FFE9);
        if !ok || self.uc.get_data().scs.active_stack().is_empty() {
            return Err(BoardError::BadExceptionReturn { value, pc });
        }
        let fp = value & 0x10 == 0;
        let sp = self.reg(RegisterARM::MSP);
        let words = self.read_words(sp, if fp { 26 } else { 8 })?;
        for (&r, &w) in Self::STACKED.iter().zip(&words) {
            self.set_reg(r, w)?;
        }
        if fp {
            for i in 0..16 {
                self.set_reg(s_reg(i), words[8 + i])?;
            }
            self.set_reg(RegisterARM::FPSCR, words[24])?;
        }
        let xpsr = words[7];
        let mut new_sp = sp + if fp { 0x68 } else { 0x20 };
        if xpsr & 1 << 9 != 0 {
            new_sp += 4;
        }
        self.set_reg(RegisterARM::MSP, new_sp)?;
        self.set_reg(RegisterARM::XPSR_NZCVQG, xpsr & !(1 << 9))?;
        let control = self.reg(RegisterARM::CONTROL);
        self.set_reg(
            RegisterARM::CONTROL,
            if fp { control | 4 } else { control & !4 },
        )?;
        self.pc = words[6] | 1;
        let hw = self.uc.get_data_mut();
        hw.scs.deactivate();
        hw.event = true;
        hw.now += RETURN_CYCLES;
        hw.stats.returns += 1;
        Ok(())
    }

    /// Takes every exception that preempts now (nesting: a higher one can follow at once).
    fn take_exceptions(&mut self) -> Result<(), BoardError> {
        loop {
            // Nothing pending (most slices): no register reads.
            if self.uc.get_data().scs.highest_pending().is_none() {
                return Ok(());
            }
            let primask = self.reg(RegisterARM::PRIMASK) & 1 != 0;
            let basepri = self.reg(RegisterARM::BASEPRI) as u8;
            let faultmask = self.reg(RegisterARM::FAULTMASK) & 1 != 0;
            let hw = self.uc.get_data();
            let Some(n) = hw.scs.next(primask, basepri, faultmask) else {
                return Ok(());
            };
            if n == exc::HARD_FAULT || n == exc::SVCALL {
                return Err(BoardError::Emulation {
                    error: format!("exception {n} is not modelled"),
                    pc: self.pc,
                });
            }
            self.enter(n)?;
        }
    }

    /// Runs the board until `until` (cycles), or earlier when the CAN controller needs the
    /// bus ([`Self::can_offer`]). Returns the cycle it stopped at.
    ///
    /// # Errors
    /// [`BoardError`]: the firmware did something the emulator cannot go on from.
    pub fn run_until(&mut self, until: u64) -> Result<u64, BoardError> {
        loop {
            let hw = self.uc.get_data_mut();
            if hw.now >= until {
                return Ok(hw.now);
            }
            if hw.iwdg.expiry().is_some_and(|at| hw.now >= at) {
                self.system_reset(0x2400_0000)?;
                self.uc.get_data_mut().stats.watchdog_resets += 1;
                continue;
            }
            if std::mem::take(&mut hw.reset_requested) {
                self.system_reset(0x1400_0000)?;
                continue;
            }
            let hw = self.uc.get_data_mut();
            hw.sync_lines();
            if std::mem::take(&mut hw.can_attention) {
                return Ok(hw.now);
            }
            self.take_exceptions()?;
            let hw = self.uc.get_data_mut();
            match hw.sleep {
                Sleep::Awake => {}
                Sleep::Event if hw.event => {
                    hw.event = false;
                    hw.sleep = Sleep::Awake;
                }
                Sleep::Interrupt if hw.scs.highest_pending().is_some() => {
                    hw.sleep = Sleep::Awake;
                }
                Sleep::Event | Sleep::Interrupt => {
                    let wake = hw
                        .next_event()
                        .map_or(until, |t| t.min(until))
                        .max(hw.now + 1);
                    hw.stats.sleep_cycles += wake - hw.now;
                    hw.now = wake;
                    continue;
                }
            }
            let next = hw.next_event().unwrap_or(u64::MAX);
            hw.stop_at = until.min(next).min(hw.now + MAX_SLICE).max(hw.now + 1);
            hw.hint = false;
            hw.stats.slices += 1;
            let result = self.uc.emu_start(u64::from(self.pc), 0xFFFF_FFFF, 0, 0);
            let hw = self.uc.get_data_mut();
            let exc_return = hw.exc_return.take();
            let fault = hw.fault.take();
            let resume = hw.resume_at.take();
            self.pc = resume.unwrap_or_else(|| self.reg(RegisterARM::PC)) | 1;
            if let Some(value) = exc_return {
                self.exception_return(value)?;
            } else if let Some(fault) = fault {
                return Err(fault);
            } else if let Err(e) = result {
                let pc = self.pc & !1;
                return Err(match e {
                    unicorn_engine::uc_error::INSN_INVALID => BoardError::InvalidInstruction { pc },
                    // 2.1 may raise the exception-return branch as an exception instead.
                    _ if pc >= 0xFFFF_FF00 => {
                        self.exception_return(pc)?;
                        continue;
                    }
                    e => uc_err(e, pc),
                });
            }
            self.drain_rtt();
        }
    }

    fn drain_rtt(&mut self) {
        let Some(rtt) = self.rtt.as_mut() else {
            return;
        };
        let now = self.uc.get_data().now;
        // Handles on the same emulator (an `Rc` inside): one reads, one writes RdOff back.
        let reader = self.uc.clone();
        let mut writer = self.uc.clone();
        let lines = rtt.drain(
            now,
            |addr, buf| {
                let _ = reader.mem_read(u64::from(addr), buf);
            },
            |addr, bytes| {
                let _ = writer.mem_write(u64::from(addr), bytes);
            },
        );
        self.lines.extend(lines);
    }

    /// The frame CAN1 would put on the bus now, if it is online, has a request, and none of
    /// its frames is on the bus.
    #[must_use]
    pub fn can_offer(&self) -> Option<CanFrame> {
        if self.on_bus.is_some() {
            return None;
        }
        self.uc.get_data().can1.offer().map(|(_, f)| f)
    }

    /// The offered frame started on the wire at `sof` (cycles).
    pub fn can_started(&mut self, sof: u64) {
        if let Some((m, _)) = self.uc.get_data().can1.offer() {
            self.uc.get_data_mut().can1.started(m, sof);
            self.on_bus = Some(m);
        }
    }

    /// The frame on the wire completed, acknowledged.
    pub fn can_transmitted(&mut self) {
        if let Some(m) = self.on_bus.take() {
            self.uc.get_data_mut().can1.transmitted(m);
        }
    }

    /// The frame on the wire failed with `lec` (no acknowledgment, a bit error).
    pub fn can_tx_error(&mut self, lec: Lec) {
        if let Some(m) = self.on_bus.take() {
            let hw = self.uc.get_data_mut();
            let now = hw.now;
            hw.can1.tx_error(m, lec, now);
        }
    }

    /// A frame from another node, its SOF at `sof` (cycles), completed now.
    pub fn can_receive(&mut self, frame: &CanFrame, sof: u64) -> Received {
        self.uc.get_data_mut().can1.receive(frame, sof)
    }
}

/// S0..S15.
fn s_reg(i: usize) -> RegisterARM {
    const S: [RegisterARM; 16] = [
        RegisterARM::S0,
        RegisterARM::S1,
        RegisterARM::S2,
        RegisterARM::S3,
        RegisterARM::S4,
        RegisterARM::S5,
        RegisterARM::S6,
        RegisterARM::S7,
        RegisterARM::S8,
        RegisterARM::S9,
        RegisterARM::S10,
        RegisterARM::S11,
        RegisterARM::S12,
        RegisterARM::S13,
        RegisterARM::S14,
        RegisterARM::S15,
    ];
    S[i]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An image of `code` (Thumb halfwords) at 0x0800_0008, after a vector table whose reset
    /// vector points at it; the stack at the top of 4 KiB of SRAM.
    fn image(code: &[u16], literals: &[u32]) -> Image {
        let mut flash: Vec<u8> = [0x2000_1000u32, 0x0800_0009]
            .iter()
            .flat_map(|w| w.to_le_bytes())
            .collect();
        flash.extend(code.iter().flat_map(|h| h.to_le_bytes()));
        flash.extend(literals.iter().flat_map(|w| w.to_le_bytes()));
        Image {
            path: "test.elf".into(),
            bytes: Vec::new(),
            segments: vec![(0x0800_0000, flash)],
            symbols: HashMap::new(),
            hints: HashMap::new(),
        }
    }

    #[test]
    fn an_unmapped_access_stops_the_run_naming_the_address_and_the_pc() {
        // movs r1, #3; lsls r1, r1, #28 (0x3000_0000: nothing there); ldr r0, [r1]; b .
        let mut board = Board::new(image(&[0x2103, 0x0709, 0x6808, 0xE7FE], &[])).unwrap();
        let e = board.run_until(10_000).unwrap_err();
        assert_eq!(
            e,
            BoardError::Unmapped {
                access: "read",
                addr: 0x3000_0000,
                pc: 0x0800_000C
            }
        );
        assert!(
            e.to_string().contains("0x30000000") && e.to_string().contains("0x0800000c"),
            "{e}"
        );
    }

    #[test]
    fn a_register_no_model_knows_is_reported_once() {
        // ldr r1, [pc, #4] (USART2's SR); ldr r0, [r1]; ldr r0, [r1]; b .
        let mut board =
            Board::new(image(&[0x4901, 0x6808, 0x6808, 0xE7FE], &[0x4000_4400])).unwrap();
        board.run_until(10_000).unwrap();
        let unknown = board.unknown_registers();
        assert_eq!(unknown.len(), 1, "{unknown:?}");
        assert_eq!(
            (unknown[0].addr, unknown[0].peripheral, unknown[0].write),
            (0x4000_4400, "USART2", false)
        );
        // Unicorn's PC in an MMIO callback is the start of the translated block (0x0800_0008),
        // not the load's own address (0x0800_000A): the report names the block.
        assert_eq!(unknown[0].pc, 0x0800_0008);
    }

    #[test]
    fn thumb_blocks_count_16_and_32_bit_instructions() {
        // movs r0, #1 (16); ldr.w r1, [r2] (32: 0xF8D2 0x1000); bx lr (16).
        let code = [0x01, 0x20, 0xD2, 0xF8, 0x00, 0x10, 0x70, 0x47];
        assert_eq!(thumb_instructions(&code), 3);
        // bl (32), b.n (16).
        assert_eq!(thumb_instructions(&[0x00, 0xF0, 0x00, 0xF8, 0xFE, 0xE7]), 2);
    }
}
