//! The flash's bytes in Unicorn's memory, driven by the FLASH model ([`crate::flash`]).
//!
//! The flash and its boot alias at 0 are two read-only mappings holding the same bytes (one
//! host buffer for both would need `unsafe`). A CPU write to either reaches the model through
//! the write-protection hook, which discards the write itself; an operation's bytes are
//! written to both copies when it ends, so the memory holds the completed operations only.
//!
//! While an operation is in flight the CPU's next access to the flash waits for its end (one
//! bank: the chip cannot read it while it writes):
//! - a block fetched from it stops the CPU before it runs ([`Sleep::Flash`]) and the board lets
//!   time run to the end as in a sleep: timers count, interrupts pend, the watchdog may reset
//!   the chip, the operation then lost;
//! - a data read: the flash is execute-only during the operation, so the read stops the CPU
//!   the same way and runs again afterwards;
//! - a write to the flash or to FLASH_CR stalls in place: the clock jumps to the end.
//!
//! Unicorn offers a misaligned write whole, then byte by byte: the model refuses the whole
//! (PGAERR) and the bytes are dropped.

use unicorn_engine::Unicorn;
use unicorn_engine::unicorn_const::Prot;

use super::BoardError;
use super::hw::{Hw, Sleep};
use crate::flash::{self, reg};
use crate::regs::{base, merge, sub_word};

type Cpu<'a> = Unicorn<'a, Hw>;

/// Where the two copies are mapped.
const COPIES: [u32; 2] = [flash::BASE, 0];

/// The flash address (in 0x0800_0000..) that `addr` reaches, if it is in the flash or its
/// boot alias.
pub(super) fn flash_addr(addr: u64) -> Option<u32> {
    let size = u64::from(flash::SIZE);
    let base = u64::from(flash::BASE);
    let off = match addr {
        a if a < size => a,
        a if (base..base + size).contains(&a) => a - base,
        _ => return None,
    };
    Some(flash::BASE + off as u32)
}

/// The FLASH register offset of `addr`, if it is in the interface's block.
pub(super) const fn register(addr: u32) -> Option<u32> {
    if addr & !0x3FF == base::FLASH {
        Some(addr & 0x3FF)
    } else {
        None
    }
}

/// A read of a FLASH register; `None` for an offset the model does not know.
pub(super) fn read(uc: &mut Cpu, off: u32, size: usize) -> Option<u32> {
    sync(uc);
    let hw = uc.get_data_mut();
    hw.stats.mmio += 1;
    hw.flash.read(off).map(|word| sub_word(word, off, size))
}

/// A write of a FLASH register; `None` for an offset the model does not know. A write of CR
/// while busy waits for the operation's end.
pub(super) fn write(uc: &mut Cpu, off: u32, size: usize, value: u32) -> Option<()> {
    sync(uc);
    if off & !3 == reg::CR {
        wait(uc);
    }
    let hw = uc.get_data_mut();
    hw.stats.mmio += 1;
    let old = hw.flash.read(off)?;
    // Bytes not written: kept in the control registers, zero (no key, no flag to clear) in
    // the others.
    let kept = match off & !3 {
        reg::ACR | reg::CR | reg::OPTCR => old,
        _ => 0,
    };
    let now = hw.now;
    let was_busy = hw.flash.op().is_some();
    hw.flash.write(off, merge(kept, off, size, value), now)?;
    if !was_busy && uc.get_data().flash.op().is_some() {
        started(uc);
    }
    Some(())
}

/// A CPU write of `size` bytes of `value` at `addr` (a flash address, [`flash_addr`]), from
/// the write-protection hook: the model programs it or sets an error flag; Unicorn discards
/// the write itself once the hook returns true.
pub(super) fn cpu_write(uc: &mut Cpu, addr: u32, size: usize, value: i64) {
    let hw = uc.get_data_mut();
    if size == 1 && hw.flash_split_bytes > 0 {
        hw.flash_split_bytes -= 1;
        return;
    }
    hw.flash_split_bytes = if (addr as usize).is_multiple_of(size) {
        0
    } else {
        size
    };
    wait(uc);
    let hw = uc.get_data_mut();
    let now = hw.now;
    if hw
        .flash
        .program(addr, size as u8, value as u64, now)
        .is_ok()
    {
        started(uc);
    }
}

