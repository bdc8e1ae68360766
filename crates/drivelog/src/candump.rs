//! candump log files (can-utils `candump -L`, python-can's `.log` format): the one parser
//! and writer of the project (`hostsim replay`, `mecanum-codec decode`, the tests' logs).
//!
//! One frame per line:
//!
//! ```text
//! (1700000000.123456) vcan0 123#DEADBEEF
//! (1700000000.124000) vcan0 301#F4010000E8030700
//! (1700000000.125000) vcan0 023#R
//! (1700000000.126000) vcan0 1ABCDEF0#00
//! ```
//!
//! - a timestamp in parentheses: seconds, a dot and 1 to 9 fraction digits (candump writes 6);
//! - the interface name;
//! - the frame ([`parse_frame`]): a 3-digit hex standard id or an 8-digit extended id, `#`,
//!   then 0 to 8 data bytes as hex pairs (optionally separated by dots between bytes, as
//!   `cansend` accepts); a remote frame is `#R` with an optional DLC digit (`123#R4`);
//! - optionally, a direction token `R` (received) or `T` (transmitted) (`candump -L -x`).
//!
//! Blank lines are skipped, and so are error frames (`candump -e`: an 8-digit id with
//! `CAN_ERR_FLAG`). Classic CAN only: a CAN FD frame (`##`), a CAN XL frame (`###`) or a DLC
//! code above 8 (`_9`..`_F`) is rejected with a [`CandumpError`] naming the line number, the
//! text and what is wrong, as is every other malformed line. The parser never panics.
//!
//! The writer produces exactly the `candump -L` form (10-digit seconds, 6-digit microseconds,
//! upper-case hex, no separators), which `canplayer` and python-can's `CanutilsLogReader` read.

use std::fmt;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use embedded_can::{ExtendedId, Frame as _, Id, StandardId};
use firmware::CanFrame;

/// One parsed line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Entry {
    /// Timestamp, ns since the Unix epoch (or whatever epoch the log uses).
    pub t_ns: u64,
    /// Interface name as logged (`vcan0`, `can0`).
    pub iface: String,
    /// The frame.
    pub frame: CanFrame,
    /// The direction token, if the line has one.
    pub direction: Option<LoggedDirection>,
}

/// The optional direction token of `candump -L -x` lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoggedDirection {
    /// `R`: received by the logging host.
    Received,
    /// `T`: transmitted by the logging host.
    Transmitted,
}

/// What is wrong with a line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ErrorKind {
    /// The line is not valid UTF-8 text.
    NotText,
    /// The timestamp is missing or malformed.
    Timestamp(&'static str),
    /// No interface name after the timestamp.
    MissingInterface,
    /// No `<id>#<data>` token after the interface.
    MissingFrame,
    /// The id is not 1 to 3 hex digits (standard, at most 0x7FF) or 8 (extended, at most
    /// 0x1FFFFFFF).
    BadId(&'static str),
    /// A CAN FD frame (`##`): not supported.
    CanFd,
    /// A CAN XL frame (`###`): not supported.
    CanXl,
    /// The data is not hex pairs.
    BadData(&'static str),
    /// More than 8 data bytes.
    TooLong(usize),
    /// A classic frame with a DLC code above 8 (`_9`..`_F` suffix): not supported.
    Len8Dlc,
    /// A remote frame whose DLC is not one digit 0..8.
    BadRemoteDlc,
    /// Something after the frame that is not a direction token.
    Trailing,
}

impl fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NotText => f.write_str("not UTF-8 text"),
            Self::Timestamp(why) => write!(f, "bad timestamp ({why})"),
            Self::MissingInterface => f.write_str("no interface name after the timestamp"),
            Self::MissingFrame => f.write_str("no <id>#<data> frame after the interface"),
            Self::BadId(why) => write!(f, "bad CAN id ({why})"),
            Self::CanFd => f.write_str("CAN FD frame (##): only classic CAN is supported"),
            Self::CanXl => f.write_str("CAN XL frame (###): only classic CAN is supported"),
            Self::BadData(why) => write!(f, "bad data ({why})"),
            Self::TooLong(n) => write!(f, "{n} data bytes, at most 8"),
            Self::Len8Dlc => f.write_str("DLC code above 8 (_9.._F) is not supported"),
            Self::BadRemoteDlc => f.write_str("remote frame DLC must be one digit 0..8"),
            Self::Trailing => {
                f.write_str("unexpected text after the frame (only R or T may follow)")
            }
        }
    }
}

