//! Damaged logs: a log written by the real writer, cut at many offsets and with bytes
//! flipped at many offsets, read by `log::for_each_message`, `replay` and `summary`.
//!
//! The expected messages come from the `mcap` crate's own reader on the intact file (its
//! chunk index and chunk reader), not from the reader under test: a log cut at byte `c`
//! must give exactly the messages of the chunks that end at or before `c`, and a damaged
//! chunk none of its messages.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use drivelog::{Direction, McapLog, Problem, ReadReport, for_each_message};
use embedded_can::StandardId;
use firmware::CanFrame;
use hostsim::engine::run_metadata;
use hostsim::replay::{self, MAX_GAP_NS, ReplayError, ReplayRunError, TimedFrame};
use hostsim::scenario::Scenario;

/// A message: topic, log time, data, publish time.
type Msg = (String, u64, Vec<u8>, u64);

/// A log written by the real writer, and what the `mcap` crate reads from it.
struct Fixture {
    bytes: Vec<u8>,
    /// Every message in file order.
    messages: Vec<Msg>,
    /// Per chunk in file order: start offset, end offset (one past), messages before its end.
    chunks: Vec<(usize, usize, usize)>,
    /// Top-level records of the file: start, end, opcode.
    records: Vec<(usize, usize, u8)>,
    /// End of the Data End record.
    data_end: usize,
}

impl Fixture {
    /// Messages in the chunks that end at or before `offset`.
    fn messages_before(&self, offset: usize) -> usize {
        self.chunks
            .iter()
            .take_while(|c| c.1 <= offset)
            .last()
            .map_or(0, |c| c.2)
    }

    /// Chunks that end at or before `offset`.
    fn chunks_before(&self, offset: usize) -> u64 {
        self.chunks.iter().take_while(|c| c.1 <= offset).count() as u64
    }

    /// Message counts at chunk boundaries (0 included).
    fn boundaries(&self) -> Vec<usize> {
        std::iter::once(0)
            .chain(self.chunks.iter().map(|c| c.2))
            .collect()
    }

    /// The top-level record holding byte `offset` (after the magic).
    fn record_at(&self, offset: usize) -> Option<(usize, usize, u8)> {
        self.records
            .iter()
            .copied()
            .find(|r| r.0 <= offset && offset < r.1)
    }
}

/// Half a second of the square with 4 KiB chunks: many chunk boundaries in a small file.
/// The built-in square, `duration_s` long, logged by the real writer into `path` (with
/// `chunk_size`-byte chunks, or the writer's default); the log is left open.
fn square_log(path: &Path, duration_s: f64, chunk_size: Option<u64>) -> McapLog {
    let mut s = Scenario::builtin("square").unwrap();
    s.duration_s = duration_s;
    let mut log = match chunk_size {
        Some(n) => McapLog::create_with_chunk_size(path, &run_metadata(&s), n),
        None => McapLog::create(path, &run_metadata(&s)),
    }
    .unwrap();
    common::run_into(&s, &mut log);
    log
}

fn fixture() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        let dir = TempDir::new("fixture");
        let path = dir.0.join("square.mcap");
        square_log(&path, 0.5, Some(4 << 10)).finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();

        let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
        let mut index = summary.chunk_indexes.clone();
        index.sort_by_key(|c| c.chunk_start_offset);
        let mut messages = Vec::new();
        let mut chunks = Vec::new();
        for c in &index {
            for m in summary.stream_chunk(&bytes, c).unwrap() {
                let m = m.unwrap();
                messages.push((
                    m.channel.topic.clone(),
                    m.log_time,
                    m.data.to_vec(),
                    m.publish_time,
                ));
            }
            let start = c.chunk_start_offset as usize;
            chunks.push((start, start + c.chunk_length as usize, messages.len()));
        }

        // The record framing: opcode, little-endian u64 length, content.
        let mut records = Vec::new();
        let mut pos = 8;
        let mut data_end = 0;
        while pos + 9 <= bytes.len() - 8 {
            let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
            let end = pos + 9 + len;
            records.push((pos, end, bytes[pos]));
            if bytes[pos] == mcap::records::op::DATA_END {
                data_end = end;
            }
            pos = end;
        }
        assert_eq!(pos, bytes.len() - 8, "the records end at the closing magic");
        assert!(
            chunks.len() >= 40,
            "{} chunks: make them smaller",
            chunks.len()
        );
        eprintln!(
            "fixture: {} bytes, {} chunks, {} messages",
            bytes.len(),
            chunks.len(),
            messages.len()
        );
        Fixture {
            bytes,
            messages,
            chunks,
            records,
            data_end,
        }
    })
}

