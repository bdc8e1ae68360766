//! Careless and hostile live clients against a paced run: the run's wall time (the
//! simulation's, as its summary reports it, and the process's, which adds the start and the
//! stop's grace for clients) and the peak resident memory of the serving process
//! (`hostsim run square --live --rate 1`, 9.1 s simulated), for each load:
//!
//! - `none`: no client, the reference;
//! - `subs34k`: one client that sends 5 `subscribe` messages of 34,000 subscriptions each
//!   (unique ids, the advertised channels in turn) and reads what it gets;
//! - `stalled200`: 200 clients that subscribe to every channel and then read nothing;
//! - `idle1000`: 1,000 connections that complete the WebSocket handshake, then send and read
//!   nothing;
//! - `silent1000`: 1,000 TCP connections that never send their handshake.
//!
//! ```sh
//! cargo build --release -p hostsim
//! cargo run --release -p live --example hostile_clients -- --hostsim target/release/hostsim
//! ```
//!
//! Options: `--hostsim PATH` (required), `--only LOAD` (repeatable), `--repeat N` (1),
//! `--rate X` (1), `--scenario NAME` (square). Peak memory is GNU time's maximum resident set
//! size of the `hostsim` process (`/usr/bin/time`). One line per run on stdout, a Markdown
//! table row; docs/reliability.md ("The live server") records the figures.

use std::io::{BufRead as _, BufReader, Read as _};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use futures_util::{SinkExt as _, StreamExt as _};
use serde_json::{Value, json};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest as _;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

type Ws = WebSocketStream<MaybeTlsStream<TcpStream>>;
type Error = Box<dyn std::error::Error>;

const LOADS: [&str; 5] = ["none", "subs34k", "stalled200", "idle1000", "silent1000"];

struct Args {
    hostsim: PathBuf,
    only: Vec<String>,
    repeat: usize,
    rate: f64,
    scenario: String,
}

fn args() -> Result<Args, Error> {
    let mut a = Args {
        hostsim: PathBuf::new(),
        only: Vec::new(),
        repeat: 1,
        rate: 1.0,
        scenario: "square".to_string(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag}: a value is missing"));
        match flag.as_str() {
            "--hostsim" => a.hostsim = value()?.into(),
            "--only" => {
                let load = value()?;
                if !LOADS.contains(&load.as_str()) {
                    return Err(format!("--only {load:?}: expected one of {LOADS:?}").into());
                }
                a.only.push(load);
            }
            "--repeat" => a.repeat = value()?.parse()?,
            "--rate" => a.rate = value()?.parse()?,
            "--scenario" => a.scenario = value()?,
            other => return Err(format!("{other:?}: unknown option (see the source)").into()),
        }
    }
    if a.hostsim.as_os_str().is_empty() {
        return Err("--hostsim PATH is required".into());
    }
    Ok(a)
}

/// What one run measured.
struct Measured {
    wall_s: f64,
    peak_rss_kb: u64,
    summary: Value,
    /// What the clients saw: served, refused, cut off.
    seen: String,
}

#[tokio::main(flavor = "current_thread")]
async fn main() -> Result<(), Error> {
    let a = args()?;
    let commit = Command::new("git")
        .args(["rev-parse", "--short", "HEAD"])
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_default();
    println!(
        "# {} {} --live --rate {} ({}; the example built at {commit})",
        a.hostsim.display(),
        a.scenario,
        a.rate,
        std::env::consts::ARCH
    );
    println!(
        "| load | simulation | process | peak RSS | late max | clients seen by the server | \
         what the clients saw |"
    );
    println!("|---|---|---|---|---|---|---|");
    for load in LOADS
        .iter()
        .filter(|l| a.only.is_empty() || a.only.iter().any(|o| o == *l))
    {
        for _ in 0..a.repeat {
            let m = run(&a, load).await?;
            let live = &m.summary["live"];
            let cut = live["clients"]
                .as_array()
                .map_or(0, |c| c.iter().filter(|c| !c["cut_off"].is_null()).count());
            println!(
                "| {load} | {:.2} s | {:.2} s | {:.1} MB | {:.1} ms | {} served, {} refused, \
                 {cut} cut off, {} dropped | {} |",
                m.summary["wall_s"].as_f64().unwrap_or(f64::NAN),
                m.wall_s,
                m.peak_rss_kb as f64 / 1000.0,
                live["late_max_s"].as_f64().unwrap_or(f64::NAN) * 1e3,
                live["clients"].as_array().map_or(0, Vec::len),
                live["refused"].as_u64().unwrap_or(0),
                live["dropped"],
                m.seen,
            );
        }
    }
    Ok(())
}

