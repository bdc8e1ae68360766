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
        let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
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
