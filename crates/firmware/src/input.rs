//! Reading what a user hands the host tools (`std` only): files read with a size bound, and
//! input quoted in an error message cut short with its control characters escaped.
//!
//! Every host program reads its configurations, scenarios, logs and images through
//! [`read_bounded`] (after checking a file's first bytes with [`read_head`] where it has a
//! magic number), so `--config /dev/zero` or a 1 GB file that is not a log fails at once,
//! naming the bound, instead of filling the memory. Every error that echoes input goes
//! through [`quote`] or [`quote_lines`]: a 10 MB line is not echoed whole, and escape
//! sequences in a file never reach the terminal raw. A TOML error ([`TomlError`]) names the
//! key path and the value it points at.

use std::borrow::Cow;
use std::fmt::{self, Write as _};
use std::fs::File;
use std::io::{self, Read};
use std::ops::Range;
use std::path::Path;
use std::string::{String, ToString};
use std::vec::Vec;

use toml::Spanned;
use toml::de::{DeTable, DeValue};

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
    quote_at_most(text, MAX_QUOTE)
}

/// [`quote`] with another bound.
fn quote_at_most(text: &str, max: usize) -> String {
    let mut out = String::new();
    for (i, c) in text.chars().enumerate() {
        if i == max {
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

/// A TOML file's error as a user reads it: the parser's (line, column, the line quoted),
/// its last line led by the key path and the value it points at
/// (`drive.esc_ids = [1, 2, 3]: invalid length 3, expected an array of length 4`).
#[derive(Debug, Clone)]
pub struct TomlError {
    /// The key path of the value the error points at, with that value as written (a table's
    /// path alone); `None` where the text does not parse or nothing is pointed at.
    pub key: Option<String>,
    /// The parser's error.
    pub parse: toml::de::Error,
}

impl TomlError {
    /// `parse`, an error of reading `text`, with the key it points at.
    #[must_use]
    pub fn new(text: &str, parse: toml::de::Error) -> Self {
        let key = parse.span().and_then(|at| toml_key(text, &at));
        Self { key, parse }
    }
}

impl fmt::Display for TomlError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let message = self.parse.message();
        let shown = self.parse.to_string();
        // The parser's text ends with its message where it shows the line.
        let place = shown
            .strip_suffix('\n')
            .and_then(|s| s.strip_suffix(message))
            .filter(|place| !place.is_empty());
        match (place, &self.key) {
            (Some(place), Some(key)) => write!(
                f,
                "{}\n{}: {}",
                quote_lines(place),
                quote(key),
                quote_message(message)
            ),
            (Some(place), None) => write!(f, "{}\n{}", quote_lines(place), quote_message(message)),
            (None, _) => f.write_str(&quote_lines(&shown)),
        }
    }
}

/// The parser's message, [`gloss`]ed and quoted at 4 × [`MAX_QUOTE`]: its own words can run
/// past one quote's bound (an unknown key's error lists every key of its table).
fn quote_message(message: &str) -> String {
    let lines: Vec<_> = gloss(message)
        .lines()
        .map(|line| quote_at_most(line, 4 * MAX_QUOTE))
        .collect();
    lines.join("\n")
}

impl std::error::Error for TomlError {}

/// Serde names the number it expected by its Rust type (`expected f32`): said as the rule.
fn gloss(message: &str) -> Cow<'_, str> {
    const RULES: [(&str, &str); 6] = [
        ("f32", "a number (f32)"),
        ("f64", "a number (f64)"),
        ("u8", "an integer in 0..=255 (u8)"),
        ("u16", "an integer in 0..=65535 (u16)"),
        ("u32", "an integer in 0..=4294967295 (u32)"),
        ("u64", "an integer >= 0 (u64)"),
    ];
    for (rust, rule) in RULES {
        if let Some(head) = message.strip_suffix(rust)
            && head.ends_with("expected ")
        {
            return Cow::Owned(std::format!("{head}{rule}"));
        }
    }
    Cow::Borrowed(message)
}

/// A step of a key path: a key or an array index.
#[derive(Clone)]
enum Step<'a> {
    Key(&'a str),
    Index(usize),
}

/// The key path of the innermost key or value of `text` whose span holds `at`
/// (`faults[3].kind`), with the value as written unless it is a table or tables. (The search
/// recurses as deep as the tables nest, which the parser bounds: 80 levels.)
fn toml_key(text: &str, at: &Range<usize>) -> Option<String> {
    let root = DeTable::parse(text).ok()?;
    let mut path = Vec::new();
    let (steps, value) = find_in_table(root.get_ref(), at, &mut path)?;
    let mut key = String::new();
    for step in steps {
        match step {
            Step::Key(k)
                if k.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "_-".contains(c)) =>
            {
                if !key.is_empty() {
                    key.push('.');
                }
                key.push_str(k);
            }
            Step::Key(k) => {
                let dot = if key.is_empty() { "" } else { "." };
                let _ = write!(key, "{dot}{k:?}");
            }
            Step::Index(i) => {
                let _ = write!(key, "[{i}]");
            }
        }
    }
    if let Some(value) = value.and_then(|span| text.get(span)) {
        let _ = write!(key, " = {}", value.trim());
    }
    Some(key)
}

type Found<'a> = (Vec<Step<'a>>, Option<Range<usize>>);

