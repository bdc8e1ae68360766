//! Hand-written JSON for the messages written most often: the CAN frames of `/can/rx`,
//! `/can/tx` and `/can/bus` (about ten per simulated millisecond).
//!
//! `core::fmt` (`write!`) costs a dynamic dispatch per argument and per piece of literal text;
//! these messages are fixed text around a few unsigned integers and booleans, so they are
//! built as byte strings with a small integer formatter, in a buffer on the stack whose write
//! position stays in a register, and appended to the chunk in one copy (about 40 ns a frame,
//! against 80 ns appending piece by piece to the `Vec` and more with `write!`). The output is
//! the same JSON text `write!` gave.

use embedded_can::{Frame, Id};
use firmware::CanFrame;

use crate::bus::{Fate, Node};

/// "00" to "99", for two digits at a time.
const DIGIT_PAIRS: &[u8; 200] = b"\
    0001020304050607080910111213141516171819\
    2021222324252627282930313233343536373839\
    4041424344454647484950515253545556575859\
    6061626364656667686970717273747576777879\
    8081828384858687888990919293949596979899";

/// 10^i for i in 0..20.
const POWERS_OF_10: [u64; 20] = {
    let mut p = [1u64; 20];
    let mut i = 1;
    while i < 20 {
        p[i] = p[i - 1] * 10;
        i += 1;
    }
    p
};

/// Decimal digits of `n` (1 to 20).
#[inline]
fn decimal_len(n: u64) -> usize {
    // log10(2) is about 1233 / 4096: an estimate from the bit length, off by at most one.
    let bits = 64 - (n | 1).leading_zeros() as usize;
    let estimate = (bits * 1233) >> 12;
    estimate + 1 - usize::from((n | 1) < POWERS_OF_10[estimate])
}

/// Every byte in decimal followed by a separator byte (patched in by [`byte_then`]),
/// padded to four bytes, and the length of each without the padding.
const BYTE_TEXT: ([[u8; 4]; 256], [u8; 256]) = {
    let mut text = [[0u8; 4]; 256];
    let mut len = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        let b = i as u8;
        if b >= 100 {
            text[i] = [b'0' + b / 100, b'0' + b / 10 % 10, b'0' + b % 10, 0];
            len[i] = 4;
        } else if b >= 10 {
            text[i] = [b'0' + b / 10, b'0' + b % 10, 0, 0];
            len[i] = 3;
        } else {
            text[i] = [b'0' + b, 0, 0, 0];
            len[i] = 2;
        }
        i += 1;
    }
    (text, len)
};

/// Longest frame message, bytes: the fixed text (about 200 bytes with the longest sender and
/// fate), two `u64` of 20 digits, a `u32` of 10, 8 bytes of 3 digits.
const LINE_CAPACITY: usize = 320;

/// One message built on the stack, then appended to the chunk in one copy: cheaper than
/// many small appends to a `Vec`, each of which checks its capacity and stores its length.
/// Each function writes at `at` and returns where the next text goes (a position kept in a
/// struct field was stored and reloaded around every piece, on the critical path).
type Line = [u8; LINE_CAPACITY];

#[inline(always)]
fn text(line: &mut Line, at: usize, s: &[u8]) -> usize {
    line[at..at + s.len()].copy_from_slice(s);
    at + s.len()
}

/// `n` in decimal.
#[inline(always)]
fn decimal(line: &mut Line, at: usize, mut n: u64) -> usize {
    let len = decimal_len(n);
    let digits = &mut line[at..at + len];
    let mut end = len;
    while n >= 100 {
        let pair = (n % 100) as usize * 2;
        n /= 100;
        end -= 2;
        digits[end..end + 2].copy_from_slice(&DIGIT_PAIRS[pair..pair + 2]);
    }
    if n >= 10 {
        let pair = n as usize * 2;
        digits[end - 2..end].copy_from_slice(&DIGIT_PAIRS[pair..pair + 2]);
    } else {
        digits[end - 1] = b'0' + n as u8;
    }
    at + len
}

