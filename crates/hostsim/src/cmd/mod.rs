//! The `hostsim` command line (a library module so that the fuzz targets reach it).
//!
//! [`Cli`], one module per subcommand with its arguments (`Args`, whose doc is the
//! subcommand's `--help`), its `execute` and what it prints; the exit statuses are the
//! constants here. `main.rs` parses, dispatches ([`Cmd::execute`]) and maps an error to
//! [`EXIT_ERROR`].
//!
//! The fuzz target (`fuzz/fuzz_targets/hostsim_args.rs`) calls [`Cmd::prepare`], which runs
//! every check a subcommand makes of its arguments before any work,
//! and nothing else. It reads the files named (configurations, scenarios) but writes none,
//! opens no socket or CAN interface, installs no signal handler, reads no log and no stdin,
//! and runs no simulation; a sweep's plan is counted there and built later
//! ([`sweep::Plan::runs`]). Each `execute` with checks (run, sweep, check, plant, replay)
//! begins with its `prepare`, so the two cannot disagree.
//!
//! A command's result is one report, a `Serialize` struct with one human rendering
//! (`Display`); [`print_report`] prints it, as text or as `--json`.
//!
//! The doc comments of the `Args` are terminal text, not Markdown: `[geometry]` names a TOML
//! table, not a link, and `<name>` a placeholder, not a tag. Rustdoc's lints on them are off.
#![allow(rustdoc::broken_intra_doc_links, rustdoc::invalid_html_tags)]

pub mod calibrate;
pub mod check;
pub mod kin;
pub mod plant;
pub mod plot;
pub mod replay;
pub mod run;
pub mod summary;
pub mod sweep;

use std::path::Path;
use std::process::ExitCode;

use anyhow::Result;
use clap::{Parser, Subcommand};

use crate::scenario::Scenario;

pub use mecanum_linux::parse_seconds;

/// Host simulator of the mecanum drive stack.
///
/// The real firmware core runs in lockstep with a simulated plant (DJI C620/M3508 or ODrive
/// drives, a 20 kg chassis on mecanum rollers with friction-limited slip) over a simulated
/// 1 Mbit/s CAN bus, in simulated time. Runs are deterministic: the same scenario and seed
/// give the same frames, bit for bit.
#[derive(Debug, Parser)]
#[command(name = "hostsim", version, about, long_about)]
pub struct Cli {
    #[command(subcommand)]
    #[allow(missing_docs)] // A doc comment here would be help text.
    pub command: Cmd,
}

/// The subcommands. Each one's help is its `Args`' doc comment: a doc comment on a variant
/// would replace it, so they have none.
#[derive(Debug, Subcommand)]
#[allow(missing_docs)]
pub enum Cmd {
    Run(run::Args),
    Replay(replay::Args),
    Plant(plant::Args),
    Check(check::Args),
    Sweep(sweep::Args),
    Summary(summary::Args),
    Calibrate(calibrate::Args),
    Plot(plot::Args),
    Kin(kin::Args),
}

/// What [`Cmd::prepare`] made of a subcommand's arguments.
pub enum Prepared {
    /// The scenario with `--config`, `--seed` and `--set` applied, and its plant.
    Run(run::Prepared),
    /// The base scenario, the seeds and parameters, the count of runs (not yet built).
    Sweep(sweep::Plan),
    /// The configuration and the robot's wiring.
    Check(check::Prepared),
    /// The configuration and the drives, IMU and pods built from it.
    Plant(Box<plant::Prepared>),
    /// Replay or play, with the checked tolerances or speed.
    Replay(replay::Mode),
    /// `summary`, `calibrate`, `plot`, `kin`: nothing to check beyond what clap parses
    /// before their work (reading a log or stdin) starts.
    Unchecked,
}

