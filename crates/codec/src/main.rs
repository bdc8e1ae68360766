//! `mecanum-codec`: the firmware's CAN codecs on the command line, for logs and for the Python
//! cross-check against the DBC files (see `--help`).
//!
//! The doc comments of [`Cli`] and its commands are its `--help`, terminal text and not
//! Markdown: `<id>#<data>` is a placeholder, not a tag. Rustdoc's lint on them is off.
#![allow(rustdoc::invalid_html_tags)]

mod canopen;
mod json;
mod message;
mod commands {
    //! One module a subcommand: its arguments, its run and its output.
    pub mod config_id;
    pub mod decode;
    pub mod golden;
    pub mod params;
}

use std::io;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use commands::decode::DecodeArgs;
use commands::{config_id, decode, golden, params};

/// Decode CAN frames with the mecanum firmware's codecs, or print golden frames.
///
/// The codecs are the firmware's own: the robot protocol (dbc/mecanum_robot.dbc), DJI
/// C620/C610 (dbc/dji_c620.dbc), ODrive CAN Simple (dbc/odrive_cansimple.dbc) and, with
/// `decode --canopen`, CANopen CiA 301/402 (dbc/cia402.dbc). `decode` reads candump lines and
/// prints JSON lines; `golden` prints frames built by the encoders, for the Python tests to
/// decode with cantools and the DBC files; `config-id` names the configuration a robot runs;
/// `params` lists the parameters a host reads and sets over CAN (or writes their EDS).
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
    /// Print the robot's parameters, one JSON line each, or its EDS.
    ///
    /// The parameters a host reads and sets over CAN (firmware::params; docs/protocol.md,
    /// section "Parameters"), one JSON line each:
    ///     {"name":"gains.kp","index":8194,"sub":1,"type":"REAL32","unit":"A/(rad/s)",
    ///      "low":0.0,"high":100.0,"change":"live","doc":"..."}
    /// `change` is when it may change: live (in any state, at the next control step),
    /// disabled (only while the robot is disabled) or fixed (read-only over CAN); `high` is
    /// null where the parameter has no upper bound (inf is a setting). With --config each
    /// line also has the configuration's "value" (null where it has no such field: another
    /// geometry layout, a pod it does not have). With --eds prints the robot's object
    /// dictionary as a CiA 306 EDS instead (dbc/mecanum_robot.eds is this output).
    #[command(verbatim_doc_comment)]
    Params {
        /// A drive configuration (TOML) whose values to print.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// Print the EDS instead of JSON lines.
        #[arg(long, conflicts_with = "config")]
        eds: bool,
    },
}

fn main() -> ExitCode {
    // Bad arguments: clap's message naming the argument, exit status 2.
    let result = match Cli::parse().command {
        Command::Decode(args) => decode::run(args.routing()),
        Command::Golden => golden::run(),
        Command::ConfigId { files } => return config_id::run(&files),
        Command::Params { config, eds } => params::run(config.as_deref(), eds),
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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory as _;
    use firmware::protocol::dji::EscModel;

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
}
