//! `mecanum-codec`: the firmware's CAN codecs on the command line, for logs and for the Python
//! cross-check against the DBC files (see `--help`).
//!
//! The doc comments of [`Cli`] and its commands are its `--help`, terminal text and not
//! Markdown: `<id>#<data>` is a placeholder, not a tag. Rustdoc's lint on them is off.
#![allow(rustdoc::invalid_html_tags)]

mod canopen;

use std::fmt::Write as _;
use std::io::{self, BufRead, Write};
use std::path::PathBuf;
use std::process::ExitCode;

use canopen::CanopenFrame;
use clap::{Parser, Subcommand};
use drivelog::candump;
use embedded_can::{Frame, Id};
use firmware::CanFrame;
use firmware::protocol::dji::{self, EscGroup, EscId, EscModel};
use firmware::protocol::odrive::{self, AxisState, ControlMode, InputMode, NodeId};
use firmware::protocol::robot::{self, Fault, HeadingSource, ModeRequest, RobotState};
use firmware::protocol::wire::Field;
use firmware::protocol::{DecodeError, non_finite_name};
use serde::Serialize;
use serde_json::Value;

/// Decode CAN frames with the mecanum firmware's codecs, or print golden frames.
///
/// The codecs are the firmware's own: the robot protocol (dbc/mecanum_robot.dbc), DJI
/// C620/C610 (dbc/dji_c620.dbc), ODrive CAN Simple (dbc/odrive_cansimple.dbc) and, with
/// `decode --canopen`, CANopen CiA 301/402 (dbc/cia402.dbc). `decode` reads candump lines and
/// prints JSON lines; `golden` prints frames built by the encoders, for the Python tests to
/// decode with cantools and the DBC files; `config-id` names the configuration a robot runs.
/// `mecanum-codec help <COMMAND>` explains each.
#[derive(Debug, Parser)]
#[command(
    name = "mecanum-codec",
    version,
    about = "Decode CAN frames with the mecanum firmware's codecs, or print golden frames.",
    long_about,
    arg_required_else_help = true,
    after_help = "Exit status: 0; 1 for a configuration that does not load (the error names the \
                  file and the line or field); 2 for bad arguments."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Decode candump lines on stdin, one JSON line per input line.
    ///
    /// Reads candump lines on stdin, one frame per line, in the log format
    ///     (1700000000.123456) vcan0 123#DEADBEEF
    /// or bare (123#DEADBEEF, 123#R, 123#R8 for remote frames; 3 hex digits = standard id,
    /// 8 = extended id; bytes may be separated by '.' between bytes): the line's <id>#<data>
    /// token, read by the same candump grammar as `hostsim replay`. Prints one JSON line per
    /// input line:
    ///     {"id":769,"protocol":"robot","message":"TWIST_CMD","fields":{"vx":0.5,...}}
    /// or, for a frame the codecs reject or a line that does not parse,
    ///     {"id":769,"error":{"kind":"wrong_dlc","message":"...","expected":8,"got":7}}
    /// and carries on with the next line. Field names are the DBC signal names, values are
    /// physical (SI) values as the DBC scales them; enums are their numbers. `message` is the
    /// DBC message name (ODrive and CANopen messages carry a `node`, DJI feedback an `esc`).
    /// Routing by id: 0x300-0x31F robot protocol, 0x1FF-0x208 DJI (C620 scale unless
    /// --dji-model c610), 0x000-0x07F ODrive CAN Simple nodes 0-3; anything else is
    /// unknown_id (--canopen routes otherwise).
    /// Error kinds: unknown_id, extended_id, remote, wrong_dlc, non_finite, out_of_range, parse.
    #[command(verbatim_doc_comment)]
    Decode(DecodeArgs),
    /// Print the golden frames: one JSON line each, for the DBC cross-check.
    ///
    /// Prints a fixed set of frames built by the Rust encoders, one JSON line each, with the
    /// candump text of the frame, the values given to the encoder ("input") and the values the
    /// Rust decoder reads back ("fields"), CANopen frames (protocol "canopen") included,
    /// each read back as `decode --canopen` does. The Python tests decode the candump text with
    /// cantools and the DBC files and compare.
    #[command(verbatim_doc_comment)]
    Golden,
    /// Print the id of each drive configuration, `0x1a2b  robot.toml`.
    ///
    /// Reads each drive configuration (TOML, validated as mecanum-runner reads it) and prints
    /// its id and path, `0x1a2b  robot.toml`: the id a robot running that configuration sends
    /// in HEARTBEAT.config_id (and a board image logs at boot), so you can tell what is flashed.
    /// Exit status 1 at the first file that does not load.
    #[command(verbatim_doc_comment)]
    ConfigId {
        /// Drive configurations (TOML, as config/dji_m3508.toml).
        #[arg(required = true, value_name = "FILE")]
        files: Vec<PathBuf>,
    },
}

