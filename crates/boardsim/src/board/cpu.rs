//! The emulated CPU: Unicorn's Cortex-M4 with the memory map, the flash, the image and the RAM
//! loaded, the peripherals' MMIO callbacks, and the hooks that count virtual time, catch faults
//! (and serve the flash's writes and stalls) and see the sleep and event hints (WFE, WFI, SEV,
//! CPSIE I).

use unicorn_engine::unicorn_const::{Arch, ArmCpuModel, HookType, MemType, Mode, Prot};
use unicorn_engine::{RegisterARM, Unicorn};

use super::flash_mem;
use super::hw::{Hw, Sleep};
use super::{Board, BoardError};
use crate::elf::{CPSIE_I, Image, SEV, WFE, WFI};
use crate::flash::{self, Timing};

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
/// The flash's size (a power of two).
const FLASH_SIZE: u32 = flash::SIZE;
/// The factory flash-size register (KiB) in system memory.
const FLASH_SIZE_REG: u32 = 0x1FFF_7A22;

/// The emulator as the board runs it.
type Cpu = Unicorn<'static, Hw>;

/// Names a failed emulator set-up step.
fn err(what: &'static str) -> impl Fn(unicorn_engine::uc_error) -> anyhow::Error {
    move |err| anyhow::anyhow!("{what}: {err:?}")
}

impl Board {
    /// A Cortex-M4 with the memory map, the flash (`flash`, else erased and the image's
    /// segments), the image's other segments and `ram` (base, bytes) loaded, and the hooks
    /// installed; its flash operations take `timing`.
    pub(super) fn cpu(
        image: &Image,
        flash: Option<&[u8]>,
        ram: &[(u32, Vec<u8>)],
        timing: Timing,
    ) -> anyhow::Result<Cpu> {
        let hw = Hw::new(timing);
        let mut uc = Unicorn::new_with_data(Arch::ARM, Mode::THUMB | Mode::MCLASS, hw)
            .map_err(err("Unicorn"))?;
        uc.ctl_set_cpu_model(ArmCpuModel::CORTEX_M4 as i32)
            .map_err(err("the Cortex-M4 model"))?;
        load(&mut uc, image, flash, ram)?;
        map_peripherals(&mut uc)?;
        count_instructions(&mut uc)?;
        catch_faults(&mut uc)?;
        hook_hints(&mut uc, image)?;
        Ok(uc)
    }
}

/// The memory map; the flash (and its boot alias at 0): `flash`, else erased (0xFF, as a
/// chip's flash outside the image is) with the image's segments; the image's other segments;
/// the factory flash-size register and `ram`.
fn load(
    uc: &mut Cpu,
    image: &Image,
    flash: Option<&[u8]>,
    ram: &[(u32, Vec<u8>)],
) -> anyhow::Result<()> {
    for (at, size, prot, _) in MEMORY {
        uc.mem_map(u64::from(at), u64::from(size), Prot(prot))
            .map_err(err("memory map"))?;
    }
    let erased;
    let contents = match flash {
        Some(bytes) => bytes,
        None => {
            erased = vec![flash::ERASED; FLASH_SIZE as usize];
            &erased
        }
    };
    for at in [flash::BASE, 0] {
        uc.mem_write(u64::from(at), contents)
            .map_err(err("flash"))?;
    }
    for (addr, bytes) in &image.segments {
        let in_flash = (flash::BASE..flash::BASE + FLASH_SIZE).contains(addr);
        if in_flash && flash.is_some() {
            continue;
        }
        uc.mem_write(u64::from(*addr), bytes).map_err(|err| {
            anyhow::anyhow!(
                "{}: a segment of {} bytes at {addr:#010x} is outside the memory map ({err:?})",
                image.path.display(),
                bytes.len()
            )
        })?;
        if in_flash {
            uc.mem_write(u64::from(addr - flash::BASE), bytes)
                .map_err(err("boot alias"))?;
        }
    }
    uc.mem_write(u64::from(FLASH_SIZE_REG), &1024u16.to_le_bytes())
        .map_err(err("flash size register"))?;
    for (addr, bytes) in ram {
        uc.mem_write(u64::from(*addr), bytes).map_err(err("RAM"))?;
    }
    Ok(())
}

