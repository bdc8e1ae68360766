//! Power cuts on the flashed image: the flash as it is at any CPU cycle of a recorded run, with
//! the operation in flight at the cut left partial, and a fresh board booted on it.
//!
//! A run records the FLASH model's completed operations ([`Board::record_flash_ops`]); the
//! flash at cycle `cut` is then the run's first image with every operation that ended by
//! `cut` applied ([`image_at`]), so a cut costs no emulation up to it. The operation in flight
//! at `cut` is applied in part, pessimistically: a program clears each of its pending bits or
//! not (a half-programmed word), an erase sets each byte of its sector to 0xFF with the share
//! of its time elapsed as probability, else leaves it (a partly erased sector), each by a
//! seeded draw. [`boot`] powers a new board on such a flash (RAM and peripherals reset) and
//! reads which parameter set it runs from its boot log (`parameters: ...`), before the CAN
//! controller starts. See `docs/reliability.md`, "Saved parameters".

use firmware::rng::SplitMix64;

use crate::board::{Board, BoardError};
use crate::elf::Image;
use crate::flash::{self, FlashOp, Operation};

/// The flash of a run at cycle `cut`: `initial` (the run's first [`Board::flash_image`]) with
/// the operations of `ops` (its [`crate::flash::Flash::history`]) that ended by `cut`, and the
/// one in flight at `cut` made partial by draws from `rng`.
#[must_use]
pub fn image_at(initial: &[u8], ops: &[FlashOp], cut: u64, rng: &mut SplitMix64) -> Vec<u8> {
    let mut image = initial.to_vec();
    for op in ops {
        if op.start >= cut {
            break;
        }
        let (at, len) = op.operation.range();
        let bytes = &mut image[(at - flash::BASE) as usize..(at - flash::BASE + len) as usize];
        if op.end <= cut {
            op.operation.apply(bytes);
            continue;
        }
        match op.operation {
            Operation::Program { value, .. } => {
                for (b, v) in bytes.iter_mut().zip(value.to_le_bytes()) {
                    // Each bit being cleared is cleared, or not.
                    #[allow(clippy::cast_possible_truncation)] // a byte of the draw
                    let done = rng.next_u64() as u8;
                    *b &= v | !done;
                }
            }
            Operation::Erase(_) | Operation::MassErase => {
                #[allow(clippy::cast_precision_loss)] // cycles of one operation
                let share = (cut - op.start) as f64 / (op.end - op.start) as f64;
                for b in bytes.iter_mut() {
                    if rng.unit() < share {
                        *b = flash::ERASED;
                    }
                }
            }
        }
        break;
    }
    image
}

/// The parameter set a board booted on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Booted {
    /// The image's built-in configuration.
    Builtin,
    /// A saved set: its record's number and its configuration's id.
    Saved {
        /// The record's number.
        seq: u32,
        /// `Config::id` of the set.
        id: u16,
    },
}

/// Powers a new board with `image` on `flash` and runs it until its boot log says which
/// parameter set it runs, at most `limit` cycles (an erase at boot takes up to 800 ms).
///
/// # Errors
/// The board stopped, or said nothing of its parameters by `limit`.
pub fn boot(image: Image, flash: &[u8], limit: u64) -> anyhow::Result<Booted> {
    let mut board = Board::with_flash_image(image, flash)?;
    let step = crate::CPU_HZ / 100;
    while board.now() < limit {
        let until = board.now() + step;
        board
            .run_until(until)
            .map_err(|e: BoardError| anyhow::anyhow!("the board stopped: {e}"))?;
        for line in board.take_lines() {
            if let Some(booted) = parse(&line.text) {
                return Ok(booted);
            }
        }
    }
    anyhow::bail!("no `parameters:` line within {limit} cycles")
}

/// The set a boot line names: `parameters: the built-in set`, `parameters: the saved set,
/// record 3, id 0x28a5`.
fn parse(line: &str) -> Option<Booted> {
    let rest = line.strip_prefix("parameters: ")?;
    if rest == "the built-in set" {
        return Some(Booted::Builtin);
    }
    let rest = rest.strip_prefix("the saved set, record ")?;
    let (seq, id) = rest.split_once(", id 0x")?;
    Some(Booted::Saved {
        seq: seq.parse().ok()?,
        id: u16::from_str_radix(id, 16).ok()?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flash::Sector;

    #[test]
    fn boot_lines_parse() {
        assert_eq!(parse("parameters: the built-in set"), Some(Booted::Builtin));
        assert_eq!(
            parse("parameters: the saved set, record 12, id 0x28a5"),
            Some(Booted::Saved {
                seq: 12,
                id: 0x28a5
            })
        );
        assert_eq!(parse("drive configuration x.toml, id 0x1234"), None);
    }

    #[test]
    fn a_cut_applies_what_ended_and_part_of_what_was_in_flight() {
        let initial = vec![flash::ERASED; flash::SIZE as usize];
        let word = |addr, value, start, end| FlashOp {
            operation: Operation::Program {
                addr,
                size: 4,
                value,
            },
            start,
            end,
        };
        let ops = [
            word(0x0800_4000, 0x1234_5678, 0, 10),
            word(0x0800_4004, 0x0000_0000, 10, 20),
        ];
        let mut rng = SplitMix64(1);
        let at =
            |image: &[u8], off: usize| u32::from_le_bytes(image[off..off + 4].try_into().unwrap());
        let done = image_at(&initial, &ops, 10, &mut rng);
        assert_eq!(
            (at(&done, 0x4000), at(&done, 0x4004)),
            (0x1234_5678, 0xFFFF_FFFF)
        );
        let half = image_at(&initial, &ops, 15, &mut rng);
        let partial = at(&half, 0x4004);
        assert!(partial != 0 && partial != u32::MAX, "{partial:#010x}");
        // An erase half done: about half the sector's bytes erased.
        let mut full = initial.clone();
        full[0x4000..0x8000].fill(0);
        let erase = [FlashOp {
            operation: Operation::Erase(Sector::containing(0x0800_4000).unwrap()),
            start: 100,
            end: 200,
        }];
        let cut = image_at(&full, &erase, 150, &mut rng);
        let erased = cut[0x4000..0x8000].iter().filter(|&&b| b == 0xFF).count();
        assert!((7_000..9_400).contains(&erased), "{erased} of 16384");
    }
}