/// `decode`'s options: which codecs read the ids outside the robot block.
#[derive(Debug, Clone, Copy, clap::Args)]
struct DecodeArgs {
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
    fn routing(self) -> Routing {
        Routing {
            model: match self.dji_model {
                DjiModel::C620 => EscModel::C620,
                DjiModel::C610 => EscModel::C610,
            },
            canopen: self.canopen,
        }
    }
}

fn main() -> ExitCode {
    // Bad arguments: clap's message naming the argument, exit status 2.
    let result = match Cli::parse().command {
        Command::Decode(args) => decode_stdin(args.routing()),
        Command::Golden => golden(),
        Command::ConfigId { files } => return config_ids(&files),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        // A closed pipe (`| head`) is not an error worth a message.
        Err(e) if e.kind() == io::ErrorKind::BrokenPipe => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("mecanum-codec: {e}");
            ExitCode::FAILURE
        }
    }
}

/// `config-id`: the id of each configuration file.
fn config_ids(files: &[PathBuf]) -> ExitCode {
    for file in files {
        match firmware::Config::from_toml_file(file) {
            Ok(config) => println!("0x{:04x}  {}", config.id(), file.display()),
            Err(e) => {
                eprintln!("mecanum-codec: {e}");
                return ExitCode::FAILURE;
            }
        }
    }
    ExitCode::SUCCESS
}

// ---------------------------------------------------------------------------------------------
// candump text (the grammar is drivelog's) and JSON (serde_json, in the order written here)

/// The frame of a line: its `<id>#<data>` token, parsed by the project's candump grammar.
fn parse_candump(line: &str) -> Result<CanFrame, String> {
    let token = line
        .split_whitespace()
        .find(|t| t.contains('#'))
        .ok_or_else(|| "no <id>#<data> token".to_owned())?;
    candump::parse_frame(token).map_err(|e| e.to_string())
}

fn candump_text(frame: &CanFrame) -> String {
    candump::format_frame(frame)
}

/// A JSON number: the codecs' integers and floats (a non-finite float is `null`, as
/// serde_json writes it; the codecs never produce one).
#[derive(Clone, Copy, Serialize)]
#[serde(untagged)]
enum Num {
    Int(i64),
    Float(f32),
}

/// Named values as a JSON object, in their order.
struct Fields<'a, V>(&'a [(&'a str, V)]);

impl<V: Serialize> Serialize for Fields<'_, V> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_map(self.0.iter().map(|(k, v)| (k, v)))
    }
}