fn find_in_table<'a>(
    table: &'a DeTable<'_>,
    at: &Range<usize>,
    path: &mut Vec<Step<'a>>,
) -> Option<Found<'a>> {
    for (key, value) in table {
        path.push(Step::Key(key.get_ref()));
        let found = if holds(&key.span(), at) {
            Some((path.clone(), None))
        } else {
            find_in_value(value, at, path)
        };
        path.pop();
        if found.is_some() {
            return found;
        }
    }
    None
}

fn find_in_value<'a>(
    value: &'a Spanned<DeValue<'_>>,
    at: &Range<usize>,
    path: &mut Vec<Step<'a>>,
) -> Option<Found<'a>> {
    let inner = match value.get_ref() {
        DeValue::Table(table) => find_in_table(table, at, path),
        DeValue::Array(items) => items.iter().enumerate().find_map(|(i, item)| {
            path.push(Step::Index(i));
            let found = find_in_value(item, at, path);
            path.pop();
            found
        }),
        _ => None,
    };
    inner.or_else(|| {
        holds(&value.span(), at).then(|| {
            let tables = match value.get_ref() {
                DeValue::Table(_) => true,
                DeValue::Array(items) => items.iter().any(|i| i.get_ref().is_table()),
                _ => false,
            };
            let shown = (!tables).then(|| value.span());
            (path.clone(), shown)
        })
    })
}

/// Whether `span` holds `at` (an empty `at` at its start too).
fn holds(span: &Range<usize>, at: &Range<usize>) -> bool {
    span.start <= at.start && at.end <= span.end && span.start < span.end
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

    /// The key path of each value, key and table a parser's error can point at.
    #[test]
    fn toml_keys_are_found_by_span() {
        let text = "top = 1\n\
                    [drive]\n\
                    esc_ids = [1, 2,\n  3]\n\
                    \"odd key\" = { a = [true] }\n\
                    [[faults]]\n\
                    kind = \"drop\"\n\
                    [[faults]]\n\
                    kind = 3\n";
        let at = |needle: &str, nth: usize| {
            let start = text.match_indices(needle).nth(nth).unwrap().0;
            start..start + needle.len()
        };
        for (span, want) in [
            (at("1", 0), "top = 1"),
            (at("[1, 2,\n  3]", 0), "drive.esc_ids = [1, 2,\n  3]"),
            (at("3", 0), "drive.esc_ids[2] = 3"),
            (at("esc_ids", 0), "drive.esc_ids"),
            (at("true", 0), "drive.\"odd key\".a[0] = true"),
            (at("[drive]", 0), "drive"),
            (at("3", 1), "faults[1].kind = 3"),
            (at("\"drop\"", 0), "faults[0].kind = \"drop\""),
        ] {
            assert_eq!(toml_key(text, &span).as_deref(), Some(want), "{span:?}");
        }
        assert_eq!(toml_key(text, &(0..text.len() + 1)), None);
        assert_eq!(
            toml_key("a = [", &(0..1)),
            None,
            "no key where it does not parse"
        );
        // Tables nested past the parser's bound: no document, so no search of them.
        let deep = std::format!("{}a = 1\nb = 2\n", "a.".repeat(100_000));
        assert_eq!(toml_key(&deep, &(deep.len() - 2..deep.len() - 1)), None);
    }

    #[test]
    fn toml_errors_lead_their_message_with_the_key() {
        #[derive(Debug, serde::Deserialize)]
        #[serde(deny_unknown_fields)]
        #[allow(dead_code)]
        struct Gains {
            kp: f32,
            ids: [u8; 2],
        }
        #[derive(Debug, serde::Deserialize)]
        #[allow(dead_code)]
        struct File {
            gains: Gains,
        }
        let error = |text: &str| {
            let parse = toml::from_str::<File>(text).unwrap_err();
            TomlError::new(text, parse).to_string()
        };
        assert_eq!(
            error("[gains]\nkp = \"1.2\"\nids = [1, 2]\n"),
            "TOML parse error at line 2, column 6\n  |\n2 | kp = \"1.2\"\n  |      ^^^^^\n\
             gains.kp = \"1.2\": invalid type: string \"1.2\", expected a number (f32)"
        );
        let msg = error("[gains]\nkp = 1.2\nids = [1, 256]\n");
        assert!(
            msg.ends_with(
                "gains.ids[1] = 256: invalid value: integer `256`, expected an integer in \
                 0..=255 (u8)"
            ),
            "{msg}"
        );
        // Input in the key or the value is quoted.
        let msg = error("[gains]\nkp = \"\\u001b[31m\"\nids = [1, 2]\n");
        assert!(
            !msg.contains('\u{1b}') && msg.contains("\\u{1b}[31m"),
            "{msg}"
        );
        // Much input in the value, the key or the message is cut.
        let msg = error(&std::format!("[gains]\nkp = \"{}\"\n", "x".repeat(10_000)));
        assert!(msg.len() < 1000 && msg.ends_with('…'), "{msg}");
        let msg = error(&std::format!("[gains]\nk{} = 1\n", "x".repeat(10_000)));
        assert!(msg.len() < 1500 && msg.ends_with('…'), "{msg}");
        // A syntax error has no key.
        let msg = error("[gains\n");
        assert!(msg.starts_with("TOML parse error at line 1"), "{msg}");
        assert!(!msg.contains("gains:"), "{msg}");
    }

    #[test]
    fn reads_stop_at_the_bound() {
        let err = read_bounded(Path::new("/dev/zero"), 1000).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::FileTooLarge);
        assert!(err.to_string().contains("1000 bytes"), "{err}");
        assert_eq!(read_head(Path::new("/dev/zero"), 8).unwrap(), [0; 8]);
    }
}
