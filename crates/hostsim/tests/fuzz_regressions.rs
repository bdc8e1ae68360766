//! Regression tests for crashes found by fuzzing (`fuzz/`, `scripts/fuzz.sh`; see
//! docs/reliability.md). Each test is named after the bug and builds its input by hand.

use drivelog::for_each_message;
use hostsim::replay::read_log_bytes;

const MAGIC: &[u8] = b"\x89MCAP0\r\n";

fn record(opcode: u8, content: &[u8]) -> Vec<u8> {
    let mut r = vec![opcode];
    r.extend_from_slice(&(content.len() as u64).to_le_bytes());
    r.extend_from_slice(content);
    r
}

fn string(s: &str) -> Vec<u8> {
    let mut out = (s.len() as u32).to_le_bytes().to_vec();
    out.extend_from_slice(s.as_bytes());
    out
}

/// A zstd frame holding `data` in one raw (stored) block: no compressor needed.
fn zstd_raw(data: &[u8]) -> Vec<u8> {
    assert!(data.len() < 256);
    let mut out = vec![0x28, 0xB5, 0x2F, 0xFD];
    // Frame header: single segment, 1-byte content size.
    out.extend_from_slice(&[0x20, data.len() as u8]);
    // Block header: last block, raw, size.
    let block = 1u32 | ((data.len() as u32) << 3);
    out.extend_from_slice(&block.to_le_bytes()[..3]);
    out.extend_from_slice(data);
    out
}

/// An MCAP file whose one zstd chunk holds the header of a Message record claiming 2^62
/// bytes. `mcap::read::ChunkFlattener` (no record length limit) reserved that much memory to
/// decompress it and the process aborted on allocation failure instead of reporting a
/// corrupt log.
fn huge_record_in_zstd_chunk() -> Vec<u8> {
    let mut inner = vec![0x05]; // Message
    inner.extend_from_slice(&(1u64 << 62).to_le_bytes());
    let compressed = zstd_raw(&inner);

    let mut chunk = Vec::new();
    chunk.extend_from_slice(&0u64.to_le_bytes()); // message start time
    chunk.extend_from_slice(&0u64.to_le_bytes()); // message end time
    chunk.extend_from_slice(&(inner.len() as u64).to_le_bytes()); // uncompressed size
    chunk.extend_from_slice(&0u32.to_le_bytes()); // uncompressed CRC: none
    chunk.extend_from_slice(&string("zstd"));
    chunk.extend_from_slice(&(compressed.len() as u64).to_le_bytes());
    chunk.extend_from_slice(&compressed);

    let mut file = MAGIC.to_vec();
    let mut header = string("");
    header.extend_from_slice(&string("fuzz-regression"));
    file.extend(record(0x01, &header));
    file.extend(record(0x06, &chunk));
    file
}

#[test]
fn mcap_huge_record_length_in_compressed_chunk_is_an_error_not_an_abort() {
    let bytes = huge_record_in_zstd_chunk();
    let mut messages = 0;
    let read = for_each_message(&bytes, |_| messages += 1, |_, _| {})
        .expect("the header record was read: damage, not an error");
    assert_eq!(messages, 0);
    let damage = read.damage.expect("reading stopped at the corrupt chunk");
    // The chunk record starts after the magic and the header record.
    let chunk_offset =
        (MAGIC.len() + 9 + string("").len() + string("fuzz-regression").len()) as u64;
    assert_eq!(damage.offset, chunk_offset, "{damage}");
    let why = damage.to_string();
    assert!(why.contains(&format!("at byte {chunk_offset}")), "{why}");

    let content = read_log_bytes(&bytes).expect("starts like MCAP");
    assert!(content.rx.is_empty() && content.tx.is_empty());
    assert!(!content.read.is_complete());
}
