//! The MCAP file itself: [`McapFile`] writes the records of the specification's data section
//! (header, metadata, schemas, channels, chunks of messages with their message indexes) and
//! the summary (schemas, channels, statistics, chunk and metadata indexes, summary offsets,
//! footer), with every CRC.
//!
//! Written here rather than by the `mcap` crate's `Writer`, whose record types (their binrw
//! encodings) it uses for every record but the two hot ones: that writer hands zstd each
//! record field by field (seven streaming calls a message, 2.5 million for the 60 s square,
//! which were 28 % of the writing thread, `docs/benchmarks.md`, "The cost of logging") and
//! cannot take a chunk built whole. Here a message is appended to the open chunk's buffer
//! (its CDR encoded in place), and the chunk is compressed in one call when it closes.
//! Messages and message indexes are framed by hand: fixed little-endian fields, written
//! millions of times. The files are read back by the `mcap` crate's reader and by the
//! Python `mcap` and `rosbags` readers in the tests.

use std::collections::BTreeMap;
use std::io::{self, Cursor, Write};

use binrw::BinWrite;
use mcap::records::{
    self, ChunkHeader, ChunkIndex, DataEnd, MessageIndexEntry, Metadata, MetadataIndex,
    SchemaHeader, Statistics, SummaryOffset,
};

/// Record opcodes (the specification's).
mod op {
    pub const HEADER: u8 = 0x01;
    pub const FOOTER: u8 = 0x02;
    pub const SCHEMA: u8 = 0x03;
    pub const CHANNEL: u8 = 0x04;
    pub const MESSAGE: u8 = 0x05;
    pub const CHUNK: u8 = 0x06;
    pub const MESSAGE_INDEX: u8 = 0x07;
    pub const CHUNK_INDEX: u8 = 0x08;
    pub const STATISTICS: u8 = 0x0B;
    pub const METADATA: u8 = 0x0C;
    pub const METADATA_INDEX: u8 = 0x0D;
    pub const SUMMARY_OFFSET: u8 = 0x0E;
    pub const DATA_END: u8 = 0x0F;
}

/// A Message record's header: channel id, sequence, log time, publish time.
const MESSAGE_HEADER_LEN: usize = 2 + 4 + 8 + 8;

/// The opcode and the length before a record's body.
const RECORD_PREFIX_LEN: usize = 1 + 8;

/// A channel's messages: the open chunk's index entries, and the count in the file.
#[derive(Default)]
struct Slot {
    entries: Vec<MessageIndexEntry>,
    messages: u64,
}

/// An MCAP file being written to `W`, sequentially (no seeking).
pub(super) struct McapFile<W: Write> {
    out: W,
    /// Bytes written so far: the next record's offset.
    pos: u64,
    /// CRC of the section being written (data, then summary).
    crc: crc32fast::Hasher,
    /// The open chunk's records, uncompressed.
    chunk: Vec<u8>,
    /// Size at which a chunk is closed before the next message, bytes.
    chunk_size: usize,
    /// Log times of the open chunk's earliest and latest message.
    chunk_times: Option<(u64, u64)>,
    /// Each added channel's messages, by channel id (`None`: no such channel).
    slots: Vec<Option<Slot>>,
    zstd: zstd::bulk::Compressor<'static>,
    compressed: Vec<u8>,
    /// A record body being encoded.
    scratch: Vec<u8>,
    /// For the summary: the schemas (header and text) and channels, in id order.
    schemas: BTreeMap<u16, (SchemaHeader, Vec<u8>)>,
    channels: BTreeMap<u16, records::Channel>,
    chunk_indexes: Vec<ChunkIndex>,
    metadata_indexes: Vec<MetadataIndex>,
    /// Log times of the file's earliest and latest message.
    times: Option<(u64, u64)>,
    finished: bool,
}

fn encode_err(e: binrw::Error) -> io::Error {
    io::Error::other(e)
}

fn span(times: Option<(u64, u64)>, t: u64) -> (u64, u64) {
    times.map_or((t, t), |(lo, hi)| (lo.min(t), hi.max(t)))
}