/// The peripheral regions, each access to the models (a register no model knows behaves as
/// memory and is reported).
fn map_peripherals(uc: &mut Cpu) -> anyhow::Result<()> {
    for (at, size) in MMIO {
        let read = move |uc: &mut Unicorn<'_, Hw>, off: u64, size: usize| -> u64 {
            let addr = at + off as u32;
            let known = match flash_mem::register(addr) {
                Some(off) => flash_mem::read(uc, off, size),
                None => uc.get_data_mut().read(addr, size),
            };
            if let Some(v) = known {
                return u64::from(v);
            }
            let pc = uc.reg_read(RegisterARM::PC).unwrap_or(0) as u32;
            let file = uc.get_data_mut().unknown_access(addr, false, pc);
            u64::from(file.read(addr & 0x3FF, size))
        };
        let write = move |uc: &mut Unicorn<'_, Hw>, off: u64, size: usize, value: u64| {
            let addr = at + off as u32;
            let mut stop = false;
            let known = match flash_mem::register(addr) {
                Some(off) => flash_mem::write(uc, off, size, value as u32),
                None => uc.get_data_mut().write(addr, size, value as u32, &mut stop),
            };
            if known.is_none() {
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
            .map_err(err("MMIO map"))?;
    }
    Ok(())
}

/// Virtual time: each block's instructions, as it starts. A stop requested here happens
/// before the block runs (it is counted when it does).
fn count_instructions(uc: &mut Cpu) -> anyhow::Result<()> {
    uc.add_block_hook(1, 0, |uc, addr, size| {
        if uc.get_data().now >= uc.get_data().stop_at {
            let _ = uc.emu_stop();
            return;
        }
        // A fetch from the flash while it is busy stalls (before the block runs).
        if uc.get_data().flash.op().is_some()
            && flash_mem::flash_addr(addr).is_some()
            && flash_mem::fetch(uc)
        {
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
    .map_err(err("block hook"))?;
    Ok(())
}

/// An access outside the memory map stops the CPU with [`BoardError::Unmapped`]; a fetch of
/// an EXC_RETURN value is a handler's return. A write to the (read-only) flash goes to the
/// FLASH model, and a read of it during an operation stalls (`flash_mem`). Unicorn's
/// invalid-instruction report of a hint the hooks expect is claimed.
fn catch_faults(uc: &mut Cpu) -> anyhow::Result<()> {
    let unmapped = HookType(
        HookType::MEM_READ_UNMAPPED.0
            | HookType::MEM_WRITE_UNMAPPED.0
            | HookType::MEM_FETCH_UNMAPPED.0
            | HookType::MEM_WRITE_PROT.0
            | HookType::MEM_READ_PROT.0
            | HookType::MEM_FETCH_PROT.0,
    );
    uc.add_mem_hook(unmapped, 1, 0, |uc, kind, addr, size, value| {
        if kind == MemType::WRITE_PROT
            && let Some(at) = flash_mem::flash_addr(addr)
        {
            // Returning true discards the CPU's own write (Unicorn 2.1.5: a read-only
            // region's TLB entry discards writes once the hook claims them).
            flash_mem::cpu_write(uc, at, size, value);
            return true;
        }
        if kind == MemType::READ_PROT
            && let Some(handled) = flash_mem::read_prot(uc, addr)
        {
            return handled;
        }
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
    .map_err(err("unmapped-access hook"))?;
    // WFE and WFI raise EXCP_YIELD/EXCP_HLT, which Unicorn 2.1 reports as an invalid
    // instruction unless a hook claims it: the hint hooks below mark the one they expect.
    uc.add_insn_invalid_hook(|uc| std::mem::take(&mut uc.get_data_mut().hint))
        .map_err(err("invalid-instruction hook"))?;
    Ok(())
}

/// WFE and WFI sleep (resuming after them), SEV sets the event register, CPSIE I stops the
/// slice if an interrupt is pending: a code hook at each of the image's hints.
fn hook_hints(uc: &mut Cpu, image: &Image) -> anyhow::Result<()> {
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
            hooked.map_err(err("hint hook"))?;
        }
    }
    Ok(())
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thumb_blocks_count_16_and_32_bit_instructions() {
        // movs r0, #1 (16); ldr.w r1, [r2] (32: 0xF8D2 0x1000); bx lr (16).
        let code = [0x01, 0x20, 0xD2, 0xF8, 0x00, 0x10, 0x70, 0x47];
        assert_eq!(thumb_instructions(&code), 3);
        // bl (32), b.n (16).
        assert_eq!(thumb_instructions(&[0x00, 0xF0, 0x00, 0xF8, 0xFE, 0xE7]), 2);
    }
}
