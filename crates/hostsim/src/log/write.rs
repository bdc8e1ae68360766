//! Writing MCAP: the records (<https://mcap.dev/spec>, little-endian, each an opcode byte,
//! a `u64` length and its fields) and the thread that compresses chunks and appends them to
//! the file.
//!
//! [`McapLog`](super::McapLog) builds each chunk's records, uncompressed, on the simulation's
//! thread and hands the chunk to a [`ChunkWriter`]; its thread computes the chunk's CRC,
//! compresses it with zstd, appends the Chunk record and its Message Index records to the
//! file in one write, and keeps the Chunk Index records for the summary section. At most one
//! chunk is in flight: [`ChunkWriter::send`] first waits until the previous one is written.

use std::collections::BTreeMap;
use std::io::{self, Write};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use mcap::records::op;

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
pub(super) const MESSAGE_PREFIX: usize = RECORD_PREFIX + 22;

/// A Message record's prefix with a zero length, to be set by [`end_message`] once the data
/// is appended. Publish time is log time.
#[inline]
pub(super) fn begin_message(out: &mut Vec<u8>, channel: u16, sequence: u32, t_ns: u64) {
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
pub(super) fn end_message(out: &mut [u8], start: usize) {
    let len = (out.len() - start - RECORD_PREFIX) as u64;
    out[start + 1..start + RECORD_PREFIX].copy_from_slice(&len.to_le_bytes());
}

/// A chunk's messages, uncompressed, with their index, as handed to the [`ChunkWriter`].
#[derive(Default)]
pub(super) struct Chunk {
    /// The chunk's records (Message records), uncompressed.
    pub records: Vec<u8>,
    /// Message index entries `(log time, offset in records)` by channel id.
    pub index: Vec<Vec<(u64, u64)>>,
    /// Earliest and latest log time of the messages.
    pub start_ns: u64,
    pub end_ns: u64,
}

impl Chunk {
    /// A chunk for channels `0..channels`.
    pub fn new(channels: usize, capacity: usize) -> Self {
        Self {
            records: Vec::with_capacity(capacity),
            index: vec![Vec::new(); channels],
            start_ns: u64::MAX,
            end_ns: 0,
        }
    }

    fn clear(&mut self) {
        self.records.clear();
        for entries in &mut self.index {
            entries.clear();
        }
        self.start_ns = u64::MAX;
        self.end_ns = 0;
    }
}

/// The file and what the writer's thread knows of it: where it ends, the CRC of everything
/// written, and the Chunk Index records of the chunks written.
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
}

impl Sink {
    /// Appends `bytes` to the file.
    pub fn write(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.out.write_all(bytes)?;
        self.crc.update(bytes);
        self.len += bytes.len() as u64;
        Ok(())
    }
}

/// The thread's working memory.
struct Compressor {
    zstd: zstd::bulk::Compressor<'static>,
    compressed: Vec<u8>,
    out: Vec<u8>,
}

impl Compressor {
    /// Compresses `chunk` and appends it and its message indexes to `sink`, in one write.
    fn append(&mut self, sink: &mut Sink, chunk: &Chunk) -> io::Result<()> {
        let uncompressed_crc = crc32fast::hash(&chunk.records);
        self.compressed.clear();
        self.compressed
            .reserve(zstd::zstd_safe::compress_bound(chunk.records.len()));
        self.zstd
            .compress_to_buffer(&chunk.records, &mut self.compressed)?;
        let out = &mut self.out;
        out.clear();
        let chunk_start = sink.len;
        record(out, op::CHUNK, |out| {
            out.extend_from_slice(&chunk.start_ns.to_le_bytes());
            out.extend_from_slice(&chunk.end_ns.to_le_bytes());
            out.extend_from_slice(&(chunk.records.len() as u64).to_le_bytes());
            out.extend_from_slice(&uncompressed_crc.to_le_bytes());
            put_str(out, "zstd");
            out.extend_from_slice(&(self.compressed.len() as u64).to_le_bytes());
            out.extend_from_slice(&self.compressed);
        });
        let chunk_length = out.len() as u64;
        let mut index_offsets = Vec::new();
        for (channel, entries) in chunk.index.iter().enumerate() {
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
            ix.extend_from_slice(&chunk.start_ns.to_le_bytes());
            ix.extend_from_slice(&chunk.end_ns.to_le_bytes());
            ix.extend_from_slice(&chunk_start.to_le_bytes());
            ix.extend_from_slice(&chunk_length.to_le_bytes());
            put_u16_u64_map(ix, index_offsets);
            ix.extend_from_slice(&index_length.to_le_bytes());
            put_str(ix, "zstd");
            ix.extend_from_slice(&(self.compressed.len() as u64).to_le_bytes());
            ix.extend_from_slice(&(chunk.records.len() as u64).to_le_bytes());
        });
        sink.chunks += 1;
        Ok(())
    }
}

