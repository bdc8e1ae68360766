//! `--live [ADDR]`, `--live-can-hz HZ`, `--live-max-clients N` and
//! `--live-max-subscriptions N`: the command-line options of every program that serves its
//! log live (`hostsim run`, `hostsim plant`, `mecanum-runner`), flattened into each
//! program's own arguments (feature `cli`).

use std::io;
use std::net::SocketAddr;

use crate::{LiveOptions, LiveReport, LiveServer, ParamLink, parse_addr};

/// The live options of a program that writes a log (`#[command(flatten)]`).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct LiveArgs {
    /// Serve the run live on ADDR to Foxglove or Lichtblick ("Open connection", Foxglove
    /// WebSocket, ws://ADDR): every channel of the log, with its schema and bytes, as it is
    /// written. 127.0.0.1:8765 when no ADDR is given; a port alone serves on loopback (0: a
    /// free port). Any other host warns: the protocol has no authentication. The loop never
    /// waits on a client: a slow one loses messages, counted on /diagnostics and at the end.
    #[arg(
        long,
        value_name = "ADDR",
        num_args = 0..=1,
        default_missing_value = "127.0.0.1:8765",
        value_parser = parse_addr,
    )]
    pub live: Option<SocketAddr>,
    /// With --live: the /can/* frames forwarded to live clients, per channel and CAN id, per
    /// second of log time, a whole number up to 1,000,000 (0: every frame). Default 100. The
    /// log keeps every frame.
    #[arg(long, value_name = "HZ", requires = "live", value_parser = parse_can_hz)]
    pub live_can_hz: Option<u32>,
    /// With --live: live clients served at once, 1 to 1024. Default 32. A connection beyond
    /// them is told so (a status error naming this option) and closed.
    #[arg(long, value_name = "N", requires = "live", value_parser = parse_max_clients)]
    pub live_max_clients: Option<usize>,
    /// With --live: subscriptions one client may hold, 1 to 4096. Default 64 (a viewer
    /// subscribes once per channel: 11). A client that asks for more, or subscribes a
    /// channel or an id twice, is told so (a status error) and disconnected.
    #[arg(long, value_name = "N", requires = "live", value_parser = parse_max_subscriptions)]
    pub live_max_subscriptions: Option<usize>,
}

/// The most `--live-can-hz` takes: one frame a microsecond, beyond any CAN bus.
pub const MAX_CAN_HZ: u32 = 1_000_000;

/// `--live-can-hz`: a whole number of frames a second, 0 to [`MAX_CAN_HZ`].
fn parse_can_hz(s: &str) -> Result<u32, String> {
    let refused = || {
        format!(
            "{s:?}: expected a whole number of frames a second, 0 (every frame) to {MAX_CAN_HZ}"
        )
    };
    let hz: u32 = s.trim().parse().map_err(|_| refused())?;
    if hz > MAX_CAN_HZ {
        return Err(refused());
    }
    Ok(hz)
}

/// The range of `--live-max-clients`: each client may hold a queue (about a MiB) and a file
/// descriptor.
pub const MAX_CLIENTS: std::ops::RangeInclusive<usize> = 1..=1024;

/// The range of `--live-max-subscriptions`: the log has 12 channels, one subscription each.
pub const MAX_SUBSCRIPTIONS: std::ops::RangeInclusive<usize> = 1..=4096;

/// A whole number of `what` in `range`.
fn parse_count(
    s: &str,
    what: &str,
    range: &std::ops::RangeInclusive<usize>,
) -> Result<usize, String> {
    let refused = || {
        format!(
            "{s:?}: expected a whole number of {what}, {} to {}",
            range.start(),
            range.end()
        )
    };
    let n: usize = s.trim().parse().map_err(|_| refused())?;
    if !range.contains(&n) {
        return Err(refused());
    }
    Ok(n)
}

/// `--live-max-clients`: in [`MAX_CLIENTS`].
fn parse_max_clients(s: &str) -> Result<usize, String> {
    parse_count(s, "clients", &MAX_CLIENTS)
}

/// `--live-max-subscriptions`: in [`MAX_SUBSCRIPTIONS`].
fn parse_max_subscriptions(s: &str) -> Result<usize, String> {
    parse_count(s, "subscriptions per client", &MAX_SUBSCRIPTIONS)
}

impl LiveArgs {
    /// The server `--live` asks for, named `name` (Foxglove shows it), listening, and
    /// serving the robot's parameters over `params` if given; `None` without `--live`.
    ///
    /// # Errors
    /// The address cannot be served, naming it and `--live`.
    pub fn serve(
        &self,
        name: String,
        params: Option<Box<dyn ParamLink>>,
    ) -> io::Result<Option<LiveServer>> {
        let Some(addr) = self.live else {
            return Ok(None);
        };
        let default = LiveOptions::default();
        let options = LiveOptions {
            name,
            can_hz: self.live_can_hz.unwrap_or(default.can_hz),
            max_clients: self.live_max_clients.unwrap_or(default.max_clients),
            max_subscriptions: self
                .live_max_subscriptions
                .unwrap_or(default.max_subscriptions),
            ..default
        };
        LiveServer::start_with(addr, options, params)
            .map(Some)
            .map_err(|e| io::Error::new(e.kind(), format!("--live: {e}")))
    }
}