/// One decoded message, protocol-independent.
struct Decoded {
    protocol: &'static str,
    message: String,
    /// The sender's address: an ODrive's `node`, a DJI ESC's `esc`.
    extra: Vec<(&'static str, Num)>,
    fields: Vec<(&'static str, Num)>,
}

impl Decoded {
    fn new(protocol: &'static str, message: impl Into<String>) -> Self {
        Self {
            protocol,
            message: message.into(),
            extra: Vec::new(),
            fields: Vec::new(),
        }
    }

    fn extra(mut self, key: &'static str, value: i64) -> Self {
        self.extra.push((key, Num::Int(value)));
        self
    }

    fn f(mut self, field: &Field, value: f32) -> Self {
        self.fields.push((field.name, Num::Float(value)));
        self
    }

    fn i(mut self, field: &Field, value: impl Into<i64>) -> Self {
        self.fields.push((field.name, Num::Int(value.into())));
        self
    }

    /// The line of `decode`: `{"id", "protocol", "message", <extra>, "fields"}`; with
    /// `golden`, the frame's candump text and the encoder's input before the fields.
    fn json(&self, id: Id, golden: Option<(&str, &Decoded)>) -> String {
        #[derive(Serialize)]
        struct Line<'a> {
            id: u32,
            protocol: &'a str,
            message: &'a str,
            #[serde(flatten)]
            extra: Fields<'a, Num>,
            #[serde(skip_serializing_if = "Option::is_none")]
            candump: Option<&'a str>,
            #[serde(skip_serializing_if = "Option::is_none")]
            input: Option<Fields<'a, Num>>,
            fields: Fields<'a, Num>,
        }
        to_line(&Line {
            id: raw_id(id),
            protocol: self.protocol,
            message: &self.message,
            extra: Fields(&self.extra),
            candump: golden.map(|(text, _)| text),
            input: golden.map(|(_, input)| Fields(&input.fields)),
            fields: Fields(&self.fields),
        })
    }
}

/// One JSON line. The values here always serialise; were one not to, the line is an error
/// line like the others (serde_json escapes its message), not a hand-written one.
fn to_line(value: &impl Serialize) -> String {
    serde_json::to_string(value).unwrap_or_else(|e| {
        serde_json::json!({"error": {"kind": "internal", "message": e.to_string()}}).to_string()
    })
}

fn raw_id(id: Id) -> u32 {
    match id {
        Id::Standard(id) => u32::from(id.as_raw()),
        Id::Extended(id) => id.as_raw(),
    }
}

/// `{"id", "error": {"kind", "message", <extra>}}` (no `id` for a line that does not parse).
fn error_json(id: Option<Id>, kind: &str, message: &str, extra: &[(&str, Value)]) -> String {
    #[derive(Serialize)]
    struct Error<'a> {
        kind: &'a str,
        message: &'a str,
        #[serde(flatten)]
        extra: Fields<'a, Value>,
    }
    #[derive(Serialize)]
    struct Line<'a> {
        #[serde(skip_serializing_if = "Option::is_none")]
        id: Option<u32>,
        error: Error<'a>,
    }
    to_line(&Line {
        id: id.map(raw_id),
        error: Error {
            kind,
            message,
            extra: Fields(extra),
        },
    })
}

fn decode_error_json(id: Id, e: &DecodeError) -> String {
    let extra: Vec<(&str, Value)> = match *e {
        DecodeError::WrongDlc { expected, got, .. } => {
            vec![("expected", expected.into()), ("got", got.into())]
        }
        DecodeError::NonFinite { field, bits } => vec![
            ("field", field.into()),
            ("value", non_finite_name(bits).into()),
            ("bits", format!("{bits:#010x}").into()),
        ],
        DecodeError::OutOfRange { field, value } => {
            vec![("field", field.into()), ("value", value.into())]
        }
        _ => Vec::new(),
    };
    error_json(Some(id), e.kind().as_str(), &e.to_string(), &extra)
}

// ---------------------------------------------------------------------------------------------
// Messages to field lists (DBC signal names from the layout tables)