/// Reads `bytes`; the count of messages delivered, if they are the first of the fixture's
/// messages in order (`None` if any differs).
fn read(bytes: &[u8]) -> (Result<ReadReport, drivelog::Damage>, Option<usize>) {
    let expected = &fixture().messages;
    let mut n = 0;
    let mut same = true;
    let r = for_each_message(
        bytes,
        |msg| {
            same &= expected.get(n).is_some_and(|m| {
                m.0 == msg.topic
                    && m.1 == msg.log_time
                    && m.2 == msg.data
                    && m.3 == msg.publish_time
            });
            n += 1;
        },
        |_, _| {},
    );
    (r, same.then_some(n))
}

/// A small deterministic generator (64-bit LCG, high bits), so failures reproduce.
struct Lcg(u64);

impl Lcg {
    fn below(&mut self, n: usize) -> usize {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((self.0 >> 33) % n as u64) as usize
    }
}

#[test]
fn an_intact_log_reads_completely() {
    let fx = fixture();
    let (r, got) = read(&fx.bytes);
    let r = r.unwrap();
    assert!(r.is_complete(), "{r}");
    assert!(r.data_complete);
    assert_eq!(r.chunks, fx.chunks.len() as u64);
    assert_eq!(r.messages, fx.messages.len() as u64);
    assert_eq!(
        got,
        Some(fx.messages.len()),
        "the reader and the mcap crate disagree"
    );
    assert!(r.to_string().starts_with("complete: "), "{r}");
}

#[test]
fn a_log_cut_anywhere_gives_exactly_its_complete_chunks() {
    let fx = fixture();
    let len = fx.bytes.len();
    // Every chunk boundary and a few bytes either side (inside the record prefix, inside the
    // chunk header, between the chunk and its message indexes), the start, the end, and 200
    // random offsets.
    let mut cuts: Vec<usize> = (0..60).collect();
    for (i, &(start, end, _)) in fx.chunks.iter().enumerate() {
        cuts.extend([end - 1, end, end + 1]);
        if i % 4 == 0 {
            cuts.extend([start + 1, start + 8, start + 9, start + 20]);
        }
    }
    cuts.extend(fx.data_end - 12..fx.data_end + 3);
    cuts.extend(len - 45..len);
    let mut rng = Lcg(1);
    cuts.extend((0..200).map(|_| rng.below(len)));
    cuts.retain(|&c| c < len);
    cuts.sort_unstable();
    cuts.dedup();
    assert!(cuts.len() > 400, "{} cuts", cuts.len());
    eprintln!("cutting at {} offsets", cuts.len());

    let header_end = fx.records[0].1;
    for &cut in &cuts {
        let (r, got) = read(&fx.bytes[..cut]);
        let r = match r {
            Ok(r) => r,
            Err(e) => {
                // Nothing readable: only a cut inside the magic or the header record.
                assert!(cut < header_end, "cut at {cut}: {e}");
                assert!(e.offset <= cut as u64, "cut at {cut}: {e}");
                continue;
            }
        };
        assert!(cut >= header_end, "cut at {cut} read as {r}");
        let want = fx.messages_before(cut);
        assert_eq!(r.messages as usize, want, "cut at {cut}: {r}");
        assert_eq!(got, Some(want), "cut at {cut}: other messages");
        assert_eq!(r.chunks, fx.chunks_before(cut), "cut at {cut}: {r}");
        assert_eq!(r.file_len, cut as u64);
        let damage = r.damage.as_ref().expect("a cut file is damaged");
        // Named at the start of the record the cut falls in (or at the cut, between records),
        // never before the end of the last complete chunk.
        let last_end = fx
            .chunks
            .iter()
            .take_while(|c| c.1 <= cut)
            .last()
            .map_or(0, |c| c.1);
        assert!(
            (last_end as u64..=cut as u64).contains(&damage.offset),
            "cut at {cut}: {damage}"
        );
        let text = r.to_string();
        assert!(
            text.contains(&format!("byte {}", damage.offset)),
            "cut at {cut}: {text}"
        );
        assert!(
            matches!(
                damage.problem,
                Problem::Truncated { .. } | Problem::Unfinished
            ),
            "cut at {cut}: {text}"
        );
        assert_eq!(r.data_complete, cut >= fx.data_end, "cut at {cut}: {text}");
    }
}

