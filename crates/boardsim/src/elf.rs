//! The board image: the ELF `cargo build --release` makes in `boards/stm32f407`, read as a
//! debug probe would flash it.
//!
//! Its load segments go where the flash holds them (the physical address: `.data`'s initial
//! values live in flash, cortex-m-rt copies them to RAM), its symbols locate the RTT control
//! block, and its code is searched for the hint instructions the emulator must see execute
//! (WFE, WFI, SEV, CPSIE I): Unicorn treats them as no-ops or invalid instructions, so the
//! board hooks their addresses.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use object::elf::PT_LOAD;
use object::read::elf::{ElfFile32, ProgramHeader};
use object::{Object, ObjectSection, ObjectSymbol, SectionKind};

/// Thumb encodings of the hint instructions the board hooks.
pub const WFE: u16 = 0xBF20;
/// Wait for interrupt.
pub const WFI: u16 = 0xBF30;
/// Send event.
pub const SEV: u16 = 0xBF40;
/// `cpsie i`: clears PRIMASK, which may let a pending interrupt in.
pub const CPSIE_I: u16 = 0xB662;

/// Bytes of an ELF32 file header.
const ELF_HEADER: u64 = 52;

/// Bytes of a board image read at most: the F407's flash is 1 MiB, and its ELF with debug
/// information some tens of MiB.
pub const MAX_IMAGE_BYTES: u64 = 256 << 20;

/// `EM_ARM`, the machine of every Cortex-M image.
const EM_ARM: u16 = 40;

/// The file header says: ELF, 32-bit, little-endian, an executable for ARM (as the board's
/// image is); else what it says instead.
fn check_header(head: &[u8]) -> Result<(), String> {
    if head.len() < 4 || &head[..4] != b"\x7fELF" {
        return Err(format!(
            "not an ELF file: it begins with \"{}\"",
            firmware::input::quote_bytes(&head[..head.len().min(16)])
        ));
    }
    if head.len() < ELF_HEADER as usize {
        return Err(format!(
            "an ELF file cut short: {} bytes, its header alone is 52",
            head.len()
        ));
    }
    if head[4] != 1 || head[5] != 1 {
        return Err(format!(
            "a {}-bit {}-endian ELF; the board's image is 32-bit little-endian (ARM Cortex-M4)",
            if head[4] == 2 { 64 } else { 32 },
            if head[5] == 2 { "big" } else { "little" }
        ));
    }
    let machine = u16::from_le_bytes([head[18], head[19]]);
    if machine != EM_ARM {
        return Err(format!(
            "an ELF for machine {machine} (e_machine; {}), not ARM (40): the board's image is \
             built for thumbv7em-none-eabihf",
            match machine {
                3 => "x86",
                62 => "x86-64",
                183 => "AArch64",
                243 => "RISC-V",
                _ => "not ARM",
            }
        ));
    }
    Ok(())
}

/// An error reading the image, naming the file.
#[derive(Debug)]
pub struct ImageError {
    /// The ELF file.
    pub path: PathBuf,
    /// What is wrong with it.
    pub what: String,
}

impl std::fmt::Display for ImageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.path.display(), self.what)
    }
}

impl std::error::Error for ImageError {}

/// A loaded board image.
#[derive(Debug, Clone)]
pub struct Image {
    /// The file it was read from.
    pub path: PathBuf,
    /// The ELF's bytes (the defmt table is read from them).
    pub bytes: Vec<u8>,
    /// (load address, bytes) of each loadable segment, in file order.
    pub segments: Vec<(u32, Vec<u8>)>,
    /// Symbol name to address.
    pub symbols: HashMap<String, u32>,
    /// Addresses of the hint instructions, by encoding ([`WFE`], [`WFI`], [`SEV`], [`CPSIE_I`]).
    pub hints: HashMap<u16, Vec<u32>>,
}

impl Image {
    /// Reads the ELF at `path`.
    ///
    /// # Errors
    /// [`ImageError`] naming the file: unreadable, not a 32-bit little-endian ELF, or without
    /// a loadable segment.
    pub fn read(path: &Path) -> Result<Self, ImageError> {
        let err = |what: String| ImageError {
            path: path.to_path_buf(),
            what,
        };
        // The header first: a file that is not the board's kind of ELF is read no further.
        let head = firmware::input::read_head(path, ELF_HEADER).map_err(|e| err(e.to_string()))?;
        check_header(&head).map_err(err)?;
        let bytes =
            firmware::input::read_bounded(path, MAX_IMAGE_BYTES).map_err(|e| err(e.to_string()))?;
        let (segments, symbols, hints) = {
            let elf = ElfFile32::<object::Endianness>::parse(&*bytes)
                .map_err(|e| err(format!("not a 32-bit ELF: {e}")))?;
            let endian = elf.endian();
            let mut segments = Vec::new();
            for ph in elf.elf_program_headers() {
                if ph.p_type(endian) != PT_LOAD || ph.p_filesz(endian) == 0 {
                    continue;
                }
                let data = ph
                    .data(endian, &*bytes)
                    .map_err(|()| err("a load segment lies outside the file".into()))?;
                segments.push((ph.p_paddr(endian), data.to_vec()));
            }
            if segments.is_empty() {
                return Err(err("no loadable segment".into()));
            }
            let symbols = elf
                .symbols()
                .filter_map(|s| Some((s.name().ok()?.to_string(), s.address() as u32)))
                .collect();
            let mut hints: HashMap<u16, Vec<u32>> = HashMap::new();
            for section in elf.sections().filter(|s| s.kind() == SectionKind::Text) {
                let data = section.data().map_err(|e| err(e.to_string()))?;
                for (i, half) in data.chunks_exact(2).enumerate() {
                    let half = u16::from_le_bytes([half[0], half[1]]);
                    if [WFE, WFI, SEV, CPSIE_I].contains(&half) {
                        let at = section.address() as u32 + 2 * i as u32;
                        hints.entry(half).or_default().push(at);
                    }
                }
            }
            (segments, symbols, hints)
        };
        Ok(Self {
            path: path.to_path_buf(),
            bytes,
            segments,
            symbols,
            hints,
        })
    }

    /// The address of `name`, if the image has that symbol.
    #[must_use]
    pub fn symbol(&self, name: &str) -> Option<u32> {
        self.symbols.get(name).copied()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An ELF32 file header of `class`, `data` and `machine`.
    fn header(class: u8, data: u8, machine: u16) -> Vec<u8> {
        let mut h = vec![0; 52];
        h[..4].copy_from_slice(b"\x7fELF");
        h[4] = class;
        h[5] = data;
        h[18..20].copy_from_slice(&machine.to_le_bytes());
        h
    }

    #[test]
    fn only_an_arm_elf32_little_endian_passes() {
        assert_eq!(check_header(&header(1, 1, EM_ARM)), Ok(()));
        for (head, says) in [
            (header(1, 1, 3), "x86"),
            (header(1, 1, 243), "RISC-V"),
            (header(2, 1, EM_ARM), "64-bit"),
            (header(1, 2, EM_ARM), "big-endian"),
            (header(1, 1, EM_ARM)[..20].to_vec(), "cut short"),
            (b"\x1b[31mnot an elf".to_vec(), "\\u{1b}[31m"),
        ] {
            let e = check_header(&head).unwrap_err();
            assert!(e.contains(says), "{says}: {e}");
        }
    }
}