/// A block at a flash address is about to run (the block hook): while an operation is in
/// flight the CPU stops there, stalled ([`Sleep::Flash`]). Returns whether it stops.
pub(super) fn fetch(uc: &mut Cpu) -> bool {
    sync(uc);
    if uc.get_data().flash.op().is_none() {
        return false;
    }
    uc.get_data_mut().sleep = Sleep::Flash;
    let _ = uc.emu_stop();
    true
}

/// A data read at `addr` found memory unreadable (the read-protection hook): if it is the
/// flash during an operation, the CPU stalls ([`Sleep::Flash`]) and `Some(false)` lets Unicorn
/// stop at the load, to run it again; `Some(true)` if the operation has ended (the read goes
/// on); `None` if it is not the flash's stall.
pub(super) fn read_prot(uc: &mut Cpu, addr: u64) -> Option<bool> {
    flash_addr(addr)?;
    uc.get_data().flash.op()?;
    sync(uc);
    if uc.get_data().flash.op().is_none() {
        return Some(true);
    }
    uc.get_data_mut().sleep = Sleep::Flash;
    Some(false)
}

/// Finishes the operation in flight if it has ended by now.
pub(super) fn sync(uc: &mut Cpu) {
    let hw = uc.get_data();
    if hw.flash.op().is_some_and(|op| hw.now >= op.end) {
        finish(uc);
    }
}

/// Stalls in place until the operation in flight ends, and finishes it.
fn wait(uc: &mut Cpu) {
    let hw = uc.get_data_mut();
    let Some(end) = hw.flash.op().map(|op| op.end) else {
        return;
    };
    if end > hw.now {
        hw.stats.flash_stall_cycles += end - hw.now;
        hw.now = end;
    }
    finish(uc);
}

/// An operation started: the flash turns execute-only (a data read then reaches the
/// read-protection hook, a translated load too once the TLB forgets the flash), and the CPU
/// stops by its end.
fn started(uc: &mut Cpu) {
    let hw = uc.get_data_mut();
    if let Some(op) = hw.flash.op() {
        hw.stop_at = hw.stop_at.min(op.end);
    }
    for at in COPIES {
        let r = uc.mem_protect(u64::from(at), u64::from(flash::SIZE), Prot::EXEC);
        check(uc, r, "flash protection");
    }
    let r = uc.ctl_flush_tlb();
    check(uc, r, "TLB flush");
}

/// Ends the operation in flight: its bytes written to both copies, the code translated from
/// the old ones forgotten, the flash readable again.
fn finish(uc: &mut Cpu) {
    let Some(op) = uc.get_data_mut().flash.finish() else {
        return;
    };
    let (at, len) = op.operation.range();
    let off = at - flash::BASE;
    match uc.mem_read_as_vec(u64::from(at), len as usize) {
        Ok(mut bytes) => {
            op.operation.apply(&mut bytes);
            for copy in COPIES {
                let r = uc.mem_write(u64::from(copy + off), &bytes);
                check(uc, r, "flash write");
                let start = u64::from(copy + off);
                let r = uc.ctl_remove_cache(start, start + u64::from(len));
                check(uc, r, "translation cache");
            }
        }
        Err(e) => check(uc, Err(e), "flash read"),
    }
    let blocks = &mut uc.get_data_mut().blocks;
    let slots = off as usize / 2..(off + len).div_ceil(2) as usize;
    blocks[slots].fill((0, 0));
    for copy in COPIES {
        let r = uc.mem_protect(
            u64::from(copy),
            u64::from(flash::SIZE),
            Prot::READ | Prot::EXEC,
        );
        check(uc, r, "flash protection");
    }
}

/// An emulator call that cannot fail on the fixed memory map, failing: the run stops.
fn check(uc: &mut Cpu, result: Result<(), unicorn_engine::uc_error>, what: &str) {
    if let Err(e) = result {
        let pc = uc.reg_read(unicorn_engine::RegisterARM::PC).unwrap_or(0) as u32;
        uc.get_data_mut()
            .fault
            .get_or_insert(BoardError::Emulation {
                error: format!("{what}: {e:?}"),
                pc,
            });
    }
}
