//! Reading logs, damaged ones included.
//!
//! [`for_each_message`] walks a file with the `mcap` crate's sans-I/O
//! [`mcap::sans_io::LinearReader`], which frames the records, checks the data and summary
//! sections' CRCs and the magic, and (a second one, on each chunk record) decompresses each
//! chunk and checks its CRC; the crate's `parse_record` parses every record. What this module
//! adds is what a killed run's log needs: where the damage is. The crate's readers stop at a
//! damaged record with an error that names no position (`unexpected end of file`, `bad chunk
//! CRC`); here the reader counts the bytes of every record it is handed, so a stop names the
//! byte offset of the record that could not be used, and what is wrong with it ([`Damage`]).
//!
//! A chunk is used whole or not at all, so the messages delivered are always the file's first
//! messages; the rule, its two limits (chunks without a CRC, private records) and the bounds
//! on work and memory are in `docs/logs.md`, section "Reading damaged logs".

use std::collections::{BTreeMap, HashMap};
use std::fmt;

use mcap::McapError;
use mcap::records::{Record, op};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

/// The MCAP magic, at the start and at the end of a file.
const MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// Opcode (1 byte) and length (8 bytes) in front of every record.
const RECORD_PREFIX: usize = 9;

/// Smallest limit on a chunk's decompressed size, bytes (the writer's chunks are about 1 MiB).
const MIN_DECOMPRESSED_LIMIT: u64 = 64 << 20;

/// Where and how an MCAP file is damaged. Its `Display` names the byte offset.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Damage {
    /// Byte offset in the file of the first record that could not be used (or of the end of
    /// the file, or of the closing magic): nothing at or after it was delivered.
    pub offset: u64,
    /// What is wrong there.
    pub problem: Problem,
}

/// What is wrong with a damaged MCAP file; see [`Damage`].
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum Problem {
    /// The file is shorter than the MCAP magic (the offset is its length).
    TooShort,
    /// The file does not start with the MCAP magic.
    NoMagic,
    /// The file ends inside a record.
    Truncated {
        /// The record's type, or `record` if not even its opcode is there.
        record: &'static str,
        /// Bytes missing to complete it.
        needs: u64,
    },
    /// The file ends after a complete record but without a Footer: its writer never finished.
    Unfinished,
    /// A record claims more bytes than the file has and more than any record can have: a
    /// corrupt length rather than a cut.
    TooLong {
        /// The record's type.
        record: &'static str,
        /// The length it states, bytes.
        len: u64,
        /// The largest this reader accepts, bytes.
        limit: u64,
    },
    /// An opcode the MCAP format does not define (a corrupt byte: this project's logs use
    /// only the format's own records).
    UnknownOpcode {
        /// The opcode.
        opcode: u8,
    },
    /// A record where the format does not allow it.
    Misplaced {
        /// The record's type.
        record: &'static str,
        /// Where it is, as a phrase ("after the Data End record").
        place: &'static str,
    },
    /// A record whose content does not parse.
    BadRecord {
        /// The record's type.
        record: &'static str,
        /// The parser's error.
        reason: String,
    },
    /// A chunk compressed with something this reader does not decompress.
    Compression {
        /// The chunk's compression name.
        name: String,
    },
    /// A chunk whose compressed data does not decompress, or not to its stated size.
    Decompression {
        /// The decompressor's error.
        reason: String,
    },
    /// A chunk whose content does not match the CRC in its header.
    ChunkCrc {
        /// The CRC in the chunk header.
        stored: u32,
        /// The CRC of the decompressed content.
        computed: u32,
    },
    /// A chunk whose content (CRC correct) holds a bad record.
    InChunk {
        /// What is wrong with it.
        reason: String,
    },
    /// The Data End record's CRC of everything before it does not match: some byte outside
    /// the chunks' contents (a record header, the metadata, a message index) is corrupt.
    DataCrc {
        /// The CRC in the Data End record.
        stored: u32,
        /// The CRC of the bytes before it.
        computed: u32,
    },
    /// The Footer's CRC of the summary section does not match.
    SummaryCrc {
        /// The CRC in the Footer.
        stored: u32,
        /// The CRC of the summary section.
        computed: u32,
    },
    /// The file does not end with the MCAP magic after its Footer.
    BadEndMagic,
    /// Bytes follow the closing magic.
    TrailingBytes {
        /// How many.
        count: u64,
    },
}