impl Cmd {
    /// Runs the subcommand: its `prepare`, then its work. The exit status, or an error for
    /// `main` to print (exit status [`EXIT_ERROR`]).
    ///
    /// # Errors
    /// Bad arguments, files, interfaces: whatever stops the command before or instead of
    /// its work.
    pub fn execute(&self) -> Result<ExitCode> {
        match self {
            Self::Run(a) => run::execute(a),
            Self::Replay(a) => replay::execute(a),
            Self::Plant(a) => plant::execute(a),
            Self::Check(a) => check::execute(a),
            Self::Sweep(a) => sweep::execute(a),
            Self::Summary(a) => summary::execute(a),
            Self::Calibrate(a) => calibrate::execute(a),
            Self::Plot(a) => plot::execute(a),
            Self::Kin(a) => kin::execute(a),
        }
    }

    /// Every check the subcommand makes before its work, and nothing else: the error
    /// `execute` would give before starting, or what it would start from.
    ///
    /// # Errors
    /// As [`Self::execute`] before its work.
    pub fn prepare(&self) -> Result<Prepared> {
        Ok(match self {
            Self::Run(a) => Prepared::Run(run::prepare(a)?),
            Self::Replay(a) => Prepared::Replay(replay::prepare(a)?),
            Self::Plant(a) => Prepared::Plant(Box::new(plant::prepare(a)?)),
            Self::Check(a) => Prepared::Check(check::prepare(a)?),
            Self::Sweep(a) => Prepared::Sweep(sweep::prepare(a)?),
            Self::Summary(_) | Self::Calibrate(_) | Self::Plot(_) | Self::Kin(_) => {
                Prepared::Unchecked
            }
        })
    }
}

/// Exit status of a command that ran and found a failure: frames that differ, a frame that
/// could not be sent, a run that did not pass.
pub const EXIT_FAILED: u8 = 1;
/// Exit status of an error before or instead of the work: bad arguments, files, interfaces.
pub const EXIT_ERROR: u8 = 2;
/// Exit status of `check` when it found a miswiring (the fix is printed), as
/// `mecanum-drive check`.
pub const EXIT_MISWIRED: u8 = 3;
/// Exit status of a `sweep` stopped by Ctrl-C (the rows finished are written), as a shell
/// reports a SIGINT death.
pub const EXIT_INTERRUPTED: u8 = 128 + 2;
/// Exit status of `replay` and `summary` for a damaged log whose complete part was used.
pub const EXIT_DAMAGED: u8 = 3;

/// The exit status of a process killed by SIGPIPE, as a shell reports it.
pub const SIGPIPE_STATUS: u8 = 128 + 13;

/// Prints a command's report on stdout: its JSON object on one line with `--json`, else its
/// text. The JSON goes through a [`serde_json::Value`], whose objects list their keys sorted
/// by name (serde_json without `preserve_order`), as every `--json` has.
///
/// # Errors
/// The report does not serialise (a map with keys that are not strings).
pub fn print_report(
    report: &(impl serde::Serialize + std::fmt::Display),
    json: bool,
) -> Result<()> {
    if json {
        println!("{}", serde_json::to_value(report)?);
    } else {
        println!("{report}");
    }
    Ok(())
}

/// Warns on stderr that the log at `path` is damaged, if it is: where, what, what was read.
pub fn warn_if_damaged(path: &Path, read: &drivelog::ReadReport, doing: &str) {
    if !read.is_complete() {
        eprintln!("warning: {} is {read}; {doing}", path.display());
    }
}

/// Warns on stderr that messages of the log at `path` did not decode, and what `doing` does
/// about them; whether there were any.
pub fn warn_if_undecodable(path: &Path, undecodable: &drivelog::Undecodable, doing: &str) -> bool {
    let any = undecodable.total() > 0;
    if any {
        eprintln!("warning: {}: {undecodable}: {doing}", path.display());
    }
    any
}

/// A scenario file, or else a built-in of that name (`square` if none); `config` replaces
/// its configuration.
pub fn load_scenario(arg: Option<&str>, config: Option<firmware::Config>) -> Result<Scenario> {
    Ok(Scenario::load(arg.unwrap_or("square"), config)?)
}

