//! The record log on a flash in RAM: saves, reboots, a sector switch, refusals, and a power
//! cut at every operation of a save and the boots around it (the old set or the new one, never
//! a mix; the new one once acknowledged).

use std::eprintln;
use std::vec::Vec;

use super::*;

const LAYOUT: Layout = Layout {
    starts: [0x4000, 0x8000],
    sector_bytes: 0x4000,
};

/// Flash from 0 to the end of sector 2, as on the F407.
fn flash() -> RamFlash {
    RamFlash::new(0xC000)
}

fn builtin() -> Config {
    Config::dji_m3508_example()
}

/// The built-in configuration with its proportional gain changed: save `i`'s set.
fn variant(i: u32) -> Config {
    let mut c = builtin();
    #[allow(clippy::cast_precision_loss)]
    let kp = 1.0 + i as f32 / 64.0;
    c.gains.kp = kp;
    c
}

/// Polls a save to its end, three words a call: the result and the calls it took.
fn finish(store: &mut Store, flash: &mut RamFlash) -> (Result<u32, SaveError>, usize) {
    for calls in 1.. {
        match store.poll(flash, 3) {
            Progress::Writing => {}
            Progress::Done(r) => return (r, calls),
            Progress::Idle => return (Err(SaveError::Busy), calls),
        }
    }
    unreachable!()
}

/// Mounts and erases as a boot does: the configuration it runs.
fn boot(flash: &mut RamFlash) -> (Store, Found, Config) {
    let (mut store, found) = Store::mount(flash, LAYOUT, &builtin()).expect("reads");
    let _ = store.erase_stale(flash);
    let running = found.saved.map_or_else(builtin, |s| s.config);
    (store, found, running)
}

#[test]
fn a_record_is_three_header_words_the_configuration_and_its_crc() {
    assert_eq!(RECORD_WORDS, 3 + ENCODED_LEN.div_ceil(4) + 1);
    assert_eq!(LAYOUT.slots(), 0x4000 / RECORD_BYTES as u32);
    let words = record(&variant(1), 7, builtin().id());
    assert_eq!(words[0], MAGIC);
    assert_eq!(words[1], 7);
    // The words are the bytes' (as a flash programs them, little-endian).
    let bytes = record_bytes(&variant(1), 7, builtin().id());
    for (b, w) in bytes.chunks_exact(4).zip(words) {
        assert_eq!(b, w.to_le_bytes());
    }
    assert!(
        matches!(parse(&bytes), Content::Record { seq: 7, config: Some(c), .. } if c == variant(1))
    );
    // One flipped bit anywhere: no record.
    for bit in [0, 40, 8 * 100 + 3, 8 * RECORD_BYTES - 1] {
        let mut damaged = bytes;
        damaged[bit / 8] ^= 1 << (bit % 8);
        assert_eq!(parse(&damaged), Content::Garbage, "bit {bit}");
    }
    assert_eq!(parse(&[0xFF; RECORD_BYTES]), Content::Blank);
}

#[test]
fn a_save_survives_a_reboot_and_the_newest_wins() {
    let mut f = flash();
    let (mut store, found, running) = boot(&mut f);
    assert_eq!((found.saved, running), (None, builtin()));
    for i in 1..=3 {
        store.begin(&variant(i), builtin().id()).unwrap();
        let (result, calls) = finish(&mut store, &mut f);
        assert_eq!(result, Ok(i));
        // 72 words at 3 a step: 24 steps.
        assert_eq!(calls, RECORD_WORDS.div_ceil(3));
    }
    let (_, found, running) = boot(&mut f);
    assert_eq!(running, variant(3));
    assert_eq!(found.saved.map(|s| s.seq), Some(3));
    assert_eq!((found.foreign, found.garbage), (0, 0));
}