/// A byte in decimal followed by `sep`.
#[inline(always)]
fn byte_then(line: &mut Line, at: usize, b: u8, sep: u8) -> usize {
    let len = usize::from(BYTE_TEXT.1[usize::from(b)]);
    line[at..at + 4].copy_from_slice(&BYTE_TEXT.0[usize::from(b)]);
    line[at + len - 1] = sep;
    at + len
}

/// The flags of a frame and the text up to its DLC, for each (remote, extended).
const FLAGS: [[&[u8]; 2]; 2] = [
    [
        br#","is_rtr":false,"is_extended":false,"is_error":false,"dlc":"#,
        br#","is_rtr":false,"is_extended":true,"is_error":false,"dlc":"#,
    ],
    [
        br#","is_rtr":true,"is_extended":false,"is_error":false,"dlc":"#,
        br#","is_rtr":true,"is_extended":true,"is_error":false,"dlc":"#,
    ],
];

/// Appends one frame as can_msgs/Frame-shaped JSON (see
/// [`CAN_FRAME_SCHEMA`](super::CAN_FRAME_SCHEMA)), data padded to 8 bytes, with `sender` and
/// `fate` for the bus channel:
///
/// `{"header":{"stamp":{"sec":1,"nsec":5000},"frame_id":"can0"},"id":513,"is_rtr":false,
/// "is_extended":false,"is_error":false,"dlc":8,"data":[0,1,2,3,4,5,6,7],"sender":"drives",
/// "fate":"delivered"}` (on one line).
pub fn write_frame_json(
    buf: &mut Vec<u8>,
    t_ns: u64,
    frame: &CanFrame,
    extra: Option<(Node, Fate)>,
) {
    let (id, ext) = match frame.id() {
        Id::Standard(id) => (u32::from(id.as_raw()), false),
        Id::Extended(id) => (id.as_raw(), true),
    };
    let mut data = [0u8; 8];
    let d = frame.data();
    data[..d.len()].copy_from_slice(d);
    let mut line: Line = [0; LINE_CAPACITY];
    let l = &mut line;
    let mut at = text(l, 0, br#"{"header":{"stamp":{"sec":"#);
    at = decimal(l, at, t_ns / 1_000_000_000);
    at = text(l, at, br#","nsec":"#);
    at = decimal(l, at, t_ns % 1_000_000_000);
    at = text(l, at, br#"},"frame_id":"can0"},"id":"#);
    at = decimal(l, at, u64::from(id));
    at = text(
        l,
        at,
        FLAGS[usize::from(frame.is_remote_frame())][usize::from(ext)],
    );
    // A DLC is at most 8 (15 for CAN FD): a byte.
    at = byte_then(l, at, frame.dlc() as u8, b',');
    at = text(l, at, br#""data":["#);
    for &b in &data[..7] {
        at = byte_then(l, at, b, b',');
    }
    at = byte_then(l, at, data[7], b']');
    if let Some((sender, fate)) = extra {
        at = text(l, at, br#","sender":""#);
        at = text(l, at, sender.name().as_bytes());
        at = text(
            l,
            at,
            match fate {
                Fate::Delivered => br#"","fate":"delivered""#,
                Fate::Dropped => br#"","fate":"dropped""#,
                Fate::Corrupted => br#"","fate":"corrupted""#,
            },
        );
    }
    at = text(l, at, b"}");
    buf.extend_from_slice(&line[..at]);
}

/// Appends `n` in decimal.
pub(super) fn push_u64(buf: &mut Vec<u8>, n: u64) {
    let mut line = [0u8; LINE_CAPACITY];
    let end = decimal(&mut line, 0, n);
    buf.extend_from_slice(&line[..end]);
}

/// Appends `n` in decimal.
pub(super) fn push_i64(buf: &mut Vec<u8>, n: i64) {
    if n < 0 {
        buf.push(b'-');
    }
    push_u64(buf, n.unsigned_abs());
}

/// Appends `v` as `Display` writes it (`{}`): the shortest digits that read back as `v`, in
/// positional notation (`0.000001`, `1`, `100000000000000000000`), `-0` for negative zero,
/// and `null` for NaN and the infinities, which JSON has no number for (`NaN` would make the
/// whole message unparseable). The digits come from `zmij` (Schubfach, about ten times faster
/// than `core::fmt` here): the shortest representation closest to `v`, as `core::fmt`'s
/// Grisu and Dragon give it; `display_f32_is_core_fmt` checks that for every `f32`.
pub(super) fn push_f32(buf: &mut Vec<u8>, v: f32) {
    if !v.is_finite() {
        buf.extend_from_slice(b"null");
        return;
    }
    let mut text = zmij::Buffer::new();
    let text = text.format_finite(v).as_bytes();
    // zmij writes `[-]digits[.digits][e[+-]exponent]`: collect the digits and where the
    // decimal point falls in them.
    let (negative, text) = match text.split_first() {
        Some((b'-', rest)) => (true, rest),
        _ => (false, text),
    };
    let (mantissa, exponent) = match text.iter().position(|&c| c == b'e') {
        Some(e) => (&text[..e], &text[e + 1..]),
        None => (text, &b""[..]),
    };
    let mut exp: i32 = 0;
    let mut exp_negative = false;
    for &c in exponent {
        match c {
            b'-' => exp_negative = true,
            b'+' => {}
            _ => exp = exp * 10 + i32::from(c - b'0'),
        }
    }
    if exp_negative {
        exp = -exp;
    }
    let mut digits = [0u8; 24];
    let mut n = 0;
    let mut point = None;
    for &c in mantissa {
        if c == b'.' {
            point = Some(n);
        } else {
            digits[n] = c;
            n += 1;
        }
    }
    // The significant digits as an integer, `d`, and the value: d * 10^k.
    let mut first = 0;
    while first < n && digits[first] == b'0' {
        first += 1;
    }
    let mut last = n;
    while last > first && digits[last - 1] == b'0' {
        last -= 1;
    }
    if negative {
        buf.push(b'-');
    }
    if first == last {
        buf.push(b'0');
        return;
    }
    let mut d = digits[first..last]
        .iter()
        .fold(0u64, |d, &c| d * 10 + u64::from(c - b'0'));
    let mut k = point.unwrap_or(n) as i32 + exp - last as i32;
    if is_tie_below(v.abs(), d, k) {
        // Two shortest candidates are equally near: zmij takes the even one, core::fmt the
        // one above.
        d += 1;
        while d.is_multiple_of(10) {
            d /= 10;
            k += 1;
        }
    }
    let mut digits = [0u8; 20];
    let mut at = digits.len();
    while d > 0 {
        at -= 1;
        digits[at] = b'0' + (d % 10) as u8;
        d /= 10;
    }
    let digits = &digits[at..];
    let len = digits.len() as i32;
    // Digits before the decimal point (negative: zeros after it before the first digit).
    let before = k + len;
    if before <= 0 {
        buf.extend_from_slice(b"0.");
        buf.resize(buf.len() + (-before) as usize, b'0');
        buf.extend_from_slice(digits);
    } else if before < len {
        let (int, frac) = digits.split_at(before as usize);
        buf.extend_from_slice(int);
        buf.push(b'.');
        buf.extend_from_slice(frac);
    } else {
        buf.extend_from_slice(digits);
        buf.resize(buf.len() + (before - len) as usize, b'0');
    }
}

/// Whether `v` (finite, positive) is exactly halfway between `d * 10^k` and
/// `(d + 1) * 10^k`: `v = (2d + 1) * 10^k / 2`. Exact, in integers: `v = odd * 2^p` with
/// `odd` odd, and `(2d + 1) * 5^k * 2^(k - 1)` has the odd part `(2d + 1) * 5^k` (for
/// `k >= 0`; for `k < 0`, `odd * 5^-k` must be `2d + 1`).
fn is_tie_below(v: f32, d: u64, k: i32) -> bool {
    let bits = v.to_bits();
    let exponent = (bits >> 23) as i32;
    let (mantissa, e) = if exponent == 0 {
        (bits & 0x7f_ffff, -149)
    } else {
        ((bits & 0x7f_ffff) | 0x80_0000, exponent - 150)
    };
    if mantissa == 0 {
        return false;
    }
    let zeros = mantissa.trailing_zeros();
    let odd = u128::from(mantissa >> zeros);
    let p = e + zeros as i32;
    let twice_plus_one = 2 * u128::from(d) + 1;
    if k >= 0 {
        p == k - 1
            && 5u128
                .checked_pow(k as u32)
                .and_then(|f| f.checked_mul(twice_plus_one))
                == Some(odd)
    } else {
        p == k - 1
            && 5u128
                .checked_pow(k.unsigned_abs())
                .and_then(|f| f.checked_mul(odd))
                == Some(twice_plus_one)
    }
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use embedded_can::{ExtendedId, StandardId};

    use super::*;

    #[test]
    fn integers_match_display() {
        let mut n = 1u64;
        let mut values = vec![0, 9, 10, 99, 100, 101, 999, 1000, u64::MAX, u64::MAX - 1];
        while let Some(m) = n.checked_mul(7) {
            values.extend([n - 1, n, n + 1]);
            n = m;
        }
        values.extend(POWERS_OF_10.iter().flat_map(|&p| [p - 1, p, p + 1]));
        let mut line = [0; LINE_CAPACITY];
        for v in values {
            let end = decimal(&mut line, 3, v);
            assert_eq!(&line[3..end], v.to_string().as_bytes());
        }
        for b in 0..=255u8 {
            let end = byte_then(&mut line, 1, b, b',');
            assert_eq!(&line[1..end], format!("{b},").as_bytes());
        }
    }

    /// `push_f32` against `core::fmt` for the `f32` with bit patterns `bits`.
    fn check_f32(bits: impl Iterator<Item = u32>) -> u64 {
        let mut ours = Vec::new();
        let mut core = Vec::new();
        let mut checked = 0;
        for b in bits {
            let v = f32::from_bits(b);
            ours.clear();
            core.clear();
            push_f32(&mut ours, v);
            if v.is_finite() {
                write!(core, "{v}").unwrap();
            } else {
                core.extend_from_slice(b"null");
            }
            assert_eq!(
                ours,
                core,
                "{b:#010x}: {} against {}",
                String::from_utf8_lossy(&ours),
                String::from_utf8_lossy(&core)
            );
            checked += 1;
        }
        checked
    }

    #[test]
    fn non_finite_floats_are_json_null() {
        for v in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut buf = b"[".to_vec();
            push_f32(&mut buf, v);
            buf.push(b']');
            let parsed: serde_json::Value = serde_json::from_slice(&buf).unwrap();
            assert_eq!(parsed, serde_json::json!([null]), "{v}");
        }
    }

    #[test]
    fn display_f32_matches_core_fmt_on_a_sample() {
        // Every 4093rd bit pattern (a prime step: all exponents, varied mantissas, both signs),
        // and the edges: zeros, subnormals, the extremes, infinities, NaN, round numbers.
        let mut special = vec![0, 0x8000_0000, 1, 0x8000_0001, 0x007f_ffff, 0x0080_0000];
        special.extend([
            0x7f7f_ffff,
            0xff7f_ffff,
            0x7f80_0000,
            0xff80_0000,
            0x7fc0_0000,
        ]);
        for v in [
            1.0f32,
            0.1,
            0.5,
            10.0,
            1e-7,
            1e7,
            123_456_790.0,
            3.4e38,
            1e-45,
            0.3,
        ] {
            special.extend([v.to_bits(), (-v).to_bits()]);
        }
        let n = check_f32(special.into_iter().chain((0..=u32::MAX).step_by(4093)));
        assert!(n > 1_000_000);
        let mut buf = Vec::new();
        for (n, text) in [(0i64, "0"), (-1, "-1"), (i64::MIN, "-9223372036854775808")] {
            buf.clear();
            push_i64(&mut buf, n);
            assert_eq!(buf, text.as_bytes());
        }
    }

    /// Every `f32` (passed with zmij 1.0.23: 14 minutes on two shared cores).
    /// `cargo test --release -p hostsim --lib -- --ignored display_f32_is_core_fmt`.
    #[test]
    #[ignore = "every f32: run it when push_f32 or zmij changes"]
    fn display_f32_is_core_fmt() {
        let threads = std::thread::available_parallelism().map_or(2, |n| n.get()) as u64;
        let per = (1u64 << 32).div_ceil(threads);
        let checked: u64 = std::thread::scope(|s| {
            let handles: Vec<_> = (0..threads)
                .map(|t| {
                    let from = t * per;
                    let to = ((t + 1) * per).min(1 << 32);
                    s.spawn(move || check_f32((from..to).map(|b| b as u32)))
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).sum()
        });
        assert_eq!(checked, 1 << 32);
    }

    /// The text `write!` gave before the formatter was hand-written.
    fn with_fmt(t_ns: u64, frame: &CanFrame, extra: Option<(Node, Fate)>) -> Vec<u8> {
        let (id, ext) = match frame.id() {
            Id::Standard(id) => (u32::from(id.as_raw()), false),
            Id::Extended(id) => (id.as_raw(), true),
        };
        let mut d = [0u8; 8];
        d[..frame.data().len()].copy_from_slice(frame.data());
        let mut buf = Vec::new();
        write!(
            buf,
            r#"{{"header":{{"stamp":{{"sec":{},"nsec":{}}},"frame_id":"can0"}},"id":{},"is_rtr":{},"is_extended":{},"is_error":false,"dlc":{},"data":[{},{},{},{},{},{},{},{}]"#,
            t_ns / 1_000_000_000,
            t_ns % 1_000_000_000,
            id,
            frame.is_remote_frame(),
            ext,
            frame.dlc(),
            d[0],
            d[1],
            d[2],
            d[3],
            d[4],
            d[5],
            d[6],
            d[7],
        )
        .unwrap();
        if let Some((sender, fate)) = extra {
            let fate = format!("{fate:?}").to_lowercase();
            write!(buf, r#","sender":"{}","fate":"{fate}""#, sender.name()).unwrap();
        }
        buf.push(b'}');
        buf
    }

    #[test]
    fn frames_are_the_json_write_gave_and_parse() {
        let frames = [
            CanFrame::standard(
                StandardId::new(0x201).unwrap(),
                &[0, 9, 10, 99, 100, 255, 1, 7],
            )
            .unwrap(),
            CanFrame::standard(StandardId::new(0x7FF).unwrap(), &[3]).unwrap(),
            CanFrame::new(ExtendedId::new(0x1FFF_FFFF).unwrap(), &[]).unwrap(),
            CanFrame::new_remote(StandardId::ZERO, 4).unwrap(),
        ];
        let extras = [
            None,
            Some((Node::Drives, Fate::Delivered)),
            Some((Node::Host, Fate::Dropped)),
            Some((Node::Controller, Fate::Corrupted)),
        ];
        for (i, frame) in frames.iter().enumerate() {
            for extra in extras {
                for t_ns in [0, 999_999_999, 1_000_000_000, 61_234_567_890, u64::MAX] {
                    let mut buf = b"prefix".to_vec();
                    write_frame_json(&mut buf, t_ns, frame, extra);
                    let json = &buf[b"prefix".len()..];
                    assert_eq!(
                        json,
                        with_fmt(t_ns, frame, extra),
                        "frame {i}, {}",
                        String::from_utf8_lossy(json)
                    );
                    let v: serde_json::Value = serde_json::from_slice(json).unwrap();
                    assert_eq!(v["data"].as_array().unwrap().len(), 8);
                    assert_eq!(v["header"]["stamp"]["sec"], t_ns / 1_000_000_000);
                }
            }
        }
    }
}
