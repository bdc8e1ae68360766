//! The runner's saved parameters (`--params FILE`): a save over CAN answered once the file is
//! renamed into place, the set run at the next start, a restore that puts the configuration
//! file's set back, both runs' logs replayed bit for bit; a file that is not a set refused.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};

use firmware::control::{LOAD_SIGNATURE, RESTORE, SAVE_SIGNATURE, STORE, SaveOutcome};
use firmware::protocol::canopen::{self, Message, NodeId, SdoRequest, SdoResponse};
use firmware::{CanFrame, Config, Controller};

mod common;
use common::{T0, bus, clock, esc_feedback, run_core};
use mecanum_runner::McapRecorder;
use mecanum_runner::params::{Found, ParamFile, ParamFileError};

/// A download to the robot's parameter service (node 127) at `ms`.
fn download(ms: u64, index: u16, sub: u8, value: u32) -> (u64, CanFrame) {
    let request = SdoRequest::Download {
        index,
        sub,
        value,
        size: 4,
    };
    let node = NodeId::new(127).unwrap();
    (
        T0 + ms * 1000 + 500,
        Message::SdoRequest { node, request }.to_can_frame(),
    )
}

/// The service's answers among `sent`, with their send times (µs from `T0`).
fn answers(sent: &[(u64, CanFrame)]) -> Vec<(u64, SdoResponse)> {
    sent.iter()
        .filter_map(|(t, f)| match canopen::decode(f) {
            Ok(Message::SdoResponse { node, response }) if node.get() == 127 => {
                Some((t - T0, response))
            }
            _ => None,
        })
        .collect()
}

fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("params_file");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    let _ = std::fs::remove_file(&path);
    path
}

/// `ParamFile` whose save ends, as the loop sees it, at the first poll after it began: the
/// file is written, synced and renamed as the runner does, but the disk's time (an fsync on a
/// busy machine can take hundreds of ms) does not decide at which step the answer comes.
struct Waiting<'a>(&'a mut ParamFile);