#[test]
fn a_set_saved_under_another_built_in_configuration_is_not_run() {
    let mut f = flash();
    let (mut store, _, _) = boot(&mut f);
    let other = Config::odrive_example();
    store.begin(&other, other.id()).unwrap();
    assert_eq!(finish(&mut store, &mut f).0, Ok(1));
    let (store, found, running) = boot(&mut f);
    assert_eq!((running, found.foreign), (builtin(), 1));
    // Its sector was erased at boot; numbers go on from it.
    assert!(f.bytes()[0x4000..0x8000].iter().all(|&b| b == 0xFF));
    assert_eq!(
        store.next_slot(),
        Some(Slot {
            sector: 0,
            index: 0
        })
    );
    // A set with a fixed field changed (the ESC ids), even under the right id, is not run.
    let mut moved = builtin();
    if let crate::config::Drive::Dji { esc_ids, .. } = &mut moved.drive {
        esc_ids.swap(0, 1);
    }
    assert!(!usable(&moved, builtin().id(), &builtin()));
    assert!(usable(&variant(2), builtin().id(), &builtin()));
}

#[test]
fn saves_fill_both_sectors_then_are_refused_until_a_boot_compacts() {
    let mut f = flash();
    let (mut store, _, _) = boot(&mut f);
    let slots = LAYOUT.slots();
    for i in 1..=2 * slots {
        store.begin(&variant(i % 50), builtin().id()).unwrap();
        assert_eq!(finish(&mut store, &mut f).0, Ok(i));
    }
    assert_eq!(
        store.begin(&variant(1), builtin().id()),
        Err(SaveError::Full)
    );
    assert_eq!(SaveError::Full.abort_code(), 0x0800_0020);
    // The boot keeps the sector with the newest record and erases the other.
    let (mut store, found, running) = boot(&mut f);
    assert_eq!(
        found.saved.map(|s| (s.seq, s.slot.sector)),
        Some((2 * slots, 1))
    );
    assert_eq!(running, variant((2 * slots) % 50));
    assert_eq!(
        store.next_slot(),
        Some(Slot {
            sector: 0,
            index: 0
        })
    );
    store.begin(&variant(7), builtin().id()).unwrap();
    assert_eq!(finish(&mut store, &mut f).0, Ok(2 * slots + 1));
    assert_eq!(boot(&mut f).2, variant(7));
}

#[test]
fn a_second_save_while_one_is_written_is_busy() {
    let mut f = flash();
    let (mut store, _, _) = boot(&mut f);
    store.begin(&variant(1), builtin().id()).unwrap();
    assert_eq!(store.poll(&mut f, 3), Progress::Writing);
    assert_eq!(
        store.begin(&variant(2), builtin().id()),
        Err(SaveError::Busy)
    );
    assert_eq!(finish(&mut store, &mut f).0, Ok(1));
    assert_eq!(store.poll(&mut f, 3), Progress::Idle);
}

/// The operations of one trial: a boot on `flash`, a save of `new`, a second boot, and a save
/// of `next`. With a cut pending, stops at the cut. Returns the set the first boot ran and how
/// many of the two saves were acknowledged.
fn trial(flash: &mut RamFlash, new: &Config, next: &Config) -> (Config, usize) {
    let Ok((mut store, found)) = Store::mount(flash, LAYOUT, &builtin()) else {
        unreachable!("reads never fail")
    };
    let old = found.saved.map_or_else(builtin, |s| s.config);
    if store.erase_stale(flash).is_err() || store.begin(new, builtin().id()).is_err() {
        return (old, 0);
    }
    if finish(&mut store, flash).0.is_err() {
        return (old, 0);
    }
    let Ok((mut again, _)) = Store::mount(flash, LAYOUT, &builtin()) else {
        return (old, 1);
    };
    if again.erase_stale(flash).is_err() || again.begin(next, builtin().id()).is_err() {
        return (old, 1);
    }
    let acked = 1 + usize::from(finish(&mut again, flash).0.is_ok());
    (old, acked)
}

