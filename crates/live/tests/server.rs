//! The live server against a client that speaks the protocol, with the log file as the
//! oracle: the handshake, the advertised channels, the messages of a subscription equal to
//! the file's, a stalled client that loses (counted) messages without holding up the log,
//! and the port closed after `stop`.

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use drivelog::{Channel, Direction, McapLog, OdometrySource, for_each_message, msg};
use embedded_can::StandardId;
use firmware::CanFrame;
use futures_util::{SinkExt as _, StreamExt as _};
use live::{LiveOptions, LiveServer};
use serde_json::{Value, json};
use tokio::net::TcpStream;
use tokio_tungstenite::MaybeTlsStream;
use tokio_tungstenite::tungstenite::client::IntoClientRequest as _;
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

mod common;

use common::{Ws, connect, next_json};

/// A file of its own for a test, removed when dropped.
struct TempFile(PathBuf);

impl TempFile {
    fn new(test: &str) -> Self {
        let name = format!("live-{}-{test}.mcap", std::process::id());
        Self(std::env::temp_dir().join(name))
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn server(options: LiveOptions) -> LiveServer {
    LiveServer::start("127.0.0.1:0".parse().unwrap(), options).unwrap()
}

/// Logs `ms` milliseconds of messages: 4 frames a millisecond on /can/rx (two ids), one on
/// /can/tx, odometry and diagnostics every 10 ms.
fn log_run(log: &mut McapLog, ms: u64) {
    log_span(log, 0..ms);
}

/// [`log_run`] from one log time to another, milliseconds.
fn log_span(log: &mut McapLog, ms: std::ops::Range<u64>) {
    let snapshot = firmware::Controller::new(&firmware::Config::dji_m3508_example())
        .unwrap()
        .snapshot();
    for i in ms {
        let t = i * 1_000_000;
        for k in 0..4u64 {
            let id = StandardId::new(0x201 + (k % 2) as u16).unwrap();
            let f = CanFrame::standard(id, &i.to_le_bytes()).unwrap();
            log.frame(Direction::Rx, t + k * 100, t, t + k * 100, &f)
                .unwrap();
        }
        let cmd = CanFrame::standard(StandardId::new(0x200).unwrap(), &[1; 8]).unwrap();
        log.frame(Direction::Tx, t + 500, t, t + 450, &cmd).unwrap();
        if i % 10 == 0 {
            log.snapshot(t, &snapshot).unwrap();
            let x = i as f64 * 1e-3;
            log.odometry(t, OdometrySource::Firmware, [x, 0.0, 0.1], [1.0, 0.0, 0.0])
                .unwrap();
        }
        log.maybe_flush().unwrap();
    }
}

/// The file's messages: (topic, log time, bytes).
fn read_file(path: &PathBuf) -> Vec<(String, u64, Vec<u8>)> {
    let bytes = std::fs::read(path).unwrap();
    let mut out = Vec::new();
    let report = for_each_message(
        &bytes,
        |m| out.push((m.topic.to_string(), m.log_time, m.data.to_vec())),
        |_, _| {},
    )
    .unwrap();
    assert!(report.is_complete(), "{report}");
    out
}

#[tokio::test]
async fn the_handshake_names_the_protocol_and_refuses_other_ones() {
    let server = server(LiveOptions::default());
    let (_, chosen) = connect(&server, "foxglove.sdk.v1").await.unwrap();
    assert_eq!(chosen.as_deref(), Some("foxglove.sdk.v1"));
    // The new name first, whatever the client's order; the old name alone is accepted.
    let (_, chosen) = connect(&server, "foxglove.websocket.v1, foxglove.sdk.v1")
        .await
        .unwrap();
    assert_eq!(chosen.as_deref(), Some("foxglove.sdk.v1"));
    let (_, chosen) = connect(&server, "foxglove.websocket.v1").await.unwrap();
    assert_eq!(chosen.as_deref(), Some("foxglove.websocket.v1"));
    // The schema-table variant is not served: a client offering it alone is refused.
    for refused in ["", "foxglove.sdk.v1.1", "something.else"] {
        let err = connect(&server, refused).await.unwrap_err();
        assert!(err.contains("400"), "{refused:?}: {err}");
    }
    let report = server.stop();
    assert_eq!(report.clients.len(), 3);
}

/// The `advertise` a client gets as soon as the tap is installed, before any message: every
/// channel, as the file's Channel and Schema records have it. The channel ids by topic.
async fn advertised_channels(ws: &mut Ws) -> HashMap<&'static str, u64> {
    let advertise = next_json(ws).await;
    assert_eq!(advertise["op"], "advertise");
    let channels = advertise["channels"].as_array().unwrap();
    assert_eq!(channels.len(), Channel::ALL.len());
    let mut ids = HashMap::new();
    for (c, expected) in channels.iter().zip(Channel::ALL) {
        assert_eq!(c["id"], u64::from(expected.id()));
        assert_eq!(c["topic"], expected.topic());
        assert_eq!(c["encoding"], "cdr");
        assert_eq!(c["schemaName"], expected.def().name);
        assert_eq!(c["schemaEncoding"], "ros2msg");
        assert_eq!(c["schema"], expected.def().schema_text());
        ids.insert(expected.topic(), c["id"].as_u64().unwrap());
    }
    ids
}

/// A `messageData`: (topic, log time, bytes), the topic from its subscription id (10 + the
/// topic's index in `topics`).
fn message_data(b: &[u8], topics: &[&str]) -> (String, u64, Vec<u8>) {
    assert_eq!(b[0], 1, "messageData");
    let sub = u32::from_le_bytes(b[1..5].try_into().unwrap());
    let log_time = u64::from_le_bytes(b[5..13].try_into().unwrap());
    (
        topics[sub as usize - 10].to_string(),
        log_time,
        b[13..].to_vec(),
    )
}

/// Every message received is one of the file's, at its log time, with its bytes.
fn assert_the_files_bytes(received: &[(String, u64, Vec<u8>)], in_file: &[(String, u64, Vec<u8>)]) {
    let by_key: HashMap<(&str, u64), Vec<&Vec<u8>>> =
        in_file.iter().fold(HashMap::new(), |mut m, (t, l, d)| {
            m.entry((t.as_str(), *l)).or_default().push(d);
            m
        });
    for (topic, log_time, data) in received {
        let same = by_key
            .get(&(topic.as_str(), *log_time))
            .unwrap_or_else(|| panic!("{topic} at {log_time} is not in the file"));
        assert!(
            same.contains(&data),
            "{topic} at {log_time}: other bytes than the file's"
        );
    }
}

#[tokio::test]
async fn subscribed_messages_are_the_files_bytes_at_their_log_times() {
    let file = TempFile::new("subscribed");
    let server = server(LiveOptions {
        name: "test run".to_string(),
        ..LiveOptions::default()
    });
    let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
    log.set_tap(Box::new(server.tap()));
    log.set_flush_interval(live::FLUSH_INTERVAL);

    let (mut ws, _) = connect(&server, "foxglove.sdk.v1").await.unwrap();
    let info = next_json(&mut ws).await;
    assert_eq!(info["op"], "serverInfo");
    assert_eq!(info["name"], "test run");
    let ids = advertised_channels(&mut ws).await;
    let topics = ["/odom", "/diagnostics", "/can/rx", "/can/tx"];
    let subscriptions: Vec<Value> = topics
        .iter()
        .enumerate()
        .map(|(i, t)| json!({"id": i + 10, "channelId": ids[t]}))
        .collect();
    let subscribe = json!({"op": "subscribe", "subscriptions": subscriptions});
    ws.send(Message::text(subscribe.to_string())).await.unwrap();
    // Let the server take the subscription before the run goes on.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let log_thread = std::thread::spawn(move || {
        log_run(&mut log, 1000);
        log.finish().unwrap();
    });

    let mut received: Vec<(String, u64, Vec<u8>)> = Vec::new();
    loop {
        let m = tokio::time::timeout(Duration::from_secs(5), ws.next())
            .await
            .expect("the server closes within 5 s");
        let Some(Ok(m)) = m else { break };
        match m {
            Message::Binary(b) => {
                received.push(message_data(&b, &topics));
                if received.iter().filter(|r| r.0 == "/odom").count() == 100 {
                    // The whole run: stop the server now that the log is finished.
                    break;
                }
            }
            Message::Close(_) => break,
            _ => {}
        }
    }
    log_thread.join().unwrap();
    let report = server.stop();
    // Whatever remains after the 100th odometry (the last 10 ms) came before the close.
    while let Ok(Some(Ok(Message::Binary(b)))) =
        tokio::time::timeout(Duration::from_secs(1), ws.next()).await
    {
        received.push(message_data(&b, &topics));
    }

    let in_file = read_file(&file.0);
    assert_the_files_bytes(&received, &in_file);
    let count = |list: &[(String, u64, Vec<u8>)], topic: &str, after: u64| {
        list.iter().filter(|r| r.0 == topic && r.1 >= after).count()
    };
    // Everything but CAN.
    for topic in ["/odom", "/diagnostics"] {
        assert_eq!(
            count(&received, topic, 0),
            count(&in_file, topic, 0),
            "{topic}"
        );
    }
    // CAN at 100 Hz per id: 2 ids on /can/rx and one on /can/tx, for one second (each id's
    // second holds one frame more: the half period of tolerance at its start).
    let rx = count(&received, "/can/rx", 0);
    let tx = count(&received, "/can/tx", 0);
    assert!((200..=202).contains(&rx), "{rx} rx frames");
    assert!((100..=101).contains(&tx), "{tx} tx frames");
    assert_eq!(
        count(&in_file, "/can/rx", 0),
        4000,
        "the file keeps every frame"
    );
    // The live status follows the firmware's on /diagnostics, in the file as sent.
    let (_, _, last) = received.iter().rfind(|r| r.0 == "/diagnostics").unwrap();
    let d: msg::DiagnosticArray = msg::decode(last).unwrap();
    assert_eq!(d.status[1].name, live::STATUS_NAME);
    assert_eq!(d.status[1].value("clients"), Some("1"));
    assert_eq!(d.status[1].value("dropped"), Some("0"));
    assert_eq!(report.dropped(), 0, "{report}");
    assert!(report.thinned >= 4000 + 1000 - 303, "{report}");
}