/// The drive configuration of `--config`, or the built-in DJI example; with a description.
pub fn load_config(path: Option<&Path>) -> Result<(firmware::Config, String)> {
    match path {
        // The error names the file, and the line or the field.
        Some(p) => Ok((
            firmware::Config::from_toml_file(p)?,
            p.display().to_string(),
        )),
        None => Ok((
            firmware::Config::dji_m3508_example(),
            "built-in DJI M3508/C620 example".to_string(),
        )),
    }
}

/// A simulated robot wired otherwise than its configuration says (`check`, `plant`).
#[derive(Debug, Clone, clap::Args)]
pub struct WiringArgs {
    /// Mount this wheel's motor the other way than the configuration's `inverted` says
    /// (FL, FR, RL, RR or 0-3; repeatable).
    #[arg(long, value_name = "WHEEL", value_parser = parse_wheel)]
    flip: Vec<usize>,
    /// Wire these two wheels' drives to each other's ids (`esc_ids`/`node_ids`), e.g.
    /// `--swap FL,RL` (repeatable, applied in order).
    #[arg(long, value_name = "WHEEL,WHEEL", value_parser = parse_wheel_pair)]
    swap: Vec<[usize; 2]>,
}

impl WiringArgs {
    /// The plant's wiring as a scenario's `[plant]` table would give it.
    pub fn spec(&self) -> crate::nodes::plant::PlantSpec {
        crate::nodes::plant::PlantSpec {
            flip: self.flip.clone(),
            swap: self.swap.clone(),
            ..crate::nodes::plant::PlantSpec::default()
        }
    }
}

/// A wheel by name (FL, FR, RL, RR, any case) or index 0-3.
pub fn parse_wheel(s: &str) -> Result<usize, String> {
    let t = s.trim();
    crate::analysis::bringup::WHEEL_NAMES
        .iter()
        .position(|n| n.eq_ignore_ascii_case(t))
        .or_else(|| t.parse::<usize>().ok().filter(|&i| i < 4))
        .ok_or_else(|| format!("{s:?} is not a wheel: FL, FR, RL, RR or 0-3"))
}

