//! `hostsim`'s whole command line: the input, split at NUL bytes, is the argument vector
//! after `hostsim` (any bytes, UTF-8 or not), parsed by clap (`Cli::try_parse_from`, its
//! error or help rendered) and, when it parses, checked as the command checks it before any
//! work (`Cmd::prepare`: ranges, the configuration and scenario loaded, a sweep's runs
//! counted against `MAX_RUNS`; plans of at most 8 runs built and checked). Never a panic.
//!
//! Nothing is written and no socket is opened: `prepare` writes no output, binds no `--live`
//! address and opens no CAN interface. What it reads stays inside the repository (the
//! working folder): a command whose `--config` or scenario is an absolute path or climbs out
//! (`/dev/stdin` would block) is parsed but not prepared. An argument vector with `--live`
//! and a colon that is not a literal address is skipped: clap would resolve `--live
//! HOST:PORT`'s host while parsing (getaddrinfo, a network lookup).
#![no_main]

use std::ffi::OsStr;
use std::net::{IpAddr, SocketAddr};
use std::os::unix::ffi::OsStrExt;
use std::path::{Component, Path};
use std::sync::Once;

use clap::Parser;
use hostsim::cmd::{Cli, Cmd, Prepared};
use hostsim::analysis::sweep::MAX_RUNS;
use libfuzzer_sys::fuzz_target;

/// Whether clap may resolve a host name: `--live` is given, and an argument (or what follows
/// its first `=`) holds a colon but is not an address, an IP or a port, which `parse_addr`
/// takes without a lookup.
fn may_look_up_a_host(args: &[&OsStr]) -> bool {
    let literal = |t: &str| {
        let t = t.trim();
        t.parse::<SocketAddr>().is_ok()
            || t.trim_start_matches('[')
                .trim_end_matches(']')
                .parse::<IpAddr>()
                .is_ok()
            || t.parse::<u16>().is_ok()
    };
    let text: Vec<&str> = args.iter().filter_map(|a| a.to_str()).collect();
    text.iter().any(|a| a.starts_with("--live"))
        && text.iter().any(|a| {
            let value = a.split_once('=').map_or(*a, |(_, v)| v);
            (a.contains(':') && !literal(a)) || (value.contains(':') && !literal(value))
        })
}

/// Whether every file `prepare` may read (a scenario, a configuration) is inside the
/// working folder.
fn reads_inside(cmd: &Cmd) -> bool {
    let (scenario, config) = match cmd {
        Cmd::Run(a) => (a.scenario.as_deref(), a.config.as_deref()),
        Cmd::Sweep(a) => (Some(a.scenario.as_str()), a.config.as_deref()),
        Cmd::Check(a) => (None, a.config.as_deref()),
        Cmd::Plant(a) => (None, a.config.as_deref()),
        _ => (None, None),
    };
    !scenario
        .map(Path::new)
        .into_iter()
        .chain(config)
        .any(|p| p.is_absolute() || p.components().any(|c| matches!(c, Component::ParentDir)))
}

fuzz_target!(|data: &[u8]| {
    static CWD: Once = Once::new();
    // The repository: `config/...` and `scenarios/...` name its files, as in the seeds.
    CWD.call_once(|| {
        std::env::set_current_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
            .expect("the repository");
    });
    let args: Vec<&OsStr> = data.split(|&b| b == 0).map(OsStr::from_bytes).collect();
    if may_look_up_a_host(&args) {
        return;
    }
    let cli = match Cli::try_parse_from(std::iter::once(OsStr::new("hostsim")).chain(args)) {
        Ok(cli) => cli,
        Err(e) => {
            // `--help`, `--version` and every refusal end here: rendered as clap prints them.
            let _ = e.render().to_string();
            return;
        }
    };
    if !reads_inside(&cli.command) {
        return;
    }
    match cli.command.prepare() {
        Ok(Prepared::Sweep(plan)) => {
            assert!(plan.count <= MAX_RUNS, "{} runs past the cap", plan.count);
            assert!(plan.seeds.len() as u64 <= MAX_RUNS);
            // A million runs per input would be the fuzzer's time, not a finding: the count
            // and its cap are checked above for any size.
            if plan.count <= 8
                && let Ok(runs) = plan.runs()
            {
                assert_eq!(runs.len() as u64, plan.count, "the plan was counted wrong");
            }
        }
        Ok(_) => {}
        Err(e) => {
            let _ = mecanum_linux::error_line(e.as_ref());
        }
    }
});
