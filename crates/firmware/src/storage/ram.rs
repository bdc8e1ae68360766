//! A flash in RAM for the host: NOR semantics (a write only clears bits, an erase sets a
//! sector's bytes to 0xFF) and an optional power cut after a number of operations, which
//! leaves the operation in flight partial (each bit of a write, each byte of an erase, done or
//! not, by a seeded draw). The simulator's robot saves to it; the record log's tests cut it.
//! The board image's flash under a cycle-timed power cut is boardsim's model, not this one.

use std::vec;
use std::vec::Vec;

use crate::rng::SplitMix64;
use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashErrorKind, ReadNorFlash, check_erase, check_read, check_write,
};

/// See the module doc.
#[derive(Debug, Clone)]
pub struct RamFlash {
    bytes: Vec<u8>,
    /// Operations (a word written, a sector erased) left before the cut; `None`: no cut.
    ops_left: Option<u64>,
    /// The cut happened: every operation since failed and changed nothing.
    cut: bool,
    /// Draws for the partial operation.
    rng: SplitMix64,
}

impl RamFlash {
    /// `len` bytes, erased.
    #[must_use]
    pub fn new(len: usize) -> Self {
        Self {
            bytes: vec![0xFF; len],
            ops_left: None,
            cut: false,
            rng: SplitMix64(0),
        }
    }

    /// The power is cut during the operation after the next `ops` ones, which is left
    /// partial by draws seeded with `seed`; then every operation fails.
    pub fn cut_after(&mut self, ops: u64, seed: u64) {
        self.ops_left = Some(ops);
        self.rng = SplitMix64(seed);
    }

    /// Whether the cut happened.
    #[must_use]
    pub const fn was_cut(&self) -> bool {
        self.cut
    }

    /// The contents.
    #[must_use]
    pub fn bytes(&self) -> &[u8] {
        &self.bytes
    }

    /// A flash with these contents, powered again (no cut pending).
    #[must_use]
    pub fn from_bytes(bytes: Vec<u8>) -> Self {
        Self {
            bytes,
            ops_left: None,
            cut: false,
            rng: SplitMix64(0),
        }
    }

    /// Counts an operation: `Ok(true)` when it is the one cut short.
    fn op(&mut self) -> Result<bool, NorFlashErrorKind> {
        if self.cut {
            return Err(NorFlashErrorKind::Other);
        }
        match &mut self.ops_left {
            Some(0) => {
                self.cut = true;
                Ok(true)
            }
            Some(n) => {
                *n -= 1;
                Ok(false)
            }
            None => Ok(false),
        }
    }
}

impl ErrorType for RamFlash {
    type Error = NorFlashErrorKind;
}

impl ReadNorFlash for RamFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        check_read(self, offset, bytes.len())?;
        let at = offset as usize;
        bytes.copy_from_slice(&self.bytes[at..at + bytes.len()]);
        Ok(())
    }

    fn capacity(&self) -> usize {
        self.bytes.len()
    }
}

impl NorFlash for RamFlash {
    const WRITE_SIZE: usize = 4;
    /// The STM32F4's small sectors.
    const ERASE_SIZE: usize = 16 * 1024;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        check_erase(self, from, to)?;
        for sector in (from..to).step_by(Self::ERASE_SIZE) {
            let range = sector as usize..sector as usize + Self::ERASE_SIZE;
            if self.op()? {
                for i in range {
                    if self.rng.next_u64() & 1 == 1 {
                        self.bytes[i] = 0xFF;
                    }
                }
                return Err(NorFlashErrorKind::Other);
            }
            self.bytes[range].fill(0xFF);
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        check_write(self, offset, bytes.len())?;
        for (i, word) in bytes.chunks_exact(Self::WRITE_SIZE).enumerate() {
            let at = offset as usize + i * Self::WRITE_SIZE;
            let partial = self.op()?;
            for (j, &b) in word.iter().enumerate() {
                // Programming clears bits only; a cut clears each of them or not.
                #[allow(clippy::cast_possible_truncation)] // a byte of the draw
                let mask = if partial {
                    self.rng.next_u64() as u8
                } else {
                    0xFF
                };
                let clear = !b & mask;
                self.bytes[at + j] &= !clear;
            }
            if partial {
                return Err(NorFlashErrorKind::Other);
            }
        }
        Ok(())
    }
}