/// A line that could not be parsed: its number (1-based), its text and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("line {line}: {kind}: \"{text}\"")]
pub struct CandumpError {
    /// Line number, 1-based.
    pub line: usize,
    /// The line, [`quote`](firmware::input::quote)d: cut to 120 characters, control
    /// characters escaped.
    pub text: String,
    /// What is wrong.
    pub kind: ErrorKind,
}

impl CandumpError {
    fn new(line: usize, text: &str, kind: ErrorKind) -> Self {
        Self {
            line,
            text: firmware::input::quote(text),
            kind,
        }
    }
}

/// Why a candump file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file could not be read.
    #[error("cannot read {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: io::Error,
    },
    /// A line is malformed or unsupported.
    #[error("{}: {source}", path.display())]
    Line {
        /// The file.
        path: PathBuf,
        /// The line's error.
        source: CandumpError,
    },
}

/// `CAN_ERR_FLAG` of SocketCAN: set in the id of an error frame (`candump -e`).
const CAN_ERR_FLAG: u32 = 0x2000_0000;

/// Whether `id` (the hex digits before `#`) is an error frame's: 8 digits with
/// `CAN_ERR_FLAG` set.
#[must_use]
pub fn is_error_frame_id(id: &str) -> bool {
    id.len() == 8 && u32::from_str_radix(id, 16).is_ok_and(|id| id & CAN_ERR_FLAG != 0)
}

/// Parses one line; `Ok(None)` for a blank line and for an error frame (`candump -e` writes
/// bus errors as frames whose 8-digit id has `CAN_ERR_FLAG`, 0x20000000, set: a bus event,
/// not a frame any node sent). `line_no` is only used in the error.
///
/// # Errors
/// [`CandumpError`] naming the line, its text and what is wrong.
pub fn parse_line(line: &str, line_no: usize) -> Result<Option<Entry>, CandumpError> {
    let err = |kind| CandumpError::new(line_no, line.trim_end(), kind);
    let mut tokens = line.split_ascii_whitespace();
    let Some(stamp) = tokens.next() else {
        return Ok(None);
    };
    let t_ns = parse_timestamp(stamp).map_err(|why| err(ErrorKind::Timestamp(why)))?;
    let iface = tokens
        .next()
        .ok_or_else(|| err(ErrorKind::MissingInterface))?;
    if iface.contains('#') {
        return Err(err(ErrorKind::MissingInterface));
    }
    let token = tokens.next().ok_or_else(|| err(ErrorKind::MissingFrame))?;
    if let Some((id, data)) = token.split_once('#')
        && is_error_frame_id(id)
    {
        // Its data must still be well formed (8 bytes of error class details at most).
        parse_frame(&format!("000#{data}")).map_err(err)?;
        return Ok(None);
    }
    let frame = parse_frame(token).map_err(err)?;
    let direction = match tokens.next() {
        None => None,
        Some("R") => Some(LoggedDirection::Received),
        Some("T") => Some(LoggedDirection::Transmitted),
        Some(_) => return Err(err(ErrorKind::Trailing)),
    };
    if tokens.next().is_some() {
        return Err(err(ErrorKind::Trailing));
    }
    Ok(Some(Entry {
        t_ns,
        iface: iface.to_string(),
        frame,
        direction,
    }))
}

