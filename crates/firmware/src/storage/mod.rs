//! Saved parameters in flash: an append-only log of fixed-size records in two erase sectors,
//! the newest intact record for this image winning at boot, and never an erase while running.
//!
//! A record is [`RECORD_WORDS`] 32-bit words: [`MAGIC`], its sequence number, the id of the
//! image's built-in configuration it was saved under, the encoded [`Config`], then a CRC-32 of
//! all of them, programmed last. A save programs a blank slot a few words at a time
//! ([`Store::poll`], between control steps) and reads it back; a slot that a power cut left
//! half-programmed fails its CRC and is skipped, so a boot finds the old set or the new one,
//! never a mix ([`Store::mount`]). Sectors are erased only at boot, before the watchdog starts
//! ([`Store::erase_stale`]): the one not holding the newest record, once a save moved on.
//! With no blank slot left (two sectors of saves since the last boot) a save is refused with
//! [`SaveError::Full`]; the next boot compacts. The flash is any
//! [`embedded_storage::nor_flash::NorFlash`] with 4-byte writes; the design and its cut
//! analysis: `docs/protocol.md`, section "Saving parameters".

#[cfg(any(test, feature = "std"))]
mod ram;
#[cfg(test)]
mod tests;

#[cfg(any(test, feature = "std"))]
pub use ram::RamFlash;

use crc::{CRC_32_ISO_HDLC, Crc};
use embedded_storage::nor_flash::{NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash};

use crate::config::{Config, ENCODED_LEN};
use crate::control::{Controller, SaveOutcome};
use crate::params;
use crate::protocol::canopen::abort_code;

/// Words a board programs before each control step: at most 300 µs of stalled CPU at the
/// datasheet's worst 100 µs a word, and a record in 24 steps.
pub const WORDS_PER_STEP: usize = 3;

/// The STM32F407's sectors 1 and 2 (16 KiB each, at `0x0800_4000` and `0x0800_8000`), as
/// offsets from the flash's start: where the board keeps its records.
pub const F407_LAYOUT: Layout = Layout {
    starts: [0x4000, 0x8000],
    sector_bytes: 0x4000,
};

/// A record's first word: `MCF1` (the `1` is the record format).
pub const MAGIC: u32 = u32::from_le_bytes(*b"MCF1");

/// Words of the encoded configuration (zero-padded to whole words).
const PAYLOAD_WORDS: usize = ENCODED_LEN.div_ceil(4);

/// Words of a record: magic, sequence number, built-in id, the configuration, CRC.
pub const RECORD_WORDS: usize = 3 + PAYLOAD_WORDS + 1;

/// Bytes of a record (a slot).
pub const RECORD_BYTES: usize = RECORD_WORDS * 4;

/// The CRC over a record's words before its last.
const CRC32: Crc<u32> = Crc::<u32>::new(&CRC_32_ISO_HDLC);

/// Where the records live: two sectors of the flash, each erased on its own, as byte offsets
/// in the [`NorFlash`]'s address space.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    /// The sectors' first bytes.
    pub starts: [u32; 2],
    /// The sectors' size (both the same), bytes.
    pub sector_bytes: u32,
}

impl Layout {
    /// Records per sector.
    #[must_use]
    pub const fn slots(&self) -> u32 {
        self.sector_bytes / RECORD_BYTES as u32
    }

    /// The offset of slot `slot`.
    const fn offset(&self, slot: Slot) -> u32 {
        self.starts[slot.sector as usize] + slot.index * RECORD_BYTES as u32
    }
}

/// A slot: a sector (0 or 1) and an index in it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Slot {
    /// 0 or 1.
    pub sector: u8,
    /// From 0.
    pub index: u32,
}

/// A record's words for `config`, saved as number `seq` under the built-in id `base_id`
/// (the words of [`record_bytes`], as a flash programs them).
#[must_use]
pub fn record(config: &Config, seq: u32, base_id: u16) -> [u32; RECORD_WORDS] {
    let bytes = record_bytes(config, seq, base_id);
    let mut words = [0u32; RECORD_WORDS];
    for (w, b) in words.iter_mut().zip(bytes.chunks_exact(4)) {
        *w = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    }
    words
}

