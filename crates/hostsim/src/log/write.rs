//! Writing MCAP: the records (<https://mcap.dev/spec>, little-endian, each an opcode byte,
//! a `u64` length and its fields), and the thread that turns what the simulation logged into
//! messages, chunks them, compresses the chunks and appends them to the file.
//!
//! [`McapLog`](super::McapLog) records each message as an [`Event`] (its values, not yet
//! text) in a [`Batch`] on the simulation's thread, and hands each batch to a
//! [`BatchWriter`]. Its thread formats the batch's messages into Message records, in order,
//! numbering them; closes a chunk whenever its records reach the chunk size, and at the end
//! of the batch; computes each chunk's CRC, compresses it with zstd and appends the Chunk
//! record and its Message Index records to the file in one write; and keeps the statistics
//! and the Chunk Index records for the summary section. [`BatchWriter::send`] hands a batch
//! over, then waits until the one before it is in the file: at most two batches are missing
//! from the file, the one handed over and the one being logged.

use std::collections::BTreeMap;
use std::io::{self, Write};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use firmware::CanFrame;
use firmware::control::Snapshot;
use firmware::protocol::{dji, odrive};
use mcap::records::op;

use super::{CHANNELS, Direction, LAST_CHANNEL, data, json};
use crate::bus::{Fate, Node};

/// Record prefix: the opcode (1 byte) and the length of the fields (8 bytes).
pub(super) const RECORD_PREFIX: usize = 9;

/// Appends a record: `opcode`, its length, and the fields `fields` appends.
pub(super) fn record(out: &mut Vec<u8>, opcode: u8, fields: impl FnOnce(&mut Vec<u8>)) {
    let start = out.len();
    out.push(opcode);
    out.extend_from_slice(&[0; 8]);
    fields(out);
    let len = (out.len() - start - RECORD_PREFIX) as u64;
    out[start + 1..start + RECORD_PREFIX].copy_from_slice(&len.to_le_bytes());
}