#[test]
fn a_flipped_byte_is_found_and_no_damaged_chunk_is_used() {
    let fx = fixture();
    let len = fx.bytes.len();
    let boundaries = fx.boundaries();
    let mut rng = Lcg(2);
    // Random offsets, and in every fifth chunk its opcode, length, times, size, CRC,
    // compression and compressed data.
    let mut offsets: Vec<usize> = (0..200).map(|_| rng.below(len)).collect();
    for &(start, end, _) in fx.chunks.iter().step_by(5) {
        offsets.extend([
            start,
            start + 3,
            start + 12,
            start + 30,
            start + 37,
            start + 41,
        ]);
        offsets.extend([
            start + 45,
            start + 49,
            start + 55,
            (start + end) / 2,
            end - 1,
        ]);
    }
    offsets.extend([fx.data_end - 2, len - 30, len - 10, len - 1]);
    let (mut checked_chunks, mut harmless_flips) = (0, 0);
    for &at in &offsets {
        let mut bytes = fx.bytes.clone();
        bytes[at] ^= 1 + rng.below(255) as u8;
        let (r, got) = read(&bytes);
        let Ok(r) = r else {
            // Nothing readable: only a flip in the magic or the header record.
            assert!(at < fx.records[0].1, "flip at {at}");
            continue;
        };
        let damage = r
            .damage
            .as_ref()
            .unwrap_or_else(|| panic!("flip at {at} not found: {r}"));
        assert!(damage.offset <= len as u64, "flip at {at}: {damage}");
        let n = got.unwrap_or_else(|| panic!("flip at {at}: other messages"));
        assert!(
            boundaries.contains(&n),
            "flip at {at}: {n} messages is not a whole number of chunks"
        );
        let Some((start, _, opcode)) = fx.record_at(at) else {
            continue;
        };
        assert!(
            n >= fx.messages_before(start),
            "flip at {at}: chunks before the flipped record were lost ({r})"
        );
        // Everything of a chunk from its size field on is covered by its checks (size, CRC,
        // compression, decompression): that chunk is refused, and only it. Except a flip that
        // leaves the decompressed records as they were (a bit of a zstd frame's entropy tables
        // that the decoding does not use: 36 of the 7,024 single-bit flips of one 878-byte
        // frame of this fixture): harmless, and only the data section's CRC (in Data End) sees
        // it. Every message is then read, unchanged.
        let data_end_record = fx.records.iter().find(|r| r.1 == fx.data_end).map(|r| r.0);
        if opcode == mcap::records::op::CHUNK
            && at >= start + 9 + 16
            && Some(damage.offset as usize) == data_end_record
            && n == fx.messages.len()
        {
            harmless_flips += 1;
            continue;
        }
        if opcode == mcap::records::op::CHUNK && at >= start + 9 + 16 {
            assert_eq!(damage.offset, start as u64, "flip at {at}: {r}");
            assert_eq!(n, fx.messages_before(start), "flip at {at}: {r}");
            checked_chunks += 1;
        }
    }
    assert!(
        checked_chunks > 50,
        "{checked_chunks} flips in chunks' checked fields"
    );
    // Rare: a handful at most of the some 250 flips.
    assert!(
        harmless_flips <= 3,
        "{harmless_flips} flips changed no record"
    );
    eprintln!(
        "flipped {} bytes, {checked_chunks} of them in a chunk's checked fields, \
         {harmless_flips} changing no record",
        offsets.len()
    );
}

