//! The embedded flash's interface (RM0090 §3.5-3.9): 1 MiB in twelve sectors (0-3 of 16 KiB,
//! 4 of 64 KiB, 5-11 of 128 KiB), erased to 0xFF, programmed by CPU writes.
//!
//! FLASH_CR is locked from reset: KEYR takes 0x4567_0123 then 0xCDEF_89AB; any other write to
//! KEYR (a wrong key, or any key while unlocked) is the invalid sequence that locks CR until the
//! next reset (the chip also answers it with a bus error; here [`Flash::locked_out`] tells).
//! Setting CR.LOCK locks again. With CR.PG set, a CPU write of PSIZE's width (x8, x16, x32,
//! x64) programs new = old AND value; a write refused sets its SR flag and changes nothing:
//! PGSERR when locked or without PG (CR "not correctly configured"), WRPERR in a sector
//! OPTCR.nWRP protects, PGPERR when the width is not PSIZE's, PGAERR when misaligned or
//! across a 128-bit row.
//! STRT with SER erases sector SNB, with MER all of them (neither, both, or SNB > 11: nothing).
//! The error flags, EOP (with EOPIE) and OPERR (with ERRIE) are write-1-to-clear; EOP or OPERR
//! with its enable raises the FLASH interrupt.
//!
//! An operation is a [`FlashOp`] in flight (BSY) from its start to its end in CPU cycles;
//! [`Flash::finish`] hands it over for its bytes to be written. Durations are DS8626's
//! (Table 40, x32: word 16 µs typical / 100 µs max; 16 KiB sector 250/500 ms, 64 KiB
//! 550/1100 ms, 128 KiB 1/2 s, mass erase 8/16 s), [`Timing`] picks the column. An erase
//! takes longer at x8 and x16 (400/300 ms for 16 KiB): embassy-stm32's F4 driver erases with
//! PSIZE as its last write left it, x8. x64 needs an external VPP and takes x32's times here.
//! This model knows nothing of memory: the board writes the bytes and stalls the CPU (`board`).
//! Option bytes (OPTKEYR, OPTSTRT), read protection, the OTP area and the caches are not
//! modelled; OPTCR reads back what is written.

/// The flash's address; the boot alias at 0 maps the same bytes.
pub const BASE: u32 = 0x0800_0000;
/// Its size (1 MiB on the F407IG and the F407VG).
pub const SIZE: u32 = 0x10_0000;
/// An erased byte.
pub const ERASED: u8 = 0xFF;
/// A program access may not cross a row of 128 bits.
pub const ROW: u32 = 16;
/// The sectors.
pub const SECTORS: u8 = 12;

/// Register offsets.
pub mod reg {
    /// Access control (latency, caches).
    pub const ACR: u32 = 0x00;
    /// Key (unlocks CR).
    pub const KEYR: u32 = 0x04;
    /// Option key.
    pub const OPTKEYR: u32 = 0x08;
    /// Status.
    pub const SR: u32 = 0x0C;
    /// Control.
    pub const CR: u32 = 0x10;
    /// Option control.
    pub const OPTCR: u32 = 0x14;
}

/// The unlock keys, written to KEYR in this order.
pub mod key {
    /// The first.
    pub const KEY1: u32 = 0x4567_0123;
    /// The second.
    pub const KEY2: u32 = 0xCDEF_89AB;
}

/// FLASH_CR bits.
pub mod cr {
    /// Program.
    pub const PG: u32 = 1;
    /// Sector erase.
    pub const SER: u32 = 1 << 1;
    /// Mass erase.
    pub const MER: u32 = 1 << 2;
    /// Sector number, bits 6:3.
    pub const SNB: u32 = 0xF << 3;
    /// Program size, bits 9:8: 0 x8, 1 x16, 2 x32, 3 x64.
    pub const PSIZE: u32 = 3 << 8;
    /// Start an erase.
    pub const STRT: u32 = 1 << 16;
    /// End-of-operation interrupt enable.
    pub const EOPIE: u32 = 1 << 24;
    /// Error interrupt enable.
    pub const ERRIE: u32 = 1 << 25;
    /// Lock.
    pub const LOCK: u32 = 1 << 31;
}