#[tokio::test]
async fn a_stalled_client_loses_counted_messages_and_holds_nothing_up() {
    let file = TempFile::new("stalled");
    let server = server(LiveOptions {
        backlog: 64,
        can_hz: 0,
        ..LiveOptions::default()
    });
    // A client with a small receive buffer that subscribes to everything, then reads nothing.
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let stream = socket.connect(server.local_addr()).await.unwrap();
    let mut request = server.url().into_client_request().unwrap();
    request
        .headers_mut()
        .insert("sec-websocket-protocol", "foxglove.sdk.v1".parse().unwrap());
    let (mut ws, _) = tokio_tungstenite::client_async(request, MaybeTlsStream::Plain(stream))
        .await
        .unwrap();
    let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
    log.set_tap(Box::new(server.tap()));
    log.set_flush_interval(live::FLUSH_INTERVAL);
    let _ = next_json(&mut ws).await;
    let advertise = next_json(&mut ws).await;
    let subscriptions: Vec<Value> = advertise["channels"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
        .map(|(i, c)| json!({"id": i, "channelId": c["id"]}))
        .collect();
    let subscribe = json!({"op": "subscribe", "subscriptions": subscriptions});
    ws.send(Message::text(subscribe.to_string())).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;

    // Five seconds of log time, as fast as the writer goes.
    let started = Instant::now();
    let log_thread = std::thread::spawn(move || {
        log_run(&mut log, 5000);
        log.finish().unwrap();
    });
    log_thread.join().unwrap();
    let logged_in = started.elapsed();
    let stats = server.stats();
    assert!(stats.dropped > 10_000, "{stats:?}");
    assert!(logged_in < Duration::from_secs(10), "{logged_in:?}");
    let stopping = Instant::now();
    let report = server.stop();
    assert!(
        stopping.elapsed() < Duration::from_secs(2),
        "{:?}",
        stopping.elapsed()
    );
    let c = &report.clients[0];
    assert_eq!(c.queued, c.sent + c.dropped, "{report}");
    assert!(c.dropped >= stats.dropped, "{report}");
    assert!(c.sent > 0, "{report}");
    drop(ws);
}

#[tokio::test]
async fn after_stop_the_port_is_closed() {
    let server = server(LiveOptions::default());
    let addr = server.local_addr();
    let (_ws, _) = connect(&server, "foxglove.sdk.v1").await.unwrap();
    let report = server.stop();
    assert_eq!(report.clients.len(), 1);
    let err = TcpStream::connect(addr).await.unwrap_err();
    assert_eq!(err.kind(), std::io::ErrorKind::ConnectionRefused);
}

/// What a client receives: a [`Ws`] or its stream half.
trait Incoming: futures_util::Stream<Item = Result<Message, WsError>> {}
impl<S: futures_util::Stream<Item = Result<Message, WsError>>> Incoming for S {}

/// Waits until `cond` holds, 5 s at most.
async fn wait_until(what: &str, mut cond: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(5);
    while !cond() {
        assert!(Instant::now() < deadline, "not within 5 s: {what}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// The next message, `None` once the connection is closed; 5 s at most.
async fn next_message(ws: &mut (impl Incoming + Unpin)) -> Option<Message> {
    tokio::time::timeout(Duration::from_secs(5), ws.next())
        .await
        .expect("a message within 5 s")
        .and_then(Result::ok)
}

/// Reads up to the server's `status` error, then its close frame: the error's message (which
/// must name each of `names`) and the close code. Data and other statuses before are skipped.
async fn expect_cut_off(ws: &mut (impl Incoming + Unpin), names: &[&str]) -> (String, u16) {
    let message = loop {
        match next_message(ws).await {
            Some(Message::Text(t)) => {
                let v: Value = serde_json::from_str(t.as_str()).unwrap();
                if v["op"] == "status" && v["level"] == 2 {
                    break v["message"].as_str().unwrap().to_string();
                }
            }
            Some(Message::Binary(_)) => {}
            other => panic!("a status error before {other:?}"),
        }
    };
    for name in names {
        assert!(message.contains(name), "{name:?} not in {message:?}");
    }
    loop {
        match next_message(ws).await {
            Some(Message::Close(Some(frame))) => return (message, u16::from(frame.code)),
            Some(Message::Binary(_)) => {}
            other => panic!("{message}: a close frame, not {other:?}"),
        }
    }
}

/// Sends `subscriptions` (id, channel id) in one `subscribe`.
async fn subscribe(ws: &mut Ws, subscriptions: impl IntoIterator<Item = (u64, u64)>) {
    let subscriptions: Vec<Value> = subscriptions
        .into_iter()
        .map(|(id, channel)| json!({"id": id, "channelId": channel}))
        .collect();
    let subscribe = json!({"op": "subscribe", "subscriptions": subscriptions});
    ws.send(Message::text(subscribe.to_string())).await.unwrap();
}

/// Waits until the server has taken every request sent before: it answers the fence, an op it
/// does not serve, with a warning, in order.
async fn fence(ws: &mut Ws) {
    let request = json!({"op": "subscribeConnectionGraph"});
    ws.send(Message::text(request.to_string())).await.unwrap();
    loop {
        let Some(Message::Text(t)) = next_message(ws).await else {
            continue;
        };
        let v: Value = serde_json::from_str(t.as_str()).unwrap();
        if v["op"] == "status" {
            let message = v["message"].as_str().unwrap();
            assert!(message.contains("subscribeConnectionGraph"), "{v}");
            return;
        }
    }
}

/// A client past `serverInfo` and `advertise`: the channel ids by topic.
async fn connected(server: &LiveServer) -> (Ws, HashMap<String, u64>) {
    let (mut ws, _) = connect(server, "foxglove.sdk.v1").await.unwrap();
    assert_eq!(next_json(&mut ws).await["op"], "serverInfo");
    let advertise = next_json(&mut ws).await;
    assert_eq!(advertise["op"], "advertise");
    let ids = advertise["channels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let topic = c["topic"].as_str().unwrap().to_string();
            (topic, c["id"].as_u64().unwrap())
        })
        .collect();
    (ws, ids)
}

/// The Foxglove ws-protocol close codes the server uses.
const CLOSE_POLICY: u16 = 1008;
const CLOSE_AGAIN: u16 = 1013;

#[tokio::test]
async fn a_client_beyond_max_clients_is_told_the_cap_and_closed_and_counted() {
    let server = server(LiveOptions {
        max_clients: 2,
        ..LiveOptions::default()
    });
    let (mut a, _) = connect(&server, "foxglove.sdk.v1").await.unwrap();
    let (mut b, _) = connect(&server, "foxglove.sdk.v1").await.unwrap();
    // serverInfo is sent once a client is registered: both hold their place.
    assert_eq!(next_json(&mut a).await["op"], "serverInfo");
    assert_eq!(next_json(&mut b).await["op"], "serverInfo");
    // The third one's handshake is accepted; then it is told why, and closed.
    let (mut c, chosen) = connect(&server, "foxglove.sdk.v1").await.unwrap();
    assert_eq!(chosen.as_deref(), Some("foxglove.sdk.v1"));
    let (message, code) =
        expect_cut_off(&mut c, &["too many clients", "--live-max-clients 2"]).await;
    assert_eq!(code, CLOSE_AGAIN, "{message}");
    assert_eq!(next_message(&mut c).await, None);
    let stats = server.stats();
    assert_eq!((stats.clients, stats.refused), (2, 1), "{stats:?}");
    // A place that frees is taken by the next client.
    drop(a);
    wait_until("the first client is gone", || server.stats().clients == 1).await;
    let (mut d, _) = connect(&server, "foxglove.sdk.v1").await.unwrap();
    assert_eq!(next_json(&mut d).await["op"], "serverInfo");
    assert_eq!(server.stats().clients, 2);
    let report = server.stop();
    assert_eq!(report.refused, 1, "{report}");
    assert_eq!(report.clients.len(), 3, "{report}");
    assert!(
        report.to_string().contains("1 connections refused"),
        "{report}"
    );
}

#[tokio::test]
async fn connections_beyond_the_handshakes_in_progress_are_closed_at_once() {
    let server = server(LiveOptions::default());
    // 64 connections that never send their handshake hold every handshake place.
    let mut silent = Vec::new();
    for _ in 0..64 {
        silent.push(TcpStream::connect(server.local_addr()).await.unwrap());
    }
    // The 65th is closed before its handshake.
    let refused = connect(&server, "foxglove.sdk.v1").await;
    assert!(refused.is_err(), "a 65th handshake in progress was served");
    wait_until("the refusal counted", || server.stats().refused >= 1).await;
    drop(silent);
    // Their places free as they close: a client is served again.
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut ws = loop {
        if let Ok((ws, _)) = connect(&server, "foxglove.sdk.v1").await {
            break ws;
        }
        assert!(Instant::now() < deadline, "no handshake place freed in 5 s");
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    assert_eq!(next_json(&mut ws).await["op"], "serverInfo");
    let _ = server.stop();
}

#[tokio::test]
async fn a_duplicate_subscription_is_refused_naming_it_and_the_client_cut_off() {
    let file = TempFile::new("duplicate");
    let server = server(LiveOptions::default());
    let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
    log.set_tap(Box::new(server.tap()));
    let (mut same_channel, ids) = connected(&server).await;
    let odom = ids["/odom"];
    // A channel subscribed twice, in two messages.
    subscribe(&mut same_channel, [(1, odom)]).await;
    fence(&mut same_channel).await;
    subscribe(&mut same_channel, [(2, odom)]).await;
    let (message, code) = expect_cut_off(
        &mut same_channel,
        &[
            "subscription 2",
            &format!("channel {odom} is subscribed already (subscription 1)"),
            "duplicate",
        ],
    )
    .await;
    assert_eq!(code, CLOSE_POLICY, "{message}");
    // An id in use, in one message.
    let (mut same_id, _) = connected(&server).await;
    subscribe(&mut same_id, [(7, odom), (7, ids["/tf"])]).await;
    let (message, code) = expect_cut_off(
        &mut same_id,
        &["subscription 7: the id is in use", "duplicate"],
    )
    .await;
    assert_eq!(code, CLOSE_POLICY, "{message}");
    // A channel twice in one message.
    let (mut twice, _) = connected(&server).await;
    subscribe(&mut twice, [(1, odom), (2, odom)]).await;
    expect_cut_off(&mut twice, &["channel", "subscribed already"]).await;
    wait_until("the three are gone", || server.stats().clients == 0).await;
    log.finish().unwrap();
    let report = server.stop();
    assert_eq!(server_cut_offs(&report), 3, "{report}");
    assert_eq!(report.refused, 0, "{report}");
}

fn server_cut_offs(report: &live::LiveReport) -> usize {
    report
        .clients
        .iter()
        .filter(|c| c.cut_off.is_some())
        .count()
}

#[tokio::test]
async fn subscriptions_beyond_max_subscriptions_are_refused_naming_the_cap() {
    let file = TempFile::new("max-subscriptions");
    let server = server(LiveOptions {
        max_subscriptions: 4,
        ..LiveOptions::default()
    });
    let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
    log.set_tap(Box::new(server.tap()));
    let (mut ws, ids) = connected(&server).await;
    let channels: Vec<u64> = Channel::ALL.iter().map(|c| ids[c.topic()]).collect();
    // 3, then 1 more (the cap), then 1 beyond it.
    subscribe(&mut ws, (0..3).map(|i| (i, channels[i as usize]))).await;
    subscribe(&mut ws, [(3, channels[3])]).await;
    fence(&mut ws).await;
    subscribe(&mut ws, [(4, channels[4])]).await;
    let (message, code) = expect_cut_off(
        &mut ws,
        &[
            "1 subscriptions more than the 4 held",
            "--live-max-subscriptions 4",
        ],
    )
    .await;
    assert_eq!(code, CLOSE_POLICY, "{message}");
    log.finish().unwrap();
    let report = server.stop();
    assert_eq!(report.clients[0].cut_off.as_deref(), Some(message.as_str()));
}

/// The issue's client: 5 `subscribe` messages of 34,000 subscriptions each (ids unique, all
/// to one channel), each some 920 KB, just under the 1 MiB a client's message may be.
fn hostile_subscribes(channel: u64) -> Vec<Message> {
    use std::fmt::Write as _;
    (0..5u64)
        .map(|k| {
            let mut m = String::from(r#"{"op":"subscribe","subscriptions":["#);
            for i in 0..34_000u64 {
                let sep = if i == 0 { "" } else { "," };
                let id = k * 34_000 + i;
                write!(m, r#"{sep}{{"id":{id},"channelId":{channel}}}"#).unwrap();
            }
            m.push_str("]}");
            Message::text(m)
        })
        .collect()
}

#[tokio::test]
async fn a_viewer_gets_every_message_while_a_client_of_34000_subscriptions_is_cut_off() {
    let file = TempFile::new("hostile");
    let server = server(LiveOptions::default());
    let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
    log.set_tap(Box::new(server.tap()));
    log.set_flush_interval(live::FLUSH_INTERVAL);
    let (mut viewer, ids) = connected(&server).await;
    subscribe(&mut viewer, [(1, ids["/odom"]), (2, ids["/diagnostics"])]).await;
    fence(&mut viewer).await;
    // The viewer reads all along, and until the close at the stop.
    let viewer = tokio::spawn(async move {
        let mut received = HashMap::<u32, usize>::new();
        while let Some(m) = next_message(&mut viewer).await {
            match m {
                Message::Binary(b) => {
                    let sub = u32::from_le_bytes(b[1..5].try_into().unwrap());
                    *received.entry(sub).or_default() += 1;
                }
                Message::Close(_) => break,
                other => panic!("{other:?}"),
            }
        }
        received
    });
    let (hostile, _) = connected(&server).await;
    let (mut hostile_tx, mut hostile_rx) = hostile.split();
    let messages = hostile_subscribes(ids["/can/rx"]);
    assert!(messages.iter().all(|m| m.len() < 1 << 20));

    // The run goes on, 10 ms of log at a time, until the hostile client is cut off and for
    // at least half a second of log; then 100 ms more, so that its last status says so.
    let (cut_tx, cut_rx) = std::sync::mpsc::channel::<()>();
    let log_thread = std::thread::spawn(move || {
        let (mut ms, mut cut) = (0, false);
        while ms < 500 || !cut {
            assert!(ms < 60_000, "not cut off within a minute of log");
            log_span(&mut log, ms..ms + 10);
            ms += 10;
            cut |= cut_rx.try_recv().is_ok();
            std::thread::sleep(Duration::from_millis(1));
        }
        log_span(&mut log, ms..ms + 100);
        log.finish().unwrap();
    });
    // Sent from a task of its own: once cut off, the client is no longer read, and what it
    // still sends fills the socket.
    let sender = tokio::spawn(async move {
        for m in messages {
            if hostile_tx.send(m).await.is_err() {
                break;
            }
        }
    });
    let (message, code) = expect_cut_off(
        &mut hostile_rx,
        &[
            "subscribe: 34000 subscriptions more than the 0 held",
            "--live-max-subscriptions 64",
        ],
    )
    .await;
    assert_eq!(code, CLOSE_POLICY, "{message}");
    cut_tx.send(()).unwrap();
    let report = tokio::task::spawn_blocking(move || {
        log_thread.join().unwrap();
        server.stop()
    })
    .await
    .unwrap();
    sender.abort();

    // The viewer got every /odom and /diagnostics of the run, then the close.
    let received = viewer.await.unwrap();
    let in_file = read_file(&file.0);
    let count = |topic: &str| in_file.iter().filter(|r| r.0 == topic).count();
    assert!(count("/odom") >= 60, "{} /odom", count("/odom"));
    assert_eq!(received.get(&1).copied(), Some(count("/odom")));
    assert_eq!(received.get(&2).copied(), Some(count("/diagnostics")));
    let viewer_report = report.clients.iter().find(|c| c.cut_off.is_none()).unwrap();
    assert_eq!(viewer_report.dropped, 0, "{report}");
    assert_eq!(server_cut_offs(&report), 1, "{report}");
    let status = server_status_in(&file.0);
    assert_eq!(status.value("cut_off"), Some("1"));
    assert_eq!(status.level, msg::DiagnosticStatus::WARN);
}

/// The live status in the last `/diagnostics` of a log.
fn server_status_in(path: &PathBuf) -> msg::DiagnosticStatus {
    let (_, _, last) = read_file(path)
        .into_iter()
        .rfind(|r| r.0 == "/diagnostics")
        .unwrap();
    let d: msg::DiagnosticArray = msg::decode(&last).unwrap();
    d.status
        .into_iter()
        .find(|s| s.name == live::STATUS_NAME)
        .unwrap()
}

#[tokio::test]
async fn a_message_beyond_the_size_cap_gets_a_status_naming_it_and_the_close() {
    let server = server(LiveOptions::default());
    let (ws, _) = connect(&server, "foxglove.sdk.v1").await.unwrap();
    let (mut tx, mut rx) = ws.split();
    let big = Message::text("x".repeat((1 << 20) + 1));
    let sender = tokio::spawn(async move { tx.send(big).await });
    let mut ws_rx = Vec::new();
    while let Some(m) = tokio::time::timeout(Duration::from_secs(5), rx.next())
        .await
        .expect("a message within 5 s")
    {
        let Ok(m) = m else { break };
        let close = matches!(m, Message::Close(_));
        ws_rx.push(m);
        if close {
            break;
        }
    }
    let status = ws_rx
        .iter()
        .filter_map(|m| match m {
            Message::Text(t) => Some(serde_json::from_str::<Value>(t.as_str()).unwrap()),
            _ => None,
        })
        .find(|v| v["op"] == "status" && v["level"] == 2)
        .unwrap_or_else(|| panic!("no status error: {ws_rx:?}"));
    let message = status["message"].as_str().unwrap();
    assert!(message.contains("at most 1048576 bytes"), "{message}");
    let Some(Message::Close(Some(frame))) = ws_rx.last() else {
        panic!("no close frame: {ws_rx:?}");
    };
    assert_eq!(u16::from(frame.code), CLOSE_POLICY);
    drop(sender);
    let report = server.stop();
    assert_eq!(server_cut_offs(&report), 1, "{report}");
}

#[tokio::test]
async fn subscriptions_that_churn_during_a_run_hold_nothing_up() {
    // A subscribe takes the server's state and the client's subscriptions in the order the
    // writing thread takes them: in the other order the two threads stopped each other.
    let file = TempFile::new("churn");
    let server = server(LiveOptions::default());
    let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
    log.set_tap(Box::new(server.tap()));
    log.set_flush_interval(Duration::from_millis(1));
    let (ws, ids) = connected(&server).await;
    let (mut tx, mut rx) = ws.split();
    let reader = tokio::spawn(async move { while let Some(Ok(_)) = rx.next().await {} });
    let (done_tx, done_rx) = std::sync::mpsc::channel();
    let log_thread = std::thread::spawn(move || {
        log_run(&mut log, 3000);
        log.finish().unwrap();
        done_tx.send(()).unwrap();
    });
    let channels: Vec<u64> = ids.values().copied().collect();
    let subs = channels
        .iter()
        .enumerate()
        .map(|(i, &c)| json!({"id": i, "channelId": c}));
    let subscribe = json!({"op": "subscribe", "subscriptions": subs.collect::<Vec<_>>()});
    let ids: Vec<usize> = (0..channels.len()).collect();
    let unsubscribe = json!({"op": "unsubscribe", "subscriptionIds": ids});
    let mut rounds = 0u32;
    let churn = async {
        while done_rx.try_recv().is_err() {
            tx.send(Message::text(subscribe.to_string())).await.unwrap();
            tx.send(Message::text(unsubscribe.to_string()))
                .await
                .unwrap();
            rounds += 1;
            tokio::task::yield_now().await;
        }
    };
    if tokio::time::timeout(Duration::from_secs(30), churn)
        .await
        .is_err()
    {
        // Stuck: a stop would wait on the server's thread for ever.
        std::mem::forget(server);
        panic!("the log did not finish within 30 s: the writing thread is held up");
    }
    log_thread.join().unwrap();
    let report = tokio::task::spawn_blocking(move || server.stop())
        .await
        .unwrap();
    reader.abort();
    assert!(rounds > 10, "{rounds} rounds");
    assert!(report.clients[0].cut_off.is_none(), "{report}");
}
