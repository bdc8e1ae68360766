//! `decode`: candump lines on stdin, one JSON line each on stdout.

use std::fmt::Write as _;
use std::io::{self, BufRead, Write};

use drivelog::candump;
use embedded_can::Frame;
use firmware::CanFrame;
use firmware::protocol::dji::EscModel;

use crate::json::{decode_error_json, error_json};
use crate::message::{Routing, route};

/// `decode`'s options: which codecs read the ids outside the robot block.
#[derive(Debug, Clone, Copy, clap::Args)]
pub(crate) struct DecodeArgs {
    /// The DJI ESC model, whose current scale the DJI frames are read with.
    #[arg(long, value_name = "MODEL", value_enum, default_value_t = DjiModel::C620)]
    dji_model: DjiModel,
    /// Route every id outside the robot block (0x300-0x31F) to CANopen (CiA 301/402,
    /// dbc/cia402.dbc) instead of DJI and ODrive, whose ids CANopen's overlap (a bus carries
    /// one drive protocol), for any node 1-127: messages are named as in the DBC with the
    /// node's number (TPDO1_1, SDO_REQUEST_2, HEARTBEAT_127; NMT, SYNC). SDO frames give
    /// `command` as received and `data` as the decoder reads it: the transfer's bytes (and
    /// its `size`, 1-4) for expedited data, the abort code of an abort, 0 for an upload
    /// request or a download response. A SYNC with a counter (DLC 1) gives it as `counter`.
    /// RPDO2's ids (0x300 + node) are the robot protocol's, or unknown_id beyond its block.
    #[arg(long)]
    canopen: bool,
}

/// `--dji-model`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum DjiModel {
    /// C620 (M3508 motors): 20 A full scale.
    C620,
    /// C610 (M2006 motors): 10 A full scale.
    C610,
}

impl DecodeArgs {
    pub(crate) fn routing(self) -> Routing {
        Routing {
            model: match self.dji_model {
                DjiModel::C620 => EscModel::C620,
                DjiModel::C610 => EscModel::C610,
            },
            canopen: self.canopen,
        }
    }
}

/// The frame of a line: its `<id>#<data>` token, parsed by the project's candump grammar.
fn parse_candump(line: &str) -> Result<CanFrame, String> {
    let token = line
        .split_whitespace()
        .find(|t| t.contains('#'))
        .ok_or_else(|| "no <id>#<data> token".to_owned())?;
    candump::parse_frame(token).map_err(|e| e.to_string())
}

fn decode_line(line: &str, routing: Routing) -> String {
    let frame = match parse_candump(line) {
        Ok(f) => f,
        Err(msg) => return error_json(None, "parse", &msg, &[("line", line.into())]),
    };
    match route(&frame, routing) {
        Ok(msg) => msg.fields().json(frame.id(), None),
        Err(e) => decode_error_json(frame.id(), &e),
    }
}

pub(crate) fn run(routing: Routing) -> io::Result<()> {
    decode_stream(io::stdin().lock(), io::stdout().lock(), routing)
}

/// Bytes of an input line decoded at most: a candump line is under 100 (CAN FD under 300).
const MAX_LINE: usize = 4096;

/// One JSON line per non-blank input line; a line that is not UTF-8, or longer than
/// [`MAX_LINE`] (read no further than that: the rest is skipped, not buffered), gets a `parse`
/// error naming its number and its first bytes, like any other line that does not parse.
fn decode_stream(mut input: impl BufRead, output: impl Write, routing: Routing) -> io::Result<()> {
    let mut out = io::BufWriter::new(output);
    let mut line = Vec::with_capacity(128);
    for n in 1.. {
        line.clear();
        let Some(overlong) = read_line_bounded(&mut input, &mut line, MAX_LINE)? else {
            break;
        };
        let answer = match std::str::from_utf8(&line) {
            _ if overlong => error_json(
                None,
                "parse",
                &format!("line {n} is longer than {MAX_LINE} bytes: not decoded"),
                &[("begins", firmware::input::quote_bytes(&line).into())],
            ),
            Ok(text) if text.trim().is_empty() => continue,
            Ok(text) => decode_line(text.trim(), routing),
            Err(e) => {
                let mut hex = String::new();
                for b in line.iter().take(firmware::input::MAX_QUOTE) {
                    let _ = write!(hex, "{b:02X}");
                }
                error_json(
                    None,
                    "parse",
                    &format!("line {n} is not UTF-8: {e}"),
                    &[("bytes", hex.into())],
                )
            }
        };
        writeln!(out, "{answer}")?;
    }
    out.flush()
}

/// Reads one line (without its `\n`) into `line`, keeping at most `max` bytes of it and
/// skipping the rest. `None` at the end of the input; else whether the line was longer.
fn read_line_bounded(
    input: &mut impl BufRead,
    line: &mut Vec<u8>,
    max: usize,
) -> io::Result<Option<bool>> {
    let (mut any, mut overlong) = (false, false);
    loop {
        let buf = input.fill_buf()?;
        if buf.is_empty() {
            return Ok(any.then_some(overlong));
        }
        any = true;
        let end = buf.iter().position(|&b| b == b'\n');
        let chunk = &buf[..end.unwrap_or(buf.len())];
        let room = max.saturating_sub(line.len());
        overlong |= chunk.len() > room;
        line.extend_from_slice(&chunk[..chunk.len().min(room)]);
        let used = end.map_or(buf.len(), |i| i + 1);
        input.consume(used);
        if end.is_some() {
            return Ok(Some(overlong));
        }
    }
}

#[cfg(test)]
mod tests {
    use firmware::protocol::ErrorKind;

    use super::*;

    fn candump_text(frame: &CanFrame) -> String {
        candump::format_frame(frame)
    }