/// FLASH_SR bits.
pub mod sr {
    /// End of operation (only with CR.EOPIE).
    pub const EOP: u32 = 1;
    /// Operation error (only with CR.ERRIE).
    pub const OPERR: u32 = 1 << 1;
    /// Write-protection error.
    pub const WRPERR: u32 = 1 << 4;
    /// Programming alignment error.
    pub const PGAERR: u32 = 1 << 5;
    /// Programming parallelism error.
    pub const PGPERR: u32 = 1 << 6;
    /// Programming sequence error.
    pub const PGSERR: u32 = 1 << 7;
    /// Busy.
    pub const BSY: u32 = 1 << 16;
}

/// ACR's bits: LATENCY[2:0], PRFTEN, ICEN, DCEN, ICRST, DCRST.
const ACR_BITS: u32 = 0x1F07;
/// CR's bits but LOCK.
const CR_BITS: u32 =
    cr::PG | cr::SER | cr::MER | cr::SNB | cr::PSIZE | cr::STRT | cr::EOPIE | cr::ERRIE;
/// OPTCR after reset (no protection, BOR off, nWRP all set).
const OPTCR_RESET: u32 = 0x0FFF_AAED;

/// Which of the datasheet's figures an operation takes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Timing {
    /// Typical.
    #[default]
    Typical,
    /// Maximum.
    Maximum,
}

/// A sector: its number, address and size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sector {
    /// 0 to 11.
    pub index: u8,
    /// Its first address (in 0x0800_0000..).
    pub start: u32,
    /// Bytes.
    pub size: u32,
}

impl Sector {
    /// Sector `index`, if there is one.
    #[must_use]
    pub const fn new(index: u8) -> Option<Self> {
        let (start, size) = match index {
            0..=3 => (BASE + 0x4000 * index as u32, 0x4000),
            4 => (BASE + 0x1_0000, 0x1_0000),
            5..=11 => (BASE + 0x2_0000 * (index as u32 - 4), 0x2_0000),
            _ => return None,
        };
        Some(Self { index, start, size })
    }

    /// The sector holding `addr` (in 0x0800_0000..), if any.
    #[must_use]
    pub fn containing(addr: u32) -> Option<Self> {
        (0..SECTORS)
            .filter_map(Self::new)
            .find(|s| (s.start..s.start + s.size).contains(&addr))
    }
}

/// What an operation does to the flash.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Operation {
    /// The `size` bytes (1, 2, 4 or 8) of `value` programmed at `addr`: new = old AND value.
    Program {
        /// Where (in 0x0800_0000..).
        addr: u32,
        /// Bytes.
        size: u8,
        /// The value written (little-endian), its low `size` bytes.
        value: u64,
    },
    /// A sector erased.
    Erase(Sector),
    /// Every sector erased.
    MassErase,
}

impl Operation {
    /// The bytes it changes: (first address, length).
    #[must_use]
    pub const fn range(&self) -> (u32, u32) {
        match *self {
            Self::Program { addr, size, .. } => (addr, size as u32),
            Self::Erase(s) => (s.start, s.size),
            Self::MassErase => (BASE, SIZE),
        }
    }

    /// `bytes` (those of [`Self::range`]) as the operation leaves them.
    pub fn apply(&self, bytes: &mut [u8]) {
        match *self {
            Self::Program { value, .. } => {
                for (b, v) in bytes.iter_mut().zip(value.to_le_bytes()) {
                    *b &= v;
                }
            }
            Self::Erase(_) | Self::MassErase => bytes.fill(ERASED),
        }
    }
}

/// An operation in flight: BSY from `start` to `end` (CPU cycles).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FlashOp {
    /// What it does.
    pub operation: Operation,
    /// The cycle it started at.
    pub start: u64,
    /// The cycle it ends at.
    pub end: u64,
}

/// Where the unlock sequence is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Keys {
    Locked,
    /// KEY1 written.
    Half,
    Unlocked,
    /// An invalid sequence: locked until reset.
    LockedOut,
}

/// The flash interface. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct Flash {
    acr: u32,
    /// CR but LOCK (which `keys` holds).
    cr: u32,
    /// SR but BSY (which `op` holds).
    sr: u32,
    optcr: u32,
    keys: Keys,
    op: Option<FlashOp>,
    timing: Timing,
    cycles_per_us: u64,
    /// The operations completed, in order, once [`Self::record`] asked for them.
    history: Option<Vec<FlashOp>>,
}

