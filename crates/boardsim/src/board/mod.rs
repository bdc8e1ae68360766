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
//!
//! The flash is the FLASH model's ([`crate::flash`]): it programs and erases in virtual time,
//! and a fetch or read of the flash while it is busy stalls the CPU to the operation's end
//! (time runs on, interrupts pend). Its contents persist across resets; [`Board::flash_image`]
//! takes them out and [`Board::with_flash_image`] starts a board on them.
//!
//! The parts: `cpu` sets up the emulator and its hooks, `hw` holds the peripheral models the
//! MMIO callbacks reach, `flash_mem` keeps the flash's bytes and stalls, `exception` enters and
//! returns from exceptions, `error` names why a run stopped.

use firmware::CanFrame;
use unicorn_engine::{RegisterARM, Unicorn};

use crate::bxcan::{BxCan, Lec, Received};
use crate::elf::Image;
use crate::flash::{self, Flash, Timing};
use crate::regs::Rcc;
use crate::rtt::{LogLine, Rtt};
use crate::tim::Timer;

mod cpu;
mod error;
mod exception;
mod flash_mem;
#[cfg(test)]
mod flash_tests;
mod hw;

pub use error::{BoardError, UnknownRegister};
pub use hw::Stats;

use hw::{Hw, Sleep};

/// Virtual time's rate: instructions (cycles) per second.
pub const CPU_HZ: u64 = 168_000_000;
/// The type C board's crystal.
pub const HSE_HZ: u32 = 12_000_000;
/// The longest slice the CPU runs without the board looking at its peripherals.
const MAX_SLICE: u64 = 20_000;

/// The interrupt lines of the modelled peripherals (RM0090 Table 61).
pub mod irq {
    /// FLASH (end of operation, error).
    pub const FLASH: usize = 4;
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

/// SRAM (base, size): its contents survive a reset.
const SRAM: (u32, usize) = (0x2000_0000, 0x2_0000);
/// CCM RAM (base, size): likewise.
const CCM: (u32, usize) = (0x1000_0000, 0x1_0000);

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
    /// The board with `image` flashed (the rest of the flash erased), out of reset.
    ///
    /// # Errors
    /// The emulator could not be set up, or the image does not fit the memory map.
    pub fn new(image: Image) -> anyhow::Result<Self> {
        Self::start(image, None)
    }

    /// The board with the flash holding `flash` (all [`flash::SIZE`] bytes, as
    /// [`Self::flash_image`] gives them) in place of the image's segments, out of reset. The
    /// image still gives the RTT control block, the hints and any segment outside the flash.
    ///
    /// # Errors
    /// `flash` is not [`flash::SIZE`] bytes long, the emulator could not be set up, or the
    /// image's other segments do not fit the memory map.
    pub fn with_flash_image(image: Image, flash: &[u8]) -> anyhow::Result<Self> {
        anyhow::ensure!(
            flash.len() == flash::SIZE as usize,
            "a flash image of {} bytes: the F407's flash is {}",
            flash.len(),
            flash::SIZE
        );
        Self::start(image, Some(flash))
    }

    fn start(image: Image, flash: Option<&[u8]>) -> anyhow::Result<Self> {
        let rtt = match image.symbol("_SEGGER_RTT") {
            Some(control) => Some(Rtt::new(control, &image.bytes)?),
            None => None,
        };
        let uc = Self::cpu(&image, flash, &[], Timing::default())?;
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
    /// RAM and the flash as they were (a flash operation in flight is lost, its bytes as before
    /// it), the time and the counters going on.
    ///
    /// # Errors
    /// The emulator could not be set up again.
    pub fn reset(&mut self) -> anyhow::Result<()> {
        let flash = self
            .uc
            .mem_read_as_vec(u64::from(flash::BASE), flash::SIZE as usize)
            .map_err(|e| anyhow::anyhow!("flash: {e:?}"))?;
        let mut ram = Vec::new();
        for (at, size) in [SRAM, CCM] {
            let bytes = self
                .uc
                .mem_read_as_vec(u64::from(at), size)
                .map_err(|e| anyhow::anyhow!("RAM: {e:?}"))?;
            ram.push((at, bytes));
        }
        let old = self.uc.get_data();
        let (now, mut stats) = (old.now, old.stats);
        let (unknown, reported) = (old.unknown.clone(), old.reported.clone());
        let timing = old.flash.timing();
        if old.flash.op().is_some() {
            stats.flash_ops_interrupted += 1;
        }
        self.uc = Self::cpu(&self.image, Some(&flash), &ram, timing)?;
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

    /// The FLASH model: its registers and the operation in flight ([`Flash::op`]: a program or
    /// an erase, its start and end in cycles).
    #[must_use]
    pub fn flash(&self) -> &Flash {
        &self.uc.get_data().flash
    }

    /// The flash's contents ([`flash::SIZE`] bytes from [`flash::BASE`]): the completed
    /// operations', not the one in flight.
    ///
    /// # Panics
    /// Never: the flash is always mapped.
    #[must_use]
    pub fn flash_image(&self) -> Vec<u8> {
        self.uc
            .mem_read_as_vec(u64::from(flash::BASE), flash::SIZE as usize)
            .expect("the flash is mapped")
    }

    /// Has the FLASH model keep every operation it completes from now on, until a reset
    /// ([`Flash::history`]).
    pub fn record_flash_ops(&mut self) {
        self.uc.get_data_mut().flash.record();
    }

    /// The datasheet figures the flash's operations take from now on (typical by default),
    /// also after resets.
    pub fn set_flash_timing(&mut self, timing: Timing) {
        self.uc.get_data_mut().flash.set_timing(timing);
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
            flash_mem::sync(&mut self.uc);
            let hw = self.uc.get_data_mut();
            hw.sync_lines();
            if std::mem::take(&mut hw.can_attention) {
                return Ok(hw.now);
            }
            if hw.sleep == Sleep::Flash {
                // Stalled on the flash: time runs to the operation's end (the next event
                // first); interrupts wait.
                if let Some(end) = hw.flash.op().map(|op| op.end) {
                    let wake = hw
                        .next_event()
                        .map_or(until, |t| t.min(until))
                        .min(end)
                        .max(hw.now + 1);
                    hw.stats.flash_stall_cycles += wake - hw.now;
                    hw.now = wake;
                    continue;
                }
                hw.sleep = Sleep::Awake;
            }
            self.take_exceptions()?;
            let hw = self.uc.get_data_mut();
            match hw.sleep {
                Sleep::Awake | Sleep::Flash => {}
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
            // A read stalled on the flash stops Unicorn with an error, at the load.
            let stalled = hw.sleep == Sleep::Flash;
            self.pc = resume.unwrap_or_else(|| self.reg(RegisterARM::PC)) | 1;
            if let Some(value) = exc_return {
                self.exception_return(value)?;
            } else if let Some(fault) = fault {
                return Err(fault);
            } else if let (Err(e), false) = (result, stalled) {
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

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

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
}