impl LiveReport {
    /// The report in a program's JSON statistics (`--stats-json`, `--json`): `url`,
    /// `clients` (each `addr`, `subprotocol`, `connected_s`, `queued`, `sent`, `dropped`,
    /// `cut_off`: null or why the server disconnected it), and the totals `sent`, `dropped`,
    /// `thinned` and `refused` (connections refused).
    #[must_use]
    pub fn to_json(&self) -> serde_json::Value {
        let clients: Vec<_> = self
            .clients
            .iter()
            .map(|c| {
                serde_json::json!({
                    "addr": c.addr.to_string(),
                    "subprotocol": c.subprotocol,
                    "connected_s": c.connected.as_secs_f64(),
                    "queued": c.queued,
                    "sent": c.sent,
                    "dropped": c.dropped,
                    "cut_off": c.cut_off,
                })
            })
            .collect();
        serde_json::json!({
            "url": self.url,
            "clients": clients,
            "sent": self.sent(),
            "dropped": self.dropped(),
            "thinned": self.thinned,
            "refused": self.refused,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        live: LiveArgs,
    }

    #[test]
    fn can_hz_is_a_whole_number_in_its_range_and_a_refusal_says_so() {
        assert_eq!(parse_can_hz("0"), Ok(0));
        assert_eq!(parse_can_hz(" 100 "), Ok(100));
        assert_eq!(parse_can_hz("1000000"), Ok(MAX_CAN_HZ));
        // "0.0001" was refused as "invalid digit found in string".
        for bad in ["0.0001", "-1", "1000001", "1e3", "", "ten"] {
            let err = parse_can_hz(bad).unwrap_err();
            assert!(
                err.contains("whole number of frames a second, 0 (every frame) to 1000000"),
                "{bad}: {err}"
            );
        }
    }

    #[test]
    fn live_takes_an_optional_address_and_can_hz_needs_it() {
        let parse = |args: &[&str]| Cli::try_parse_from([&["prog"], args].concat());
        assert_eq!(parse(&[]).unwrap().live.live, None);
        assert_eq!(
            parse(&["--live"]).unwrap().live.live,
            Some(crate::DEFAULT_ADDR)
        );
        let cli = parse(&["--live", "9000", "--live-can-hz", "0"]).unwrap();
        assert_eq!(cli.live.live.unwrap().port(), 9000);
        assert_eq!(cli.live.live_can_hz, Some(0));
        assert!(parse(&["--live-can-hz", "10"]).is_err());
        assert!(parse(&["--live-max-clients", "10"]).is_err());
        assert!(parse(&["--live-max-subscriptions", "10"]).is_err());
        let err = parse(&["--live", "nowhere"]).unwrap_err().to_string();
        assert!(err.contains("nowhere"), "{err}");
    }

    #[test]
    fn the_caps_are_whole_numbers_in_their_ranges_and_a_refusal_names_option_and_value() {
        let parse = |args: &[&str]| Cli::try_parse_from([&["prog", "--live"], args].concat());
        let cli = parse(&[
            "--live-max-clients",
            "2",
            "--live-max-subscriptions",
            "4096",
        ])
        .unwrap();
        assert_eq!(cli.live.live_max_clients, Some(2));
        assert_eq!(cli.live.live_max_subscriptions, Some(4096));
        for (option, bad, range) in [
            ("--live-max-clients", "0", "clients, 1 to 1024"),
            ("--live-max-clients", "1025", "clients, 1 to 1024"),
            ("--live-max-clients", "-1", "clients, 1 to 1024"),
            (
                "--live-max-subscriptions",
                "0",
                "subscriptions per client, 1 to 4096",
            ),
            (
                "--live-max-subscriptions",
                "34000",
                "subscriptions per client, 1 to 4096",
            ),
            (
                "--live-max-subscriptions",
                "1.5",
                "subscriptions per client, 1 to 4096",
            ),
        ] {
            let err = parse(&[&format!("{option}={bad}")])
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(option) && err.contains(bad) && err.contains(range),
                "{option} {bad}: {err}"
            );
        }
        // The defaults are the library's, and hold a subscription to every channel.
        let server = LiveArgs {
            live: Some(parse_addr("127.0.0.1:0").unwrap()),
            ..LiveArgs::default()
        };
        assert!(LiveOptions::default().max_subscriptions >= drivelog::Channel::ALL.len());
        let server = server.serve("caps".into(), None).unwrap().unwrap();
        let status = drivelog::MessageTap::status(&mut server.tap()).unwrap();
        assert_eq!(status.value("max_clients"), Some("32"));
        assert_eq!(status.value("max_subscriptions"), Some("64"));
        let _ = server.stop();
    }

    #[test]
    fn serving_an_address_in_use_names_live_and_the_address() {
        let first = LiveArgs {
            live: Some(parse_addr("127.0.0.1:0").unwrap()),
            ..LiveArgs::default()
        };
        let server = first.serve("a".into(), None).unwrap().unwrap();
        let taken = LiveArgs {
            live: Some(server.local_addr()),
            ..LiveArgs::default()
        };
        let Err(err) = taken.serve("b".into(), None) else {
            panic!("a second server on {}", server.local_addr());
        };
        let err = err.to_string();
        assert!(
            err.starts_with("--live: ") && err.contains(&server.local_addr().to_string()),
            "{err}"
        );
        assert!(
            LiveArgs::default()
                .serve("c".into(), None)
                .unwrap()
                .is_none()
        );
        let _ = server.stop();
    }
}