/// One paced run under `load`.
async fn run(a: &Args, load: &str) -> Result<Measured, Error> {
    let out = std::env::temp_dir().join(format!("hostile-clients-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out)?;
    let time_file = out.join("time.txt");
    let started = Instant::now();
    let mut child = Command::new("/usr/bin/time")
        .arg("-o")
        .arg(&time_file)
        .args(["-f", "%M %e"])
        .arg(&a.hostsim)
        .args([
            "run",
            &a.scenario,
            "--live",
            "127.0.0.1:0",
            "--no-plot",
            "--json",
        ])
        .args(["--rate", &a.rate.to_string(), "--out"])
        .arg(&out)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()?;
    let mut stdout = child.stdout.take().ok_or("no stdout")?;
    let stdout = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stdout.read_to_string(&mut s);
        s
    });
    let stderr = child.stderr.take().ok_or("no stderr")?;
    let (url_tx, url_rx) = std::sync::mpsc::channel();
    let stderr = std::thread::spawn(move || {
        let mut all = String::new();
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.strip_prefix("live: ws://") {
                let url = rest.split_whitespace().next().unwrap_or_default();
                let _ = url_tx.send(format!("ws://{url}"));
            }
            all.push_str(&line);
            all.push('\n');
        }
        all
    });
    let url = url_rx
        .recv_timeout(Duration::from_secs(30))
        .map_err(|_| "no `live:` line from hostsim")?;

    // The load, until the run ends; what the clients hold is dropped after it.
    let (ended_tx, ended) = tokio::sync::watch::channel(false);
    let load_task = {
        let (url, load) = (url.clone(), load.to_string());
        tokio::spawn(async move { apply(&url, &load, ended).await })
    };
    let status = tokio::task::spawn_blocking(move || child.wait()).await??;
    let wall_s = started.elapsed().as_secs_f64();
    let _ = ended_tx.send(true);
    let seen = tokio::time::timeout(Duration::from_secs(10), load_task)
        .await
        .map_or_else(
            |_| "(the load did not end)".to_string(),
            |r| r.unwrap_or_else(|e| e.to_string()),
        );
    let stdout = stdout.join().unwrap_or_default();
    let stderr = stderr.join().unwrap_or_default();
    if !status.success() {
        return Err(format!("hostsim exited with {status}: {stderr}").into());
    }
    let time = std::fs::read_to_string(&time_file)?;
    let peak_rss_kb = time
        .split_whitespace()
        .next()
        .and_then(|k| k.parse().ok())
        .ok_or(format!("{}: {time:?}", time_file.display()))?;
    let summary: Value = serde_json::from_str(&stdout)?;
    let _ = std::fs::remove_dir_all(&out);
    Ok(Measured {
        wall_s,
        peak_rss_kb,
        summary,
        seen,
    })
}

/// Applies `load` to the server at `url`, holding its connections until the run has ended;
/// says what the clients saw.
async fn apply(url: &str, load: &str, mut ended: Ended) -> String {
    let (seen, held) = match load {
        "none" => ("-".to_string(), Held::default()),
        "subs34k" => (subs34k(url).await, Held::default()),
        "stalled200" => stalled(url, 200).await,
        "idle1000" => idle(url, 1000).await,
        "silent1000" => silent(url, 1000).await,
        _ => unreachable!(),
    };
    let _ = ended.wait_for(|e| *e).await;
    drop(held);
    seen
}

type Ended = tokio::sync::watch::Receiver<bool>;

/// Connections held open, unread, until the run has ended.
#[derive(Default)]
struct Held {
    _ws: Vec<Ws>,
    _tcp: Vec<TcpStream>,
}

async fn connect(url: &str) -> Result<Ws, Error> {
    let mut request = url.into_client_request()?;
    request
        .headers_mut()
        .insert("sec-websocket-protocol", "foxglove.sdk.v1".parse()?);
    Ok(tokio_tungstenite::connect_async(request).await?.0)
}

/// The next text message, as JSON (binary ones skipped); `None` at the close.
async fn next_json(
    ws: &mut (
             impl futures_util::Stream<Item = Result<Message, tokio_tungstenite::tungstenite::Error>>
             + Unpin
         ),
) -> Option<Value> {
    while let Some(Ok(m)) = ws.next().await {
        if let Message::Text(t) = m {
            return serde_json::from_str(t.as_str()).ok();
        }
    }
    None
}

