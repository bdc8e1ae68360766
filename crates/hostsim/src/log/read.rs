//! Reading MCAP logs, damaged ones included.
//!
//! [`for_each_message`] walks a file record by record and hands every message to a closure.
//! It reads whatever a log is: complete, cut short by a killed run, or with flipped bytes.
//!
//! # Whole chunks or nothing
//!
//! Messages live in chunks. A chunk is used only whole: its record must be complete, it must
//! decompress to the size its header states, its CRC must match, and every record inside it
//! must parse; only then are its messages delivered. Reading stops at the first record that
//! cannot be used, and [`ReadReport::damage`] says where (the byte offset of that record) and
//! what is wrong, while the counts say what was read before it. So the messages delivered are
//! always the file's first messages, in whole chunks, and never anything from a damaged chunk
//! or after it: a log replayed from them has no hole in its time line.
//!
//! One limit: a chunk whose writer left its CRC out (0, "not computed", which the
//! specification allows) cannot be checked by itself. Its flipped bytes show only at the Data
//! End record, whose CRC covers the whole data section, and by then its messages have been
//! delivered; the report names the damage, but the messages before it are not all
//! trustworthy. hostsim's own logs always carry chunk CRCs.
//!
//! A second, chosen one: private records (opcodes 0x80-0xFF, which the specification lets a
//! reader skip) are reported as damage, not skipped. A flipped opcode byte turns a chunk into
//! such a record, and skipping it would drop that chunk silently and deliver the ones after
//! it: the file's messages would no longer be a prefix. hostsim writes no private records;
//! the message says what the record may be.
//!
//! Checked besides the chunks: the record framing (a known opcode; a length within the file),
//! the record contents (the `mcap` crate's parser), the data section CRC (in the Data End
//! record, which covers the records outside chunks), the summary section CRC (in the Footer)
//! and the closing magic. A file that ends after a complete record without a Footer (its writer
//! never finished) is reported as damaged too: that is what a killed run leaves.
//!
//! Work and memory are bounded by the file: records are slices of it, and a chunk is
//! decompressed only if its stated size is at most max(64 MiB, file length).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fmt;

