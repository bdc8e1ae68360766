//! MCAP write throughput: how many CAN frames per second [`McapLog`] writes (CDR
//! `can_msgs/msg/Frame` messages in zstd chunks, as `hostsim run` logs them).
//!
//! `cargo run --release -p hostsim --example mcap_throughput -- [FRAMES] [FILE]` prints one
//! JSON line `{"frames":..,"seconds":..,"frames_per_s":..,"bytes":..}`.
//! `scripts/mcap_throughput.py` writes the same frames with the Python `mcap` writer, and
//! `scripts/bench.sh` reports the ratio of the two.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use drivelog::{Direction, McapLog};
use embedded_can::{Frame as _, StandardId};
use firmware::CanFrame;

/// Frame `i` of the sequence (the Python side builds the same): four drives' feedback ids in
/// turn, 1 kHz each, the index in the data bytes.
fn frame(i: u64) -> (u64, CanFrame) {
    let id = StandardId::new(0x201 + (i % 4) as u16).expect("0x201..0x204 are standard ids");
    let b = i.to_le_bytes();
    let data = [b[0], b[1], b[2], b[3], 0x5A, 0xA5, (i % 251) as u8, 0x19];
    let frame = CanFrame::new(id, &data).expect("8 data bytes fit a frame");
    (i * 250_000, frame)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let frames: u64 = match args.next() {
        Some(n) => n.parse().map_err(|e| format!("FRAMES {n:?}: {e}"))?,
        None => 1_000_000,
    };
    let path = args.next().map_or_else(
        || std::env::temp_dir().join("mcap_throughput.mcap"),
        PathBuf::from,
    );
    let start = Instant::now();
    let mut log = McapLog::create(&path, &BTreeMap::new())?;
    for i in 0..frames {
        let (t_ns, f) = frame(i);
        log.frame(Direction::Rx, t_ns, t_ns, t_ns, &f)?;
        log.maybe_flush()?;
    }
    log.finish()?;
    let seconds = start.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(&path)?.len();
    println!(
        r#"{{"frames":{frames},"seconds":{seconds:.6},"frames_per_s":{:.1},"bytes":{bytes}}}"#,
        frames as f64 / seconds
    );
    Ok(())
}
