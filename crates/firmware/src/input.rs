//! Reading what a user hands the host tools (`std` only): files read with a size bound, and
//! input quoted in an error message cut short with its control characters escaped.
//!
//! Every host program reads its configurations, scenarios, logs and images through
//! [`read_bounded`] (after checking a file's first bytes with [`read_head`] where it has a
//! magic number), so `--config /dev/zero` or a 1 GB file that is not a log fails at once,
//! naming the bound, instead of filling the memory. Every error that echoes input goes
//! through [`quote`] or [`quote_lines`]: a 10 MB line is not echoed whole, and escape
//! sequences in a file never reach the terminal raw.

use std::fs::File;
use std::io::{self, Read};
use std::path::Path;
use std::string::String;
use std::vec::Vec;

/// Characters of input an error message quotes, at most.
pub const MAX_QUOTE: usize = 120;

/// Bytes of a TOML file (a configuration, a scenario) read at most: such files are a few kB.
pub const MAX_TOML_BYTES: u64 = 1 << 20;

/// The whole of `path`, or an error if it holds more than `limit` bytes (which names the
/// bound; the file is not read past it). Reads devices and pipes too, to the bound.
///
/// # Errors
/// The OS error, or [`io::ErrorKind::FileTooLarge`] past the bound.
pub fn read_bounded(path: &Path, limit: u64) -> io::Result<Vec<u8>> {
    let file = File::open(path)?;
    let hint = file.metadata().map_or(0, |m| m.len()).min(limit);
    let mut bytes = Vec::with_capacity(usize::try_from(hint).unwrap_or(0));
    file.take(limit.saturating_add(1)).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(io::Error::new(
            io::ErrorKind::FileTooLarge,
            std::format!("larger than {limit} bytes, the most read of such a file"),
        ));
    }
    Ok(bytes)
}

/// A UTF-8 text file of at most [`MAX_TOML_BYTES`] ([`read_bounded`]).
///
/// # Errors
/// As [`read_bounded`], or [`io::ErrorKind::InvalidData`] naming the first byte that is not
/// UTF-8.
pub fn read_toml_text(path: &Path) -> io::Result<String> {
    String::from_utf8(read_bounded(path, MAX_TOML_BYTES)?).map_err(|e| {
        io::Error::new(
            io::ErrorKind::InvalidData,
            std::format!("not UTF-8 text (byte {})", e.utf8_error().valid_up_to()),
        )
    })
}

/// The first `n` bytes of `path` (fewer if it is shorter).
///
/// # Errors
/// The OS error.
pub fn read_head(path: &Path, n: u64) -> io::Result<Vec<u8>> {
    let mut head = Vec::new();
    File::open(path)?.take(n).read_to_end(&mut head)?;
    Ok(head)
}

/// `text` for an error message: at most [`MAX_QUOTE`] characters (then `…`), control
/// characters escaped (`\u{1b}`, `\n`).
#[must_use]
pub fn quote(text: &str) -> String {
    let mut out = String::new();
    for (i, c) in text.chars().enumerate() {
        if i == MAX_QUOTE {
            out.push('…');
            break;
        }
        if c.is_control() {
            out.extend(c.escape_debug());
        } else {
            out.push(c);
        }
    }
    out
}

/// A multi-line message that quotes input (a TOML parser's, with the offending line): each
/// line [`quote`]d, so the message keeps its shape and no line is long or raw.
#[must_use]
pub fn quote_lines(text: &str) -> String {
    text.lines().map(quote).collect::<Vec<_>>().join("\n")
}

/// [`quote`] of bytes that may not be UTF-8 (a file's first bytes): lossy, then quoted.
#[must_use]
pub fn quote_bytes(bytes: &[u8]) -> String {
    quote(&String::from_utf8_lossy(bytes))
}

#[cfg(test)]
mod tests {
    use std::string::ToString;

    use super::*;

    #[test]
    fn quotes_are_short_and_escaped() {
        assert_eq!(quote("kp = 1"), "kp = 1");
        assert_eq!(quote("a\u{1b}[31mb\u{7}"), "a\\u{1b}[31mb\\u{7}");
        let long = "x".repeat(10_000_000);
        let q = quote(&long);
        assert_eq!(q.chars().count(), MAX_QUOTE + 1);
        assert!(q.ends_with('…'));
        assert_eq!(
            quote_lines("line 1\n1 | \u{1b}x\n  | ^"),
            "line 1\n1 | \\u{1b}x\n  | ^"
        );
    }

    #[test]
    fn reads_stop_at_the_bound() {
        let err = read_bounded(Path::new("/dev/zero"), 1000).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::FileTooLarge);
        assert!(err.to_string().contains("1000 bytes"), "{err}");
        assert_eq!(read_head(Path::new("/dev/zero"), 8).unwrap(), [0; 8]);
    }
}