/// `(seconds.fraction)` to ns.
fn parse_timestamp(token: &str) -> Result<u64, &'static str> {
    let inner = token
        .strip_prefix('(')
        .and_then(|t| t.strip_suffix(')'))
        .ok_or("expected (seconds.fraction)")?;
    let (secs, frac) = inner.split_once('.').ok_or("no decimal point")?;
    if secs.is_empty() || !secs.bytes().all(|b| b.is_ascii_digit()) {
        return Err("seconds are not decimal digits");
    }
    if frac.is_empty() || frac.len() > 9 || !frac.bytes().all(|b| b.is_ascii_digit()) {
        return Err("fraction must be 1 to 9 decimal digits");
    }
    let secs: u64 = secs.parse().map_err(|_| "seconds out of range")?;
    let mut ns: u64 = frac.parse().map_err(|_| "fraction out of range")?;
    for _ in frac.len()..9 {
        ns *= 10;
    }
    secs.checked_mul(1_000_000_000)
        .and_then(|s| s.checked_add(ns))
        .ok_or("seconds out of range")
}

/// `<id>#<data>` to a frame.
///
/// # Errors
/// The [`ErrorKind`] of the first problem found.
pub fn parse_frame(token: &str) -> Result<CanFrame, ErrorKind> {
    let (id_text, rest) = token.split_once('#').ok_or(ErrorKind::MissingFrame)?;
    if rest.starts_with("##") {
        return Err(ErrorKind::CanXl);
    }
    if rest.starts_with('#') {
        return Err(ErrorKind::CanFd);
    }
    if id_text.is_empty() {
        return Err(ErrorKind::BadId("empty"));
    }
    if !id_text.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(ErrorKind::BadId("not hex digits"));
    }
    let id: Id = match id_text.len() {
        1..=3 => {
            let raw =
                u16::from_str_radix(id_text, 16).map_err(|_| ErrorKind::BadId("not hex digits"))?;
            StandardId::new(raw)
                .ok_or(ErrorKind::BadId("above 0x7FF"))?
                .into()
        }
        8 => {
            let raw =
                u32::from_str_radix(id_text, 16).map_err(|_| ErrorKind::BadId("not hex digits"))?;
            ExtendedId::new(raw)
                .ok_or(ErrorKind::BadId("above 0x1FFFFFFF"))?
                .into()
        }
        _ => {
            return Err(ErrorKind::BadId(
                "a standard id has 3 hex digits, an extended id 8",
            ));
        }
    };
    if let Some(dlc) = rest.strip_prefix(['R', 'r']) {
        let dlc = match dlc.as_bytes() {
            [] => 0,
            [d @ b'0'..=b'8'] => d - b'0',
            _ => return Err(ErrorKind::BadRemoteDlc),
        };
        return CanFrame::new_remote(id, usize::from(dlc)).ok_or(ErrorKind::BadRemoteDlc);
    }
    if rest.contains('_') {
        return Err(ErrorKind::Len8Dlc);
    }
    // Dots may only separate whole bytes.
    if rest.starts_with('.') || rest.ends_with('.') || rest.contains("..") {
        return Err(ErrorKind::BadData("misplaced '.' separator"));
    }
    for chunk in rest.split('.') {
        if chunk.len() % 2 != 0 {
            return Err(ErrorKind::BadData("odd number of hex digits"));
        }
    }
    let mut data = [0u8; 8];
    let mut len = 0usize;
    let mut digits = rest.bytes().filter(|&b| b != b'.');
    while let Some(hi) = digits.next() {
        let lo = digits
            .next()
            .ok_or(ErrorKind::BadData("odd number of hex digits"))?;
        let byte = hex_value(hi)
            .zip(hex_value(lo))
            .map(|(h, l)| h << 4 | l)
            .ok_or(ErrorKind::BadData("not hex digits"))?;
        if len < 8 {
            data[len] = byte;
        }
        len += 1;
    }
    if len > 8 {
        return Err(ErrorKind::TooLong(len));
    }
    // len <= 8 checked above.
    CanFrame::new(id, &data[..len]).ok_or(ErrorKind::TooLong(len))
}