use mcap::records::{ChunkHeader, MessageHeader, Record, op};

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
    /// An opcode the MCAP format does not define (a corrupt byte: hostsim logs use only the
    /// format's own records).
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
    /// A chunk compressed with something other than zstd (or nothing).
    Compression {
        /// The chunk's compression name.
        name: String,
    },
    /// A chunk whose compressed data does not decompress (or not within its stated size).
    Decompression {
        /// The decompressor's error.
        reason: String,
    },
    /// A chunk that decompresses to a size other than the one its header states.
    ChunkSize {
        /// Stated in the chunk header, bytes.
        stated: u64,
        /// Decompressed, bytes.
        actual: u64,
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
        /// Offset of the bad record in the decompressed content.
        at: u64,
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
            Problem::ChunkSize { stated, actual } => write!(
                f,
                "the Chunk record at byte {at} decompresses to {actual} bytes, not the \
                 {stated} its header states"
            ),
            Problem::ChunkCrc { stored, computed } => write!(
                f,
                "CRC mismatch in the Chunk record at byte {at} (stored {stored:#010x}, \
                 computed {computed:#010x})"
            ),
            Problem::InChunk { at: inner, reason } => write!(
                f,
                "the Chunk record at byte {at} holds a bad record at byte {inner} of its \
                 content: {reason}"
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

/// The record at `pos` of `buf` (`pos < buf.len()`): its opcode and content.
fn record_at(buf: &[u8], pos: usize, limit: u64) -> Result<(u8, &[u8]), Problem> {
    let rest = buf.get(pos..).unwrap_or_default();
    let Some(&opcode) = rest.first() else {
        return Err(Problem::Truncated {
            record: "record",
            needs: RECORD_PREFIX as u64,
        });
    };
    if !(op::HEADER..=op::DATA_END).contains(&opcode) {
        return Err(Problem::UnknownOpcode { opcode });
    }
    let record = record_name(opcode);
    let Some(len) = rest.get(1..RECORD_PREFIX) else {
        return Err(Problem::Truncated {
            record,
            needs: (RECORD_PREFIX - rest.len()) as u64,
        });
    };
    let mut le = [0u8; 8];
    le.copy_from_slice(len);
    let len = u64::from_le_bytes(le);
    let available = (rest.len() - RECORD_PREFIX) as u64;
    if len > available {
        return Err(if len > limit {
            Problem::TooLong { record, len, limit }
        } else {
            Problem::Truncated {
                record,
                needs: len - available,
            }
        });
    }
    // len <= available, which is a slice length: it fits in usize.
    let end = RECORD_PREFIX + len as usize;
    Ok((opcode, &rest[RECORD_PREFIX..end]))
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

/// Calls `f(topic, log_time_ns, data)` for every message of an MCAP file in file order, and
/// `meta(name, key-values)` for every metadata record, and says what it read. See the
/// [module documentation](self): a damaged file is read up to the first damaged record.
///
/// # Errors
/// [`Damage`] if nothing is readable: the file does not start with the MCAP magic and a
/// Header record. Any damage after the Header is not an error: the returned
/// [`ReadReport`] says where it is and what was read before it.
pub fn for_each_message(
    bytes: &[u8],
    mut f: impl FnMut(&str, u64, &[u8]),
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
    let mut reader = Reader::default();
    let mut report = ReadReport {
        file_len,
        ..ReadReport::default()
    };
    let mut pos = MAGIC.len();
    let mut header_read = false;
    // End of the Data End record, where the summary section starts.
    let mut data_end: Option<usize> = None;
    let found = loop {
        if pos == bytes.len() {
            break if header_read {
                Some(damage(pos, Problem::Unfinished))
            } else {
                Some(damage(
                    pos,
                    Problem::Truncated {
                        record: "Header",
                        needs: RECORD_PREFIX as u64,
                    },
                ))
            };
        }
        let (opcode, content) = match record_at(bytes, pos, limit) {
            Ok(r) => r,
            Err(problem) => break Some(damage(pos, problem)),
        };
        let record = record_name(opcode);
        let end = pos + RECORD_PREFIX + content.len();
        if data_end.is_some() && !allowed_in_summary(opcode) {
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
            if !matches!(parsed, Record::Header(_)) {
                break Some(damage(
                    pos,
                    Problem::Misplaced {
                        record,
                        place: "where the file's first record, a Header, belongs",
                    },
                ));
            }
            header_read = true;
            pos = end;
            continue;
        }
        match parsed {
            Record::Chunk { header, data } => {
                if let Err(problem) = reader.chunk(&header, &data, limit, &mut report, &mut f) {
                    break Some(damage(pos, problem));
                }
                report.chunks += 1;
            }
            Record::Channel(c) => {
                reader.topics.insert(c.id, c.topic);
            }
            Record::Message { header, data } => {
                if let Err(reason) = reader.check_channel(&header, &HashSet::new()) {
                    break Some(damage(pos, Problem::BadRecord { record, reason }));
                }
                reader.deliver(&header, &data, &mut report, &mut f);
            }
            Record::Metadata(m) => meta(&m.name, &m.metadata),
            Record::DataEnd(d) => {
                if d.data_section_crc != 0 {
                    let computed = crc32fast::hash(&bytes[..pos]);
                    if computed != d.data_section_crc {
                        break Some(damage(
                            pos,
                            Problem::DataCrc {
                                stored: d.data_section_crc,
                                computed,
                            },
                        ));
                    }
                }
                report.data_complete = true;
                data_end = Some(end);
            }
            Record::Footer(footer) => break check_end(bytes, pos, end, data_end, &footer),
            _ => {}
        }
        pos = end;
    };
    match found {
        Some(d) if !header_read => Err(d),
        found => {
            report.damage = found;
            Ok(report)
        }
    }
}

/// Checks the summary CRC of the Footer at `pos` (ending at `end`) and the closing magic.
fn check_end(
    bytes: &[u8],
    pos: usize,
    end: usize,
    data_end: Option<usize>,
    footer: &mcap::records::Footer,
) -> Option<Damage> {
    let damage = |offset: usize, problem| {
        Some(Damage {
            offset: offset as u64,
            problem,
        })
    };
    // The summary CRC covers the summary section and the Footer up to the CRC itself (its
    // opcode, length, summary start and summary offset start).
    if let Some(start) = data_end
        && footer.summary_crc != 0
    {
        let covered = bytes
            .get(start..pos + RECORD_PREFIX + 16)
            .unwrap_or_default();
        let computed = crc32fast::hash(covered);
        if computed != footer.summary_crc {
            return damage(
                pos,
                Problem::SummaryCrc {
                    stored: footer.summary_crc,
                    computed,
                },
            );
        }
    }
    let tail = &bytes[end..];
    if tail.len() < MAGIC.len() {
        if MAGIC.starts_with(tail) {
            return damage(
                end,
                Problem::Truncated {
                    record: "closing magic",
                    needs: (MAGIC.len() - tail.len()) as u64,
                },
            );
        }
        return damage(end, Problem::BadEndMagic);
    }
    if &tail[..MAGIC.len()] != MAGIC {
        return damage(end, Problem::BadEndMagic);
    }
    if tail.len() > MAGIC.len() {
        return damage(
            end + MAGIC.len(),
            Problem::TrailingBytes {
                count: (tail.len() - MAGIC.len()) as u64,
            },
        );
    }
    None
}

/// State of a walk through a file: topics by channel, the decompressor and its buffer.
#[derive(Default)]
struct Reader {
    topics: HashMap<u16, String>,
    zstd: Option<zstd::bulk::Decompressor<'static>>,
    content: Vec<u8>,
}

impl Reader {
    /// A message must be on a channel defined before it: earlier in the file, or earlier in
    /// its own chunk (`in_chunk`).
    fn check_channel(&self, header: &MessageHeader, in_chunk: &HashSet<u16>) -> Result<(), String> {
        if self.topics.contains_key(&header.channel_id) || in_chunk.contains(&header.channel_id) {
            Ok(())
        } else {
            Err(format!(
                "a Message on channel {}, which has no Channel record before it",
                header.channel_id
            ))
        }
    }

    fn deliver(
        &self,
        header: &MessageHeader,
        data: &[u8],
        report: &mut ReadReport,
        f: &mut impl FnMut(&str, u64, &[u8]),
    ) {
        if let Some(topic) = self.topics.get(&header.channel_id) {
            f(topic, header.log_time, data);
            report.messages += 1;
            report.last_time_ns = Some(
                report
                    .last_time_ns
                    .map_or(header.log_time, |t| t.max(header.log_time)),
            );
        }
    }

    /// Decompresses and checks a chunk, then delivers its messages: all of them, or none if
    /// anything in it is wrong.
    fn chunk(
        &mut self,
        header: &ChunkHeader,
        data: &[u8],
        limit: u64,
        report: &mut ReadReport,
        f: &mut impl FnMut(&str, u64, &[u8]),
    ) -> Result<(), Problem> {
        let content: &[u8] = match header.compression.as_str() {
            "" => data,
            "zstd" => {
                if header.uncompressed_size > limit {
                    return Err(Problem::TooLong {
                        record: "Chunk's content",
                        len: header.uncompressed_size,
                        limit,
                    });
                }
                let decompressor = match &mut self.zstd {
                    Some(d) => d,
                    none => none.insert(zstd::bulk::Decompressor::new().map_err(|e| {
                        Problem::Decompression {
                            reason: e.to_string(),
                        }
                    })?),
                };
                self.content.clear();
                // At most `limit` (64 MiB or the file's length): checked above.
                self.content.reserve(header.uncompressed_size as usize);
                decompressor
                    .decompress_to_buffer(data, &mut self.content)
                    .map_err(|e| Problem::Decompression {
                        reason: e.to_string(),
                    })?;
                &self.content
            }
            other => {
                return Err(Problem::Compression {
                    name: other.to_string(),
                });
            }
        };
        if content.len() as u64 != header.uncompressed_size {
            return Err(Problem::ChunkSize {
                stated: header.uncompressed_size,
                actual: content.len() as u64,
            });
        }
        if header.uncompressed_crc != 0 {
            let computed = crc32fast::hash(content);
            if computed != header.uncompressed_crc {
                return Err(Problem::ChunkCrc {
                    stored: header.uncompressed_crc,
                    computed,
                });
            }
        }
        // First parse and check every record, then deliver: a chunk is used whole or not at all.
        let mut records = Vec::new();
        let mut new_channels = HashSet::new();
        let mut pos = 0;
        while pos < content.len() {
            let in_chunk = |reason: String| Problem::InChunk {
                at: pos as u64,
                reason,
            };
            let (opcode, body) = record_at(content, pos, u64::MAX).map_err(|p| {
                in_chunk(match p {
                    Problem::Truncated { record, needs } => format!(
                        "a {record} record runs past the end of the content (needs {needs} \
                         more bytes)"
                    ),
                    Problem::UnknownOpcode { opcode } => {
                        format!("unknown record opcode {opcode:#04x}")
                    }
                    other => format!("{other:?}"),
                })
            })?;
            let record = record_name(opcode);
            if !matches!(opcode, op::SCHEMA | op::CHANNEL | op::MESSAGE) {
                return Err(in_chunk(format!(
                    "a {record} record, which does not belong in a chunk"
                )));
            }
            let parsed = mcap::parse_record(opcode, body)
                .map_err(|e| in_chunk(format!("bad {record} record: {e}")))?;
            match &parsed {
                Record::Channel(c) => {
                    new_channels.insert(c.id);
                }
                Record::Message { header, .. } => {
                    self.check_channel(header, &new_channels)
                        .map_err(in_chunk)?;
                }
                _ => {}
            }
            records.push(parsed);
            pos += RECORD_PREFIX + body.len();
        }
        for record in records {
            match record {
                Record::Channel(c) => {
                    self.topics.insert(c.id, c.topic);
                }
                Record::Message { header, data } => self.deliver(&header, &data, report, f),
                _ => {}
            }
        }
        Ok(())
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
        f.extend(record(op::HEADER, &[string(""), string("test")].concat()));
        f.extend_from_slice(middle);
        f.extend(record(op::DATA_END, &0u32.to_le_bytes()));
        f.extend(record(op::FOOTER, &[0u8; 20]));
        f.extend_from_slice(MAGIC);
        f
    }

    #[test]
    fn private_records_are_reported_with_what_they_may_be() {
        for opcode in [0x80u8, 0xF0] {
            let file = file_with(&record(opcode, &[1, 2, 3, 4]));
            let report = for_each_message(&file, |_, _, _| {}, |_, _| {}).unwrap();
            let damage = report.damage.expect("damage");
            assert!(
                matches!(damage.problem, Problem::UnknownOpcode { opcode: o } if o == opcode),
                "{damage}"
            );
            assert!(damage.to_string().contains("private record"), "{damage}");
        }
        let report =
            for_each_message(&file_with(&record(0x7F, &[])), |_, _, _| {}, |_, _| {}).unwrap();
        let damage = report.damage.expect("damage");
        assert!(damage.to_string().contains("a corrupt record"), "{damage}");
        // The frame around them is well formed: without them the file is intact.
        let report = for_each_message(&file_with(&[]), |_, _, _| {}, |_, _| {}).unwrap();
        assert!(report.is_complete() && report.data_complete, "{report}");
    }
}
