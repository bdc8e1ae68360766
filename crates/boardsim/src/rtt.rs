//! The board's log: defmt frames in the SEGGER RTT up-buffer 0, read from guest RAM as a
//! debug probe does (read WrOff and RdOff, copy the bytes, write RdOff back), then decoded
//! with the format strings of the ELF's `.defmt` table (`defmt-decoder`).
//!
//! defmt-rtt's buffer is 1 KiB in NoBlockTrim mode: what does not fit is cut, so the board
//! drains it after every emulation slice. Frames are rzcobs-encoded and end with a 0x00 byte;
//! the bytes are kept until a frame is complete, each complete frame is decoded on its own.

use defmt_decoder::{DecodeError, Table};

/// One decoded log line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogLine {
    /// When the board drained it, CPU cycles since reset.
    pub at: u64,
    /// The defmt level (`info`, `warn`, ...), empty for a `println`.
    pub level: String,
    /// The formatted message.
    pub text: String,
}

/// The RTT channel and its decoder.
pub struct Rtt {
    /// Address of `_SEGGER_RTT` (the control block).
    control: u32,
    table: Option<Table>,
    /// Bytes of an incomplete frame.
    partial: Vec<u8>,
    /// Bytes drained so far.
    pub bytes: u64,
    /// Frames that did not decode.
    pub malformed: u64,
}

impl std::fmt::Debug for Rtt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Rtt")
            .field("control", &self.control)
            .field("bytes", &self.bytes)
            .finish_non_exhaustive()
    }
}

/// Offset of up-buffer 0 in the control block: the 16-byte id, MaxNumUpBuffers,
/// MaxNumDownBuffers.
const UP0: u32 = 24;

impl Rtt {
    /// The channel of the control block at `control`, decoded with the defmt table of `elf`
    /// (`None` if the ELF has no defmt table: lines are then reported as raw frames).
    ///
    /// # Errors
    /// The table is in the ELF but does not parse (e.g. a defmt version the decoder does not
    /// know).
    pub fn new(control: u32, elf: &[u8]) -> anyhow::Result<Self> {
        Ok(Self {
            control,
            table: Table::parse(elf)?,
            partial: Vec::new(),
            bytes: 0,
            malformed: 0,
        })
    }

    /// After a reset: the bytes of a frame the firmware had not finished are dropped (it
    /// starts its log anew).
    pub fn reset(&mut self) {
        self.partial.clear();
    }

    /// Moves what the firmware wrote since the last call out of its buffer: `read(addr, buf)`
    /// and `write(addr, bytes)` access guest memory. Returns the complete lines, stamped `at`.
    pub fn drain(
        &mut self,
        at: u64,
        read: impl Fn(u32, &mut [u8]),
        mut write: impl FnMut(u32, &[u8]),
    ) -> Vec<LogLine> {
        let mut desc = [0u8; 24];
        read(self.control + UP0, &mut desc);
        let word = |i: usize| u32::from_le_bytes([desc[i], desc[i + 1], desc[i + 2], desc[i + 3]]);
        let (buffer, size, wr, rd) = (word(4), word(8), word(12), word(16));
        if size == 0 || wr == rd || wr >= size || rd >= size {
            return Vec::new();
        }
        let mut chunk = vec![0u8; ((wr + size - rd) % size) as usize];
        if wr > rd {
            read(buffer + rd, &mut chunk);
        } else {
            let first = (size - rd) as usize;
            read(buffer + rd, &mut chunk[..first]);
            read(buffer, &mut chunk[first..]);
        }
        write(self.control + UP0 + 16, &wr.to_le_bytes());
        self.bytes += chunk.len() as u64;
        self.partial.extend_from_slice(&chunk);
        self.lines(at)
    }

    /// Decodes the complete frames in `partial`.
    fn lines(&mut self, at: u64) -> Vec<LogLine> {
        let mut out = Vec::new();
        while let Some(end) = self.partial.iter().position(|&b| b == 0) {
            let frame: Vec<u8> = self.partial.drain(..=end).collect();
            if frame.len() == 1 {
                // A lone terminator (defmt-rtt starts its stream with one): no frame.
                continue;
            }
            let Some(table) = &self.table else {
                out.push(LogLine {
                    at,
                    level: String::new(),
                    text: format!("(no defmt table) {frame:02x?}"),
                });
                continue;
            };
            let mut decoder = table.new_stream_decoder();
            decoder.received(&frame);
            match decoder.decode() {
                Ok(f) => out.push(LogLine {
                    at,
                    level: f
                        .level()
                        .map(|l| l.as_str().to_string())
                        .unwrap_or_default(),
                    text: f.display_message().to_string(),
                }),
                Err(DecodeError::UnexpectedEof | DecodeError::Malformed) => {
                    self.malformed += 1;
                    out.push(LogLine {
                        at,
                        level: "error".into(),
                        text: format!("(a defmt frame that does not decode: {frame:02x?})"),
                    });
                }
            }
        }
        out
    }
}