#[test]
fn a_power_cut_at_any_operation_boots_the_old_set_or_the_new_one() {
    let slots = LAYOUT.slots();
    let (mut cuts, mut booted_new, mut after_ack) = (0, 0, 0);
    // Histories that leave the next save in the middle of a sector, at a sector's last slot,
    // past a half-written record, and with a sector to erase at boot.
    for history in [0, 1, 5, slots - 1, slots, slots + 3, 2 * slots - 1] {
        let mut f = flash();
        let (mut store, _, _) = boot(&mut f);
        for i in 1..=history {
            store.begin(&variant(i % 40), builtin().id()).unwrap();
            assert!(finish(&mut store, &mut f).0.is_ok());
        }
        if history == 5 {
            // A save cut short before this trial: garbage in the next slot.
            let mut cut = f.clone();
            cut.cut_after(30, 1);
            store.begin(&variant(39), builtin().id()).unwrap();
            let _ = finish(&mut store, &mut cut);
            f = RamFlash::from_bytes(cut.bytes().to_vec());
        }
        let (new, next) = (variant(41), variant(42));
        // The operations of an uncut trial, counted by a cut that never comes.
        let mut counted = f.clone();
        counted.cut_after(u64::MAX, 0);
        let (old, acked) = trial(&mut counted, &new, &next);
        assert_eq!(acked, 2, "history {history}");
        assert_ne!(old, new);
        let ops = ops_of(&f, &new, &next);
        for op in 0..ops {
            for seed in 0..3 {
                let mut cut = f.clone();
                cut.cut_after(op, seed);
                let (_, acked) = trial(&mut cut, &new, &next);
                assert!(cut.was_cut());
                let mut powered = RamFlash::from_bytes(cut.bytes().to_vec());
                let (_, found, running) = boot(&mut powered);
                // Before the first acknowledgement the old set or the new one; after it the
                // new one or the next (never the old again); after the second, the next.
                let allowed: &[&Config] = match acked {
                    0 => &[&old, &new],
                    1 => &[&new, &next],
                    _ => &[&next],
                };
                assert!(
                    allowed.contains(&&running),
                    "history {history}, cut at op {op}, {acked} acknowledged: {found:?}"
                );
                cuts += 1;
                booted_new += usize::from(running != old);
                after_ack += usize::from(acked > 0);
            }
        }
    }
    eprintln!("{cuts} cuts, {after_ack} after an acknowledged save, {booted_new} booted a new set");
    // Cuts land before and after the commit words: every outcome is seen.
    assert!(
        cuts > 3000 && after_ack > 1000,
        "{cuts} cuts, {after_ack} after an ack"
    );
    assert!(
        booted_new > 1000 && booted_new < cuts,
        "{booted_new} of {cuts} booted a new set"
    );
}

/// Operations (words written, sectors erased) of an uncut [`trial`] from `flash`.
fn ops_of(flash: &RamFlash, new: &Config, next: &Config) -> u64 {
    (0..)
        .find(|&n| {
            let mut f = flash.clone();
            f.cut_after(n, 0);
            trial(&mut f, new, next);
            !f.was_cut()
        })
        .unwrap_or(0)
}

#[test]
fn erase_error_leaves_the_sector_stale_and_saves_that_need_it_refused() {
    let mut f = flash();
    let (mut store, _, _) = boot(&mut f);
    let slots = LAYOUT.slots();
    for i in 1..=slots {
        store.begin(&variant(i % 40), builtin().id()).unwrap();
        assert!(finish(&mut store, &mut f).0.is_ok());
    }
    store.begin(&variant(1), builtin().id()).unwrap();
    assert!(finish(&mut store, &mut f).0.is_ok());
    // Sector 0 is full and stale now; its erase fails at once.
    let (mut store, found) = Store::mount(&mut f, LAYOUT, &builtin()).unwrap();
    assert_eq!(found.saved.map(|s| s.slot.sector), Some(1));
    assert_eq!(store.stale(), [true, false]);
    let mut failing = f.clone();
    failing.cut_after(0, 0);
    assert!(store.erase_stale(&mut failing).is_err());
    let copies: Vec<u32> = (0..slots - 1)
        .map(|i| {
            store.begin(&variant(i % 40), builtin().id()).unwrap();
            finish(&mut store, &mut f).0.unwrap()
        })
        .collect();
    assert_eq!(copies.len() as u32, slots - 1);
    assert_eq!(
        store.begin(&variant(2), builtin().id()),
        Err(SaveError::Full)
    );
}
