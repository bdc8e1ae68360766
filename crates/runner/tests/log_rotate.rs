//! `--log-max-mb`/`--log-keep`: the runner's loop with a rotated log, against a bus and a
//! clock in memory. Several files, at most K kept, the oldest removed, each a complete MCAP
//! file; the first replays bit for bit.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use firmware::{CanFrame, Config, Controller};
use mecanum_linux::{LinkEvent, Recorder};

mod common;
use common::{bus, clock, enable_at, esc_feedback, run_for, twists};
use mecanum_runner::{McapRecorder, TapMaker, rotated_path};

/// Run length: 3 s, 3000 steps.
const RUN_MS: u64 = 3000;

/// The ESCs report every millisecond; the host enables at 10 ms and drives until 2.5 s; and
/// sends `writes` (parameter requests).
fn session(writes: &[(u64, CanFrame)]) -> VecDeque<(u64, CanFrame)> {
    let mut frames = esc_feedback(0..RUN_MS);
    frames.push(enable_at(10));
    frames.extend(twists(20..2500));
    frames.extend_from_slice(writes);
    frames.sort_by_key(|f| f.0);
    frames.into()
}

/// What a run left: the recorder's totals, the frames sent, the files of the directory.
struct Run {
    files: u64,
    messages: u64,
    steps: u64,
    frames_received: u64,
    sent: usize,
    slowest_rotation: std::time::Duration,
}

/// The recorder, waiting after each step until its writer and the rotation's threads are
/// done ([`McapRecorder::settle`]): a run's files follow its log time, not the machine's load.
/// It also keeps the most CPU time the loop's thread spent in a step's hand-over that started
/// a file: what a rotation costs the loop, whatever the machine's load (a wall-clock time
/// would count the time the thread was not running).
struct Settled<'a> {
    recorder: &'a mut McapRecorder,
    slowest_rotation: std::time::Duration,
}

/// The CPU time the calling thread has used.
fn thread_cpu_time() -> std::time::Duration {
    cpu_time::ThreadTime::now().as_duration()
}

impl Recorder for Settled<'_> {
    fn received(&mut self, t_us: u64, frame: &CanFrame) {
        self.recorder.received(t_us, frame);
    }

    fn stepped(&mut self, t_us: u64, controller: &Controller) {
        self.recorder.stepped(t_us, controller);
    }

    fn shut_down(&mut self, t_us: u64, controller: &Controller) {
        self.recorder.shut_down(t_us, controller);
    }

    fn sent(&mut self, step_us: u64, sent_us: u64, frame: &CanFrame, sent: bool) {
        self.recorder.sent(step_us, sent_us, frame, sent);
    }

    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        self.recorder.link(t_us, event);
    }

    fn step_done(&mut self) {
        let (files, start) = (self.recorder.files(), thread_cpu_time());
        self.recorder.step_done();
        if self.recorder.files() > files {
            self.slowest_rotation = self.slowest_rotation.max(thread_cpu_time() - start);
        }
        self.recorder.settle();
    }
}

/// A 3 s run logged in `dir`, rotated at `max_bytes`, keeping `keep` files; served to the
/// taps of `tap` if given ([`McapRecorder::serve`]); the host's `writes` in it.
fn run(
    dir: &Path,
    max_bytes: u64,
    keep: usize,
    tap: Option<TapMaker>,
    writes: &[(u64, CanFrame)],
) -> Run {
    let _ = std::fs::remove_dir_all(dir);
    let config = Config::dji_m3508_example();
    // As fast as the machine goes: the recorder waits for its threads at each step
    // (`Settled`), so the hand-overs and rotations fall at the same log times on an idle or a
    // busy machine. (Without it, on a loaded core the writer fell behind and a run made 2-4
    // files instead of 5+.)
    let clock = clock((0..RUN_MS).map(|k| (k * 53) % 300), 0);
    let mut bus = bus(&clock, session(writes));
    let mut recorder =
        McapRecorder::rotating(dir, &Controller::new(&config).unwrap(), max_bytes, keep).unwrap();
    if let Some(tap) = tap {
        recorder.serve(tap, std::time::Duration::from_millis(50));
    }
    let mut settled = Settled {
        recorder: &mut recorder,
        slowest_rotation: std::time::Duration::ZERO,
    };
    let report = run_for(&config, &clock, &mut bus, RUN_MS * 1000, &mut settled);
    let slowest_rotation = settled.slowest_rotation;
    assert_eq!(recorder.dropped(), 0);
    let result = Run {
        files: recorder.files(),
        messages: recorder.messages(),
        steps: report.steps,
        frames_received: report.frames_received,
        sent: bus.sent.len(),
        slowest_rotation,
    };
    recorder.finish().unwrap();
    result
}