impl<W: Write> McapFile<W> {
    /// Starts the file on `out`: the magic and the Header record. Chunks are zstd at `level`,
    /// closed before the message that finds `chunk_size` uncompressed bytes in them.
    pub(super) fn new(
        out: W,
        profile: &str,
        library: &str,
        level: i32,
        chunk_size: u64,
    ) -> io::Result<Self> {
        let mut file = Self {
            out,
            pos: 0,
            crc: crc32fast::Hasher::new(),
            chunk: Vec::new(),
            chunk_size: usize::try_from(chunk_size).unwrap_or(usize::MAX),
            chunk_times: None,
            slots: Vec::new(),
            zstd: zstd::bulk::Compressor::new(level)?,
            compressed: Vec::new(),
            scratch: Vec::new(),
            schemas: BTreeMap::new(),
            channels: BTreeMap::new(),
            chunk_indexes: Vec::new(),
            metadata_indexes: Vec::new(),
            times: None,
            finished: false,
        };
        file.put(mcap::MAGIC)?;
        let header = records::Header {
            profile: profile.to_string(),
            library: library.to_string(),
        };
        file.record(op::HEADER, &header)?;
        Ok(file)
    }

    /// Writes `bytes` to the file, counted and in the section's CRC.
    fn put(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.out.write_all(bytes)?;
        self.crc.update(bytes);
        self.pos += bytes.len() as u64;
        Ok(())
    }

    /// Writes the record `body` (encoded by the `mcap` crate's binrw type), then `tail`.
    fn record_with<B>(&mut self, op: u8, body: &B, tail: &[u8]) -> io::Result<()>
    where
        B: for<'a> BinWrite<Args<'a> = ()>,
    {
        let mut scratch = std::mem::take(&mut self.scratch);
        scratch.clear();
        body.write_le(&mut Cursor::new(&mut scratch))
            .map_err(encode_err)?;
        let len = (scratch.len() + tail.len()) as u64;
        let result = self
            .put(&[op])
            .and_then(|()| self.put(&len.to_le_bytes()))
            .and_then(|()| self.put(&scratch))
            .and_then(|()| self.put(tail));
        self.scratch = scratch;
        result
    }

    fn record<B>(&mut self, op: u8, body: &B) -> io::Result<()>
    where
        B: for<'a> BinWrite<Args<'a> = ()>,
    {
        self.record_with(op, body, &[])
    }

    /// A Schema record, `id` from 1.
    pub(super) fn add_schema(
        &mut self,
        id: u16,
        name: &str,
        encoding: &str,
        text: &[u8],
    ) -> io::Result<()> {
        let header = SchemaHeader {
            id,
            name: name.to_string(),
            encoding: encoding.to_string(),
        };
        self.schema_record(&header, text)?;
        self.schemas.insert(id, (header, text.to_vec()));
        Ok(())
    }

    /// A Schema record: the header, then the text with its length.
    fn schema_record(&mut self, header: &SchemaHeader, text: &[u8]) -> io::Result<()> {
        let mut tail = u32::try_from(text.len())
            .map_err(io::Error::other)?
            .to_le_bytes()
            .to_vec();
        tail.extend_from_slice(text);
        self.record_with(op::SCHEMA, header, &tail)
    }

    /// A Channel record, without channel metadata.
    pub(super) fn add_channel(
        &mut self,
        id: u16,
        schema_id: u16,
        topic: &str,
        message_encoding: &str,
    ) -> io::Result<()> {
        let channel = records::Channel {
            id,
            schema_id,
            topic: topic.to_string(),
            message_encoding: message_encoding.to_string(),
            metadata: BTreeMap::new(),
        };
        self.record(op::CHANNEL, &channel)?;
        self.channels.insert(id, channel);
        let id = usize::from(id);
        if self.slots.len() <= id {
            self.slots.resize_with(id + 1, || None);
        }
        self.slots[id].get_or_insert_with(Slot::default);
        Ok(())
    }

    /// A Metadata record (between chunks: the open one is closed first), indexed in the
    /// summary.
    pub(super) fn write_metadata(&mut self, metadata: &Metadata) -> io::Result<()> {
        self.end_chunk()?;
        let offset = self.pos;
        self.record(op::METADATA, metadata)?;
        self.metadata_indexes.push(MetadataIndex {
            offset,
            length: self.pos - offset,
            name: metadata.name.clone(),
        });
        Ok(())
    }

