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
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest as _;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

type Ws = WebSocketStream<MaybeTlsStream<TcpStream>>;

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

async fn connect(server: &LiveServer, protocols: &str) -> Result<(Ws, Option<String>), String> {
    let mut request = server.url().into_client_request().unwrap();
    if !protocols.is_empty() {
        request
            .headers_mut()
            .insert("sec-websocket-protocol", protocols.parse().unwrap());
    }
    let (ws, response) = tokio_tungstenite::connect_async(request)
        .await
        .map_err(|e| e.to_string())?;
    let chosen = response
        .headers()
        .get("sec-websocket-protocol")
        .map(|h| h.to_str().unwrap().to_string());
    Ok((ws, chosen))
}

async fn next_json(ws: &mut Ws) -> Value {
    loop {
        let m = tokio::time::timeout(Duration::from_secs(5), ws.next())
            .await
            .expect("a message within 5 s")
            .expect("open")
            .expect("no error");
        if let Message::Text(t) = m {
            return serde_json::from_str(t.as_str()).unwrap();
        }
    }
}

/// Logs `ms` milliseconds of messages: 4 frames a millisecond on /can/rx (two ids), one on
/// /can/tx, odometry and diagnostics every 10 ms.
fn log_run(log: &mut McapLog, ms: u64) {
    let snapshot = firmware::Controller::new(&firmware::Config::dji_m3508_example())
        .unwrap()
        .snapshot();
    for i in 0..ms {
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
    // The channels are advertised as soon as the tap is installed, before any message.
    let advertise = next_json(&mut ws).await;
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
                assert_eq!(b[0], 1, "messageData");
                let sub = u32::from_le_bytes(b[1..5].try_into().unwrap());
                let log_time = u64::from_le_bytes(b[5..13].try_into().unwrap());
                let topic = topics[sub as usize - 10].to_string();
                received.push((topic, log_time, b[13..].to_vec()));
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
        let sub = u32::from_le_bytes(b[1..5].try_into().unwrap());
        let log_time = u64::from_le_bytes(b[5..13].try_into().unwrap());
        received.push((
            topics[sub as usize - 10].to_string(),
            log_time,
            b[13..].to_vec(),
        ));
    }

    let in_file = read_file(&file.0);
    let by_key: HashMap<(&str, u64), Vec<&Vec<u8>>> =
        in_file.iter().fold(HashMap::new(), |mut m, (t, l, d)| {
            m.entry((t.as_str(), *l)).or_default().push(d);
            m
        });
    for (topic, log_time, data) in &received {
        let same = by_key
            .get(&(topic.as_str(), *log_time))
            .unwrap_or_else(|| panic!("{topic} at {log_time} is not in the file"));
        assert!(
            same.contains(&data),
            "{topic} at {log_time}: other bytes than the file's"
        );
    }
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