/// The `.mcap` files of `dir`, sorted, and nothing else (no `.part` left over).
fn listing(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    names
}

/// Reads `path` with drivelog's reader: complete, with its metadata; its message count.
fn complete_messages(path: &Path) -> u64 {
    let bytes = std::fs::read(path).unwrap();
    let mut messages = 0u64;
    let mut program = None;
    let report = drivelog::for_each_message(
        &bytes,
        |_| messages += 1,
        |_, meta| program = meta.get("program").cloned(),
    )
    .unwrap();
    assert!(report.is_complete(), "{}: {report}", path.display());
    assert_eq!(
        program.as_deref(),
        Some("mecanum-runner"),
        "{}",
        path.display()
    );
    messages
}

fn tmp(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name)
}

/// About a quarter of a second of the run per hand-over, some 10-30 kB compressed: a limit of
/// 40 kB rotates every one or two hand-overs.
const MAX_BYTES: u64 = 40_000;

#[test]
fn a_rotated_log_keeps_the_newest_k_complete_files() {
    let dir = tmp("rotated_keep3");
    let run = run(&dir, MAX_BYTES, 3, None, &[]);
    assert!(run.files >= 5, "{} files", run.files);
    let expected: Vec<String> = (run.files - 2..=run.files)
        .map(|i| format!("runner-{i:06}.mcap"))
        .collect();
    assert_eq!(listing(&dir), expected);
    assert!(!rotated_path(&dir, 1).exists());
    for name in &expected {
        let path = dir.join(name);
        let messages = complete_messages(&path);
        // The last file holds whatever the run had left after its last rotation: complete,
        // but as short as a hand-over (a run ended one with 99 messages).
        let least = if *name == expected[2] { 1 } else { 100 };
        assert!(messages >= least, "{name}: {messages} messages");
        let content = hostsim::replay::read_log(&path).unwrap();
        assert!(!content.steps.is_empty(), "{name}: no steps");
        // Every file but the last ended past the limit (it rotated there), not far past it.
        let len = std::fs::metadata(&path).unwrap().len();
        if *name != expected[2] {
            assert!(
                (MAX_BYTES..4 * MAX_BYTES).contains(&len),
                "{name}: {len} bytes"
            );
        }
    }
    // What the loop paid for a rotation: starting the next file, not finishing the last
    // (CPU time of the loop's thread: the time it was preempted on a busy machine is not
    // the rotation's).
    eprintln!(
        "{} files; slowest rotation: {:?} CPU",
        run.files, run.slowest_rotation
    );
    assert!(
        run.slowest_rotation < std::time::Duration::from_millis(10),
        "{:?}",
        run.slowest_rotation
    );
}

#[test]
fn every_file_of_a_rotated_log_is_whole_and_the_first_replays_bit_for_bit() {
    let dir = tmp("rotated_keep_all");
    let run = run(&dir, MAX_BYTES, 1000, None, &[]);
    assert!(run.files >= 5, "{} files", run.files);
    let names = listing(&dir);
    assert_eq!(names.len() as u64, run.files);
    // The files hold every message, every step (and the shutdown), every frame, once.
    let (mut messages, mut steps, mut rx, mut tx) = (0, 0, 0, 0);
    let mut last_step = 0;
    for name in &names {
        let path = dir.join(name);
        messages += complete_messages(&path);
        let content = hostsim::replay::read_log(&path).unwrap();
        assert!(
            content.steps[0].t_ns > last_step || last_step == 0,
            "{name}"
        );
        last_step = content.steps.last().unwrap().t_ns;
        steps += content.steps.len() as u64;
        rx += content.rx.len() as u64;
        tx += content.tx.len();
    }
    assert_eq!(messages, run.messages);
    assert_eq!(steps, run.steps + 1);
    assert_eq!(rx, run.frames_received);
    assert_eq!(tx, run.sent);

    // The first file starts with an empty core: bit-identical, every frame compared.
    let first = rotated_path(&dir, 1);
    let content = hostsim::replay::read_log(&first).unwrap();
    let replay = hostsim::replay::replay_mcap(&first).unwrap();
    assert!(replay.identical(), "{:?}", replay.difference);
    assert_eq!(replay.compared, content.tx.len());
    assert!(replay.compared > 250, "{} frames compared", replay.compared);
    // A later file starts mid-drive (the core enabled and moving): from an empty core its
    // frames differ, as the documentation says.
    let third = rotated_path(&dir, 3);
    let later = hostsim::replay::replay_mcap(&third).unwrap();
    assert!(!later.identical());
}

