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

use std::collections::BTreeMap;

use mcap::McapError;
use mcap::records::{Record, op};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

mod channels;
mod damage;
mod report;

use channels::Channels;
pub use damage::{Damage, Problem};
pub use report::{Message, ReadReport, Undecodable};

/// The MCAP magic, at the start and at the end of a file.
const MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// Opcode (1 byte) and length (8 bytes) in front of every record.
const RECORD_PREFIX: usize = 9;

/// Smallest limit on a chunk's decompressed size, bytes (the writer's chunks are about 1 MiB).
const MIN_DECOMPRESSED_LIMIT: u64 = 64 << 20;
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
    check_magic(bytes)?;
    let mut walk = Walk::new(bytes);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_emit_chunks(true)
            .with_validate_data_section_crc(true)
            .with_validate_summary_section_crc(true)
            .with_check_finishes_after_end_magic(true)
            .with_record_length_limit(usize::try_from(walk.limit).unwrap_or(usize::MAX)),
    );
    // Bytes handed to the reader.
    let mut fed = 0usize;
    let found = loop {
        let event = match reader.next_event() {
            None => break None,
            Some(Ok(event)) => event,
            Some(Err(e)) => break Some(walk.failure(e)),
        };
        match event {
            LinearReadEvent::ReadRequest(need) => {
                let n = need.min(bytes.len() - fed);
                reader.insert(n).copy_from_slice(&bytes[fed..fed + n]);
                reader.notify_read(n);
                fed += n;
            }
            LinearReadEvent::Record { opcode, data } => {
                if let Err(damage) = walk.record(opcode, data, &mut f, &mut meta) {
                    break Some(damage);
                }
            }
        }
    };
    walk.finish(found)
}

/// A file shorter than the magic, or not starting with it.
fn check_magic(bytes: &[u8]) -> Result<(), Damage> {
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
    Ok(())
}

fn damage(offset: usize, problem: Problem) -> Damage {
    Damage {
        offset: offset as u64,
        problem,
    }
}

/// A walk through a file's records: where it is, what it has read, what it has met.
struct Walk<'a> {
    bytes: &'a [u8],
    /// The longest record (or chunk's content) accepted, bytes.
    limit: u64,
    channels: Channels,
    report: ReadReport,
    /// The offset of the next record.
    pos: usize,
    header_read: bool,
    data_end_read: bool,
    /// The end of the Footer, once read: what follows is the closing magic.
    footer_end: Option<usize>,
}

impl<'a> Walk<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        let file_len = bytes.len() as u64;
        Self {
            bytes,
            limit: file_len.max(MIN_DECOMPRESSED_LIMIT),
            channels: Channels::default(),
            report: ReadReport {
                file_len,
                ..ReadReport::default()
            },
            pos: MAGIC.len(),
            header_read: false,
            data_end_read: false,
            footer_end: None,
        }
    }

    /// Where and what the reader's error `e` is, at the record at [`pos`](Self::pos) (or the
    /// closing magic after the Footer).
    fn failure(&self, e: McapError) -> Damage {
        let (bytes, pos) = (self.bytes, self.pos);
        let problem = match e {
            McapError::UnexpectedEof | McapError::BadMagic if self.footer_end.is_some() => {
                let end = self.footer_end.unwrap_or(pos);
                let tail = &bytes[end..];
                let problem = if tail.len() < MAGIC.len() && MAGIC.starts_with(tail) {
                    Problem::Truncated {
                        record: "closing magic",
                        needs: (MAGIC.len() - tail.len()) as u64,
                    }
                } else {
                    Problem::BadEndMagic
                };
                return damage(end, problem);
            }
            McapError::UnexpectedEof if !self.header_read && pos == bytes.len() => {
                Problem::Truncated {
                    record: "Header",
                    needs: RECORD_PREFIX as u64,
                }
            }
            McapError::UnexpectedEof => truncation(bytes, pos),
            McapError::BytesAfterEndMagic => {
                let at = self.footer_end.unwrap_or(pos) + MAGIC.len();
                return damage(
                    at,
                    Problem::TrailingBytes {
                        count: (bytes.len() - at) as u64,
                    },
                );
            }
            McapError::RecordTooLarge { opcode, len } => Problem::TooLong {
                record: record_name(opcode),
                len,
                limit: self.limit,
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
        damage(pos, problem)
    }

    /// Uses the record at [`pos`](Self::pos), opcode `opcode` and `content`, and moves past
    /// it; the damage if it cannot be used.
    fn record(
        &mut self,
        opcode: u8,
        content: &[u8],
        f: &mut impl FnMut(&Message<'_>),
        meta: &mut impl FnMut(&str, &BTreeMap<String, String>),
    ) -> Result<(), Damage> {
        let pos = self.pos;
        let record = record_name(opcode);
        let end = pos + RECORD_PREFIX + content.len();
        if !(op::HEADER..=op::DATA_END).contains(&opcode) {
            return Err(damage(pos, Problem::UnknownOpcode { opcode }));
        }
        if self.data_end_read && !allowed_in_summary(opcode) {
            return Err(damage(
                pos,
                Problem::Misplaced {
                    record,
                    place: "after the Data End record",
                },
            ));
        }
        let parsed = mcap::parse_record(opcode, content).map_err(|e| {
            damage(
                pos,
                Problem::BadRecord {
                    record,
                    reason: e.to_string(),
                },
            )
        })?;
        if !self.header_read {
            let Record::Header(h) = parsed else {
                return Err(damage(
                    pos,
                    Problem::Misplaced {
                        record,
                        place: "where the file's first record, a Header, belongs",
                    },
                ));
            };
            self.report.profile = h.profile;
            self.header_read = true;
            self.pos = end;
            return Ok(());
        }
        match parsed {
            Record::Chunk { header, .. } => {
                let raw = &self.bytes[pos..end];
                let result = self
                    .channels
                    .chunk(&header, raw, self.limit, &mut self.report, f);
                if let Err(problem) = result {
                    return Err(damage(pos, problem));
                }
                self.report.chunks += 1;
            }
            Record::Schema { .. } | Record::Channel(_) => self.channels.add(&parsed),
            Record::Message { header, data } => {
                if let Err(reason) = self.channels.check(header.channel_id) {
                    return Err(damage(pos, Problem::BadRecord { record, reason }));
                }
                self.channels.deliver(&header, &data, &mut self.report, f);
            }
            Record::Metadata(m) => meta(&m.name, &m.metadata),
            Record::DataEnd(_) => {
                // The reader checked its CRC before handing it over.
                self.report.data_complete = true;
                self.data_end_read = true;
            }
            Record::Footer(_) => self.footer_end = Some(end),
            _ => {}
        }
        self.pos = end;
        Ok(())
    }

    /// The report, with the damage `found` (if any); the damage alone, as an error, if not
    /// even the Header was read.
    fn finish(mut self, found: Option<Damage>) -> Result<ReadReport, Damage> {
        // The reader ends without an error at the end of the file only after the closing
        // magic.
        let found = found
            .or_else(|| (self.footer_end.is_none()).then(|| damage(self.pos, Problem::Unfinished)));
        match found {
            Some(d) if !self.header_read => Err(d),
            found => {
                self.report.damage = found;
                Ok(self.report)
            }
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