impl fmt::Display for Damage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let at = self.offset;
        match &self.problem {
            Problem::TooShort => write!(
                f,
                "the file has {at} bytes, fewer than the {} of the MCAP magic",
                MAGIC.len()
            ),
            Problem::NoMagic => write!(f, "the file does not start with the MCAP magic"),
            Problem::Truncated { record, needs } => write!(
                f,
                "truncated inside the {record} record at byte {at} (needs {needs} more bytes)"
            ),
            Problem::Unfinished => write!(
                f,
                "cut short at byte {at}: the file ends after a complete record but has no \
                 Footer (its writer did not finish)"
            ),
            Problem::TooLong { record, len, limit } => write!(
                f,
                "the {record} record at byte {at} states a length of {len} bytes, more than \
                 the file has and than the {limit} this reader accepts (a corrupt length)"
            ),
            Problem::UnknownOpcode { opcode } if *opcode >= 0x80 => write!(
                f,
                "record opcode {opcode:#04x} at byte {at}: a private record of another \
                 writer, or a corrupt opcode (private records are not skipped, so that a \
                 corrupt one never hides a chunk)"
            ),
            Problem::UnknownOpcode { opcode } => write!(
                f,
                "unknown record opcode {opcode:#04x} at byte {at} (a corrupt record)"
            ),
            Problem::Misplaced { record, place } => {
                write!(f, "a {record} record at byte {at} {place}")
            }
            Problem::BadRecord { record, reason } => {
                write!(f, "bad {record} record at byte {at}: {reason}")
            }
            Problem::Compression { name } => write!(
                f,
                "the Chunk record at byte {at} uses compression {name:?}, which this reader \
                 does not support"
            ),
            Problem::Decompression { reason } => write!(
                f,
                "the Chunk record at byte {at} does not decompress: {reason}"
            ),
            Problem::ChunkCrc { stored, computed } => write!(
                f,
                "CRC mismatch in the Chunk record at byte {at} (stored {stored:#010x}, \
                 computed {computed:#010x})"
            ),
            Problem::InChunk { reason } => write!(
                f,
                "the Chunk record at byte {at} holds a bad record: {reason}"
            ),
            Problem::DataCrc { stored, computed } => write!(
                f,
                "the data section's CRC in the Data End record at byte {at} does not match \
                 (stored {stored:#010x}, computed {computed:#010x}): a byte before it is corrupt"
            ),
            Problem::SummaryCrc { stored, computed } => write!(
                f,
                "the summary section's CRC in the Footer at byte {at} does not match \
                 (stored {stored:#010x}, computed {computed:#010x})"
            ),
            Problem::BadEndMagic => write!(
                f,
                "the file does not end with the MCAP magic (at byte {at}, after the Footer)"
            ),
            Problem::TrailingBytes { count } => {
                write!(
                    f,
                    "{count} bytes follow the closing MCAP magic, from byte {at}"
                )
            }
        }
    }
}

impl std::error::Error for Damage {}

/// What [`for_each_message`] read, and where it stopped if the file is damaged.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReadReport {
    /// File length, bytes.
    pub file_len: u64,
    /// The MCAP profile in the file's Header (`ros2` for this project's logs).
    pub profile: String,
    /// Chunks read and used (complete, CRC correct).
    pub chunks: u64,
    /// Messages delivered.
    pub messages: u64,
    /// Largest log time of the messages delivered, ns.
    pub last_time_ns: Option<u64>,
    /// The Data End record was read and its CRC matched: every message of the file was
    /// delivered, whatever [`damage`](Self::damage) says about the summary section after it.
    pub data_complete: bool,
    /// Where and why reading stopped early; `None` for a complete, intact file.
    pub damage: Option<Damage>,
}