/// A parameter set over CAN mid-run (gains.kp at 1.2 s): each file records the configuration
/// in force at its first step, the old one before the change and the new one after it (the
/// next file was prepared before the change: it is prepared again).
#[test]
fn each_rotated_file_records_the_configuration_in_force_at_its_start() {
    let dir = tmp("rotated_param");
    let config = Config::dji_m3508_example();
    let kp = firmware::params::find("gains.kp").unwrap();
    let node = firmware::params::service_node(&config);
    let write = kp.download(node, 1.5f32.to_bits()).unwrap();
    let run = run(&dir, MAX_BYTES, 1000, None, &[(1200, write)]);
    assert!(run.files >= 5, "{} files", run.files);
    let mut changed = config;
    changed.gains.kp = 1.5;
    // The step that answered the write (0x580 + node), ns: the change is in force from it.
    let answer_id = 0x580 + u16::from(node);
    let (mut before, mut after, mut answered) = (0, 0, None);
    for name in listing(&dir) {
        let content = hostsim::replay::read_log(&dir.join(&name)).unwrap();
        let id = Config::from_toml_str(content.config.as_deref().unwrap())
            .unwrap()
            .id();
        answered = answered.or(content.tx.iter().find_map(|f| {
            let embedded_can::Id::Standard(sid) = embedded_can::Frame::id(&f.frame) else {
                return None;
            };
            (sid.as_raw() == answer_id).then_some(f.t_ns)
        }));
        let first_step = content.steps[0].t_ns;
        match answered {
            Some(t) if first_step > t => {
                assert_eq!(id, changed.id(), "{name}: starts after the change");
                after += 1;
            }
            _ => {
                assert_eq!(id, config.id(), "{name}: starts before the change");
                before += 1;
            }
        }
    }
    assert!(answered.is_some(), "the write was answered");
    assert!(
        before >= 1 && after >= 2,
        "{before} files before, {after} after"
    );
}

/// What each tap of a served log saw: the channels shown, the messages (log time order).
#[derive(Default)]
struct Seen {
    channels: usize,
    messages: u64,
}

struct Counting(Arc<Mutex<Seen>>);

impl drivelog::MessageTap for Counting {
    fn channels(&mut self, _: &[drivelog::Channel]) {
        self.0.lock().unwrap().channels += 1;
    }
    fn message(&mut self, _: drivelog::Channel, _: u64, _: u64, _: &[u8]) {
        self.0.lock().unwrap().messages += 1;
    }
}

#[test]
fn a_served_rotated_log_gives_each_file_a_tap_that_sees_all_of_it() {
    let dir = tmp("rotated_served");
    let taps: Arc<Mutex<Vec<Arc<Mutex<Seen>>>>> = Arc::default();
    let made = Arc::clone(&taps);
    let maker: TapMaker = Arc::new(move || {
        let seen = Arc::<Mutex<Seen>>::default();
        made.lock().unwrap().push(Arc::clone(&seen));
        Box::new(Counting(seen))
    });
    let run = run(&dir, MAX_BYTES, 1000, Some(maker), &[]);
    assert!(run.files >= 5, "{} files", run.files);
    let taps = taps.lock().unwrap();
    assert_eq!(taps.len() as u64, run.files, "a tap per file");
    for (i, seen) in taps.iter().enumerate() {
        let seen = seen.lock().unwrap();
        let file = rotated_path(&dir, i as u64 + 1);
        assert_eq!(seen.channels, 1, "{}", file.display());
        assert_eq!(
            seen.messages,
            complete_messages(&file),
            "{}",
            file.display()
        );
    }
}

#[test]
fn rotation_rejects_a_zero_size_or_keep_naming_the_option() {
    let config = Config::dji_m3508_example();
    let dir = tmp("rotated_bad");
    let e = McapRecorder::rotating(&dir, &Controller::new(&config).unwrap(), 1000, 0)
        .err()
        .unwrap();
    assert!(e.to_string().contains("--log-keep 0"), "{e}");
    let e = McapRecorder::rotating(&dir, &Controller::new(&config).unwrap(), 0, 3)
        .err()
        .unwrap();
    assert!(e.to_string().contains("--log-max-mb 0"), "{e}");
}