impl mecanum_linux::ParamStore for Waiting<'_> {
    fn begin(&mut self, config: &Config, builtin_id: u16) -> Result<(), SaveOutcome> {
        self.0.begin(config, builtin_id)
    }

    fn poll(&mut self) -> Option<SaveOutcome> {
        loop {
            if let Some(outcome) = self.0.poll() {
                return Some(outcome);
            }
            if !self.0.busy() {
                return None;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    }
}

/// Runs `controller` for 400 ms with ESC feedback and `requests`, saving to `file` (each
/// save ending by the next step: [`Waiting`]) and logging to `log`: the frames sent, after
/// checking that the log replays bit for bit.
fn session(
    controller: &mut Controller,
    file: &mut ParamFile,
    requests: &[(u64, CanFrame)],
    log: &Path,
) -> Vec<(u64, CanFrame)> {
    let mut frames = esc_feedback(0..400);
    frames.extend_from_slice(requests);
    frames.sort_by_key(|f| f.0);
    let clock = clock((0..400u64).map(|k| (k * 31) % 200), 0);
    let mut bus = bus(&clock, VecDeque::from(frames));
    let mut recorder = McapRecorder::create(log, controller).unwrap();
    run_core(
        controller,
        &clock,
        &mut bus,
        400_000,
        &mut recorder,
        &mut Waiting(file),
    );
    recorder.finish().unwrap();
    let replay = hostsim::replay::replay_mcap(log).unwrap();
    assert!(replay.identical(), "{:?}", replay.difference);
    bus.sent.clone()
}

#[test]
fn a_saved_set_is_run_at_the_next_start_and_a_restore_puts_the_file_set_back() {
    let builtin = Config::dji_m3508_example();
    let params = scratch("robot.params");
    let (mut file, found) = ParamFile::open(&params, &builtin).unwrap();
    assert_eq!(found, Found::Missing);

    // Run 1: kp set to 1.5, then saved.
    let mut ctl = Controller::new(&builtin).unwrap();
    let kp = 1.5f32.to_bits();
    let sent = session(
        &mut ctl,
        &mut file,
        &[
            download(50, 0x2002, 1, kp),
            download(100, STORE, 1, SAVE_SIGNATURE),
        ],
        &scratch("run1.mcap"),
    );
    let got = answers(&sent);
    assert_eq!(got.len(), 2, "{got:?}");
    assert_eq!(
        got[1].1,
        SdoResponse::Downloaded {
            index: STORE,
            sub: 1
        }
    );
    // Answered once the file was in place: at the second step after the request's (the core
    // serves it at the next step; the file is written before the one after).
    assert!(got[1].0 > 101_000 && got[1].0 < 103_500, "{got:?}");
    let saved_id = ctl.config_id();
    assert_ne!(saved_id, builtin.id());
    let log = hostsim::replay::read_log(&scratch_log("run1.mcap")).unwrap();
    assert_eq!(
        log.saves.iter().map(|s| s.outcome).collect::<Vec<_>>(),
        [SaveOutcome::Stored { seq: 1 }]
    );
    assert_eq!(std::fs::metadata(&params).unwrap().len(), 288);

    // Run 2 starts on the saved set; a restore (disabled) puts the built-in set back and
    // saves it; the log says which built-in set, so its replay restores the same.
    let (mut file, found) = ParamFile::open(&params, &builtin).unwrap();
    let Found::Saved { config, seq } = found else {
        panic!("{found:?}")
    };
    assert_eq!((config.id(), seq), (saved_id, 1));
    let mut ctl = Controller::new(&builtin)
        .unwrap()
        .with_saved(&config, seq)
        .unwrap();
    assert_eq!(ctl.config_id(), saved_id);
    let sent = session(
        &mut ctl,
        &mut file,
        &[download(100, RESTORE, 1, LOAD_SIGNATURE)],
        &scratch("run2.mcap"),
    );
    let got = answers(&sent);
    assert_eq!(got.len(), 1, "{got:?}");
    assert_eq!(
        got[0].1,
        SdoResponse::Downloaded {
            index: RESTORE,
            sub: 1
        }
    );
    assert_eq!(ctl.config_id(), builtin.id());
    let (_, found) = ParamFile::open(&params, &builtin).unwrap();
    assert!(
        matches!(found, Found::Saved { ref config, seq: 2 } if config.id() == builtin.id()),
        "{found:?}"
    );
}

/// The path [`scratch`] gave, without removing it.
fn scratch_log(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("params_file")
        .join(name)
}

#[test]
fn a_file_that_is_not_a_saved_set_is_refused_and_kept() {
    let builtin = Config::dji_m3508_example();
    let path = scratch("robot.toml");
    std::fs::write(&path, "[gains]\nkp = 1.0\n").unwrap();
    let e = ParamFile::open(&path, &builtin).unwrap_err();
    assert!(matches!(e, ParamFileError::NotASet { len: 17, .. }), "{e}");
    assert!(e.to_string().contains("not a saved parameter set"), "{e}");
    assert_eq!(std::fs::read(&path).unwrap(), b"[gains]\nkp = 1.0\n");
    // A file whose folder is not there: refused at start, not at the first save.
    let nowhere = scratch("robot.toml")
        .with_file_name("no-such-folder")
        .join("robot.params");
    let e = ParamFile::open(&nowhere, &builtin).unwrap_err();
    assert!(
        e.to_string().contains("no-such-folder does not exist"),
        "{e}"
    );

    // A set whose CRC fails: reported, the built-in set runs.
    let mut bytes = firmware::storage::record_bytes(&builtin, 3, builtin.id());
    bytes[100] ^= 0x10;
    let damaged = scratch("damaged.params");
    std::fs::write(&damaged, bytes).unwrap();
    assert_eq!(
        ParamFile::open(&damaged, &builtin).unwrap().1,
        Found::Damaged
    );
    // Saved for another configuration file.
    let other = Config::odrive_example();
    let foreign = scratch("foreign.params");
    std::fs::write(
        &foreign,
        firmware::storage::record_bytes(&other, 4, other.id()),
    )
    .unwrap();
    assert_eq!(
        ParamFile::open(&foreign, &builtin).unwrap().1,
        Found::Other {
            base_id: other.id()
        }
    );
}