    #[test]
    fn parses_candump_forms() {
        let f = parse_candump("(1700000000.123456) vcan0 123#DEADBEEF").unwrap();
        assert_eq!(f.data(), &[0xDE, 0xAD, 0xBE, 0xEF]);
        assert_eq!(candump_text(&f), "123#DEADBEEF");
        let f = parse_candump("301#F4.01.06.FF.E8.03.07.00").unwrap();
        assert_eq!(f.dlc(), 8);
        let f = parse_candump("023#R8").unwrap();
        assert!(f.is_remote_frame());
        assert_eq!(candump_text(&f), "023#R8");
        let f = parse_candump("12345678#").unwrap();
        assert!(f.is_extended());
        assert!(parse_candump("123#ABC").is_err());
        assert!(parse_candump("823#00").is_err());
        assert!(parse_candump("123#000000000000000000").is_err());
        assert!(parse_candump("123##1").is_err());
        assert!(parse_candump("hello").is_err());
    }

    #[test]
    fn decode_line_reports_errors_and_values() {
        let ok = decode_line("301#F40106FFE8030700", Routing::default());
        assert!(ok.contains("\"message\":\"TWIST_CMD\""), "{ok}");
        assert!(ok.contains("\"vx\":0.5"), "{ok}");
        let err = decode_line("301#F40106FFE80307", Routing::default());
        assert!(err.contains("\"kind\":\"wrong_dlc\""), "{err}");
        let err = decode_line("garbage", Routing::default());
        assert!(err.contains("\"kind\":\"parse\""), "{err}");
        assert_eq!(ErrorKind::WrongDlc.as_str(), "wrong_dlc");
    }

    /// The three output lines of `input`: a TWIST_CMD, the line under test, a TWIST_CMD.
    fn decoded_between_two_twists(input: impl BufRead) -> Vec<String> {
        let mut out = Vec::new();
        decode_stream(input, &mut out, Routing::default()).unwrap();
        let text = String::from_utf8(out).unwrap();
        let lines: Vec<String> = text.lines().map(str::to_string).collect();
        assert_eq!(lines.len(), 3, "{text}");
        assert!(
            lines[0].contains("TWIST_CMD") && lines[2].contains("TWIST_CMD"),
            "{text}"
        );
        lines
    }

    #[test]
    fn a_line_that_is_not_utf8_is_an_error_line_and_the_rest_go_on() {
        let input: &[u8] = b"301#F40106FFE8030700\n\xFF\xFE\n\n301#F40106FFE8030700\r\n";
        let lines = decoded_between_two_twists(input);
        assert!(lines[1].contains("\"kind\":\"parse\""), "{}", lines[1]);
        assert!(lines[1].contains("line 2 is not UTF-8"), "{}", lines[1]);
        assert!(lines[1].contains("\"bytes\":\"FFFE\""), "{}", lines[1]);
    }

    #[test]
    fn a_line_past_the_bound_is_skipped_not_buffered_and_the_rest_go_on() {
        let mut input = b"301#F40106FFE8030700\n".to_vec();
        input.extend(std::iter::repeat_n(0x1b, 3 * MAX_LINE));
        input.extend_from_slice(b"\n301#F40106FFE8030700");
        // A reader that hands over 100 bytes at a time: the bound holds across its buffers.
        let lines = decoded_between_two_twists(io::BufReader::with_capacity(100, &input[..]));
        assert!(
            lines[1].contains("line 2 is longer than 4096 bytes"),
            "{}",
            lines[1]
        );
        // The start is quoted, cut and escaped: no raw ESC reaches a terminal.
        assert!(
            !lines[1].contains('\u{1b}') && lines[1].len() < 1200,
            "{}",
            lines[1]
        );
    }

    #[test]
    fn canopen_ids_route_to_canopen_only_with_the_flag() {
        let canopen = Routing {
            canopen: true,
            ..Routing::default()
        };
        // 0x201: DJI feedback of ESC 1, or RPDO1 of node 1 (DLC 6).
        let dji = decode_line("201#1FFF03E8FC182500", Routing::default());
        assert!(dji.contains("\"message\":\"FEEDBACK_1\""), "{dji}");
        let rpdo = decode_line("201#0F00D0070000", canopen);
        assert!(rpdo.contains("\"protocol\":\"canopen\""), "{rpdo}");
        assert!(
            rpdo.contains("\"message\":\"RPDO1_1\",\"node\":1"),
            "{rpdo}"
        );
        assert!(
            rpdo.contains("{\"controlword\":15,\"target_velocity\":2000}"),
            "{rpdo}"
        );
        // NMT (0x000) is ODrive's Get_Version without the flag (not implemented there).
        let nmt = decode_line("000#0100", canopen);
        assert!(nmt.contains("{\"command\":1,\"node\":0}"), "{nmt}");
        assert!(!nmt.contains("\"node\":0,\"fields\""), "{nmt}");
        let odrive = decode_line("000#0100", Routing::default());
        assert!(odrive.contains("\"kind\":\"unknown_id\""), "{odrive}");
        // The robot block stays the robot's: RPDO2 of node 1 is TWIST_CMD's id.
        let twist = decode_line("301#F40106FFE8030700", canopen);
        assert!(twist.contains("\"message\":\"TWIST_CMD\""), "{twist}");
        let rpdo2 = decode_line("341#0F00D0070000", canopen);
        assert!(rpdo2.contains("\"kind\":\"unknown_id\""), "{rpdo2}");
        let sync = decode_line("080#05", canopen);
        assert!(
            sync.contains("\"message\":\"SYNC\",\"counter\":5,\"fields\":{}"),
            "{sync}"
        );
    }
}