/// The thread that compresses and appends chunks, and the two channels to it: chunks go
/// there, and each comes back (emptied, for reuse) once it is in the file, or the error that
/// stopped the thread.
pub(super) struct ChunkWriter {
    to_thread: Option<SyncSender<Chunk>>,
    from_thread: Receiver<io::Result<Chunk>>,
    thread: Option<JoinHandle<Sink>>,
    /// A chunk was sent and has not come back yet.
    in_flight: bool,
}

impl ChunkWriter {
    /// Starts the thread, which appends to `sink`, compressing at zstd `level`.
    pub fn start(sink: Sink, level: i32) -> io::Result<Self> {
        let zstd = zstd::bulk::Compressor::new(level)?;
        let (to_thread, chunks) = sync_channel::<Chunk>(1);
        let (done, from_thread) = sync_channel(1);
        let mut compressor = Compressor {
            zstd,
            compressed: Vec::new(),
            out: Vec::new(),
        };
        let thread = std::thread::Builder::new()
            .name("mcap-writer".to_string())
            .spawn(move || {
                let mut sink = sink;
                for mut chunk in chunks {
                    match compressor.append(&mut sink, &chunk) {
                        Ok(()) => {
                            chunk.clear();
                            if done.send(Ok(chunk)).is_err() {
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

    /// Waits until the chunk in flight, if any, is in the file; returns it emptied.
    ///
    /// # Errors
    /// The error that stopped the thread.
    pub fn wait(&mut self) -> io::Result<Option<Chunk>> {
        if !self.in_flight {
            return Ok(None);
        }
        self.in_flight = false;
        match self.from_thread.recv() {
            Ok(result) => result.map(Some),
            Err(_) => Err(self.stopped()),
        }
    }

    /// Hands `chunk` to the thread, after waiting for the one in flight; returns that one,
    /// emptied, for reuse.
    ///
    /// # Errors
    /// The error that stopped the thread.
    pub fn send(&mut self, chunk: Chunk) -> io::Result<Option<Chunk>> {
        let spare = self.wait()?;
        let Some(to_thread) = &self.to_thread else {
            return Err(self.stopped());
        };
        if to_thread.send(chunk).is_err() {
            return Err(self.stopped());
        }
        self.in_flight = true;
        Ok(spare)
    }

    /// Waits for the chunk in flight, stops the thread and returns the file.
    ///
    /// # Errors
    /// The error that stopped the thread.
    pub fn finish(&mut self) -> io::Result<Sink> {
        self.wait()?;
        self.to_thread = None;
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(sink)) => Ok(sink),
            _ => Err(self.stopped()),
        }
    }

    /// The error for a thread that is gone without saying why (it panicked, or an earlier
    /// error was already reported).
    fn stopped(&self) -> io::Error {
        io::Error::other("the MCAP writer thread has stopped")
    }
}

impl Drop for ChunkWriter {
    fn drop(&mut self) {
        // Let the thread finish the chunk in flight and end.
        self.to_thread = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