/// A record's bytes for `config`, saved as number `seq` under the built-in id `base_id`:
/// what a slot holds, or the runner's parameter file.
#[must_use]
pub fn record_bytes(config: &Config, seq: u32, base_id: u16) -> [u8; RECORD_BYTES] {
    let mut bytes = [0u8; RECORD_BYTES];
    bytes[0..4].copy_from_slice(&MAGIC.to_le_bytes());
    bytes[4..8].copy_from_slice(&seq.to_le_bytes());
    bytes[8..12].copy_from_slice(&u32::from(base_id).to_le_bytes());
    bytes[12..12 + ENCODED_LEN].copy_from_slice(&config.encode());
    let crc = CRC32.checksum(&bytes[..RECORD_BYTES - 4]);
    bytes[RECORD_BYTES - 4..].copy_from_slice(&crc.to_le_bytes());
    bytes
}

/// What a slot holds.
#[derive(Debug, Clone, Copy, PartialEq)]
// No heap on the MCU: a slot is parsed on the stack, one at a time.
#[allow(clippy::large_enum_variant)]
pub enum Content {
    /// Every byte erased (0xFF).
    Blank,
    /// An intact record: its number, the built-in id it was saved under, its configuration
    /// (`None` if this firmware cannot decode it or [`Config::validate`] refuses it).
    Record {
        /// The sequence number.
        seq: u32,
        /// The built-in configuration's id it was saved under.
        base_id: u16,
        /// The configuration.
        config: Option<Config>,
    },
    /// Neither: a save or an erase cut short, or another use of the flash.
    Garbage,
}

/// What `bytes` (one slot) holds.
#[must_use]
pub fn parse(bytes: &[u8; RECORD_BYTES]) -> Content {
    if bytes.iter().all(|&b| b == 0xFF) {
        return Content::Blank;
    }
    let word = |i: usize| u32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    let crc = CRC32.checksum(&bytes[..RECORD_BYTES - 4]);
    let base = word(8);
    if word(0) != MAGIC || word(RECORD_BYTES - 4) != crc || base > u32::from(u16::MAX) {
        return Content::Garbage;
    }
    let config = Config::decode(&bytes[12..12 + ENCODED_LEN])
        .ok()
        .filter(|c| c.validate().is_ok());
    Content::Record {
        seq: word(4),
        #[allow(clippy::cast_possible_truncation)] // checked above
        base_id: base as u16,
        config,
    }
}

/// The configuration a boot found saved for this image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Saved {
    /// The configuration.
    pub config: Config,
    /// Its record's sequence number.
    pub seq: u32,
    /// Where it is.
    pub slot: Slot,
}

/// What [`Store::mount`] found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Found {
    /// The newest record usable by this image ([`usable`]), if any: the configuration to run.
    pub saved: Option<Saved>,
    /// Intact records passed over for that: saved under another built-in configuration, or
    /// not decodable by this firmware (a report, not an error).
    pub foreign: u32,
    /// Slots neither blank nor intact (a save cut short).
    pub garbage: u32,
}

/// Whether `config`, saved under `base_id`, may be run by an image whose built-in
/// configuration is `builtin`: the same built-in id, and only parameters a host may write
/// differ from it ([`params::reachable`]).
#[must_use]
pub fn usable(config: &Config, base_id: u16, builtin: &Config) -> bool {
    base_id == builtin.id() && params::reachable(builtin, config)
}

/// Why a save failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SaveError {
    /// No blank slot is left (the sectors are erased only at boot).
    Full,
    /// A save is still being written.
    Busy,
    /// The flash refused an operation.
    Flash(NorFlashErrorKind),
    /// The slot read back differs from what was programmed.
    Verify,
}

impl SaveError {
    /// The CiA 301 SDO abort code the parameter service answers a save with.
    #[must_use]
    pub const fn abort_code(self) -> u32 {
        match self {
            Self::Full => abort_code::NOT_STORED,
            Self::Busy => abort_code::DEVICE_STATE,
            Self::Flash(_) | Self::Verify => abort_code::HARDWARE,
        }
    }
}