impl Flash {
    /// After reset (locked, idle), for a CPU of `cpu_hz`, its operations taking `timing`.
    #[must_use]
    pub const fn new(cpu_hz: u64, timing: Timing) -> Self {
        Self {
            acr: 0,
            cr: 0,
            sr: 0,
            optcr: OPTCR_RESET,
            keys: Keys::Locked,
            op: None,
            timing,
            cycles_per_us: cpu_hz / 1_000_000,
            history: None,
        }
    }

    /// The figures its operations take.
    #[must_use]
    pub const fn timing(&self) -> Timing {
        self.timing
    }

    /// Its operations from now on take `timing`.
    pub const fn set_timing(&mut self, timing: Timing) {
        self.timing = timing;
    }

    /// The operation in flight (BSY), if any.
    #[must_use]
    pub const fn op(&self) -> Option<&FlashOp> {
        self.op.as_ref()
    }

    /// CR is locked.
    #[must_use]
    pub fn locked(&self) -> bool {
        self.keys != Keys::Unlocked
    }

    /// An invalid key sequence locked CR until reset (the chip's bus error).
    #[must_use]
    pub fn locked_out(&self) -> bool {
        self.keys == Keys::LockedOut
    }

    /// The FLASH interrupt's line: EOP with EOPIE, or OPERR with ERRIE.
    #[must_use]
    pub const fn irq(&self) -> bool {
        (self.sr & sr::EOP != 0 && self.cr & cr::EOPIE != 0)
            || (self.sr & sr::OPERR != 0 && self.cr & cr::ERRIE != 0)
    }

    /// A read of the word at `off`; `None` for an offset the model does not know.
    #[must_use]
    pub fn read(&self, off: u32) -> Option<u32> {
        Some(match off & !3 {
            reg::ACR => self.acr,
            reg::KEYR | reg::OPTKEYR => 0,
            reg::SR => self.sr | if self.op.is_some() { sr::BSY } else { 0 },
            reg::CR => self.cr | if self.locked() { cr::LOCK } else { 0 },
            reg::OPTCR => self.optcr,
            _ => return None,
        })
    }

    /// A write of the word `value` at `off` at cycle `now`; `None` for an offset the model does
    /// not know. The board finishes an operation in flight before a CR write (the chip stalls
    /// the write until BSY clears).
    pub fn write(&mut self, off: u32, value: u32, now: u64) -> Option<()> {
        match off & !3 {
            reg::ACR => self.acr = value & ACR_BITS,
            reg::KEYR => {
                self.keys = match (self.keys, value) {
                    (Keys::Locked, key::KEY1) => Keys::Half,
                    (Keys::Half, key::KEY2) => Keys::Unlocked,
                    _ => Keys::LockedOut,
                };
            }
            reg::OPTKEYR => {}
            reg::SR => self.sr &= !(value & (sr::EOP | sr::OPERR | ERRORS)),
            reg::CR => self.write_cr(value, now),
            reg::OPTCR => self.optcr = value,
            _ => return None,
        }
        Some(())
    }

    fn write_cr(&mut self, value: u32, now: u64) {
        if self.locked() {
            return;
        }
        self.cr = value & CR_BITS;
        if value & cr::LOCK != 0 {
            self.keys = Keys::Locked;
        }
        if self.cr & cr::STRT != 0 && self.op.is_none() {
            self.start_erase(now);
        }
        if self.op.is_none() {
            self.cr &= !cr::STRT;
        }
    }

    /// STRT: an erase of sector SNB (SER) or of all (MER).
    fn start_erase(&mut self, now: u64) {
        let operation = match (self.cr & cr::SER != 0, self.cr & cr::MER != 0) {
            (true, false) => match Sector::new(((self.cr & cr::SNB) >> 3) as u8) {
                Some(s) => Operation::Erase(s),
                None => return,
            },
            (false, true) => Operation::MassErase,
            _ => return,
        };
        let protected = match operation {
            Operation::Erase(s) => self.protected(s.index),
            _ => (0..SECTORS).any(|i| self.protected(i)),
        };
        if protected {
            self.error(sr::WRPERR);
            return;
        }
        let ms = erase_ms(operation.range().1, self.psize(), self.timing);
        self.op = Some(FlashOp {
            operation,
            start: now,
            end: now + ms * 1000 * self.cycles_per_us,
        });
    }