/// Two different wheels, `A,B`.
pub fn parse_wheel_pair(s: &str) -> Result<[usize; 2], String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?}: expected two wheels, e.g. FL,RL"))?;
    let (a, b) = (parse_wheel(a)?, parse_wheel(b)?);
    if a == b {
        return Err(format!("{s:?}: a wheel cannot swap with itself"));
    }
    Ok([a, b])
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory as _;

    use super::*;

    fn parse(args: &[&str]) -> Cmd {
        Cli::try_parse_from(std::iter::once("hostsim").chain(args.iter().copied()))
            .expect("parses")
            .command
    }

    #[test]
    fn the_command_line_is_well_formed() {
        Cli::command().debug_assert();
    }

    #[test]
    fn prepare_writes_nothing_and_binds_nothing() {
        let dir = std::env::temp_dir().join(format!("hostsim-prepare-{}", std::process::id()));
        let out = dir.join("out");
        let out = out.to_str().expect("UTF-8");
        // What `prepare` returns holds no server or file (its types have none); no output is
        // made either.
        for args in [
            &[
                "run",
                "--out",
                out,
                "--live",
                "127.0.0.1:9",
                "--set",
                "gains.kp=1.1",
            ][..],
            &["sweep", "square", "--out", out, "--seeds", "1..3"],
            &[
                "plant",
                "--iface",
                "nosuch0",
                "--log",
                out,
                "--live",
                "9",
                "--stats-json",
                out,
            ],
        ] {
            let prepared = parse(args).prepare();
            assert!(prepared.is_ok(), "{args:?}: {:?}", prepared.err());
        }
        assert!(!dir.exists(), "prepare made {}", dir.display());
    }

    #[test]
    fn a_sweep_is_counted_before_it_is_built() {
        let Ok(Prepared::Sweep(plan)) =
            parse(&["sweep", "square", "--seeds", "0..999999"]).prepare()
        else {
            panic!("a million runs is within the cap");
        };
        assert_eq!(plan.count, crate::analysis::sweep::MAX_RUNS);
        let refused = parse(&[
            "sweep",
            "square",
            "--seeds",
            "0..999999",
            "--set",
            "gains.kp=1,2",
        ])
        .prepare()
        .err()
        .expect("two million runs are past the cap")
        .to_string();
        assert!(refused.contains("2000000 runs"), "{refused}");
    }

    #[test]
    fn replay_options_are_checked_before_the_log_is_read() {
        let mode = |args: &[&str]| match parse(args).prepare() {
            Ok(Prepared::Replay(mode)) => Ok(mode),
            Ok(_) => unreachable!("a replay"),
            Err(e) => Err(e.to_string()),
        };
        assert_eq!(
            mode(&["replay", "nosuch.mcap", "--iface", "vcan0", "--speed", "2"]),
            Ok(replay::Mode::Play {
                iface: "vcan0".into(),
                speed: 2.0,
                only: replay::Only::Rx
            })
        );
        assert!(
            mode(&["replay", "nosuch.mcap", "--speed", "2"])
                .is_err_and(|e| e.contains("need --iface"))
        );
        assert!(
            mode(&["replay", "nosuch.mcap", "--position-tolerance", "inf"])
                .is_err_and(|e| e.contains("--position-tolerance"))
        );
    }

    /// The dictionary of the fuzz target `hostsim_args` (libFuzzer's format): every
    /// subcommand, option and possible value clap knows, and the names their values take
    /// (built-in scenarios, wheels, the fields `--set` takes). scripts/fuzz.sh adds the
    /// repository's configuration and scenario files.
    fn fuzz_dictionary() -> String {
        let mut words = std::collections::BTreeSet::new();
        let mut cli = Cli::command();
        cli.build();
        let mut commands = vec![&cli];
        commands.extend(cli.get_subcommands());
        for c in commands {
            words.insert(c.get_name().to_string());
            for a in c.get_arguments() {
                words.extend(a.get_long().map(|l| format!("--{l}")));
                words.extend(a.get_short().map(|s| format!("-{s}")));
                words.extend(
                    a.get_possible_values()
                        .iter()
                        .map(|v| v.get_name().to_string()),
                );
            }
        }
        words.extend(Scenario::BUILTINS.map(String::from));
        words.extend(crate::analysis::bringup::WHEEL_NAMES.map(String::from));
        let plant = crate::scenario::PLANT_FIELDS.map(|f| format!("plant.{f}"));
        words.extend(plant);
        let config = firmware::Config::dji_m3508_example().to_toml_string();
        let config: toml::Table = toml::from_str(&config).expect("the example's TOML");
        for (table, fields) in &config {
            for (key, value) in fields.as_table().into_iter().flatten() {
                if value.is_float() || value.is_integer() {
                    words.insert(format!("{table}.{key}"));
                }
            }
        }
        let mut text = String::from(
            "# The dictionary of fuzz/fuzz_targets/hostsim_args.rs (scripts/fuzz.sh passes it),\n\
             # from hostsim's clap definition: checked by hostsim's unit test\n\
             # cmd::tests::the_fuzz_dictionary_is_up_to_date; UPDATE_FUZZ_DICT=1 rewrites it.\n\
             \"\\x00\"\n",
        );
        for w in words {
            text.push_str(&format!("{w:?}\n"));
        }
        text
    }

    #[test]
    fn the_fuzz_dictionary_is_up_to_date() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/hostsim_args.dict");
        let now = fuzz_dictionary();
        if std::fs::read_to_string(&path).ok().as_deref() == Some(now.as_str()) {
            return;
        }
        if std::env::var_os("UPDATE_FUZZ_DICT").is_some() {
            std::fs::write(&path, now).expect("the dictionary written");
        } else {
            panic!(
                "{} is out of date; rerun with UPDATE_FUZZ_DICT=1 to rewrite it. Now:\n{now}",
                path.display()
            );
        }
    }
}