#[test]
fn a_flipped_chunk_crc_names_the_chunk_and_the_crcs() {
    let fx = fixture();
    let (start, _, _) = fx.chunks[10];
    let mut bytes = fx.bytes.clone();
    // Chunk content: start time (8), end time (8), uncompressed size (8), CRC (4).
    bytes[start + 9 + 24] ^= 0x01;
    let (r, got) = read(&bytes);
    let r = r.unwrap();
    assert_eq!(got, Some(fx.chunks[9].2));
    let d = r.damage.as_ref().unwrap();
    assert_eq!(d.offset, start as u64);
    assert!(matches!(d.problem, Problem::ChunkCrc { .. }), "{d}");
    assert!(
        r.to_string()
            .contains(&format!("CRC mismatch in the Chunk record at byte {start}")),
        "{r}"
    );
}

/// A folder of its own for a test, removed when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(test: &str) -> Self {
        let dir =
            std::env::temp_dir().join(format!("hostsim-damaged-{}-{test}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir)
    }

    /// Writes `bytes` to `name` in the folder.
    fn write(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let path = self.0.join(name);
        std::fs::write(&path, bytes).unwrap();
        path
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[test]
fn replay_of_a_cut_log_is_bit_identical_up_to_the_cut_and_summary_reports_it() {
    let fx = fixture();
    let dir = TempDir::new("replay");
    let mut rng = Lcg(3);
    // Schemas, channels and the metadata with the configuration precede the chunks; the cuts
    // start in the second chunk, so that every cut log keeps some messages to replay.
    let mut cuts: Vec<usize> = fx
        .chunks
        .iter()
        .skip(1)
        .step_by(7)
        .map(|c| c.1 + 5)
        .collect();
    cuts.extend((0..8).map(|_| fx.chunks[3].1 + rng.below(fx.data_end - fx.chunks[3].1)));
    for cut in cuts {
        let path = dir.write(&format!("cut-{cut}.mcap"), &fx.bytes[..cut]);
        let report = replay::replay_mcap(&path).unwrap();
        let read = report.read.clone().unwrap();
        assert!(!read.is_complete(), "cut at {cut}");
        assert!(report.identical(), "cut at {cut}: {:?}", report.difference);
        // Every /can/tx frame read whose step is before the cut-off was compared: the last
        // message's time less the longest a sent frame read took to come off the wire.
        let last = read.last_time_ns.unwrap();
        let read_tx = || {
            fx.messages
                .iter()
                .take(read.messages as usize)
                .filter(|m| m.0 == "/can/tx")
        };
        let lag = read_tx().map(|m| m.1 - m.3).max().unwrap();
        assert!(lag > 0 && lag < 2_000_000, "{lag} ns");
        let want = read_tx().filter(|m| m.3 + lag < last).count();
        assert_eq!(report.compared, want, "cut at {cut}");
        assert!(report.compared > 0, "cut at {cut}");

        let s = hostsim::analysis::summary::summarize(&path).unwrap();
        assert_eq!(s.read, read);
        assert_eq!(s.topics.values().sum::<u64>(), read.messages);
    }
    // Cut inside the metadata, before any message: the configuration is missing.
    let metadata = fx
        .records
        .iter()
        .find(|r| r.2 == mcap::records::op::METADATA)
        .unwrap();
    let path = dir.write("no-metadata.mcap", &fx.bytes[..metadata.0 + 20]);
    let err = replay::replay_mcap(&path).unwrap_err();
    assert!(matches!(err, ReplayError::NoConfig { .. }), "{err}");
    // Cut inside the first chunk: the configuration is there, no message is. Nothing to
    // compare is an error that says so, not a "difference" of the replay's first frame.
    let path = dir.write("first-chunk.mcap", &fx.bytes[..fx.chunks[0].0 + 20]);
    let err = replay::replay_mcap(&path).unwrap_err();
    assert!(matches!(err, ReplayError::NothingToReplay { .. }), "{err}");
    assert!(err.to_string().contains("no CAN frames"), "{err}");
}

#[test]
fn a_log_without_firmware_frames_is_nothing_to_replay() {
    // What `hostsim plant --log` writes: the frames as the plant saw them on the interface,
    // not at the firmware's steps.
    let dir = TempDir::new("plant-log");
    let path = dir.0.join("plant.mcap");
    let config = firmware::Config::dji_m3508_example().to_toml_string();
    let metadata = BTreeMap::from([
        ("config".to_string(), config),
        ("program".to_string(), replay::PLANT_PROGRAM.to_string()),
    ]);
    let mut log = McapLog::create(&path, &metadata).unwrap();
    let frame = CanFrame::standard(StandardId::new(0x201).unwrap(), &[0; 8]).unwrap();
    for ms in 0..100 {
        let t = ms * 1_000_000;
        log.frame(Direction::Rx, t, t, t, &frame).unwrap();
    }
    log.finish().unwrap();
    let err = replay::replay_mcap(&path).unwrap_err();
    assert!(matches!(err, ReplayError::NothingToReplay { .. }), "{err}");
    assert!(err.to_string().contains("hostsim plant"), "{err}");
}

/// A log written by the real writer whose last `/can/tx` frame has a corrupt time near
/// 2^64 ns: CRCs correct, so only the time line can tell.
fn log_with_time(dir: &TempDir, name: &str, t_ns: u64) -> PathBuf {
    let path = dir.0.join(name);
    let mut log = square_log(&path, 0.2, None);
    let frame = CanFrame::standard(StandardId::new(0x200).unwrap(), &[0; 8]).unwrap();
    log.frame(Direction::Tx, t_ns, t_ns, t_ns, &frame).unwrap();
    log.finish().unwrap();
    path
}

#[test]
fn a_corrupt_timestamp_is_refused_not_replayed_for_centuries() {
    let start = std::time::Instant::now();
    let dir = TempDir::new("time");
    let path = log_with_time(&dir, "huge-time.mcap", u64::MAX - 5);
    let err = replay::replay_mcap(&path).unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, ReplayError::TimeGap { .. }), "{text}");
    assert!(text.contains("18446744073.709"), "{text}");
    assert!(text.contains("huge-time.mcap"), "{text}");
    // The summary reads it as it is (no loop there), with its absurd duration.
    let s = hostsim::analysis::summary::summarize(&path).unwrap();
    assert!(s.duration_s > 1e10);
    // A jump of just over the limit is refused; the limit itself is replayed.
    let path = log_with_time(&dir, "long-gap.mcap", 200_000_000 + MAX_GAP_NS + 1);
    assert!(matches!(
        replay::replay_mcap(&path),
        Err(ReplayError::TimeGap { .. })
    ));
    assert!(start.elapsed().as_secs() < 60, "{:?}", start.elapsed());
}