impl ReadReport {
    /// `true` if the file is complete and intact.
    #[must_use]
    pub const fn is_complete(&self) -> bool {
        self.damage.is_none()
    }

    /// The messages read, as a phrase: "12345 messages up to t=12.340 s".
    #[must_use]
    pub fn messages_read(&self) -> String {
        let mut text = format!("{} message{}", self.messages, plural(self.messages));
        if let Some(t) = self.last_time_ns {
            text.push_str(&format!(" up to t={:.3} s", t as f64 * 1e-9));
        }
        text
    }
}

fn plural(n: u64) -> &'static str {
    if n == 1 { "" } else { "s" }
}

impl fmt::Display for ReadReport {
    /// `complete: 68 chunks, 686425 messages up to t=60.000 s`, or
    /// `damaged: <where and what>; read the 41 complete chunks before it: 12345 messages up
    /// to t=12.340 s`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (n, s) = (self.chunks, plural(self.chunks));
        let messages = self.messages_read();
        match &self.damage {
            None => write!(f, "complete: {n} chunk{s}, {messages}"),
            Some(d) if self.data_complete => write!(
                f,
                "damaged: {d}; every message was read before it: {n} chunk{s}, {messages}"
            ),
            Some(d) => write!(
                f,
                "damaged: {d}; read the {n} complete chunk{s} before it: {messages}"
            ),
        }
    }
}

/// A message as [`for_each_message`] hands it over.
#[derive(Debug, Clone, Copy)]
pub struct Message<'a> {
    /// Its channel's topic.
    pub topic: &'a str,
    /// Its channel's schema name (`can_msgs/msg/Frame`...); empty for a channel without one.
    pub schema: &'a str,
    /// Log time, ns.
    pub log_time: u64,
    /// Publish time, ns.
    pub publish_time: u64,
    /// The message's data (CDR in this project's logs).
    pub data: &'a [u8],
}

/// Messages a reader could not decode, by topic, and the first of them. Every command that
/// reads a log decodes through one and reports it: nothing is skipped in silence
/// (`docs/logs.md`, "Reading damaged logs").
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Undecodable {
    /// Messages not decoded, by topic.
    pub by_topic: BTreeMap<String, u64>,
    /// The first: topic, log time (ns) and why, the reason [`quote`](firmware::input::quote)d.
    pub first: Option<(String, u64, String)>,
}

impl Undecodable {
    /// `m`'s data decoded as `M`; `None`, counted, if it is not one.
    pub fn decode<M: crate::msg::RosMsg>(&mut self, m: &Message<'_>) -> Option<M> {
        match crate::msg::decode::<M>(m.data) {
            Ok(value) => Some(value),
            Err(e) => {
                self.count(m, &e);
                None
            }
        }
    }

    /// A `/can/rx` or `/can/tx` message's frame; `None`, counted, if the message does not
    /// decode or holds no valid CAN frame (identifier or length out of range).
    pub fn frame(&mut self, m: &Message<'_>) -> Option<firmware::CanFrame> {
        let frame = self.decode::<crate::msg::Frame>(m)?;
        let can = frame.to_can();
        if can.is_none() {
            self.count(
                m,
                &"not a valid CAN frame (identifier or length out of range)",
            );
        }
        can
    }

    /// Counts `m` as not decoded, for `why`.
    pub fn count(&mut self, m: &Message<'_>, why: &dyn fmt::Display) {
        *self.by_topic.entry(m.topic.to_string()).or_default() += 1;
        if self.first.is_none() {
            let why = firmware::input::quote(&why.to_string());
            self.first = Some((m.topic.to_string(), m.log_time, why));
        }
    }