/// Appends a string: `u32` byte length, then UTF-8.
pub(super) fn put_str(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(&(s.len() as u32).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}

/// Appends a map or array: `u32` byte length, then the entries `entries` appends.
fn put_prefixed(out: &mut Vec<u8>, entries: impl FnOnce(&mut Vec<u8>)) {
    let start = out.len();
    out.extend_from_slice(&[0; 4]);
    entries(out);
    let len = (out.len() - start - 4) as u32;
    out[start..start + 4].copy_from_slice(&len.to_le_bytes());
}

/// A `Map<string, string>`.
pub(super) fn put_string_map(out: &mut Vec<u8>, map: &BTreeMap<String, String>) {
    put_prefixed(out, |out| {
        for (k, v) in map {
            put_str(out, k);
            put_str(out, v);
        }
    });
}

/// A `Map<uint16, uint64>`.
fn put_u16_u64_map(out: &mut Vec<u8>, entries: impl IntoIterator<Item = (u16, u64)>) {
    put_prefixed(out, |out| {
        for (k, v) in entries {
            out.extend_from_slice(&k.to_le_bytes());
            out.extend_from_slice(&v.to_le_bytes());
        }
    });
}

/// Header record.
pub(super) fn header(out: &mut Vec<u8>, profile: &str, library: &str) {
    record(out, op::HEADER, |out| {
        put_str(out, profile);
        put_str(out, library);
    });
}

/// Schema record.
pub(super) fn schema(out: &mut Vec<u8>, id: u16, name: &str, encoding: &str, data: &[u8]) {
    record(out, op::SCHEMA, |out| {
        out.extend_from_slice(&id.to_le_bytes());
        put_str(out, name);
        put_str(out, encoding);
        out.extend_from_slice(&(data.len() as u32).to_le_bytes());
        out.extend_from_slice(data);
    });
}

/// Channel record (no channel metadata).
pub(super) fn channel(out: &mut Vec<u8>, id: u16, schema_id: u16, topic: &str, encoding: &str) {
    record(out, op::CHANNEL, |out| {
        out.extend_from_slice(&id.to_le_bytes());
        out.extend_from_slice(&schema_id.to_le_bytes());
        put_str(out, topic);
        put_str(out, encoding);
        put_string_map(out, &BTreeMap::new());
    });
}

/// Metadata record.
pub(super) fn metadata(out: &mut Vec<u8>, name: &str, map: &BTreeMap<String, String>) {
    record(out, op::METADATA, |out| {
        put_str(out, name);
        put_string_map(out, map);
    });
}

/// Bytes in front of a message's data: record prefix, channel id (2), sequence (4), log
/// time (8), publish time (8).
const MESSAGE_PREFIX: usize = RECORD_PREFIX + 22;

/// A Message record's prefix with a zero length, to be set by [`end_message`] once the data
/// is appended. Publish time is log time.
#[inline]
fn begin_message(out: &mut Vec<u8>, channel: u16, sequence: u32, t_ns: u64) {
    let mut p = [0u8; MESSAGE_PREFIX];
    p[0] = op::MESSAGE;
    p[9..11].copy_from_slice(&channel.to_le_bytes());
    p[11..15].copy_from_slice(&sequence.to_le_bytes());
    p[15..23].copy_from_slice(&t_ns.to_le_bytes());
    p[23..31].copy_from_slice(&t_ns.to_le_bytes());
    out.extend_from_slice(&p);
}

/// Sets the length of the Message record that starts at `start` of `out` and ends at its end.
#[inline]
fn end_message(out: &mut [u8], start: usize) {
    let len = (out.len() - start - RECORD_PREFIX) as u64;
    out[start + 1..start + RECORD_PREFIX].copy_from_slice(&len.to_le_bytes());
}

/// A logged message, or the four of a pose, as values: the writing thread makes the text.
#[derive(Clone, Copy)]
pub(super) enum Event {
    /// `/can/rx` or `/can/tx`.
    Can {
        t_ns: u64,
        frame: CanFrame,
        dir: Direction,
    },
    /// `/can/bus`.
    Bus {
        t_ns: u64,
        frame: CanFrame,
        sender: Node,
        fate: Fate,
    },
    /// `/motors/feedback`, decoded.
    Dji { t_ns: u64, feedback: dji::Feedback },
    Odrive {
        t_ns: u64,
        feedback: odrive::Addressed<odrive::Feedback>,
    },
    /// `/firmware/snapshot`: [`Batch::snapshots`]`[index]`.
    Snapshot { t_ns: u64, index: u32 },
    /// `/cmd/twist`.
    Twist {
        t_ns: u64,
        twist: [f32; 3],
        streaming: bool,
    },
    /// `/odom/pose`, `/tf`, `/ground_truth/pose`, `/tf`: [`Batch::poses`]`[index]`, the
    /// odometry and the ground truth.
    Poses { t_ns: u64, index: u32 },
    /// `/firmware/log`: [`Batch::texts`]`[index]`.
    Text { t_ns: u64, level: i32, index: u32 },
}

/// The messages logged between two hand-overs to the writing thread, in order. The larger
/// values are kept beside the events, so that an event stays small.
#[derive(Default)]
pub(super) struct Batch {
    pub events: Vec<Event>,
    pub snapshots: Vec<Snapshot>,
    pub poses: Vec<[[f64; 3]; 2]>,
    pub texts: Vec<String>,
}

impl Batch {
    pub fn is_empty(&self) -> bool {
        self.events.is_empty()
    }

    pub fn clear(&mut self) {
        self.events.clear();
        self.snapshots.clear();
        self.poses.clear();
        self.texts.clear();
    }
}

/// Message counts and times, for the Statistics record.
#[derive(Clone)]
pub(super) struct Stats {
    /// Messages per channel id.
    pub counts: [u64; LAST_CHANNEL as usize + 1],
    pub messages: u64,
    /// Earliest and latest log time (`u64::MAX` and 0 before the first message).
    pub first_ns: u64,
    pub last_ns: u64,
}

/// The file and what the writer's thread knows of it: where it ends, the CRC of everything
/// written, the Chunk Index records of the chunks written, and the statistics.
pub(super) struct Sink {
    /// The file, after the bytes written already.
    pub out: Box<dyn Write + Send>,
    /// Bytes written, i.e. the offset of the next record.
    pub len: u64,
    /// CRC-32 of every byte written (the Data End record's data section CRC).
    pub crc: crc32fast::Hasher,
    /// Chunk Index records, for the summary section.
    pub chunk_indexes: Vec<u8>,
    pub chunks: u32,
    pub stats: Stats,
}

impl Sink {
    /// A sink appending to `out`, after `head` (already written there).
    pub fn new(out: Box<dyn Write + Send>, head: &[u8]) -> Self {
        let mut crc = crc32fast::Hasher::new();
        crc.update(head);
        Self {
            out,
            len: head.len() as u64,
            crc,
            chunk_indexes: Vec::new(),
            chunks: 0,
            stats: Stats {
                counts: [0; LAST_CHANNEL as usize + 1],
                messages: 0,
                first_ns: u64::MAX,
                last_ns: 0,
            },
        }
    }

    /// Appends `bytes` to the file.
    fn write(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.out.write_all(bytes)?;
        self.crc.update(bytes);
        self.len += bytes.len() as u64;
        Ok(())
    }
}

/// The writing thread's state: the open chunk and its message index, the message numbering,
/// the compressor and its buffers.
struct Chunker {
    chunk_size: usize,
    seq: u32,
    /// The open chunk's Message records.
    records: Vec<u8>,
    /// Its message index: `(log time, offset in records)` by channel id.
    index: Vec<Vec<(u64, u64)>>,
    /// Its earliest and latest log time.
    start_ns: u64,
    end_ns: u64,
    zstd: zstd::bulk::Compressor<'static>,
    compressed: Vec<u8>,
    out: Vec<u8>,
}

impl Chunker {
    /// Formats `batch`'s messages into chunks and appends them to `sink`; the last chunk
    /// ends with the batch.
    fn batch(&mut self, sink: &mut Sink, batch: &Batch) -> io::Result<()> {
        for event in &batch.events {
            self.event(sink, batch, event)?;
        }
        self.close(sink)
    }

    fn event(&mut self, sink: &mut Sink, batch: &Batch, event: &Event) -> io::Result<()> {
        let ch = CHANNELS;
        match *event {
            Event::Can { t_ns, frame, dir } => {
                let channel = match dir {
                    Direction::Rx => ch.rx,
                    Direction::Tx => ch.tx,
                };
                self.message(sink, channel, t_ns, |buf| {
                    json::write_frame_json(buf, t_ns, &frame, None);
                })
            }
            Event::Bus {
                t_ns,
                frame,
                sender,
                fate,
            } => self.message(sink, ch.bus, t_ns, |buf| {
                json::write_frame_json(buf, t_ns, &frame, Some((sender, fate)));
            }),
            Event::Dji { t_ns, feedback } => self.message(sink, ch.feedback, t_ns, |buf| {
                data::dji_feedback(buf, &feedback);
            }),
            Event::Odrive { t_ns, feedback } => self.message(sink, ch.feedback, t_ns, |buf| {
                data::odrive_feedback(buf, &feedback);
            }),
            Event::Snapshot { t_ns, index } => self.message(sink, ch.snapshot, t_ns, |buf| {
                data::snapshot(buf, &batch.snapshots[index as usize]);
            }),
            Event::Twist {
                t_ns,
                twist,
                streaming,
            } => self.message(sink, ch.twist, t_ns, |buf| {
                data::twist(buf, twist, streaming);
            }),
            Event::Poses { t_ns, index } => {
                let [odom, truth] = batch.poses[index as usize];
                for (pose, frame, child, pose_ch) in [
                    // The odometry's origin is where the run starts, the world's origin: its
                    // pose is in `world`, the frame /tf places, so a viewer can draw it.
                    (odom, "world", "base_link_odom", ch.odom),
                    (truth, "world", "base_link", ch.truth),
                ] {
                    self.message(sink, pose_ch, t_ns, |buf| {
                        data::pose(buf, t_ns, frame, pose);
                    })?;
                    self.message(sink, ch.tf, t_ns, |buf| {
                        data::transform(buf, t_ns, child, pose);
                    })?;
                }
                Ok(())
            }
            Event::Text { t_ns, level, index } => self.message(sink, ch.log, t_ns, |buf| {
                data::text(buf, t_ns, level, &batch.texts[index as usize]);
            }),
        }
    }

    /// Appends a Message record on `channel` at `t_ns` whose data `data` appends; closes the
    /// chunk once it reaches its size.
    #[inline]
    fn message(
        &mut self,
        sink: &mut Sink,
        channel: u16,
        t_ns: u64,
        data: impl FnOnce(&mut Vec<u8>),
    ) -> io::Result<()> {
        self.seq = self.seq.wrapping_add(1);
        let start = self.records.len();
        begin_message(&mut self.records, channel, self.seq, t_ns);
        data(&mut self.records);
        end_message(&mut self.records, start);
        self.index[usize::from(channel)].push((t_ns, start as u64));
        self.start_ns = self.start_ns.min(t_ns);
        self.end_ns = self.end_ns.max(t_ns);
        let stats = &mut sink.stats;
        stats.counts[usize::from(channel)] += 1;
        stats.messages += 1;
        stats.first_ns = stats.first_ns.min(t_ns);
        stats.last_ns = stats.last_ns.max(t_ns);
        if self.records.len() >= self.chunk_size {
            self.close(sink)?;
        }
        Ok(())
    }

    /// Compresses the open chunk, if it holds anything, and appends it and its message
    /// indexes to `sink` in one write.
    fn close(&mut self, sink: &mut Sink) -> io::Result<()> {
        if self.records.is_empty() {
            return Ok(());
        }
        let uncompressed_crc = crc32fast::hash(&self.records);
        self.compressed.clear();
        self.compressed
            .reserve(zstd::zstd_safe::compress_bound(self.records.len()));
        self.zstd
            .compress_to_buffer(&self.records, &mut self.compressed)?;
        let (start_ns, end_ns) = (self.start_ns, self.end_ns);
        let out = &mut self.out;
        out.clear();
        let chunk_start = sink.len;
        record(out, op::CHUNK, |out| {
            out.extend_from_slice(&start_ns.to_le_bytes());
            out.extend_from_slice(&end_ns.to_le_bytes());
            out.extend_from_slice(&(self.records.len() as u64).to_le_bytes());
            out.extend_from_slice(&uncompressed_crc.to_le_bytes());
            put_str(out, "zstd");
            out.extend_from_slice(&(self.compressed.len() as u64).to_le_bytes());
            out.extend_from_slice(&self.compressed);
        });
        let chunk_length = out.len() as u64;
        let mut index_offsets = Vec::new();
        for (channel, entries) in self.index.iter().enumerate() {
            if entries.is_empty() {
                continue;
            }
            // Channel ids are u16 (the index has one entry per channel).
            let channel = channel as u16;
            index_offsets.push((channel, chunk_start + out.len() as u64));
            record(out, op::MESSAGE_INDEX, |out| {
                out.extend_from_slice(&channel.to_le_bytes());
                out.extend_from_slice(&((entries.len() * 16) as u32).to_le_bytes());
                for &(t, offset) in entries {
                    out.extend_from_slice(&t.to_le_bytes());
                    out.extend_from_slice(&offset.to_le_bytes());
                }
            });
        }
        let index_length = out.len() as u64 - chunk_length;
        sink.write(out)?;
        record(&mut sink.chunk_indexes, op::CHUNK_INDEX, |ix| {
            ix.extend_from_slice(&start_ns.to_le_bytes());
            ix.extend_from_slice(&end_ns.to_le_bytes());
            ix.extend_from_slice(&chunk_start.to_le_bytes());
            ix.extend_from_slice(&chunk_length.to_le_bytes());
            put_u16_u64_map(ix, index_offsets);
            ix.extend_from_slice(&index_length.to_le_bytes());
            put_str(ix, "zstd");
            ix.extend_from_slice(&(self.compressed.len() as u64).to_le_bytes());
            ix.extend_from_slice(&(self.records.len() as u64).to_le_bytes());
        });
        sink.chunks += 1;
        self.records.clear();
        for entries in &mut self.index {
            entries.clear();
        }
        self.start_ns = u64::MAX;
        self.end_ns = 0;
        Ok(())
    }
}

/// The thread that writes batches, and the two channels to it: batches go there, and each
/// comes back (emptied, for reuse) once it is in the file, or the error that stopped the
/// thread.
pub(super) struct BatchWriter {
    to_thread: Option<SyncSender<Batch>>,
    from_thread: Receiver<io::Result<Batch>>,
    thread: Option<JoinHandle<Sink>>,
    /// A batch was sent and has not come back yet.
    in_flight: bool,
}

impl BatchWriter {
    /// Starts the thread, which appends to `sink` chunks of `chunk_size` uncompressed bytes
    /// (or the end of a batch), compressed at zstd `level`.
    pub fn start(sink: Sink, chunk_size: usize, level: i32) -> io::Result<Self> {
        let mut chunker = Chunker {
            chunk_size,
            seq: 0,
            records: Vec::with_capacity(chunk_size.min(super::CHUNK_SIZE as usize) + 4096),
            index: vec![Vec::new(); usize::from(LAST_CHANNEL) + 1],
            start_ns: u64::MAX,
            end_ns: 0,
            zstd: zstd::bulk::Compressor::new(level)?,
            compressed: Vec::new(),
            out: Vec::new(),
        };
        // One batch waits while the thread writes the one before it; two answers at most are
        // pending (the previous batch's, and the waiting one's if the thread is quick).
        let (to_thread, batches) = sync_channel::<Batch>(1);
        let (done, from_thread) = sync_channel(2);
        let thread = std::thread::Builder::new()
            .name("mcap-writer".to_string())
            .spawn(move || {
                let mut sink = sink;
                for mut batch in batches {
                    match chunker.batch(&mut sink, &batch) {
                        Ok(()) => {
                            batch.clear();
                            if done.send(Ok(batch)).is_err() {
                                break;
                            }
                        }
                        Err(e) => {
                            let _ = done.send(Err(e));
                            break;
                        }
                    }
                }
                sink
            })?;
        Ok(Self {
            to_thread: Some(to_thread),
            from_thread,
            thread: Some(thread),
            in_flight: false,
        })
    }

    /// Waits until the batch in flight, if any, is in the file; returns it emptied.
    ///
    /// # Errors
    /// The error that stopped the thread.
    pub fn wait(&mut self) -> io::Result<Option<Batch>> {
        if !self.in_flight {
            return Ok(None);
        }
        self.in_flight = false;
        match self.from_thread.recv() {
            Ok(result) => result.map(Some),
            Err(_) => Err(stopped()),
        }
    }

    /// Hands `batch` to the thread, then waits until the one handed over before it is in the
    /// file, and returns that one, emptied, for reuse. The thread finds `batch` waiting when
    /// it is done with the previous one: it does not idle between batches while this thread
    /// wakes up.
    ///
    /// # Errors
    /// The error that stopped the thread.
    pub fn send(&mut self, batch: Batch) -> io::Result<Option<Batch>> {
        let sent = self
            .to_thread
            .as_ref()
            .is_some_and(|to_thread| to_thread.send(batch).is_ok());
        // The previous batch's error, if that is what stopped the thread.
        let previous = self.wait()?;
        if !sent {
            return Err(stopped());
        }
        self.in_flight = true;
        Ok(previous)
    }

    /// Waits for the batch in flight, stops the thread and returns the file.
    ///
    /// # Errors
    /// The error that stopped the thread.
    pub fn finish(&mut self) -> io::Result<Sink> {
        self.wait()?;
        self.to_thread = None;
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(sink)) => Ok(sink),
            _ => Err(stopped()),
        }
    }
}

/// The error for a thread that is gone without saying why (it panicked, or an earlier error
/// was already reported).
fn stopped() -> io::Error {
    io::Error::other("the MCAP writer thread has stopped")
}

impl Drop for BatchWriter {
    fn drop(&mut self) {
        // Let the thread finish the batch in flight and end.
        self.to_thread = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
