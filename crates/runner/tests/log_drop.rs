//! The runner's loop with its log on a disk that stops answering: the loop never waits for
//! it; what does not fit in the pending batch is dropped and counted, in the recorder and in
//! the log itself (a `/rosout` warning once the disk answers again).

use std::collections::VecDeque;
use std::io::{self, Write};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant as WallInstant};

use drivelog::read::for_each_message;
use drivelog::{CHUNK_SIZE, McapLog, msg};
use firmware::{CanFrame, Config, Controller};
use mecanum_linux::{LinkEvent, Recorder};

mod common;
use common::{bus, clock, enable_at, esc_feedback, run_for};
use mecanum_runner::{MAX_PENDING_EVENTS, McapRecorder, metadata};

/// A file whose writes wait while `stalled` is set (a disk that stops answering), in memory.
struct Stalling {
    stalled: Arc<AtomicBool>,
    bytes: Arc<Mutex<Vec<u8>>>,
}

impl Write for Stalling {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        while self.stalled.load(Ordering::Relaxed) {
            std::thread::sleep(Duration::from_millis(1));
        }
        self.bytes.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// The McapRecorder, with the wall time of its slowest hook call (what the loop waited).
struct Timed<'a> {
    log: &'a mut McapRecorder,
    slowest: Duration,
}

impl Timed<'_> {
    fn time(&mut self, f: impl FnOnce(&mut McapRecorder)) {
        let begin = WallInstant::now();
        f(self.log);
        self.slowest = self.slowest.max(begin.elapsed());
    }
}

impl Recorder for Timed<'_> {
    fn received(&mut self, t_us: u64, frame: &CanFrame) {
        self.time(|l| l.received(t_us, frame));
    }
    fn stepped(&mut self, t_us: u64, controller: &Controller) {
        self.time(|l| l.stepped(t_us, controller));
    }
    fn shut_down(&mut self, t_us: u64, controller: &Controller) {
        self.time(|l| l.shut_down(t_us, controller));
    }
    fn sent(&mut self, step_us: u64, sent_us: u64, frame: &CanFrame, sent: bool) {
        self.time(|l| l.sent(step_us, sent_us, frame, sent));
    }
    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        self.time(|l| l.link(t_us, event));
    }
    fn step_done(&mut self) {
        self.time(McapRecorder::step_done);
    }
}

const STEPS: u64 = 10_000;

/// The four ESCs report every millisecond; the host enables at 10 ms.
fn session() -> VecDeque<(u64, CanFrame)> {
    let mut frames = esc_feedback(0..STEPS);
    frames.push(enable_at(10));
    frames.sort_by_key(|f| f.0);
    frames.into()
}

#[test]
fn a_stalled_disk_costs_dropped_messages_never_a_late_step() {
    let config = Config::dji_m3508_example();
    let stalled = Arc::new(AtomicBool::new(false));
    let bytes = Arc::new(Mutex::new(Vec::new()));
    let out = Stalling {
        stalled: Arc::clone(&stalled),
        bytes: Arc::clone(&bytes),
    };
    let log = McapLog::on_writer(
        Path::new("stalled.mcap"),
        Box::new(out),
        &metadata(&config),
        CHUNK_SIZE,
    )
    .unwrap();
    let mut recorder = McapRecorder::on_log(log);
    stalled.store(true, Ordering::Relaxed);
    // A loop that waited for the disk would hang: the disk answers again after 5 s at the
    // latest, and the slowest hook then shows the wait.
    let (done, finished) = std::sync::mpsc::channel::<()>();
    let release = {
        let stalled = Arc::clone(&stalled);
        std::thread::spawn(move || {
            let _ = finished.recv_timeout(Duration::from_secs(5));
            stalled.store(false, Ordering::Relaxed);
        })
    };

    let clock = clock([], 0);
    let mut bus = bus(&clock, session());
    let mut timed = Timed {
        log: &mut recorder,
        slowest: Duration::ZERO,
    };
    let began = WallInstant::now();
    let report = run_for(&config, &clock, &mut bus, STEPS * 1000, &mut timed);
    let (wall, slowest) = (began.elapsed(), timed.slowest);
    let (messages, dropped) = (recorder.messages(), recorder.dropped());
    println!(
        "stalled disk: {} steps in {wall:?} of wall time, slowest recorder call {slowest:?}; \
         {messages} messages kept, {dropped} dropped (pending batch limit {MAX_PENDING_EVENTS})",
        report.steps
    );
    assert_eq!(report.steps, STEPS);
    assert_eq!(report.node.controller.state_at_stop, "ENABLED");
    assert!(slowest < Duration::from_millis(100), "{slowest:?}");
    // 10 s of a 1 kHz run is some 65,000 messages: the first hand-over's batch went to the
    // stalled writer, the next batch filled up to the limit, the rest was dropped.
    assert!(dropped >= 20_000, "{dropped} dropped");
    assert!(
        messages <= 2 * MAX_PENDING_EVENTS as u64,
        "{messages} messages kept"
    );

    // The disk answers again: the run's end is written, with the count.
    done.send(()).unwrap();
    release.join().unwrap();
    recorder.finish().unwrap();
    let bytes = bytes.lock().unwrap().clone();
    let mut read = 0u64;
    let mut warnings = Vec::new();
    let report = for_each_message(
        &bytes,
        |m| {
            read += 1;
            if m.topic == "/rosout" {
                let log = msg::decode::<msg::Log>(m.data).unwrap();
                if log.level == msg::Log::WARN {
                    warnings.push(log.msg);
                }
            }
        },
        |_, _| {},
    )
    .unwrap();
    assert!(report.is_complete(), "{report}");
    println!("log: {read} messages read; warnings {warnings:?}");
    assert!(
        warnings.iter().any(
            |w| w.contains("messages dropped: the log writer fell behind")
                && w.contains(&format!("({dropped} in all)"))
        ),
        "{warnings:?}"
    );
    // What was kept, and the warning (logged after the count was taken).
    assert_eq!(read, messages + warnings.len() as u64);
}