    /// Messages not decoded in all.
    #[must_use]
    pub fn total(&self) -> u64 {
        self.by_topic.values().sum()
    }

    /// Messages of `topic` not decoded.
    #[must_use]
    pub fn on(&self, topic: &str) -> u64 {
        self.by_topic.get(topic).copied().unwrap_or(0)
    }
}

impl fmt::Display for Undecodable {
    /// `2 messages could not be decoded (/can/rx 1, /odom 1); the first: /can/rx at 1.234000 s:
    /// ...`, or `every message decoded`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Some((topic, t_ns, why)) = &self.first else {
            return f.write_str("every message decoded");
        };
        let topics: Vec<String> = self
            .by_topic
            .iter()
            .map(|(t, n)| format!("{t} {n}"))
            .collect();
        write!(
            f,
            "{} messages could not be decoded ({}); the first: {topic} at {:.6} s: {why}",
            self.total(),
            topics.join(", "),
            *t_ns as f64 * 1e-9
        )
    }
}

/// The name of a record type, as the MCAP specification writes it.
fn record_name(opcode: u8) -> &'static str {
    match opcode {
        op::HEADER => "Header",
        op::FOOTER => "Footer",
        op::SCHEMA => "Schema",
        op::CHANNEL => "Channel",
        op::MESSAGE => "Message",
        op::CHUNK => "Chunk",
        op::MESSAGE_INDEX => "Message Index",
        op::CHUNK_INDEX => "Chunk Index",
        op::ATTACHMENT => "Attachment",
        op::ATTACHMENT_INDEX => "Attachment Index",
        op::STATISTICS => "Statistics",
        op::METADATA => "Metadata",
        op::METADATA_INDEX => "Metadata Index",
        op::SUMMARY_OFFSET => "Summary Offset",
        op::DATA_END => "Data End",
        _ => "unknown",
    }
}

/// Records that may follow the Data End record (the summary section and the Footer).
const fn allowed_in_summary(opcode: u8) -> bool {
    matches!(
        opcode,
        op::SCHEMA
            | op::CHANNEL
            | op::CHUNK_INDEX
            | op::ATTACHMENT_INDEX
            | op::METADATA_INDEX
            | op::STATISTICS
            | op::SUMMARY_OFFSET
            | op::FOOTER
    )
}

/// A channel as the reader knows it.
struct ChannelInfo {
    topic: String,
    schema: String,
}

/// State of a walk through a file: channels and schemas.
#[derive(Default)]
struct Channels {
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, ChannelInfo>,
}

impl Channels {
    fn add(&mut self, record: &Record<'_>) {
        match record {
            Record::Schema { header, .. } => {
                self.schemas.insert(header.id, header.name.clone());
            }
            Record::Channel(c) => {
                let schema = self.schemas.get(&c.schema_id).cloned().unwrap_or_default();
                self.channels.insert(
                    c.id,
                    ChannelInfo {
                        topic: c.topic.clone(),
                        schema,
                    },
                );
            }
            _ => {}
        }
    }

    /// A message must be on a channel defined before it.
    fn check(&self, channel_id: u16) -> Result<(), String> {
        if self.channels.contains_key(&channel_id) {
            Ok(())
        } else {
            Err(format!(
                "a Message on channel {channel_id}, which has no Channel record before it"
            ))
        }
    }