const fn hex_value(b: u8) -> Option<u8> {
    match b {
        b'0'..=b'9' => Some(b - b'0'),
        b'a'..=b'f' => Some(b - b'a' + 10),
        b'A'..=b'F' => Some(b - b'A' + 10),
        _ => None,
    }
}

/// Parses a whole log; blank lines are skipped.
///
/// # Errors
/// The first line's [`CandumpError`].
pub fn parse_log(text: &str) -> Result<Vec<Entry>, CandumpError> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if let Some(e) = parse_line(line, i + 1)? {
            out.push(e);
        }
    }
    Ok(out)
}

/// As [`parse_log`], from bytes: a line that is not UTF-8 is an error ([`ErrorKind::NotText`]).
///
/// # Errors
/// The first line's [`CandumpError`].
pub fn parse_log_bytes(bytes: &[u8]) -> Result<Vec<Entry>, CandumpError> {
    let mut out = Vec::new();
    for (i, line) in bytes.split(|&b| b == b'\n').enumerate() {
        let line = line.strip_suffix(b"\r").unwrap_or(line);
        let text = std::str::from_utf8(line).map_err(|_| {
            CandumpError::new(i + 1, &String::from_utf8_lossy(line), ErrorKind::NotText)
        })?;
        if let Some(e) = parse_line(text, i + 1)? {
            out.push(e);
        }
    }
    Ok(out)
}

/// Reads and parses a candump log file.
///
/// # Errors
/// [`ReadError`] naming the file (and the line).
pub fn read_file(path: &Path) -> Result<Vec<Entry>, ReadError> {
    let bytes =
        firmware::input::read_bounded(path, crate::read::MAX_LOG_BYTES).map_err(|source| {
            ReadError::Io {
                path: path.to_path_buf(),
                source,
            }
        })?;
    parse_log_bytes(&bytes).map_err(|source| ReadError::Line {
        path: path.to_path_buf(),
        source,
    })
}

/// Whether `bytes` look like a candump log: the first non-blank line starts with `(`
/// followed by a digit.
#[must_use]
pub fn looks_like_candump(bytes: &[u8]) -> bool {
    let start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(bytes.len());
    matches!(&bytes[start..], [b'(', d, ..] if d.is_ascii_digit())
}

/// A frame in candump notation: `123#DEADBEEF`, `123#R`, `123#R4` (the frame's `Display`).
#[must_use]
pub fn format_frame(frame: &CanFrame) -> String {
    frame.to_string()
}

/// Whether `iface` can be written into a log line (non-empty, no whitespace, no `#`, no
/// parentheses).
#[must_use]
pub fn valid_iface(iface: &str) -> bool {
    !iface.is_empty()
        && !iface
            .chars()
            .any(|c| c.is_whitespace() || c == '#' || c == '(' || c == ')')
}

/// One log line without the newline: `(SSSSSSSSSS.UUUUUU) iface ID#DATA`. The timestamp is
/// truncated to microseconds, as candump writes it.
///
/// Returns `None` if `iface` is not [valid](valid_iface).
#[must_use]
pub fn format_line(t_ns: u64, iface: &str, frame: &CanFrame) -> Option<String> {
    valid_iface(iface).then(|| {
        format!(
            "({:010}.{:06}) {iface} {}",
            t_ns / 1_000_000_000,
            (t_ns % 1_000_000_000) / 1000,
            format_frame(frame)
        )
    })
}

/// Writes candump log lines to any [`Write`].
#[derive(Debug)]
pub struct Writer<W: Write> {
    out: W,
    iface: String,
}