fn robot_fields(msg: &robot::Message) -> Decoded {
    use robot::layout as l;
    use robot::{Command as C, Telemetry as T};
    let d = Decoded::new("robot", msg.def().name);
    match *msg {
        robot::Message::Command(C::Estop) => d.i(&l::ESTOP_MAGIC, l::ESTOP_MAGIC_VALUE),
        robot::Message::Command(C::Twist(t)) => d
            .f(&l::TWIST_VX, t.vx)
            .f(&l::TWIST_VY, t.vy)
            .f(&l::TWIST_WZ, t.wz)
            .i(&l::TWIST_SEQ, t.seq),
        robot::Message::Command(C::Mode(m)) => d.i(&l::MODE_REQUEST, m.raw()),
        robot::Message::Command(C::StatusRequest) => d,
        robot::Message::Command(C::ImuYawRate(g)) => d
            .f(&l::IMU_YAW_RATE_VALUE, g.yaw_rate)
            .i(&l::IMU_SEQ, g.seq),
        robot::Message::Command(C::WheelTest(t)) => d
            .i(&l::TEST_WHEEL, t.wheel)
            .f(&l::TEST_SPEED, t.speed)
            .i(&l::TEST_DURATION, t.duration_ms),
        robot::Message::Command(C::PodCounts(c)) => d
            .i(&l::POD_COUNT[0], c.counts[0])
            .i(&l::POD_COUNT[1], c.counts[1])
            .i(&l::POD_COUNT[2], c.counts[2])
            .i(&l::POD_SEQ, c.seq),
        robot::Message::Telemetry(T::OdomSlip(s)) => d
            .f(&l::SLIP_VX, s.vx)
            .f(&l::SLIP_VY, s.vy)
            .f(&l::SLIP_WZ, s.wz)
            .i(&l::SLIP_SOURCE, s.source.raw()),
        robot::Message::Telemetry(T::OdomPosition(o)) => d.f(&l::ODOM_X, o.x).f(&l::ODOM_Y, o.y),
        robot::Message::Telemetry(T::OdomVelocity(o)) => d
            .f(&l::ODOM_HEADING, o.heading)
            .f(&l::ODOM_VX, o.vx)
            .f(&l::ODOM_VY, o.vy)
            .f(&l::ODOM_WZ, o.wz),
        robot::Message::Telemetry(T::Status(s)) => d
            .i(&l::STATUS_STATE, s.state.raw())
            .i(&l::STATUS_FAULT, s.fault.raw())
            .i(&l::STATUS_RX_ERRORS, s.rx_errors)
            .i(&l::STATUS_UNKNOWN_IDS, s.unknown_ids)
            .i(&l::STATUS_MOTORS_ONLINE, s.motors_online)
            .i(&l::STATUS_HEADING_SOURCE, s.heading_source.raw())
            .i(&l::STATUS_SEQ, s.seq),
        robot::Message::Telemetry(T::StatusCounters(c)) => d
            .i(&l::COUNTERS_REPEATED_SEQ, c.repeated_seq)
            .i(&l::COUNTERS_WRONG_DLC, c.wrong_dlc)
            .i(&l::COUNTERS_OUT_OF_RANGE, c.out_of_range)
            .i(&l::COUNTERS_NON_FINITE, c.non_finite),
        robot::Message::Telemetry(T::Heartbeat(h)) => d
            .i(&l::HEARTBEAT_UPTIME, h.uptime_ms)
            .i(&l::HEARTBEAT_STATE, h.state.raw())
            .i(&l::HEARTBEAT_VERSION, h.protocol_version)
            .i(&l::HEARTBEAT_CONFIG_ID, h.config_id),
        robot::Message::Telemetry(T::WheelTestResult(r)) => d
            .i(&l::RESULT_WHEEL, r.wheel)
            .i(&l::RESULT_OUTCOME, r.outcome.raw())
            .f(&l::RESULT_ANGLE, r.angle)
            .f(&l::RESULT_PEAK_CURRENT, r.peak_current),
    }
}

fn odrive_fields(msg: &odrive::Message) -> Decoded {
    use odrive::layout as l;
    use odrive::{Command as C, Feedback as F};
    let node = msg.node().get();
    let d =
        Decoded::new("odrive", format!("Axis{node}_{}", msg.def().name)).extra("node", node.into());
    match *msg {
        odrive::Message::Command(a) => match a.msg {
            C::Estop => d,
            C::GetError | C::GetHeartbeat | C::GetEncoderEstimates => d.extra("request", 1),
            C::SetAxisState(s) => d.i(&l::REQUESTED_STATE, s.raw()),
            C::SetControllerMode {
                control_mode,
                input_mode,
            } => d
                .i(&l::CONTROL_MODE, control_mode.raw())
                .i(&l::INPUT_MODE, input_mode.raw()),
            C::SetInputVel { vel, torque_ff } => {
                d.f(&l::INPUT_VEL, vel).f(&l::INPUT_TORQUE_FF, torque_ff)
            }
            C::ClearErrors { identify } => d.i(&l::IDENTIFY, identify),
        },
        odrive::Message::Feedback(a) => match a.msg {
            F::Heartbeat(h) => d
                .i(&l::HB_AXIS_ERROR, h.axis_error)
                .i(&l::HB_AXIS_STATE, h.axis_state.raw())
                .i(&l::HB_PROCEDURE_RESULT, h.procedure_result)
                .i(&l::HB_TRAJECTORY_DONE, h.trajectory_done),
            F::Error {
                active_errors,
                disarm_reason,
            } => d
                .i(&l::ERR_ACTIVE, active_errors)
                .i(&l::ERR_DISARM_REASON, disarm_reason),
            F::EncoderEstimates { pos, vel } => d.f(&l::POS_ESTIMATE, pos).f(&l::VEL_ESTIMATE, vel),
        },
    }
}