    fn deliver(
        &self,
        header: &mcap::records::MessageHeader,
        data: &[u8],
        report: &mut ReadReport,
        f: &mut impl FnMut(&Message<'_>),
    ) {
        if let Some(c) = self.channels.get(&header.channel_id) {
            f(&Message {
                topic: &c.topic,
                schema: &c.schema,
                log_time: header.log_time,
                publish_time: header.publish_time,
                data,
            });
            report.messages += 1;
            report.last_time_ns = Some(
                report
                    .last_time_ns
                    .map_or(header.log_time, |t| t.max(header.log_time)),
            );
        }
    }

    /// Reads a chunk, whose whole record (prefix included) is `raw`, then delivers its
    /// messages: all of them, or none if anything in it is wrong.
    fn chunk(
        &mut self,
        header: &mcap::records::ChunkHeader,
        raw: &[u8],
        limit: u64,
        report: &mut ReadReport,
        f: &mut impl FnMut(&Message<'_>),
    ) -> Result<(), Problem> {
        if !matches!(header.compression.as_str(), "" | "zstd" | "lz4") {
            return Err(Problem::Compression {
                name: header.compression.clone(),
            });
        }
        if header.uncompressed_size > limit {
            return Err(Problem::TooLong {
                record: "Chunk's content",
                len: header.uncompressed_size,
                limit,
            });
        }
        let chunk_problem = |e: McapError| match e {
            McapError::BadChunkCrc { saved, calculated } => Problem::ChunkCrc {
                stored: saved,
                computed: calculated,
            },
            McapError::UnsupportedCompression(name) => Problem::Compression { name },
            McapError::ChunkTooLarge(len) => Problem::TooLong {
                record: "Chunk's content",
                len,
                limit,
            },
            McapError::DecompressionError(reason) => Problem::Decompression { reason },
            other @ (McapError::Io(_)
            | McapError::UnexpectedEoc
            | McapError::UnexpectedEof
            | McapError::BadChunkLength { .. }) => Problem::Decompression {
                reason: other.to_string(),
            },
            other => Problem::InChunk {
                reason: other.to_string(),
            },
        };
        // The crate's linear reader on this one record: it decompresses the chunk and checks
        // its CRC before it hands over any record in it, and refuses any record in it longer
        // than `limit` (its `ChunkReader` has no such bound, and a corrupt length inside a
        // chunk makes it try to allocate that much).
        let mut reader = LinearReader::new_with_options(
            LinearReaderOptions::default()
                .with_skip_start_magic(true)
                .with_skip_end_magic(true)
                .with_prevalidate_chunk_crcs(true)
                .with_record_length_limit(usize::try_from(limit).unwrap_or(usize::MAX)),
        );
        let mut fed = 0;
        let mut inner = Vec::new();
        while let Some(event) = reader.next_event() {
            match event.map_err(chunk_problem)? {
                LinearReadEvent::ReadRequest(need) => {
                    let n = need.min(raw.len() - fed);
                    reader.insert(n).copy_from_slice(&raw[fed..fed + n]);
                    reader.notify_read(n);
                    fed += n;
                }
                LinearReadEvent::Record { opcode, data } => {
                    let record = mcap::parse_record(opcode, data).map_err(chunk_problem)?;
                    inner.push(record.into_owned());
                }
            }
        }
        // First read and check every record, then deliver: a chunk is used whole or not at all.
        let mut records = Vec::new();
        let mut new_channels = Channels::default();
        for record in inner {
            match &record {
                Record::Schema { .. } | Record::Channel(_) => new_channels.add(&record),
                Record::Message { header, .. } => {
                    if self.check(header.channel_id).is_err() {
                        new_channels
                            .check(header.channel_id)
                            .map_err(|reason| Problem::InChunk { reason })?;
                    }
                }
                other => {
                    return Err(Problem::InChunk {
                        reason: format!(
                            "a {} record, which does not belong in a chunk",
                            record_name(other.opcode())
                        ),
                    });
                }
            }
            records.push(record);
        }
        for record in records {
            match record {
                Record::Schema { .. } | Record::Channel(_) => self.add(&record),
                Record::Message { header, data } => self.deliver(&header, &data, report, f),
                _ => {}
            }
        }
        Ok(())
    }
}

/// What a record that could not be read is: the opcode and the bytes missing, from the
/// record prefix at `pos` of `bytes` (the crate's reader says only "unexpected end of file").
fn truncation(bytes: &[u8], pos: usize) -> Problem {
    let rest = bytes.get(pos..).unwrap_or_default();
    let Some(&opcode) = rest.first() else {
        return Problem::Unfinished;
    };
    let record = record_name(opcode);
    let Some(len) = rest.get(1..RECORD_PREFIX) else {
        return Problem::Truncated {
            record,
            needs: (RECORD_PREFIX - rest.len()) as u64,
        };
    };
    let len = u64::from_le_bytes(len.try_into().unwrap_or_default());
    Problem::Truncated {
        record,
        needs: len.saturating_sub((rest.len() - RECORD_PREFIX) as u64),
    }
}

/// Bytes of a log read at most ([`read_log_file`]): 4 GiB, an hour of a robot's log about
/// seven times over; the runner's `--log-max-mb` rotates long sessions into smaller files.
pub const MAX_LOG_BYTES: u64 = 4 << 30;

/// A log file's bytes for [`for_each_message`], its magic checked first: a file that does not
/// begin with the MCAP magic is read no further than its first 8 bytes, which are returned
/// (so [`for_each_message`] names the problem, [`Problem::NoMagic`] or
/// [`Problem::TooShort`], without a 1 GB file that is not a log being read whole).
///
/// # Errors
/// The OS error, or [`std::io::ErrorKind::FileTooLarge`] past [`MAX_LOG_BYTES`].
pub fn read_log_file(path: &std::path::Path) -> std::io::Result<Vec<u8>> {
    let head = firmware::input::read_head(path, MAGIC.len() as u64)?;
    if head != MAGIC {
        return Ok(head);
    }
    firmware::input::read_bounded(path, MAX_LOG_BYTES)
}

/// Calls `f` for every message of an MCAP file in file order, and `meta(name, key-values)` for
/// every metadata record, and says what it read. A damaged file is read up to the first
/// damaged record (see the [module documentation](self) and `docs/logs.md`, section "Reading
/// damaged logs").
///
/// # Errors
/// [`Damage`] if nothing is readable: the file does not start with the MCAP magic and a
/// Header record. Any damage after the Header is not an error: the returned [`ReadReport`]
/// says where it is and what was read before it.
pub fn for_each_message(
    bytes: &[u8],
    mut f: impl FnMut(&Message<'_>),
    mut meta: impl FnMut(&str, &BTreeMap<String, String>),
) -> Result<ReadReport, Damage> {
    let file_len = bytes.len() as u64;
    let damage = |offset: usize, problem| Damage {
        offset: offset as u64,
        problem,
    };
    if bytes.len() < MAGIC.len() {
        return Err(if MAGIC.starts_with(bytes) {
            damage(bytes.len(), Problem::TooShort)
        } else {
            damage(0, Problem::NoMagic)
        });
    }
    if &bytes[..MAGIC.len()] != MAGIC {
        return Err(damage(0, Problem::NoMagic));
    }
    let limit = file_len.max(MIN_DECOMPRESSED_LIMIT);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_emit_chunks(true)
            .with_validate_data_section_crc(true)
            .with_validate_summary_section_crc(true)
            .with_check_finishes_after_end_magic(true)
            .with_record_length_limit(usize::try_from(limit).unwrap_or(usize::MAX)),
    );
    let mut channels = Channels::default();
    let mut report = ReadReport {
        file_len,
        ..ReadReport::default()
    };
    // Bytes handed to the reader, and the offset of the next record.
    let mut fed = 0usize;
    let mut pos = MAGIC.len();
    let mut header_read = false;
    let mut data_end_read = false;
    // The end of the Footer, once read: what follows is the closing magic.
    let mut footer_end: Option<usize> = None;
    let found = loop {
        let event = match reader.next_event() {
            None => break None,
            Some(Ok(event)) => event,
            Some(Err(e)) => {
                let problem = match e {
                    McapError::UnexpectedEof | McapError::BadMagic if footer_end.is_some() => {
                        let end = footer_end.unwrap_or(pos);
                        let tail = &bytes[end..];
                        let problem = if tail.len() < MAGIC.len() && MAGIC.starts_with(tail) {
                            Problem::Truncated {
                                record: "closing magic",
                                needs: (MAGIC.len() - tail.len()) as u64,
                            }
                        } else {
                            Problem::BadEndMagic
                        };
                        break Some(damage(end, problem));
                    }
                    McapError::UnexpectedEof if !header_read && pos == bytes.len() => {
                        Problem::Truncated {
                            record: "Header",
                            needs: RECORD_PREFIX as u64,
                        }
                    }
                    McapError::UnexpectedEof => truncation(bytes, pos),
                    McapError::BytesAfterEndMagic => {
                        let at = footer_end.unwrap_or(pos) + MAGIC.len();
                        break Some(damage(
                            at,
                            Problem::TrailingBytes {
                                count: (bytes.len() - at) as u64,
                            },
                        ));
                    }
                    McapError::RecordTooLarge { opcode, len } => Problem::TooLong {
                        record: record_name(opcode),
                        len,
                        limit,
                    },
                    McapError::BadDataCrc { saved, calculated } => Problem::DataCrc {
                        stored: saved,
                        computed: calculated,
                    },
                    McapError::BadSummaryCrc { saved, calculated } => Problem::SummaryCrc {
                        stored: saved,
                        computed: calculated,
                    },
                    other => Problem::BadRecord {
                        record: record_name(bytes.get(pos).copied().unwrap_or(0)),
                        reason: other.to_string(),
                    },
                };
                break Some(damage(pos, problem));
            }
        };
        let (opcode, content) = match event {
            LinearReadEvent::ReadRequest(need) => {
                let n = need.min(bytes.len() - fed);
                reader.insert(n).copy_from_slice(&bytes[fed..fed + n]);
                reader.notify_read(n);
                fed += n;
                continue;
            }
            LinearReadEvent::Record { opcode, data } => (opcode, data),
        };
        let record = record_name(opcode);
        let end = pos + RECORD_PREFIX + content.len();
        if !(op::HEADER..=op::DATA_END).contains(&opcode) {
            break Some(damage(pos, Problem::UnknownOpcode { opcode }));
        }
        if data_end_read && !allowed_in_summary(opcode) {
            break Some(damage(
                pos,
                Problem::Misplaced {
                    record,
                    place: "after the Data End record",
                },
            ));
        }
        let parsed = match mcap::parse_record(opcode, content) {
            Ok(r) => r,
            Err(e) => {
                break Some(damage(
                    pos,
                    Problem::BadRecord {
                        record,
                        reason: e.to_string(),
                    },
                ));
            }
        };
        if !header_read {
            let Record::Header(h) = parsed else {
                break Some(damage(
                    pos,
                    Problem::Misplaced {
                        record,
                        place: "where the file's first record, a Header, belongs",
                    },
                ));
            };
            report.profile = h.profile;
            header_read = true;
            pos = end;
            continue;
        }
        match parsed {
            Record::Chunk { header, .. } => {
                let raw = &bytes[pos..end];
                let result = channels.chunk(&header, raw, limit, &mut report, &mut f);
                if let Err(problem) = result {
                    break Some(damage(pos, problem));
                }
                report.chunks += 1;
            }
            Record::Schema { .. } | Record::Channel(_) => channels.add(&parsed),
            Record::Message { header, data } => {
                if let Err(reason) = channels.check(header.channel_id) {
                    break Some(damage(pos, Problem::BadRecord { record, reason }));
                }
                channels.deliver(&header, &data, &mut report, &mut f);
            }
            Record::Metadata(m) => meta(&m.name, &m.metadata),
            Record::DataEnd(_) => {
                // The reader checked its CRC before handing it over.
                report.data_complete = true;
                data_end_read = true;
            }
            Record::Footer(_) => footer_end = Some(end),
            _ => {}
        }
        pos = end;
    };
    // The reader ends without an error at the end of the file only after the closing magic.
    let found = found.or_else(|| (footer_end.is_none()).then(|| damage(pos, Problem::Unfinished)));
    match found {
        Some(d) if !header_read => Err(d),
        found => {
            report.damage = found;
            Ok(report)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(opcode: u8, content: &[u8]) -> Vec<u8> {
        let mut r = vec![opcode];
        r.extend_from_slice(&(content.len() as u64).to_le_bytes());
        r.extend_from_slice(content);
        r
    }

    fn string(s: &str) -> Vec<u8> {
        let mut v = (s.len() as u32).to_le_bytes().to_vec();
        v.extend_from_slice(s.as_bytes());
        v
    }

    /// Magic, Header, `middle`, Data End (no CRC), an empty Footer, magic.
    fn file_with(middle: &[u8]) -> Vec<u8> {
        let mut f = MAGIC.to_vec();
        f.extend(record(
            op::HEADER,
            &[string("ros2"), string("test")].concat(),
        ));
        f.extend_from_slice(middle);
        f.extend(record(op::DATA_END, &0u32.to_le_bytes()));
        f.extend(record(op::FOOTER, &[0u8; 20]));
        f.extend_from_slice(MAGIC);
        f
    }

    fn read(bytes: &[u8]) -> Result<ReadReport, Damage> {
        for_each_message(bytes, |_| {}, |_, _| {})
    }

    #[test]
    fn private_records_are_reported_with_what_they_may_be() {
        for opcode in [0x80u8, 0xF0] {
            let file = file_with(&record(opcode, &[1, 2, 3, 4]));
            let report = read(&file).unwrap();
            let damage = report.damage.expect("damage");
            assert!(
                matches!(damage.problem, Problem::UnknownOpcode { opcode: o } if o == opcode),
                "{damage}"
            );
            assert_eq!(damage.offset, 8 + 9 + 16);
            assert!(damage.to_string().contains("private record"), "{damage}");
        }
        let report = read(&file_with(&record(0x7F, &[]))).unwrap();
        let damage = report.damage.expect("damage");
        assert!(damage.to_string().contains("a corrupt record"), "{damage}");
        // The frame around them is well formed: without them the file is intact.
        let report = read(&file_with(&[])).unwrap();
        assert!(report.is_complete() && report.data_complete, "{report}");
        assert_eq!(report.profile, "ros2");
    }

    #[test]
    fn the_end_of_a_file_is_checked_to_the_last_byte() {
        let file = file_with(&[]);
        let n = file.len();
        // The closing magic cut, wrong, or followed by more bytes.
        let d = read(&file[..n - 3]).unwrap().damage.unwrap();
        assert_eq!(d.offset as usize, n - 8);
        assert!(
            matches!(
                d.problem,
                Problem::Truncated {
                    record: "closing magic",
                    needs: 3
                }
            ),
            "{d}"
        );
        let mut bad = file.clone();
        bad[n - 1] ^= 1;
        let d = read(&bad).unwrap().damage.unwrap();
        assert_eq!(
            (d.offset as usize, &d.problem),
            (n - 8, &Problem::BadEndMagic)
        );
        let mut long = file.clone();
        long.extend_from_slice(b"xyz");
        let d = read(&long).unwrap().damage.unwrap();
        assert_eq!(
            (d.offset as usize, &d.problem),
            (n, &Problem::TrailingBytes { count: 3 })
        );
        // Cut inside the Footer: how much it lacks.
        let d = read(&file[..n - 8 - 5]).unwrap().damage.unwrap();
        assert!(
            matches!(
                d.problem,
                Problem::Truncated {
                    record: "Footer",
                    needs: 5
                }
            ),
            "{d}"
        );
        // Cut between records: unfinished.
        let d = read(&file[..n - 8 - 29]).unwrap().damage.unwrap();
        assert_eq!(d.problem, Problem::Unfinished, "{d}");
    }
}
