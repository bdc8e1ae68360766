//! The channels and schemas met so far, the delivery of messages on them, and chunks, each
//! read and checked whole before any of its messages is delivered.

use std::collections::HashMap;

use mcap::McapError;
use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::{Message, Problem, ReadReport, record_name};

/// A channel as the reader knows it.
struct ChannelInfo {
    topic: String,
    schema: String,
}

/// State of a walk through a file: channels and schemas.
#[derive(Default)]
pub(super) struct Channels {
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, ChannelInfo>,
}

impl Channels {
    pub(super) fn add(&mut self, record: &Record<'_>) {
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
    pub(super) fn check(&self, channel_id: u16) -> Result<(), String> {
        if self.channels.contains_key(&channel_id) {
            Ok(())
        } else {
            Err(format!(
                "a Message on channel {channel_id}, which has no Channel record before it"
            ))
        }
    }

    pub(super) fn deliver(
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
    pub(super) fn chunk(
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
        let inner = chunk_records(raw, limit)?;
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

/// The records of a chunk whose whole record (prefix included) is `raw`, decompressed, its CRC
/// checked, none longer than `limit`.
fn chunk_records(raw: &[u8], limit: u64) -> Result<Vec<Record<'static>>, Problem> {
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
    Ok(inner)
}