/// Past `serverInfo` and `advertise`: the channel ids; `Err` with the status of a refusal.
async fn handshake(ws: &mut Ws) -> Result<Vec<u64>, String> {
    loop {
        let Some(v) = next_json(ws).await else {
            return Err("closed".to_string());
        };
        match v["op"].as_str() {
            Some("advertise") => {
                let channels = v["channels"].as_array().cloned().unwrap_or_default();
                return Ok(channels.iter().filter_map(|c| c["id"].as_u64()).collect());
            }
            Some("status") => return Err(v["message"].as_str().unwrap_or_default().to_string()),
            _ => {}
        }
    }
}

fn subscribe(subscriptions: impl Iterator<Item = (u64, u64)>) -> Message {
    let subs: Vec<Value> = subscriptions
        .map(|(id, channel)| json!({"id": id, "channelId": channel}))
        .collect();
    Message::text(json!({"op": "subscribe", "subscriptions": subs}).to_string())
}

/// One client, 5 `subscribe` messages of 34,000 subscriptions each, reading all it gets.
async fn subs34k(url: &str) -> String {
    let Ok(mut ws) = connect(url).await else {
        return "no connection".to_string();
    };
    let channels = match handshake(&mut ws).await {
        Ok(c) if !c.is_empty() => c,
        other => return format!("refused: {other:?}"),
    };
    let (mut tx, mut rx) = ws.split();
    let sender = tokio::spawn(async move {
        for k in 0..5u64 {
            let subs =
                (0..34_000u64).map(|i| (k * 34_000 + i, channels[i as usize % channels.len()]));
            if tx.send(subscribe(subs)).await.is_err() {
                break;
            }
        }
        tx
    });
    let (mut messages, mut status) = (0u64, None);
    while let Some(Ok(m)) = rx.next().await {
        match m {
            Message::Binary(_) => messages += 1,
            Message::Text(t) => {
                let v: Value = serde_json::from_str(t.as_str()).unwrap_or_default();
                if v["level"] == 2 {
                    status = v["message"]
                        .as_str()
                        .map(|s| s.chars().take(60).collect::<String>());
                }
            }
            Message::Close(_) => break,
            _ => {}
        }
    }
    sender.abort();
    match status {
        Some(s) => format!("{messages} messages, then cut off: \"{s}...\""),
        None => format!("{messages} messages, never cut off"),
    }
}

/// `n` clients that subscribe to every channel and then read nothing.
async fn stalled(url: &str, n: usize) -> (String, Held) {
    let (mut held, mut refused, mut failed) = (Vec::new(), 0, 0);
    for _ in 0..n {
        let Ok(mut ws) = connect(url).await else {
            failed += 1;
            continue;
        };
        match handshake(&mut ws).await {
            Ok(channels) => {
                let subs = channels.iter().enumerate().map(|(i, &c)| (i as u64, c));
                let _ = ws.send(subscribe(subs)).await;
                held.push(ws);
            }
            Err(_) => refused += 1,
        }
    }
    let seen = format!(
        "{} subscribed, {refused} told the cap, {failed} not connected",
        held.len()
    );
    (
        seen,
        Held {
            _ws: held,
            _tcp: Vec::new(),
        },
    )
}

/// `n` connections that complete the handshake, then send and read nothing.
async fn idle(url: &str, n: usize) -> (String, Held) {
    let (mut held, mut failed) = (Vec::new(), 0);
    for _ in 0..n {
        match connect(url).await {
            Ok(ws) => held.push(ws),
            Err(_) => failed += 1,
        }
    }
    let seen = format!("{} handshakes done, {failed} failed", held.len());
    (
        seen,
        Held {
            _ws: held,
            _tcp: Vec::new(),
        },
    )
}

/// `n` TCP connections that never send their handshake.
async fn silent(url: &str, n: usize) -> (String, Held) {
    let addr = url.trim_start_matches("ws://").to_string();
    let (mut held, mut failed) = (Vec::new(), 0);
    for _ in 0..n {
        match TcpStream::connect(&addr).await {
            Ok(s) => held.push(s),
            Err(_) => failed += 1,
        }
    }
    let seen = format!("{} connected, {failed} failed", held.len());
    (
        seen,
        Held {
            _ws: Vec::new(),
            _tcp: held,
        },
    )
}