    /// Appends a message on channel `channel_id` (added before) to the open chunk, its data
    /// written in place by `encode`; returns the data as written.
    ///
    /// # Errors
    /// Closing the full chunk before it failed.
    pub(super) fn message(
        &mut self,
        channel_id: u16,
        log_ns: u64,
        publish_ns: u64,
        encode: impl FnOnce(&mut Vec<u8>),
    ) -> io::Result<&[u8]> {
        let id = usize::from(channel_id);
        if !matches!(self.slots.get(id), Some(Some(_))) {
            return Err(io::Error::other(format!(
                "no channel {channel_id} in this log"
            )));
        }
        if self.chunk.len() > self.chunk_size {
            self.end_chunk()?;
        }
        let start = self.chunk.len();
        let mut header = [0u8; RECORD_PREFIX_LEN + MESSAGE_HEADER_LEN];
        header[0] = op::MESSAGE;
        // header[1..9]: the record's length, once the data is in (below).
        header[9..11].copy_from_slice(&channel_id.to_le_bytes());
        // header[11..15]: the sequence, 0: the specification's "recorded as zero" for messages
        // whose publisher assigns none. A global count costs 0.9 MB (8 %) of the 60 s square's
        // log.
        header[15..23].copy_from_slice(&log_ns.to_le_bytes());
        header[23..31].copy_from_slice(&publish_ns.to_le_bytes());
        self.chunk.extend_from_slice(&header);
        let data = self.chunk.len();
        encode(&mut self.chunk);
        let len = (self.chunk.len() - start - RECORD_PREFIX_LEN) as u64;
        self.chunk[start + 1..start + RECORD_PREFIX_LEN].copy_from_slice(&len.to_le_bytes());
        if let Some(Some(slot)) = self.slots.get_mut(id) {
            slot.entries.push(MessageIndexEntry {
                log_time: log_ns,
                offset: start as u64,
            });
            slot.messages += 1;
        }
        self.chunk_times = Some(span(self.chunk_times, log_ns));
        self.times = Some(span(self.times, log_ns));
        Ok(&self.chunk[data..])
    }

    /// Closes the open chunk, if it has messages: the Chunk record, compressed in one call,
    /// then a Message Index record per channel in it.
    fn end_chunk(&mut self) -> io::Result<()> {
        let Some((start, end)) = self.chunk_times.take() else {
            return Ok(());
        };
        let uncompressed_crc = crc32fast::hash(&self.chunk);
        self.compressed.clear();
        self.compressed
            .reserve(zstd::zstd_safe::compress_bound(self.chunk.len()));
        self.zstd
            .compress_to_buffer(&self.chunk, &mut self.compressed)?;
        let header = ChunkHeader {
            message_start_time: start,
            message_end_time: end,
            uncompressed_size: self.chunk.len() as u64,
            uncompressed_crc,
            compression: "zstd".to_string(),
            compressed_size: self.compressed.len() as u64,
        };
        let chunk_start_offset = self.pos;
        let compressed = std::mem::take(&mut self.compressed);
        let written = self.record_with(op::CHUNK, &header, &compressed);
        self.compressed = compressed;
        written?;
        let chunk_length = self.pos - chunk_start_offset;
        let index_start = self.pos;
        let mut message_index_offsets = BTreeMap::new();
        let mut slots = std::mem::take(&mut self.slots);
        let mut buf = std::mem::take(&mut self.scratch);
        let mut result = Ok(());
        for (id, slot) in slots.iter_mut().enumerate() {
            let Some(Slot { entries, .. }) = slot else {
                continue;
            };
            if entries.is_empty() || result.is_err() {
                entries.clear();
                continue;
            }
            // Channel id, then the entries' byte length and the entries (log time, offset).
            let body = 2 + 4 + entries.len() * 16;
            buf.clear();
            buf.push(op::MESSAGE_INDEX);
            buf.extend_from_slice(&(body as u64).to_le_bytes());
            buf.extend_from_slice(&(id as u16).to_le_bytes());
            buf.extend_from_slice(&((entries.len() * 16) as u32).to_le_bytes());
            for e in entries.drain(..) {
                buf.extend_from_slice(&e.log_time.to_le_bytes());
                buf.extend_from_slice(&e.offset.to_le_bytes());
            }
            message_index_offsets.insert(id as u16, self.pos);
            result = self.put(&buf);
        }
        self.slots = slots;
        self.scratch = buf;
        result?;
        self.chunk_indexes.push(ChunkIndex {
            message_start_time: start,
            message_end_time: end,
            chunk_start_offset,
            chunk_length,
            message_index_offsets,
            message_index_length: self.pos - index_start,
            compression: header.compression,
            compressed_size: header.compressed_size,
            uncompressed_size: header.uncompressed_size,
        });
        self.chunk.clear();
        Ok(())
    }

