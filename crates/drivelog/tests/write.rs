//! The MCAP writer through its public API: what it writes reads back (through the `mcap`
//! crate's index and this crate's reader alike), the same messages make the same file, a tap
//! sees the file's bytes, and a failing, panicking or stalled file is an error or a count,
//! never a panic or a wait.

use std::collections::{BTreeMap, HashMap};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant as WallInstant};

use drivelog::write::DIAGNOSTIC_NAME;
use drivelog::{
    CHUNK_SIZE, Channel, Direction, LogError, METADATA_NAME, McapLog, Message, MessageTap,
    OdometrySource, WHEEL_NAMES, for_each_message, msg,
};
use embedded_can::{Frame as _, StandardId};
use firmware::CanFrame;

/// A message read back, as the `mcap` crate's index gives it too: (topic, log time, publish
/// time, data).
fn owned(m: &Message<'_>) -> (String, u64, u64, Vec<u8>) {
    (
        m.topic.to_string(),
        m.log_time,
        m.publish_time,
        m.data.to_vec(),
    )
}

/// A file of its own for a test, removed when dropped.
struct TempFile(PathBuf);

impl TempFile {
    fn new(test: &str) -> Self {
        let name = format!("drivelog-{}-{test}.mcap", std::process::id());
        Self(std::env::temp_dir().join(name))
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn frame(i: u64) -> CanFrame {
    let id = StandardId::new(0x201 + (i % 4) as u16).unwrap();
    let b = i.to_le_bytes();
    CanFrame::standard(id, &[b[0], b[1], b[2], 7, 0, 255, 100, 9]).unwrap()
}

/// Logs milliseconds `steps` of every kind of message (5 frames a millisecond, the rest
/// every 10 ms).
fn log_steps(log: &mut McapLog, steps: std::ops::Range<u64>) -> Result<(), LogError> {
    let snapshot = firmware::Controller::new(&firmware::Config::dji_m3508_example())
        .unwrap()
        .snapshot();
    for i in steps {
        let t = i * 1_000_000;
        for k in 0..4 {
            let f = frame(i * 4 + k);
            log.frame(Direction::Rx, t + 100 * k, t + 100 * k, t + 100 * k, &f)?;
        }
        log.frame(Direction::Tx, t + 500, t, t + 450, &frame(i))?;
        if i % 10 == 0 {
            log.snapshot(t, &snapshot)?;
            log.odometry(
                t,
                OdometrySource::Firmware,
                [0.1, 0.2, 0.3],
                [0.5, 0.0, 0.1],
            )?;
            log.odometry(
                t,
                OdometrySource::GroundTruth,
                [0.1, 0.2, 0.31],
                [0.5, 0.0, 0.1],
            )?;
            log.twist(t, [0.5, 0.0, -0.25])?;
            log.bus_fault(t, "drives", "dropped", &frame(i), &frame(i))?;
        }
        if i % 100 == 0 {
            log.text(t, msg::Log::INFO, "state ENABLED")?;
        }
        log.maybe_flush()?;
    }
    Ok(())
}

#[test]
fn a_log_reads_back_through_the_crates_index_and_our_reader_alike() {
    let file = TempFile::new("indexes");
    let metadata = BTreeMap::from([("config".to_string(), "x = 1".to_string())]);
    let mut log = McapLog::create_with_chunk_size(&file.0, &metadata, 64 << 10).unwrap();
    log_steps(&mut log, 0..1500).unwrap();
    let written = log.messages();
    log.finish().unwrap();
    let bytes = std::fs::read(&file.0).unwrap();

    // This crate's reader: complete, every CRC checked, in file order.
    let mut read = Vec::new();
    let mut meta = Vec::new();
    let report = for_each_message(
        &bytes,
        |m| read.push(owned(m)),
        |name, kv| meta.push((name.to_string(), kv.clone())),
    )
    .unwrap();
    assert!(report.is_complete(), "{report}");
    assert_eq!(report.messages, written);
    assert_eq!(report.profile, "ros2");
    assert_eq!(meta, vec![(METADATA_NAME.to_string(), metadata)]);

    // The mcap crate: statistics, schemas, and every chunk through its index.
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    let stats = summary.stats.as_ref().unwrap();
    assert_eq!(stats.message_count, written);
    assert_eq!(stats.channel_count, Channel::ALL.len() as u32);
    assert_eq!(stats.metadata_count, 1);
    assert!(summary.chunk_indexes.len() > 10);
    for c in summary.channels.values() {
        let channel = Channel::from_topic(&c.topic).unwrap();
        assert_eq!(c.id, channel.id());
        assert_eq!(c.message_encoding, "cdr");
        let schema = c.schema.as_ref().unwrap();
        assert_eq!(
            (schema.name.as_str(), schema.encoding.as_str()),
            (channel.def().name, "ros2msg")
        );
        assert_eq!(&*schema.data, channel.def().schema_text().as_bytes());
    }
    let mut from_index = Vec::new();
    let mut indexes = summary.chunk_indexes.clone();
    indexes.sort_by_key(|c| c.chunk_start_offset);
    for index in &indexes {
        // Each chunk's message index lists its messages (the first chunk holds the
        // schemas and channels only, and has none).
        let listed: usize = if index.message_index_offsets.is_empty() {
            0
        } else {
            summary
                .read_message_indexes(&bytes, index)
                .unwrap()
                .values()
                .map(Vec::len)
                .sum()
        };
        let before = from_index.len();
        for m in summary.stream_chunk(&bytes, index).unwrap() {
            let m = m.unwrap();
            from_index.push((
                m.channel.topic.clone(),
                m.log_time,
                m.publish_time,
                m.data.to_vec(),
            ));
        }
        assert_eq!(listed, from_index.len() - before);
    }
    assert_eq!(from_index, read);
    let counts: HashMap<&str, usize> = read.iter().fold(HashMap::new(), |mut m, r| {
        *m.entry(r.0.as_str()).or_default() += 1;
        m
    });
    assert_eq!(counts["/can/rx"], 6000);
    assert_eq!(counts["/can/tx"], 1500);
    assert_eq!(counts["/tf"], 300);
    assert_eq!(counts["/rosout"], 15);

    // The messages decode to what was logged.
    let tx = read.iter().find(|r| r.0 == "/can/tx").unwrap();
    let f: msg::Frame = msg::decode(&tx.3).unwrap();
    assert_eq!((tx.1, tx.2, f.header.stamp.to_ns()), (500, 0, 450));
    assert_eq!(f.to_can(), Some(frame(0)));
    let fault = read.iter().find(|r| r.0 == "/can/faults").unwrap();
    let fault: msg::BusFault = msg::decode(&fault.3).unwrap();
    assert_eq!(
        (fault.sender.as_str(), fault.fate.as_str()),
        ("drives", "dropped")
    );
    assert_eq!(fault.received.to_vec(), frame(0).data().to_vec());
    let js = read.iter().find(|r| r.0 == "/joint_states").unwrap();
    let js: msg::JointState = msg::decode(&js.3).unwrap();
    assert_eq!(js.name, WHEEL_NAMES.map(str::to_string).to_vec());
    assert_eq!(
        (js.position.len(), js.velocity.len(), js.effort.len()),
        (4, 4, 4)
    );
    let diag = read.iter().find(|r| r.0 == "/diagnostics").unwrap();
    let diag: msg::DiagnosticArray = msg::decode(&diag.3).unwrap();
    let status = &diag.status[0];
    assert_eq!(status.value("state"), Some("DISABLED"));
    assert_eq!(status.value("rx_wrong_dlc"), Some("0"));
    assert_eq!(status.value("repeated_seq"), Some("0"));
    let tf = read.iter().rfind(|r| r.0 == "/tf").unwrap();
    let tf: msg::TfMessage = msg::decode(&tf.3).unwrap();
    let t = &tf.transforms[0];
    assert_eq!(
        (t.header.frame_id.as_str(), t.child_frame_id.as_str()),
        ("odom", "base_link_truth")
    );
    assert!((t.transform.rotation.yaw() - 0.31).abs() < 1e-12);
}

#[test]
fn bytes_written_counts_what_the_writer_thread_wrote() {
    let tmp = TempFile::new("bytes-written");
    let mut log = McapLog::create(&tmp.0, &BTreeMap::new()).unwrap();
    let header = log.bytes_written();
    // The header, schemas, channels and metadata, on disk (in the `.part`) at creation.
    assert_eq!(
        header,
        std::fs::metadata(log.part().unwrap()).unwrap().len()
    );
    assert!(header > 1000, "{header} bytes");
    // 600 ms: hand-overs at 250 and 500 ms, the second waits for the first's writing.
    log_steps(&mut log, 0..600).unwrap();
    let written = log.bytes_written();
    assert!(written > header + 10_000, "{header} -> {written} bytes");
    log.finish().unwrap();
    let len = std::fs::metadata(&tmp.0).unwrap().len();
    assert!(written < len, "{written} written, file {len}");
}

#[test]
fn wait_written_leaves_every_handed_batch_in_the_file() {
    let tmp = TempFile::new("wait-written");
    let mut log = McapLog::create(&tmp.0, &BTreeMap::new()).unwrap();
    log.drop_when_behind(1 << 15);
    // Hand-overs at 250 and 500 ms, neither waited for; the last 100 ms stay open.
    log_steps(&mut log, 0..600).unwrap();
    log.wait_written().unwrap();
    let written = log.bytes_written();
    // Each batch ends with a flush: what was written is on disk, whatever the thread's speed.
    assert_eq!(
        written,
        std::fs::metadata(log.part().unwrap()).unwrap().len()
    );
    assert!(written > 10_000, "{written} bytes");
    log.wait_written().unwrap();
    assert_eq!(log.bytes_written(), written, "the open batch stays open");
    assert_eq!(log.dropped(), 0);
    log.finish().unwrap();
}

#[test]
fn the_same_messages_make_the_same_file() {
    let (a, b) = (TempFile::new("same-a"), TempFile::new("same-b"));
    for file in [&a, &b] {
        let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
        log_steps(&mut log, 0..1200).unwrap();
        log.finish().unwrap();
    }
    // Chunks close on log time here, long before the half second of wall-clock time.
    assert_eq!(std::fs::read(&a.0).unwrap(), std::fs::read(&b.0).unwrap());
}

/// A tap that keeps what it is shown, behind a mutex the test reads.
#[derive(Default)]
struct Seen {
    channels: Vec<Vec<Channel>>,
    messages: Vec<(String, u64, u64, Vec<u8>)>,
    batches: usize,
}

struct Keep(std::sync::Arc<std::sync::Mutex<Seen>>);

impl MessageTap for Keep {
    fn channels(&mut self, channels: &[Channel]) {
        self.0.lock().unwrap().channels.push(channels.to_vec());
    }
    fn message(&mut self, channel: Channel, log_ns: u64, publish_ns: u64, cdr: &[u8]) {
        let m = (
            channel.topic().to_string(),
            log_ns,
            publish_ns,
            cdr.to_vec(),
        );
        self.0.lock().unwrap().messages.push(m);
    }
    fn end_batch(&mut self) {
        self.0.lock().unwrap().batches += 1;
    }
    fn status(&mut self) -> Option<msg::DiagnosticStatus> {
        Some(msg::DiagnosticStatus {
            name: "tap".to_string(),
            values: vec![msg::KeyValue {
                key: "seen".to_string(),
                value: self.0.lock().unwrap().messages.len().to_string(),
            }],
            ..msg::DiagnosticStatus::default()
        })
    }
}

#[test]
fn a_tap_sees_every_message_as_the_file_has_it() {
    let file = TempFile::new("tap");
    let seen = std::sync::Arc::new(std::sync::Mutex::new(Seen::default()));
    let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
    log.set_tap(Box::new(Keep(seen.clone())));
    log.set_flush_interval(Duration::from_millis(50));
    log_steps(&mut log, 0..600).unwrap();
    log.finish().unwrap();
    let bytes = std::fs::read(&file.0).unwrap();
    let mut read = Vec::new();
    let report = for_each_message(&bytes, |m| read.push(owned(m)), |_, _| {}).unwrap();
    assert!(report.is_complete(), "{report}");
    let seen = seen.lock().unwrap();
    assert_eq!(seen.channels, vec![Channel::ALL.to_vec()]);
    assert_eq!(seen.messages.len(), read.len());
    assert!(
        seen.messages == read,
        "the tap saw other bytes than the file's"
    );
    // A hand-over every 50 ms of log time: 12 in 600 ms, and the last at the finish.
    assert_eq!(seen.batches, 12);
    // The tap's status follows the firmware's on /diagnostics, in the file too.
    let diag = read.iter().rfind(|r| r.0 == "/diagnostics").unwrap();
    let diag: msg::DiagnosticArray = msg::decode(&diag.3).unwrap();
    assert_eq!(diag.status.len(), 2);
    assert_eq!(diag.status[0].name, DIAGNOSTIC_NAME);
    assert_eq!(diag.status[1].name, "tap");
    let n: usize = diag.status[1].value("seen").unwrap().parse().unwrap();
    assert!(n > 0 && n < read.len(), "{n}");
}

#[test]
fn a_tap_status_alone_is_logged_only_with_a_tap() {
    let diagnostics = |tap: bool| {
        let file = TempFile::new(if tap { "tap-status" } else { "no-tap-status" });
        let seen = std::sync::Arc::new(std::sync::Mutex::new(Seen::default()));
        let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
        if tap {
            log.set_tap(Box::new(Keep(seen)));
        }
        log.step(1_000, msg::Step::STEP).unwrap();
        log.tap_status(2_000).unwrap();
        let messages = log.messages();
        log.finish().unwrap();
        let mut out = Vec::new();
        let bytes = std::fs::read(&file.0).unwrap();
        for_each_message(
            &bytes,
            |m| {
                if m.topic == "/diagnostics" {
                    let d: msg::DiagnosticArray = msg::decode(m.data).unwrap();
                    let names: Vec<_> = d.status.iter().map(|s| s.name.clone()).collect();
                    out.push((m.log_time, d.header.stamp, names));
                }
            },
            |_, _| {},
        )
        .unwrap();
        (messages, out)
    };
    let (messages, tapped) = diagnostics(true);
    assert_eq!(messages, 2);
    assert_eq!(
        tapped,
        vec![(2_000, msg::Time::from_ns(2_000), vec!["tap".to_string()])]
    );
    assert_eq!(diagnostics(false), (1, vec![]));
}

#[test]
fn without_a_tap_diagnostics_have_the_firmware_status_alone() {
    let file = TempFile::new("no-tap");
    let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
    log_steps(&mut log, 0..20).unwrap();
    log.finish().unwrap();
    let bytes = std::fs::read(&file.0).unwrap();
    let mut statuses = Vec::new();
    for_each_message(
        &bytes,
        |m| {
            if m.topic == "/diagnostics" {
                let d: msg::DiagnosticArray = msg::decode(m.data).unwrap();
                statuses.push(d.status.len());
            }
        },
        |_, _| {},
    )
    .unwrap();
    assert_eq!(statuses, vec![1, 1]);
}

/// A file that takes `room` bytes, then fails as a full disk does (or panics).
struct Full {
    room: usize,
    panic: bool,
}

impl Full {
    /// A disk with `room` bytes free.
    fn disk(room: usize) -> Self {
        Self { room, panic: false }
    }

    /// A writer that panics once `room` bytes are written.
    fn panicking(room: usize) -> Self {
        Self { room, panic: true }
    }
}

impl Write for Full {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        if self.room == 0 {
            assert!(!self.panic, "a writer that panics");
            return Err(io::ErrorKind::StorageFull.into());
        }
        let n = buf.len().min(self.room);
        self.room -= n;
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

fn log_on(path: &Path, out: Full) -> McapLog {
    McapLog::on_writer(path, Box::new(out), &BTreeMap::new(), 16 << 10).unwrap()
}

#[test]
fn a_full_disk_comes_back_as_an_error_naming_the_file() {
    let path = Path::new("/nowhere/full.mcap");
    let mut log = log_on(path, Full::disk(100_000));
    let err = log_steps(&mut log, 0..10_000).unwrap_err();
    let LogError::Io { path: p, source } = &err;
    assert_eq!(p, path);
    assert_eq!(source.kind(), io::ErrorKind::StorageFull, "{err}");
    // Found at the hand-over after the batch whose write failed (100 kB hold some 1.2 s
    // of these messages, a batch is 250 ms), not at the end of the run.
    assert!(log.messages() < 2_000 * 6, "{}", log.messages());
    // Every later hand-over fails too, and so does finishing.
    let err = log_steps(&mut log, 20_000..21_000).unwrap_err();
    assert!(err.to_string().contains("an earlier write failed"), "{err}");
    let LogError::Io { path: p, source } = log.finish().unwrap_err();
    assert_eq!(
        (p.as_path(), source.kind()),
        (path, io::ErrorKind::StorageFull)
    );
}

#[test]
fn a_writer_thread_that_panics_is_an_error_not_a_panic() {
    let path = Path::new("/nowhere/panic.mcap");
    // Room for the header, schemas and metadata; the first batch's chunk panics.
    let mut log = log_on(path, Full::panicking(20_000));
    let err = log_steps(&mut log, 0..10_000).unwrap_err();
    assert!(
        err.to_string().contains("writer thread has stopped"),
        "{err}"
    );
    assert!(log.finish().is_err());
    // Dropped without finishing: no panic either.
    let mut log = log_on(path, Full::panicking(20_000));
    let _ = log_steps(&mut log, 0..1000);
    drop(log);
}

/// A file whose writes wait while `stalled` is set (a disk that stops answering), kept
/// in memory.
struct Stalling {
    stalled: std::sync::Arc<std::sync::atomic::AtomicBool>,
    bytes: std::sync::Arc<std::sync::Mutex<Vec<u8>>>,
}

impl Write for Stalling {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        while self.stalled.load(std::sync::atomic::Ordering::Relaxed) {
            std::thread::sleep(Duration::from_millis(1));
        }
        self.bytes.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

#[test]
fn behind_a_stalled_writer_messages_are_dropped_and_counted_not_waited_for() {
    use std::sync::atomic::Ordering;
    let stalled = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let bytes = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let out = Stalling {
        stalled: stalled.clone(),
        bytes: bytes.clone(),
    };
    let path = Path::new("/nowhere/stalled.mcap");
    let mut log = McapLog::on_writer(path, Box::new(out), &BTreeMap::new(), CHUNK_SIZE)
        .expect("header written before the stall");
    log.drop_when_behind(1000);
    stalled.store(true, Ordering::Relaxed);
    // A failed assertion must not leave the writer stalled: the log's drop waits for it.
    struct Unstall(std::sync::Arc<std::sync::atomic::AtomicBool>);
    impl Drop for Unstall {
        fn drop(&mut self) {
            self.0.store(false, std::sync::atomic::Ordering::Relaxed);
        }
    }
    let _unstall = Unstall(stalled.clone());
    let mut slowest = Duration::ZERO;
    let mut steps = |log: &mut McapLog, range: std::ops::Range<u64>| {
        for i in range {
            let t = i * 1_000_000;
            for k in 0..5 {
                log.frame(Direction::Rx, t, t, t, &frame(i * 5 + k))
                    .unwrap();
            }
            let begin = WallInstant::now();
            // A blocking hand-over would wait for the stalled writer forever.
            log.maybe_flush().unwrap();
            slowest = slowest.max(begin.elapsed());
        }
    };
    // Two seconds of 5 frames a millisecond: the first 1000 frames (full batch) go to the
    // writer, which stalls on them; the next batch fills up to 1000 and the rest of the
    // 10 000 are dropped.
    steps(&mut log, 0..2000);
    assert_eq!(log.dropped(), 10_000 - 1000 - 1000);
    assert_eq!(log.messages(), 1000 + 1000);
    // The disk answers again: once the writer has caught up, nothing more is dropped (here
    // less than a batch: this loop runs far faster than the writer).
    stalled.store(false, Ordering::Relaxed);
    std::thread::sleep(Duration::from_millis(500));
    steps(&mut log, 2000..2100);
    assert_eq!(log.dropped(), 8000);
    assert!(slowest < Duration::from_millis(100), "{slowest:?}");
    log.finish().unwrap();

    let bytes = bytes.lock().unwrap().clone();
    let mut frames = 0;
    let mut warnings = Vec::new();
    let report = for_each_message(
        &bytes,
        |m| match m.topic {
            "/can/rx" => frames += 1,
            "/rosout" => warnings.push(msg::decode::<msg::Log>(m.data).unwrap()),
            _ => {}
        },
        |_, _| {},
    )
    .unwrap();
    assert!(report.is_complete(), "{report}");
    assert_eq!(frames, 1000 + 1000 + 500);
    assert_eq!(warnings.len(), 1);
    assert_eq!(warnings[0].level, msg::Log::WARN);
    assert!(
        warnings[0].msg.starts_with("8000 messages dropped"),
        "{}",
        warnings[0].msg
    );
}

/// A run in simulated time writes the same bytes however slowly the machine runs it: with
/// `flush_on_log_time_only` a pause longer than the wall-clock interval (a loaded machine)
/// moves no chunk boundary; without it, the pause ends a chunk where it fell.
#[test]
fn a_log_flushed_on_log_time_only_is_the_same_bytes_however_slowly_it_is_written() {
    let write = |name: &str, log_time_only: bool, pause: bool| {
        let file = TempFile::new(name);
        let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
        if log_time_only {
            log.flush_on_log_time_only();
        }
        // 1 ms of log time a message: one hand-over at 250 ms of log time; the wall clock
        // is read at every 64th call.
        for i in 0..300u64 {
            log.text(i * 1_000_000, msg::Log::INFO, "step").unwrap();
            if pause && i == 127 {
                std::thread::sleep(Duration::from_millis(600));
            }
            log.maybe_flush().unwrap();
        }
        log.finish().unwrap();
        std::fs::read(&file.0).unwrap()
    };
    let fast = write("log-time-fast", true, false);
    assert_eq!(write("log-time-slow", true, true), fast);
    let wall = write("wall-slow", false, true);
    assert_ne!(
        wall,
        write("wall-fast", false, false),
        "the pause moved no chunk boundary"
    );
}