/// What [`Store::poll`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Progress {
    /// No save in progress.
    Idle,
    /// Words programmed; more to come.
    Writing,
    /// The save ended: its sequence number, or why it failed.
    Done(Result<u32, SaveError>),
}

/// A save being programmed.
#[derive(Debug, Clone)]
struct Writing {
    words: [u32; RECORD_WORDS],
    slot: Slot,
    /// Words programmed so far.
    done: usize,
}

/// The record log's state between boots: where the next save goes. See the module doc.
#[derive(Debug, Clone)]
pub struct Store {
    layout: Layout,
    /// The next slot to program; `None` when none is left.
    next: Option<Slot>,
    /// The next record's number.
    seq: u32,
    /// Sector `i` is blank (erased and not yet written since).
    blank: [bool; 2],
    /// Sector `i` is to be erased at boot ([`Store::erase_stale`]).
    stale: [bool; 2],
    writing: Option<Writing>,
}

impl Store {
    /// Reads every slot of `layout` and finds the configuration to run ([`Found`]) for an
    /// image whose built-in configuration is `builtin`, and where the next save goes. Reads
    /// only; [`erase_stale`](Self::erase_stale) does the erases it plans.
    ///
    /// # Errors
    /// The flash's read error.
    pub fn mount<F: ReadNorFlash>(
        flash: &mut F,
        layout: Layout,
        builtin: &Config,
    ) -> Result<(Self, Found), F::Error> {
        let mut found = Found {
            saved: None,
            foreign: 0,
            garbage: 0,
        };
        let mut last_used: [Option<u32>; 2] = [None; 2];
        let mut newest_seq: Option<u32> = None;
        let mut buf = [0u8; RECORD_BYTES];
        for sector in 0..2u8 {
            for index in 0..layout.slots() {
                let slot = Slot { sector, index };
                flash.read(layout.offset(slot), &mut buf)?;
                let content = parse(&buf);
                if content != Content::Blank {
                    last_used[usize::from(sector)] = Some(index);
                }
                let Content::Record {
                    seq,
                    base_id,
                    config,
                } = content
                else {
                    found.garbage += u32::from(content == Content::Garbage);
                    continue;
                };
                newest_seq = Some(newest_seq.map_or(seq, |n| n.max(seq)));
                match config.filter(|c| usable(c, base_id, builtin)) {
                    Some(config) if found.saved.is_none_or(|s| seq > s.seq) => {
                        found.saved = Some(Saved { config, seq, slot });
                    }
                    Some(_) => {}
                    None => found.foreign += 1,
                }
            }
        }
        let keep = found.saved.map(|s| s.slot.sector);
        let blank = last_used.map(|l| l.is_none());
        let stale = [0u8, 1].map(|s| !blank[usize::from(s)] && keep != Some(s));
        let next = match keep {
            Some(s) => {
                last_used[usize::from(s)].map(|index| after(layout, Slot { sector: s, index }))
            }
            None => Some(Slot {
                sector: 0,
                index: 0,
            }),
        };
        let store = Self {
            layout,
            next: next.filter(|_| layout.slots() > 0),
            seq: newest_seq.map_or(1, |n| n.wrapping_add(1).max(1)),
            blank,
            stale,
            writing: None,
        };
        Ok((store, found))
    }

    /// The sectors [`erase_stale`](Self::erase_stale) would erase.
    #[must_use]
    pub const fn stale(&self) -> [bool; 2] {
        self.stale
    }

    /// Erases the sectors that hold no record the boot keeps and are not blank. For boot only,
    /// before the watchdog starts: an erase stops the CPU for hundreds of milliseconds.
    ///
    /// # Errors
    /// The flash's erase error (the sector stays stale; saves that need it are refused).
    pub fn erase_stale<F: NorFlash>(&mut self, flash: &mut F) -> Result<(), F::Error> {
        for s in 0..2 {
            if self.stale[s] {
                let from = self.layout.starts[s];
                flash.erase(from, from + self.layout.sector_bytes)?;
                self.stale[s] = false;
                self.blank[s] = true;
            }
        }
        Ok(())
    }