    /// Closes the open chunk and flushes the file: a reader of the file sees every message
    /// so far.
    pub(super) fn flush(&mut self) -> io::Result<()> {
        self.end_chunk()?;
        self.out.flush()
    }

    /// Ends the file: the last chunk, the Data End record, the summary and the footer. Does
    /// nothing the second time.
    pub(super) fn finish(&mut self) -> io::Result<()> {
        if self.finished {
            return Ok(());
        }
        self.end_chunk()?;
        self.finished = true;
        let data_section_crc = std::mem::take(&mut self.crc).finalize();
        self.record(op::DATA_END, &DataEnd { data_section_crc })?;
        self.crc = crc32fast::Hasher::new();
        let summary_start = self.pos;
        let mut offsets = Vec::new();
        let mut group = |file: &mut Self, opcode: u8, start: u64| {
            if file.pos > start {
                offsets.push(SummaryOffset {
                    group_opcode: opcode,
                    group_start: start,
                    group_length: file.pos - start,
                });
            }
        };
        let schema_count = self.schemas.len() as u16;
        let start = self.pos;
        for (header, text) in std::mem::take(&mut self.schemas).into_values() {
            self.schema_record(&header, &text)?;
        }
        group(self, op::SCHEMA, start);
        let start = self.pos;
        let channels = std::mem::take(&mut self.channels);
        for channel in channels.values() {
            self.record(op::CHANNEL, channel)?;
        }
        group(self, op::CHANNEL, start);
        let start = self.pos;
        let (message_start_time, message_end_time) = self.times.unwrap_or((0, 0));
        let channel_message_counts: BTreeMap<u16, u64> = (self.slots.iter().enumerate())
            .filter_map(|(id, slot)| Some((id as u16, slot.as_ref()?.messages)))
            .filter(|(_, n)| *n > 0)
            .collect();
        let stats = Statistics {
            message_count: channel_message_counts.values().sum(),
            schema_count,
            channel_count: channels.len() as u32,
            attachment_count: 0,
            metadata_count: self.metadata_indexes.len() as u32,
            chunk_count: self.chunk_indexes.len() as u32,
            message_start_time,
            message_end_time,
            channel_message_counts,
        };
        self.record(op::STATISTICS, &stats)?;
        group(self, op::STATISTICS, start);
        let start = self.pos;
        for index in std::mem::take(&mut self.chunk_indexes) {
            self.record(op::CHUNK_INDEX, &index)?;
        }
        group(self, op::CHUNK_INDEX, start);
        let start = self.pos;
        for index in std::mem::take(&mut self.metadata_indexes) {
            self.record(op::METADATA_INDEX, &index)?;
        }
        group(self, op::METADATA_INDEX, start);
        let summary_offset_start = self.pos;
        for offset in &offsets {
            self.record(op::SUMMARY_OFFSET, offset)?;
        }
        // The footer's CRC covers the summary and the footer up to the CRC itself.
        self.put(&[op::FOOTER])?;
        self.put(&20u64.to_le_bytes())?;
        self.put(&summary_start.to_le_bytes())?;
        self.put(&summary_offset_start.to_le_bytes())?;
        let summary_crc = std::mem::take(&mut self.crc).finalize();
        self.put(&summary_crc.to_le_bytes())?;
        self.put(mcap::MAGIC)?;
        self.out.flush()
    }

    /// The file's writer, once finished.
    pub(super) fn into_inner(self) -> W {
        self.out
    }
}
