//! Power cuts at random CPU cycles while the flashed image erases a stale sector at boot and
//! then saves a new parameter set while it drives: every fresh board booted on the flash as
//! the cut left it (the operation in flight made partial) runs the old set or the new one,
//! byte for byte (by its configuration id), never a mix and never garbage; every cut after
//! the save was acknowledged on the bus boots the new one. `BOARDSIM_POWER_CUTS=N` sets the
//! number of cuts (default 400; `docs/reliability.md` has a run of 10,000).

use boardsim::flash::Operation;
use boardsim::powercut::{Booted, boot, image_at};
use boardsim::run::Harness;
use boardsim::{Board, CPU_HZ, Image};
use firmware::control::STORE;
use firmware::params::find;
use firmware::protocol::canopen::{self, Message, SdoResponse};
use firmware::rng::SplitMix64;
use hostsim::scenario::{Action, ParamName, ParamSet, Scenario, StoreCommand};

mod common;
use common::{elf, run_board};

/// The square for `duration_s`, running `config`, with gains.kp set to `kp` at 0.5 s and the
/// set saved at 0.6 s.
fn save_kp(config: firmware::Config, kp: f64, duration_s: f64) -> Scenario {
    let mut s = Scenario::builtin("square").unwrap();
    s.config = config;
    s.duration_s = duration_s;
    let mut set = Action::at(0.5);
    set.set = Some(ParamSet {
        param: ParamName(find("gains.kp").unwrap()),
        value: kp,
    });
    let mut save = Action::at(0.6);
    save.store = Some(StoreCommand::Save);
    s.actions.extend([set, save]);
    s.actions.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    s
}

fn with_kp(config: firmware::Config, kp: f32) -> firmware::Config {
    let mut c = config;
    c.gains.kp = kp;
    c
}

#[test]
fn a_power_cut_at_any_cycle_boots_the_old_set_or_the_new_one() {
    let cuts: usize = std::env::var("BOARDSIM_POWER_CUTS")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(400);
    let image = Image::read(&elf()).unwrap();
    let builtin = Scenario::builtin("square").unwrap().config;
    let (old, new) = (with_kp(builtin, 1.25), with_kp(builtin, 1.5));

    // A chip with the old set saved, and garbage in sector 2 (a save cut short there, say):
    // the next boot erases sector 2 before its watchdog starts.
    let first = run_board(
        Board::new(image.clone()).unwrap(),
        &save_kp(builtin, 1.25, 1.0),
        Harness::default(),
    )
    .unwrap();
    let mut flash = first.board.flash_image();
    flash[0x8000..0x8040].fill(0);

    // The recorded run: that boot's erase, then a save of the new set while driving.
    let mut board = Board::with_flash_image(image.clone(), &flash).unwrap();
    board.record_flash_ops();
    let initial = board.flash_image();
    let run = run_board(board, &save_kp(old, 1.5, 1.0), Harness::default()).unwrap();
    let ops = run.board.flash().history().to_vec();
    let erases: Vec<_> = ops
        .iter()
        .filter(|o| matches!(o.operation, Operation::Erase(_)))
        .collect();
    let programs = ops.len() - erases.len();
    assert_eq!(
        (erases.len(), programs),
        (1, firmware::storage::RECORD_WORDS)
    );
    // The save's acknowledgement on the bus, in the board's cycles.
    let acked_ns = run
        .sent
        .iter()
        .find_map(|(t, f)| match canopen::decode(f) {
            Ok(Message::SdoResponse { response, .. })
                if response
                    == (SdoResponse::Downloaded {
                        index: STORE,
                        sub: 1,
                    }) =>
            {
                Some(*t)
            }
            _ => None,
        })
        .expect("the save acknowledged");
    let acked = (acked_ns + run.boot_ns) * (CPU_HZ / 1_000_000) / 1000;
    let last_op = ops[ops.len() - 1].end;
    assert!(
        acked > last_op,
        "acknowledged at {acked}, the last word at {last_op}"
    );

    // Cuts: a third inside the boot's erase, a third inside the save's words, a third anywhere
    // from the save's first word to as long after its acknowledgement.
    let mut rng = SplitMix64(47);
    let mut counts = [[0usize; 2]; 3]; // [erase, program, anywhere] x [old, new]
    let limit = 2 * CPU_HZ; // 2 s: boot, and an 800 ms erase at most
    let save_start = ops[1].start;
    let span = 2 * (acked - save_start);
    for i in 0..cuts {
        let kind = i % 3;
        let cut = match kind {
            0 => erases[0].start + rng.next_u64() % (erases[0].end - erases[0].start),
            1 => {
                let p = &ops[1 + (rng.next_u64() as usize) % programs];
                p.start + rng.next_u64() % (p.end - p.start)
            }
            _ => save_start + rng.next_u64() % span,
        };
        let cut_flash = image_at(&initial, &ops, cut, &mut rng);
        let booted = boot(image.clone(), &cut_flash, limit).unwrap();
        let Booted::Saved { id, .. } = booted else {
            panic!("cut {i} at cycle {cut}: booted {booted:?}, neither saved set");
        };
        assert!(
            id == old.id() || id == new.id(),
            "cut {i} at cycle {cut}: id {id:#06x}, neither {:#06x} nor {:#06x}",
            old.id(),
            new.id()
        );
        if cut >= acked {
            assert_eq!(
                id,
                new.id(),
                "cut {i} at cycle {cut}, after the acknowledgement"
            );
        }
        counts[kind][usize::from(id == new.id())] += 1;
    }
    eprintln!(
        "{cuts} power cuts: inside the boot's erase {:?}, inside the save's words {:?}, \
         anywhere {:?} (old, new)",
        counts[0], counts[1], counts[2]
    );
    // Every cut inside the erase boots the old set; inside the words too (the CRC is last).
    assert_eq!(counts[0][1], 0);
    assert_eq!(counts[1][1], 0);
    assert!(counts[2][0] > 0 && counts[2][1] > 0, "{:?}", counts[2]);
}