    /// The slot the next save goes to, if one is left.
    #[must_use]
    pub fn next_slot(&self) -> Option<Slot> {
        self.next.filter(|n| {
            // The first slot of a sector only once that sector is blank.
            n.index > 0 || self.blank[usize::from(n.sector)]
        })
    }

    /// Starts saving `config` under the built-in id `base_id`: [`poll`](Self::poll) programs
    /// it. Nothing is written here.
    ///
    /// # Errors
    /// [`SaveError::Busy`] while a save is being written; [`SaveError::Full`] with no blank
    /// slot left.
    pub fn begin(&mut self, config: &Config, base_id: u16) -> Result<(), SaveError> {
        if self.writing.is_some() {
            return Err(SaveError::Busy);
        }
        let slot = self.next_slot().ok_or(SaveError::Full)?;
        self.writing = Some(Writing {
            words: record(config, self.seq, base_id),
            slot,
            done: 0,
        });
        Ok(())
    }

    /// Programs at most `max_words` more words of the save in progress, in order (the CRC
    /// last); after the last, reads the slot back. Each call is bounded: `max_words` times the
    /// flash's word program time.
    pub fn poll<F: NorFlash>(&mut self, flash: &mut F, max_words: usize) -> Progress {
        let Some(w) = &mut self.writing else {
            return Progress::Idle;
        };
        let base = self.layout.offset(w.slot);
        if w.done == 0 {
            // The slot is used from its first word on, whatever happens next.
            self.blank[usize::from(w.slot.sector)] = false;
            self.next = Some(after(self.layout, w.slot));
        }
        let end = (w.done + max_words.max(1)).min(RECORD_WORDS);
        let mut bytes = [0u8; 4];
        while w.done < end {
            bytes.copy_from_slice(&w.words[w.done].to_le_bytes());
            #[allow(clippy::cast_possible_truncation)] // < RECORD_BYTES
            let at = base + (w.done * 4) as u32;
            if let Err(e) = flash.write(at, &bytes) {
                self.writing = None;
                return Progress::Done(Err(SaveError::Flash(e.kind())));
            }
            w.done += 1;
        }
        if w.done < RECORD_WORDS {
            return Progress::Writing;
        }
        let (words, seq) = (w.words, w.words[1]);
        self.writing = None;
        let mut back = [0u8; RECORD_BYTES];
        let read = flash.read(base, &mut back);
        let same = read.is_ok()
            && back
                .chunks_exact(4)
                .zip(words)
                .all(|(b, w)| b == w.to_le_bytes());
        if !same {
            return Progress::Done(Err(SaveError::Verify));
        }
        self.seq = seq.wrapping_add(1).max(1);
        Progress::Done(Ok(seq))
    }

    /// The edge's part before each control step: takes the save `ctl` asked for at the
    /// previous step, programs at most `max_words` words of it, and reports its end to `ctl`.
    /// Returns that end, for the edge's log (the core's input, given before this step).
    pub fn serve<F: NorFlash>(
        &mut self,
        ctl: &mut Controller,
        flash: &mut F,
        max_words: usize,
    ) -> Option<SaveOutcome> {
        if let Some(config) = ctl.take_save()
            && let Err(e) = self.begin(&config, ctl.builtin_id())
        {
            let outcome = SaveOutcome::from(Err(e));
            ctl.on_saved(outcome);
            return Some(outcome);
        }
        let Progress::Done(result) = self.poll(flash, max_words) else {
            return None;
        };
        let outcome = SaveOutcome::from(result);
        ctl.on_saved(outcome);
        Some(outcome)
    }

    /// Whether a save is being written.
    #[must_use]
    pub const fn busy(&self) -> bool {
        self.writing.is_some()
    }
}

/// The slot after `slot`: the next in its sector, else the other sector's first (which
/// [`Store::next_slot`] offers only while that sector is blank).
const fn after(layout: Layout, slot: Slot) -> Slot {
    if slot.index + 1 < layout.slots() {
        Slot {
            sector: slot.sector,
            index: slot.index + 1,
        }
    } else {
        Slot {
            sector: 1 - slot.sector,
            index: 0,
        }
    }
}