fn dji_fields(msg: &dji::Message) -> Decoded {
    use dji::layout as l;
    match msg {
        dji::Message::Command(c) => {
            let mut d = Decoded::new("dji", c.group.def().name);
            for (field, amps) in c.group.fields().iter().zip(c.amps()) {
                d = d.f(field, amps);
            }
            d
        }
        dji::Message::Feedback(fb) => {
            Decoded::new("dji", format!("{}_{}", l::FEEDBACK.name, fb.esc.get()))
                .extra("esc", fb.esc.get().into())
                .i(&l::ROTOR_ANGLE, fb.rotor_angle)
                .i(&l::ROTOR_SPEED, fb.rotor_speed_rpm)
                .f(&l::TORQUE_CURRENT, fb.current_amps())
                .i(&l::TEMPERATURE, fb.temperature_c)
        }
    }
}

/// Any decoded message.
enum AnyMessage {
    Robot(robot::Message),
    Odrive(odrive::Message),
    Dji(dji::Message),
    Canopen(CanopenFrame),
}

impl AnyMessage {
    fn fields(&self) -> Decoded {
        match self {
            Self::Robot(m) => robot_fields(m),
            Self::Odrive(m) => odrive_fields(m),
            Self::Dji(m) => dji_fields(m),
            Self::Canopen(m) => m.fields(),
        }
    }

    fn to_can_frame(&self) -> CanFrame {
        match self {
            Self::Robot(m) => m.to_can_frame(),
            Self::Odrive(m) => m.to_can_frame(),
            Self::Dji(m) => m.to_can_frame(),
            Self::Canopen(m) => m.to_can_frame(),
        }
    }

    /// The routing that reads this message's frame back (`decode --canopen` for CANopen).
    fn routing(&self) -> Routing {
        Routing {
            model: EscModel::C620,
            canopen: matches!(self, Self::Canopen(_)),
        }
    }
}

/// Largest ODrive node routed to the ODrive codec (the DBC covers nodes 0-3).
const ODRIVE_MAX_NODE: u16 = 3;

/// Which codecs `decode` uses for ids outside the robot block.
#[derive(Clone, Copy, Debug)]
struct Routing {
    /// The DJI ESC model (the current scale).
    model: EscModel,
    /// CANopen for every id outside the robot block, instead of DJI and ODrive.
    canopen: bool,
}

impl Default for Routing {
    fn default() -> Self {
        Self {
            model: EscModel::C620,
            canopen: false,
        }
    }
}