impl<W: Write> Writer<W> {
    /// A writer that logs every frame on `iface`.
    ///
    /// # Errors
    /// [`io::ErrorKind::InvalidInput`] if `iface` is not [valid](valid_iface).
    pub fn new(out: W, iface: &str) -> io::Result<Self> {
        if !valid_iface(iface) {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("interface name {iface:?} cannot be written into a candump log"),
            ));
        }
        Ok(Self {
            out,
            iface: iface.to_string(),
        })
    }

    /// Writes one line.
    ///
    /// # Errors
    /// The underlying writer's error.
    pub fn write(&mut self, t_ns: u64, frame: &CanFrame) -> io::Result<()> {
        // The interface was checked in `new`.
        let line = format_line(t_ns, &self.iface, frame).unwrap_or_default();
        writeln!(self.out, "{line}")
    }

    /// Flushes and returns the inner writer.
    ///
    /// # Errors
    /// The flush error.
    pub fn finish(mut self) -> io::Result<W> {
        self.out.flush()?;
        Ok(self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
    }

    #[test]
    fn parses_the_documented_line() {
        let e = parse_line("(1700000000.123456) vcan0 123#DEADBEEF", 1)
            .unwrap()
            .unwrap();
        assert_eq!(e.t_ns, 1_700_000_000_123_456_000);
        assert_eq!(e.iface, "vcan0");
        assert_eq!(e.frame, frame(0x123, &[0xDE, 0xAD, 0xBE, 0xEF]));
        assert_eq!(e.direction, None);
    }

    #[test]
    fn parses_remote_empty_dotted_and_direction() {
        let p = |s| parse_line(s, 3).unwrap().unwrap();
        assert_eq!(
            p("(0.5) can0 023#R").frame,
            CanFrame::remote(StandardId::new(0x23).unwrap(), 0)
        );
        assert_eq!(
            p("(0.5) can0 023#R4").frame,
            CanFrame::remote(StandardId::new(0x23).unwrap(), 4)
        );
        assert_eq!(p("(0.5) can0 303#").frame, frame(0x303, &[]));
        assert_eq!(p("(0.5) can0 1#0a.0B").frame, frame(0x001, &[10, 11]));
        assert_eq!(p("(1.000000001) x 7FF#00").t_ns, 1_000_000_001);
        assert_eq!(
            p("(1.0) vcan0 200#00 T").direction,
            Some(LoggedDirection::Transmitted)
        );
        assert_eq!(parse_line("   ", 1).unwrap(), None);
        // An extended id (29 bits, 8 digits): a frame like any other.
        let ext = p("(1.0) vcan0 1ABCDEF0#0102").frame;
        assert_eq!(
            ext.id(),
            Id::Extended(ExtendedId::new(0x1ABC_DEF0).unwrap())
        );
        assert_eq!(
            (ext.data(), ext.to_string().as_str()),
            (&[1u8, 2][..], "1ABCDEF0#0102")
        );
        // An error frame (candump -e: bus-off, CRC errors...) is skipped.
        assert_eq!(
            parse_line("(1.5) can0 20000080#0000000000000000", 1).unwrap(),
            None
        );
        // ... but not one whose data is malformed.
        assert!(parse_line("(1.5) can0 20000080#00ZZ", 1).is_err());
    }

    #[test]
    fn rejects_with_the_line_number_and_text() {
        let e = |s| parse_line(s, 42).unwrap_err();
        let fd = e("(1.0) vcan0 123##1AABB");
        let text = fd.to_string();
        assert!(text.starts_with("line 42: CAN FD frame"), "{text}");
        assert!(text.contains("123##1AABB"), "{text}");
        assert_eq!(
            e("(1.0) vcan0 1234#00").kind,
            ErrorKind::BadId("a standard id has 3 hex digits, an extended id 8")
        );
        assert_eq!(
            e("(1.0) vcan0 40000000#00").kind,
            ErrorKind::BadId("above 0x1FFFFFFF")
        );
        assert_eq!(e("(1.0) vcan0 123##1AABB").kind, ErrorKind::CanFd);
        assert_eq!(e("(1.0) vcan0 123###x").kind, ErrorKind::CanXl);
        assert_eq!(
            e("(1.0) vcan0 123#1122334455667788_9").kind,
            ErrorKind::Len8Dlc
        );
        assert_eq!(
            e("(1.0) vcan0 123#112233445566778899").kind,
            ErrorKind::TooLong(9)
        );
        assert_eq!(
            e("(1.0) vcan0 123#ABC").kind,
            ErrorKind::BadData("odd number of hex digits")
        );
        assert_eq!(
            e("(1.0) vcan0 123#ZZ").kind,
            ErrorKind::BadData("not hex digits")
        );
        assert_eq!(
            e("(1.0) vcan0 800#00").kind,
            ErrorKind::BadId("above 0x7FF")
        );
        assert_eq!(e("(1.0) vcan0 123#R9").kind, ErrorKind::BadRemoteDlc);
        assert_eq!(e("(1.0) vcan0").kind, ErrorKind::MissingFrame);
        assert_eq!(e("(1.0)").kind, ErrorKind::MissingInterface);
        assert_eq!(e("(1.0) vcan0 123#00 X").kind, ErrorKind::Trailing);
        assert!(matches!(
            e("1.0 vcan0 123#00").kind,
            ErrorKind::Timestamp(_)
        ));
        assert!(matches!(
            e("(1) vcan0 123#00").kind,
            ErrorKind::Timestamp(_)
        ));
        assert!(matches!(
            e("(-1.0) vcan0 123#00").kind,
            ErrorKind::Timestamp(_)
        ));
        assert!(matches!(
            e("(99999999999999999999.0) vcan0 123#00").kind,
            ErrorKind::Timestamp(_)
        ));
    }

    #[test]
    fn log_errors_count_lines_from_one_and_skip_blank_lines() {
        let text = "(1.0) vcan0 123#00\n\n(1.1) vcan0 123##0\n";
        let e = parse_log(text).unwrap_err();
        assert_eq!((e.line, e.kind), (3, ErrorKind::CanFd));
        let bytes = b"(1.0) vcan0 123#00\r\n(1.1) vcan0 \xff#00\n";
        let e = parse_log_bytes(bytes).unwrap_err();
        assert_eq!((e.line, e.kind), (2, ErrorKind::NotText));
        assert_eq!(parse_log_bytes(b"(1.0) vcan0 123#00\r\n").unwrap().len(), 1);
    }

    #[test]
    fn writes_candump_l_lines() {
        let f = frame(0x123, &[0xDE, 0xAD, 0xBE, 0xEF]);
        assert_eq!(
            format_line(1_700_000_000_123_456_789, "vcan0", &f).unwrap(),
            "(1700000000.123456) vcan0 123#DEADBEEF"
        );
        assert_eq!(
            format_line(5_000, "can0", &frame(0x7, &[])).unwrap(),
            "(0000000000.000005) can0 007#"
        );
        let r = CanFrame::remote(StandardId::new(0x23).unwrap(), 8);
        assert_eq!(format_frame(&r), "023#R8");
        assert_eq!(format_line(0, "bad iface", &f), None);
        let mut w = Writer::new(Vec::new(), "vcan0").unwrap();
        w.write(1_000_000, &f).unwrap();
        let text = String::from_utf8(w.finish().unwrap()).unwrap();
        assert_eq!(text, "(0000000000.001000) vcan0 123#DEADBEEF\n");
        assert!(Writer::new(Vec::new(), "").is_err());
    }

    #[test]
    fn detects_candump_content() {
        assert!(looks_like_candump(b"\n (1.0) vcan0 123#00"));
        assert!(!looks_like_candump(b"\x89MCAP0\r\n"));
        assert!(!looks_like_candump(b""));
    }
}