    /// A CPU write of `size` bytes of `value` at `addr` (in 0x0800_0000..) at `now`: starts
    /// programming them, or sets the error flag it returns and changes nothing. The board
    /// finishes an operation in flight first (the chip stalls the write until BSY clears).
    ///
    /// # Errors
    /// The SR flag set: [`sr::PGSERR`], [`sr::WRPERR`], [`sr::PGPERR`] or [`sr::PGAERR`].
    pub fn program(&mut self, addr: u32, size: u8, value: u64, now: u64) -> Result<(), u32> {
        debug_assert!(self.op.is_none(), "the board finishes an operation first");
        let error = if self.locked() || self.cr & cr::PG == 0 {
            Some(sr::PGSERR)
        } else if Sector::containing(addr).is_none_or(|s| self.protected(s.index)) {
            Some(sr::WRPERR)
        } else if u32::from(size) != 1 << self.psize() {
            Some(sr::PGPERR)
        } else if !addr.is_multiple_of(u32::from(size)) || addr % ROW + u32::from(size) > ROW {
            Some(sr::PGAERR)
        } else {
            None
        };
        if let Some(flag) = error {
            self.error(flag);
            return Err(flag);
        }
        let us = match self.timing {
            Timing::Typical => PROGRAM_US.0,
            Timing::Maximum => PROGRAM_US.1,
        };
        self.op = Some(FlashOp {
            operation: Operation::Program { addr, size, value },
            start: now,
            end: now + us * self.cycles_per_us,
        });
        Ok(())
    }

    /// Ends the operation in flight (BSY clears, STRT too, EOP with EOPIE) and returns it,
    /// for its bytes to be written.
    pub fn finish(&mut self) -> Option<FlashOp> {
        let op = self.op.take()?;
        if let Some(history) = &mut self.history {
            history.push(op);
        }
        self.cr &= !cr::STRT;
        if self.cr & cr::EOPIE != 0 {
            self.sr |= sr::EOP;
        }
        Some(op)
    }

    /// Keeps every operation completed from now on ([`Self::history`]): a power-cut
    /// harness replays them to make the flash at any cycle (`crate::powercut`).
    pub fn record(&mut self) {
        self.history.get_or_insert_with(Vec::new);
    }

    /// The operations completed since [`Self::record`], in order (empty without it).
    #[must_use]
    pub fn history(&self) -> &[FlashOp] {
        self.history.as_deref().unwrap_or(&[])
    }

    /// PSIZE: 0 x8 to 3 x64.
    const fn psize(&self) -> u32 {
        (self.cr & cr::PSIZE) >> 8
    }

    /// OPTCR.nWRP clear for sector `index`.
    const fn protected(&self, index: u8) -> bool {
        self.optcr >> (16 + index as u32) & 1 == 0
    }

    fn error(&mut self, flag: u32) {
        self.sr |= flag;
        if self.cr & cr::ERRIE != 0 {
            self.sr |= sr::OPERR;
        }
    }
}

/// The error flags.
const ERRORS: u32 = sr::WRPERR | sr::PGAERR | sr::PGPERR | sr::PGSERR;

/// A program access (byte, half-word or word), µs: (typical, maximum).
const PROGRAM_US: (u64, u64) = (16, 100);