#[test]
fn the_time_gap_check_bounds_replay_and_candump_replay() {
    let frame = CanFrame::standard(StandardId::new(0x123).unwrap(), &[1]).unwrap();
    let at = |t_ns| TimedFrame { t_ns, frame };
    assert!(replay::check_time_gaps(&[at(0), at(MAX_GAP_NS), at(2 * MAX_GAP_NS)]).is_ok());
    let gap = replay::check_time_gaps(&[at(5), at(MAX_GAP_NS + 6)]).unwrap_err();
    assert_eq!((gap.from_ns, gap.to_ns), (5, MAX_GAP_NS + 6));
    assert!(gap.to_string().contains("123#01"), "{gap}");
    // Out of order: the time line is sorted first.
    assert!(replay::check_time_gaps(&[at(MAX_GAP_NS + 1), at(1)]).is_ok());
    let gap = replay::check_time_gaps(&[at(MAX_GAP_NS + 1)]).unwrap_err();
    assert_eq!(gap.from_ns, 0, "the first frame counts from the start");

    let config = firmware::Config::dji_m3508_example();
    let r = replay::replay_frames(&config, &[at(0)], &[at(u64::MAX)]);
    assert!(matches!(r, Err(ReplayRunError::TimeGap(_))), "{r:?}");
    let split = replay::SplitLog {
        rx: vec![at(0), at(u64::MAX - 1)],
        all: vec![at(0), at(u64::MAX - 1)],
        ..replay::SplitLog::default()
    };
    let r = replay::replay_split(&config, &split, replay::OdometryTolerance::default());
    assert!(matches!(r, Err(ReplayRunError::TimeGap(_))), "{r:?}");
}

