//! `--live [ADDR]` and `--live-can-hz HZ`: the command-line options of every program that
//! serves its log live (`hostsim run`, `hostsim plant`, `mecanum-runner`), flattened into
//! each program's own arguments (feature `cli`).

use std::io;
use std::net::SocketAddr;

use crate::{LiveOptions, LiveReport, LiveServer, parse_addr};

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

impl LiveArgs {
    /// The server `--live` asks for, named `name` (Foxglove shows it), listening; `None`
    /// without `--live`.
    ///
    /// # Errors
    /// The address cannot be served, naming it and `--live`.
    pub fn serve(&self, name: String) -> io::Result<Option<LiveServer>> {
        let Some(addr) = self.live else {
            return Ok(None);
        };
        let options = LiveOptions {
            name,
            can_hz: self.live_can_hz.unwrap_or(LiveOptions::default().can_hz),
            ..LiveOptions::default()
        };
        LiveServer::start(addr, options)
            .map(Some)
            .map_err(|e| io::Error::new(e.kind(), format!("--live: {e}")))
    }
}

impl LiveReport {
    /// The report in a program's JSON statistics (`--stats-json`, `--json`): `url`,
    /// `clients` (each `addr`, `subprotocol`, `connected_s`, `queued`, `sent`, `dropped`),
    /// and the totals `sent`, `dropped`, `thinned`.
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
                })
            })
            .collect();
        serde_json::json!({
            "url": self.url,
            "clients": clients,
            "sent": self.sent(),
            "dropped": self.dropped(),
            "thinned": self.thinned,
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
        let err = parse(&["--live", "nowhere"]).unwrap_err().to_string();
        assert!(err.contains("nowhere"), "{err}");
    }

    #[test]
    fn serving_an_address_in_use_names_live_and_the_address() {
        let first = LiveArgs {
            live: Some(parse_addr("127.0.0.1:0").unwrap()),
            live_can_hz: None,
        };
        let server = first.serve("a".into()).unwrap().unwrap();
        let taken = LiveArgs {
            live: Some(server.local_addr()),
            live_can_hz: None,
        };
        let Err(err) = taken.serve("b".into()) else {
            panic!("a second server on {}", server.local_addr());
        };
        let err = err.to_string();
        assert!(
            err.starts_with("--live: ") && err.contains(&server.local_addr().to_string()),
            "{err}"
        );
        assert!(LiveArgs::default().serve("c".into()).unwrap().is_none());
        let _ = server.stop();
    }
}