/// An erase of `bytes` (a sector, or all for a mass erase) at `psize` (0 x8 .. 3 x64), ms
/// (DS8626; x64 as x32).
const fn erase_ms(bytes: u32, psize: u32, timing: Timing) -> u64 {
    // [x8, x16, x32] typical; the maximum is twice as long.
    let typical: [u64; 3] = match bytes {
        0x4000 => [400, 300, 250],
        0x1_0000 => [1200, 700, 550],
        0x2_0000 => [2000, 1300, 1000],
        _ => [16_000, 11_000, 8000],
    };
    let ms = typical[if psize > 2 { 2 } else { psize as usize }];
    match timing {
        Timing::Typical => ms,
        Timing::Maximum => 2 * ms,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CPU: u64 = 168_000_000;
    /// PSIZE x32.
    const X32: u32 = 2 << 8;

    fn unlocked() -> Flash {
        let mut f = Flash::new(CPU, Timing::Typical);
        f.write(reg::KEYR, key::KEY1, 0);
        f.write(reg::KEYR, key::KEY2, 0);
        f
    }

    #[test]
    fn the_keys_in_order_unlock_and_a_wrong_sequence_locks_until_reset() {
        let mut f = Flash::new(CPU, Timing::Typical);
        assert_eq!(f.read(reg::CR), Some(0x8000_0000));
        f.write(reg::CR, cr::PG, 0);
        assert_eq!(
            f.read(reg::CR),
            Some(cr::LOCK),
            "CR is write-protected while locked"
        );
        let mut f = unlocked();
        assert_eq!(f.read(reg::CR), Some(0));
        f.write(reg::CR, cr::PG | X32, 0);
        assert_eq!(f.read(reg::CR), Some(0x201));
        f.write(reg::CR, cr::LOCK | 0x201, 0);
        assert_eq!(f.read(reg::CR), Some(0x8000_0201));
        assert!(f.locked() && !f.locked_out());
        // Unlocks again; then a key while unlocked is an invalid sequence.
        f.write(reg::KEYR, key::KEY1, 0);
        f.write(reg::KEYR, key::KEY2, 0);
        assert!(!f.locked());
        f.write(reg::KEYR, key::KEY1, 0);
        assert!(f.locked_out() && f.read(reg::CR) == Some(0x8000_0201));

        for wrong in [
            [key::KEY2, key::KEY1],
            [key::KEY1, key::KEY1],
            [0x1234, key::KEY2],
        ] {
            let mut f = Flash::new(CPU, Timing::Typical);
            f.write(reg::KEYR, wrong[0], 0);
            f.write(reg::KEYR, wrong[1], 0);
            assert!(f.locked_out(), "{wrong:x?}");
            // The right sequence no longer unlocks.
            f.write(reg::KEYR, key::KEY1, 0);
            f.write(reg::KEYR, key::KEY2, 0);
            f.write(reg::CR, cr::PG, 0);
            assert_eq!(f.read(reg::CR), Some(cr::LOCK), "{wrong:x?}");
        }
        assert_eq!(f.read(reg::KEYR), Some(0), "KEYR reads 0");
    }

    #[test]
    fn a_word_programs_with_and_semantics_for_16_us() {
        let mut f = unlocked();
        f.write(reg::CR, cr::PG | X32, 0);
        assert_eq!(f.program(0x0800_4000, 4, 0x0000_FFFF, 1000), Ok(()));
        let op = *f.op().unwrap();
        assert_eq!((op.start, op.end), (1000, 1000 + 16 * 168));
        assert_eq!(f.read(reg::SR), Some(sr::BSY));
        let mut bytes = 0xFFFF_00FFu32.to_le_bytes();
        let (at, len) = op.operation.range();
        assert_eq!((at, len), (0x0800_4000, 4));
        op.operation.apply(&mut bytes);
        assert_eq!(u32::from_le_bytes(bytes), 0x0000_00FF);
        assert_eq!(f.finish(), Some(op));
        assert_eq!(f.read(reg::SR), Some(0), "no EOP without EOPIE");

        let mut f = Flash::new(CPU, Timing::Maximum);
        f.write(reg::KEYR, key::KEY1, 0);
        f.write(reg::KEYR, key::KEY2, 0);
        f.write(reg::CR, cr::PG | X32 | cr::EOPIE, 0);
        f.program(0x0800_4004, 4, 0, 0).unwrap();
        assert_eq!(f.op().unwrap().end, 100 * 168);
        f.finish();
        assert_eq!(f.read(reg::SR), Some(sr::EOP));
        assert!(f.irq());
        f.write(reg::SR, sr::EOP, 0);
        assert!(!f.irq() && f.read(reg::SR) == Some(0));
    }

    #[test]
    fn refused_writes_set_their_flag_and_start_nothing() {
        // Locked, or unlocked without PG: a sequence error.
        let mut f = Flash::new(CPU, Timing::Typical);
        assert_eq!(f.program(0x0800_4000, 4, 0, 0), Err(sr::PGSERR));
        let mut f = unlocked();
        assert_eq!(f.program(0x0800_4000, 4, 0, 0), Err(sr::PGSERR));
        // A half-word at x32: parallelism.
        f.write(reg::CR, cr::PG | X32 | cr::ERRIE, 0);
        assert_eq!(f.program(0x0800_4000, 2, 0, 0), Err(sr::PGPERR));
        assert_eq!(
            f.read(reg::SR),
            Some(sr::PGSERR | sr::PGPERR | sr::OPERR),
            "flags accumulate; OPERR with ERRIE"
        );
        assert!(f.op().is_none() && f.irq());
        // Write 1 to clear (embassy writes back what it read).
        let read = f.read(reg::SR).unwrap();
        f.write(reg::SR, read, 0);
        assert_eq!(f.read(reg::SR), Some(0));
        // A byte anywhere at x8; a misaligned word (here across a row) at x32: alignment.
        f.write(reg::CR, cr::PG, 0);
        assert_eq!(f.program(0x0800_400F, 1, 0, 0), Ok(()));
        f.finish();
        f.write(reg::CR, cr::PG | X32, 0);
        assert_eq!(f.program(0x0800_400E, 4, 0, 0), Err(sr::PGAERR));
        assert_eq!(f.program(0x0800_4002, 4, 0, 0), Err(sr::PGAERR));
        // A double word at x64 (a VSTR of a D register) in a row's second half.
        f.write(reg::CR, cr::PG | 3 << 8, 0);
        assert_eq!(f.program(0x0800_4008, 8, 0, 0), Ok(()));
        assert_eq!(
            f.finish().map(|op| op.operation.range()),
            Some((0x0800_4008, 8))
        );
        // A sector nWRP protects.
        f.write(reg::OPTCR, OPTCR_RESET & !(1 << 17), 0);
        assert_eq!(f.program(0x0800_4000, 4, 0, 0), Err(sr::WRPERR));
        assert!(f.op().is_none());
    }

    #[test]
    fn strt_erases_sector_snb_for_its_time_at_psize() {
        let mut f = unlocked();
        f.write(reg::CR, cr::SER | 1 << 3 | X32, 0);
        f.write(reg::CR, cr::SER | 1 << 3 | X32 | cr::STRT, 500);
        let op = *f.op().unwrap();
        let sector = Sector::new(1).unwrap();
        assert_eq!(op.operation, Operation::Erase(sector));
        assert_eq!(op.operation.range(), (0x0800_4000, 0x4000));
        assert_eq!((op.start, op.end), (500, 500 + 42_000_000), "250 ms");
        assert_eq!(f.read(reg::CR).unwrap() & cr::STRT, cr::STRT);
        let mut bytes = vec![0u8; 0x4000];
        op.operation.apply(&mut bytes);
        assert!(bytes.iter().all(|&b| b == 0xFF));
        f.finish();
        assert_eq!(
            f.read(reg::CR).unwrap() & cr::STRT,
            0,
            "STRT clears with BSY"
        );

        // embassy's erase: PSIZE left at x8.
        let erase = |index: u32, timing| {
            let mut f = Flash::new(CPU, timing);
            f.write(reg::KEYR, key::KEY1, 0);
            f.write(reg::KEYR, key::KEY2, 0);
            f.write(reg::CR, cr::SER | index << 3 | cr::STRT, 0);
            f.op().map(|op| op.end / 168_000)
        };
        assert_eq!(erase(1, Timing::Typical), Some(400));
        assert_eq!(erase(4, Timing::Typical), Some(1200));
        assert_eq!(erase(11, Timing::Maximum), Some(4000));
        assert_eq!(erase(12, Timing::Typical), None, "no sector 12 on the F407");
        let mut f = unlocked();
        f.write(reg::CR, cr::SER | cr::MER | cr::STRT, 0);
        assert!(f.op().is_none(), "SER and MER: neither");
        f.write(reg::CR, cr::MER | X32 | cr::STRT, 0);
        assert_eq!(f.op().map(|op| op.end / 168_000), Some(8000));
    }

    #[test]
    fn the_sectors_tile_the_megabyte() {
        let mut at = BASE;
        for i in 0..SECTORS {
            let s = Sector::new(i).unwrap();
            assert_eq!(s.start, at, "sector {i}");
            assert_eq!(Sector::containing(at + s.size - 1), Some(s));
            at += s.size;
        }
        assert_eq!(at, BASE + SIZE);
        assert_eq!(
            Sector::new(5).map(|s| (s.start, s.size)),
            Some((0x0802_0000, 0x2_0000))
        );
        assert_eq!(Sector::containing(BASE + SIZE), None);
    }
}