#[test]
fn a_log_is_a_readable_part_until_finished_and_the_last_good_one_stays() {
    // The log is written as NAME.mcap.part, readable from its header on, and renamed to
    // NAME.mcap when finished: until then (or if the run never finishes) the last good
    // NAME.mcap stays as it was.
    let dir = TempDir::new("part");
    let path = dir.0.join("run.mcap");
    let part = drivelog::part_path(&path);
    McapLog::create(&path, &Default::default())
        .unwrap()
        .finish()
        .unwrap();
    let good = std::fs::read(&path).unwrap();
    let log = McapLog::create(&path, &Default::default()).unwrap();
    assert_eq!(log.part(), Some(part.as_path()));
    let (r, _) = read(&std::fs::read(&part).unwrap());
    let r = r.expect("readable before the first message");
    assert_eq!(r.damage.map(|d| d.problem), Some(Problem::Unfinished));
    assert_eq!(
        std::fs::read(&path).unwrap(),
        good,
        "the last good log is untouched"
    );
    log.finish().unwrap();
    assert!(!part.exists());
    let (r, _) = read(&std::fs::read(&path).unwrap());
    assert!(r.unwrap().is_complete());

    // Dropped unfinished (a run that failed): the .part stays, the last good log too.
    let log = McapLog::create(&path, &Default::default()).unwrap();
    drop(log);
    let (r, _) = read(&std::fs::read(&part).unwrap());
    assert!(r.is_ok());
    assert!(
        read(&std::fs::read(&path).unwrap())
            .0
            .unwrap()
            .is_complete()
    );
}

#[test]
fn garbage_and_empty_files_are_errors_not_damage() {
    for bytes in [
        &b""[..],
        b"\x89MC",
        b"not an mcap file",
        b"\x89MCAP0\r\n",
        b"\x89MCAP0\r\n\x01\x05",
    ] {
        let (r, _) = read(bytes);
        let e = r.unwrap_err();
        assert!(e.offset <= bytes.len() as u64, "{e}");
    }
}

#[test]
fn remote_and_extended_frames_read_back_as_written_and_count_on_the_bus() {
    use embedded_can::{ExtendedId, Frame as _};
    let ext = ExtendedId::new(0x1ABC_DEF0).unwrap();
    let std_id = StandardId::new(0x029).unwrap();
    let frames = [
        CanFrame::new_remote(std_id, 8).unwrap(),
        CanFrame::new(ext, &[1, 2, 3]).unwrap(),
        CanFrame::new_remote(ext, 4).unwrap(),
    ];
    // A second of a bus carrying only these (a plant log of a real bus): they read back as
    // written, and the summary's load is their exact length, as the simulated bus would time
    // them.
    let dir = TempDir::new("remote-extended");
    let path = dir.0.join("bus.mcap");
    let mut log = McapLog::create(&path, &BTreeMap::new()).unwrap();
    let mut bits = 0u64;
    let mut written = Vec::new();
    for ms in 0..=1000u64 {
        let frame = frames[(ms % 3) as usize];
        let t = ms * 1_000_000;
        log.frame(Direction::Rx, t, t, t, &frame).unwrap();
        written.push(TimedFrame { t_ns: t, frame });
        bits += u64::from(hostsim::bus::frame_bits(&frame));
    }
    log.finish().unwrap();
    let content = replay::read_log(&path).unwrap();
    assert_eq!(content.rx, written);
    let s = hostsim::analysis::summary::summarize(&path).unwrap();
    let load = s.bus_load.unwrap();
    assert!(
        (load - bits as f64 / 1e6).abs() < 1e-12,
        "{load} vs {bits} bits in 1 s"
    );
    // A remote frame has no data bits: far below eight-byte frames' load.
    assert!(load < 0.1, "{load}");
}

