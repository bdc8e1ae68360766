//! What the live server's tests share: a client's connection and its next text message.

use std::time::Duration;

use futures_util::StreamExt as _;
use live::LiveServer;
use serde_json::Value;
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest as _;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

/// A client's connection.
pub type Ws = WebSocketStream<MaybeTlsStream<TcpStream>>;

/// Connects to `server` offering the subprotocols `protocols` (none if empty); the connection
/// and the subprotocol the server chose, or the handshake's error.
pub async fn connect(server: &LiveServer, protocols: &str) -> Result<(Ws, Option<String>), String> {
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

/// The next text message, as JSON; fails the test after 5 s.
pub async fn next_json(ws: &mut Ws) -> Value {
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
