//! Where and how a log is damaged: [`Damage`], its offset and [`Problem`].

use std::fmt;

use super::MAGIC;

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