#[test]
fn a_log_in_the_old_json_layout_is_refused_in_one_line() {
    // What earlier versions wrote: MCAP without the ros2 profile, JSON messages.
    let dir = TempDir::new("old-layout");
    let path = dir.0.join("old.mcap");
    let mut w = mcap::Writer::new(std::io::BufWriter::new(
        std::fs::File::create(&path).unwrap(),
    ))
    .unwrap();
    let schema = w
        .add_schema("can_msgs/msg/Frame", "jsonschema", b"{}")
        .unwrap();
    let channel = w
        .add_channel(schema, "/can/rx", "json", &BTreeMap::new())
        .unwrap();
    let header = mcap::records::MessageHeader {
        channel_id: channel,
        sequence: 1,
        log_time: 0,
        publish_time: 0,
    };
    w.write_to_known_channel(&header, br#"{"id":513,"dlc":0,"data":[]}"#)
        .unwrap();
    w.finish().unwrap();
    drop(w);
    let err = replay::replay_mcap(&path).unwrap_err();
    assert!(matches!(err, ReplayError::OldLayout { .. }), "{err}");
    let text = err.to_string();
    assert!(
        text.contains("old.mcap") && text.contains("JSON layout"),
        "{text}"
    );
    assert!(!text.contains('\n'), "{text}");
    let err = hostsim::analysis::summary::summarize(&path).unwrap_err();
    assert!(err.contains("JSON layout"), "{err}");
}

#[test]
fn an_undecodable_inbound_frame_fails_replay_and_summary_and_plot_count_it() {
    // The square log rewritten message by message, its 1000th /can/rx cut to 3 bytes of CDR:
    // every chunk whole and intact, one message that does not decode.
    let fx = fixture();
    let dir = TempDir::new("undecodable");
    let path = dir.0.join("one-bad.mcap");
    let file = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    let mut w = mcap::WriteOptions::new()
        .profile("ros2")
        .create(file)
        .unwrap();
    let mut metadata = Vec::new();
    drivelog::for_each_message(
        &fx.bytes,
        |_| {},
        |name, kv| {
            metadata.push((name.to_string(), kv.clone()));
        },
    )
    .unwrap();
    for (name, metadata) in metadata {
        w.write_metadata(&mcap::records::Metadata { name, metadata })
            .unwrap();
    }
    let (mut rx, mut bad_at) = (0, 0);
    for m in mcap::MessageStream::new(&fx.bytes).unwrap() {
        let mut m = m.unwrap();
        if m.channel.topic == "/can/rx" {
            rx += 1;
            if rx == 1000 {
                m.data = std::borrow::Cow::Owned(m.data[..3].to_vec());
                bad_at = m.log_time;
            }
        }
        w.write(&m).unwrap();
    }
    w.finish().unwrap();
    drop(w);
    assert!(rx > 1000 && bad_at > 0);
    let first = format!("the first: /can/rx at {:.6} s", bad_at as f64 * 1e-9);

    let err = replay::replay_mcap(&path).unwrap_err();
    assert!(matches!(err, ReplayError::Undecodable { .. }), "{err}");
    let text = err.to_string();
    for says in [
        "one-bad.mcap",
        "1 messages could not be decoded (/can/rx 1)",
        &first,
    ] {
        assert!(text.contains(says), "{says}: {text}");
    }
    let s = hostsim::analysis::summary::summarize(&path).unwrap();
    assert!(s.read.is_complete());
    assert_eq!(s.undecodable.total(), 1);
    assert_eq!(s.undecodable.on("/can/rx"), 1);
    let track = hostsim::analysis::plot::track_from_log(&path).unwrap();
    assert_eq!(track.undecodable.total(), 0, "the plot reads odometry only");
}