fn route(frame: &CanFrame, routing: Routing) -> Result<AnyMessage, DecodeError> {
    let id = match frame.id() {
        Id::Standard(id) => id.as_raw(),
        Id::Extended(id) => return Err(DecodeError::ExtendedId { id: id.as_raw() }),
    };
    if robot::in_block(id) {
        robot::decode(frame).map(AnyMessage::Robot)
    } else if routing.canopen {
        CanopenFrame::decode(frame).map(AnyMessage::Canopen)
    } else if dji::is_dji_id(id) {
        dji::decode(frame, routing.model).map(AnyMessage::Dji)
    } else if id >> odrive::layout::CMD_BITS <= ODRIVE_MAX_NODE {
        odrive::decode(frame).map(AnyMessage::Odrive)
    } else {
        Err(DecodeError::UnknownId { id: frame.id() })
    }
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

fn decode_stdin(routing: Routing) -> io::Result<()> {
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

// ---------------------------------------------------------------------------------------------
// Golden frames

/// The golden messages, each with the values given to its encoder: the message's own
/// fields, but for the DJI current commands the amps before rounding to raw values (and for
/// CANopen SDO frames the command byte the encoder chose).
fn golden_set() -> Vec<(AnyMessage, Decoded)> {
    use odrive::{Addressed, Command as OC, Feedback as OF};
    use robot::{Command as RC, Telemetry as RT};
    let node = |n| NodeId::new(n).unwrap_or(NodeId::new(0).unwrap_or_else(|| unreachable!()));
    let esc = |n| EscId::new(n).unwrap_or_else(|| unreachable!("ESC ids 1..=8"));
    let mut v = vec![
        AnyMessage::Robot(robot::Message::Command(RC::Estop)),
        AnyMessage::Robot(robot::Message::Command(RC::Twist(robot::TwistCmd {
            vx: 0.5,
            vy: -0.25,
            wz: 1.0,
            seq: 7,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::Twist(robot::TwistCmd {
            vx: 32.767,
            vy: -32.767,
            wz: 0.0004,
            seq: 255,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::Twist(robot::TwistCmd {
            vx: -1.2345,
            vy: 2.0,
            wz: -2.50137,
            seq: 0,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::StatusRequest)),
        AnyMessage::Robot(robot::Message::Command(RC::ImuYawRate(robot::ImuYawRate {
            yaw_rate: 0.001_745_329_3,
            seq: 0,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::ImuYawRate(robot::ImuYawRate {
            yaw_rate: -34.906_586,
            seq: 255,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::ImuYawRate(robot::ImuYawRate {
            yaw_rate: 35.0,
            seq: 17,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::PodCounts(robot::PodCounts {
            counts: [0, 65535, 32768],
            seq: 0,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::PodCounts(robot::PodCounts {
            counts: [1234, 40000, 0],
            seq: 255,
        }))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomSlip(robot::OdomSlip {
            vx: 0.012,
            vy: -0.345,
            wz: 0.2,
            source: robot::OdometrySource::Pods3,
        }))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomSlip(robot::OdomSlip {
            vx: -32.767,
            vy: 32.767,
            wz: -0.001,
            source: robot::OdometrySource::WheelsPodsSilent,
        }))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomSlip(robot::OdomSlip {
            vx: 0.0,
            vy: 0.0,
            wz: 0.0,
            source: robot::OdometrySource::Pods2Gyro,
        }))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomPosition(
            robot::OdomPosition {
                x: 12.3456,
                y: -0.0001,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomPosition(
            robot::OdomPosition {
                x: -150_000.0,
                y: 200_000.0,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomVelocity(
            robot::OdomVelocity {
                heading: 3.1234,
                vx: 0.1,
                vy: -0.2,
                wz: 0.3,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomVelocity(
            robot::OdomVelocity {
                heading: -1.2345,
                vx: -32.767,
                vy: 32.767,
                wz: -0.001,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::StatusCounters(
            robot::StatusCounters {
                repeated_seq: 65535,
                wrong_dlc: 0,
                out_of_range: 513,
                non_finite: 7,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::StatusCounters(
            robot::StatusCounters {
                repeated_seq: 258,
                wrong_dlc: 65535,
                out_of_range: 0,
                non_finite: 1,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::Heartbeat(robot::Heartbeat {
            uptime_ms: 4_000_000_000,
            state: RobotState::Enabled,
            protocol_version: robot::PROTOCOL_VERSION,
            config_id: 0xBEEF,
        }))),
    ];
    for (wheel, speed, duration_ms) in [(0, 3.0, 1000), (3, -10.0, 3000), (1, 0.001, 1)] {
        v.push(AnyMessage::Robot(robot::Message::Command(RC::WheelTest(
            robot::WheelTest {
                wheel,
                speed,
                duration_ms,
            },
        ))));
    }
    for (wheel, outcome, angle, peak_current) in [
        (0, robot::TestOutcome::Done, 2.5, 3.99),
        (1, robot::TestOutcome::Stopped, -0.5, -4.0),
        (2, robot::TestOutcome::Fault, 32.767, 300.0),
        (3, robot::TestOutcome::Refused, 0.0, 0.0),
    ] {
        v.push(AnyMessage::Robot(robot::Message::Telemetry(
            RT::WheelTestResult(robot::WheelTestResult {
                wheel,
                outcome,
                angle,
                peak_current,
            }),
        )));
    }
    for request in [
        ModeRequest::Disable,
        ModeRequest::Enable,
        ModeRequest::Reset,
    ] {
        v.push(AnyMessage::Robot(robot::Message::Command(RC::Mode(
            request,
        ))));
    }
    for (state, fault, heading_source) in [
        (RobotState::Disabled, Fault::None, HeadingSource::Wheels),
        (RobotState::Fault, Fault::MotorStale, HeadingSource::Wheels),
        (RobotState::Fault, Fault::MotorMissing, HeadingSource::Gyro),
        (RobotState::Fault, Fault::DriveError, HeadingSource::Wheels),
        (RobotState::Disabled, Fault::Watchdog, HeadingSource::Wheels),
        (RobotState::Fault, Fault::Config, HeadingSource::Wheels),
        (
            RobotState::Fault,
            Fault::EncoderStuck,
            HeadingSource::Wheels,
        ),
        (RobotState::Estop, Fault::None, HeadingSource::Wheels),
        (
            RobotState::Fault,
            Fault::WheelRunaway,
            HeadingSource::Wheels,
        ),
        (RobotState::Fault, Fault::WheelFight, HeadingSource::Wheels),
        (RobotState::WheelTest, Fault::None, HeadingSource::Wheels),
        (
            RobotState::Enabled,
            Fault::None,
            HeadingSource::WheelsGyroSilent,
        ),
        (RobotState::Enabled, Fault::None, HeadingSource::Gyro),
        (RobotState::Fault, Fault::DriveSilent, HeadingSource::Wheels),
        (
            RobotState::Fault,
            Fault::DriveRebooted,
            HeadingSource::Wheels,
        ),
        (RobotState::Fault, Fault::DriveSetup, HeadingSource::Gyro),
        (
            RobotState::Fault,
            Fault::DriveTransition,
            HeadingSource::Wheels,
        ),
        (RobotState::Fault, Fault::DriveNmt, HeadingSource::Wheels),
    ] {
        v.push(AnyMessage::Robot(robot::Message::Telemetry(RT::Status(
            robot::Status {
                state,
                fault,
                rx_errors: 65535,
                unknown_ids: 513,
                motors_online: 0b1011,
                heading_source,
                seq: 42,
            },
        ))));
    }
    for n in 0..=3 {
        let cmd =
            |msg| AnyMessage::Odrive(odrive::Message::Command(Addressed { node: node(n), msg }));
        let fb =
            |msg| AnyMessage::Odrive(odrive::Message::Feedback(Addressed { node: node(n), msg }));
        v.extend([
            cmd(OC::Estop),
            cmd(OC::GetError),
            cmd(OC::GetHeartbeat),
            cmd(OC::GetEncoderEstimates),
            cmd(OC::SetAxisState(AxisState::ClosedLoopControl)),
            cmd(OC::SetAxisState(AxisState::Idle)),
            cmd(OC::SetControllerMode {
                control_mode: ControlMode::VelocityControl,
                input_mode: InputMode::VelRamp,
            }),
            cmd(OC::SetControllerMode {
                control_mode: ControlMode::VelocityControl,
                input_mode: InputMode::Passthrough,
            }),
            cmd(OC::SetInputVel {
                vel: 12.5 * f32::from(n) - 3.25,
                torque_ff: 0.1,
            }),
            cmd(OC::ClearErrors { identify: n == 1 }),
            fb(OF::Heartbeat(odrive::Heartbeat {
                axis_error: 0x0100_0000,
                axis_state: AxisState::ClosedLoopControl,
                procedure_result: 3 + n,
                trajectory_done: true,
            })),
            fb(OF::Error {
                active_errors: 0x0000_1000,
                disarm_reason: 0x8000_0001,
            }),
            fb(OF::EncoderEstimates {
                pos: -1234.5678,
                vel: 1.0e-3 * f32::from(n),
            }),
        ]);
    }
    v.extend(canopen::golden_set().into_iter().map(AnyMessage::Canopen));
    for n in 1..=8u8 {
        v.push(AnyMessage::Dji(dji::Message::Feedback(dji::Feedback {
            model: EscModel::C620,
            esc: esc(n),
            rotor_angle: 1023 * u16::from(n),
            rotor_speed_rpm: 1000 - 700 * i16::from(n),
            torque_current: -2000 * i16::from(n),
            temperature_c: 20 + 5 * n,
        })));
    }
    let mut golden: Vec<(AnyMessage, Decoded)> = v
        .into_iter()
        .map(|msg| {
            let input = msg.fields();
            (msg, input)
        })
        .collect();
    // The last set is exact ties (k + 1/2 LSB, binary fractions): nearest even raw value.
    let lsb = EscModel::C620.amps_per_lsb();
    for (group, amps) in [
        (EscGroup::Esc1To4, [20.0, -20.0, 1.5, -0.0006]),
        (EscGroup::Esc5To8, [20.0, -20.0, 1.5, -0.0006]),
        (
            EscGroup::Esc1To4,
            [2.5 * lsb, -2.5 * lsb, 1.5 * lsb, -3.5 * lsb],
        ),
    ] {
        let msg = AnyMessage::Dji(dji::Message::Command(dji::CurrentCommand::from_amps(
            EscModel::C620,
            group,
            amps,
        )));
        let mut input = msg.fields();
        input.fields = group
            .fields()
            .iter()
            .zip(amps)
            .map(|(field, a)| (field.name, Num::Float(a)))
            .collect();
        golden.push((msg, input));
    }
    golden
}

fn golden() -> io::Result<()> {
    let mut out = io::BufWriter::new(io::stdout().lock());
    for (msg, input) in golden_set() {
        let frame = msg.to_can_frame();
        let line = match route(&frame, msg.routing()) {
            Ok(decoded) => decoded
                .fields()
                .json(frame.id(), Some((&candump_text(&frame), &input))),
            // A golden frame the decoder rejects is a bug; print it so the tests fail loudly.
            Err(e) => decode_error_json(frame.id(), &e),
        };
        writeln!(out, "{line}")?;
    }
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory as _;
    use firmware::protocol::ErrorKind;

    fn parse(args: &[&str]) -> Result<Command, clap::Error> {
        Cli::try_parse_from(std::iter::once("mecanum-codec").chain(args.iter().copied()))
            .map(|cli| cli.command)
    }

    /// The error of a bad command line: clap's kind, and its text (which exits 2).
    fn refused(args: &[&str]) -> (clap::error::ErrorKind, String) {
        let e = parse(args).expect_err("refused");
        assert_eq!(e.exit_code(), 2, "{args:?}: {e}");
        (e.kind(), e.to_string())
    }

    #[test]
    fn the_command_line_is_well_formed() {
        Cli::command().debug_assert();
    }

    #[test]
    fn good_command_lines_parse() {
        let routing = |args: &[&str]| match parse(args) {
            Ok(Command::Decode(a)) => a.routing(),
            other => panic!("{args:?}: {other:?}"),
        };
        let r = routing(&["decode"]);
        assert!(r.model == EscModel::C620 && !r.canopen);
        let r = routing(&["decode", "--dji-model", "c610", "--canopen"]);
        assert!(r.model == EscModel::C610 && r.canopen);
        let r = routing(&["decode", "--canopen", "--dji-model=c620"]);
        assert!(r.model == EscModel::C620 && r.canopen);
        assert!(matches!(parse(&["golden"]), Ok(Command::Golden)));
        match parse(&["config-id", "a.toml", "b.toml"]) {
            Ok(Command::ConfigId { files }) => {
                assert_eq!(files, [PathBuf::from("a.toml"), PathBuf::from("b.toml")]);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn bad_command_lines_are_refused_naming_the_argument() {
        use clap::error::ErrorKind as K;
        for (args, kind, names) in [
            (
                &["decode", "--dji-model", "c999"][..],
                K::InvalidValue,
                &["c999", "--dji-model", "c620, c610"][..],
            ),
            (
                &["decode", "--dji-model"],
                K::InvalidValue,
                &["--dji-model"],
            ),
            (&["decode", "--turbo"], K::UnknownArgument, &["--turbo"]),
            (&["decode", "extra"], K::UnknownArgument, &["extra"]),
            (&["golden", "--canopen"], K::UnknownArgument, &["--canopen"]),
            (&["encode"], K::InvalidSubcommand, &["encode"]),
            (&["config-id"], K::MissingRequiredArgument, &["<FILE>"]),
        ] {
            let (got, text) = refused(args);
            assert_eq!(got, kind, "{args:?}: {text}");
            for name in names {
                assert!(text.contains(name), "{args:?} does not name {name}: {text}");
            }
        }
        // No command: the help, on stderr, exit status 2.
        let (kind, text) = refused(&[]);
        assert_eq!(kind, K::DisplayHelpOnMissingArgumentOrSubcommand);
        assert!(
            text.contains("decode") && text.contains("config-id"),
            "{text}"
        );
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

    #[test]
    fn every_golden_frame_decodes() {
        for (msg, _) in golden_set() {
            let frame = msg.to_can_frame();
            assert!(
                route(&frame, msg.routing()).is_ok(),
                "{}",
                candump_text(&frame)
            );
        }
    }
}
