//! The server's tasks: accepting connections, a client's handshake and reading, and writing
//! its queue to its socket.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use foxglove::websocket::ws_protocol::server::Status;
use futures_util::stream::SplitSink;
use futures_util::{SinkExt as _, StreamExt as _};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, Semaphore};
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode};
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, WebSocketConfig};
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

use super::client::{Client, lock};
use super::shared::Shared;
use super::{HANDSHAKE_TIMEOUT, MAX_CLIENT_MESSAGE, MAX_HANDSHAKES, READ_BUFFER, WRITE_BUFFER};
use crate::{SUBPROTOCOL, SUBPROTOCOL_LEGACY};

/// Accepts clients until told to stop; then closes the port and lets the clients go.
pub(super) async fn serve(listener: TcpListener, shared: Arc<Shared>, stop: Arc<Notify>) {
    let mut tasks = tokio::task::JoinSet::new();
    let handshakes = Arc::new(Semaphore::new(MAX_HANDSHAKES));
    loop {
        tokio::select! {
            () = stop.notified() => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, addr)) => match Arc::clone(&handshakes).try_acquire_owned() {
                    Ok(permit) => {
                        tasks.spawn(client_task(stream, addr, Arc::clone(&shared), permit));
                    }
                    // Too many handshakes under way: closed at once, nothing allocated.
                    Err(_) => {
                        shared.refused.fetch_add(1, Ordering::Relaxed);
                        drop(stream);
                    }
                },
                // Out of file descriptors, say: try again shortly.
                Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
            },
            Some(_) = tasks.join_next(), if !tasks.is_empty() => {}
        }
    }
    drop(listener);
    shared.stopping.store(true, Ordering::Relaxed);
    shared.wake_all();
    let grace = shared.options.close_grace;
    let _ = tokio::time::timeout(grace, async { while tasks.join_next().await.is_some() {} }).await;
    // The clients still sending (stalled) are cut off: their tasks end with the runtime.
}

type Ws = WebSocketStream<TcpStream>;
type Sink = SplitSink<Ws, Message>;

async fn client_task(
    stream: TcpStream,
    addr: SocketAddr,
    shared: Arc<Shared>,
    handshaking: tokio::sync::OwnedSemaphorePermit,
) {
    let _ = stream.set_nodelay(true);
    let mut chosen = None;
    // The refusal is tungstenite's own type (the `Callback` trait's), however large.
    #[allow(clippy::result_large_err)]
    let negotiate = |request: &Request, mut response: Response| {
        let offered: Vec<&str> = request
            .headers()
            .get_all("sec-websocket-protocol")
            .iter()
            .flat_map(|h| h.to_str().unwrap_or_default().split(','))
            .map(str::trim)
            .collect();
        let Some(protocol) = [SUBPROTOCOL, SUBPROTOCOL_LEGACY]
            .into_iter()
            .find(|p| offered.contains(p))
        else {
            let mut refusal = ErrorResponse::new(Some(format!(
                "expected the WebSocket subprotocol {SUBPROTOCOL} (or {SUBPROTOCOL_LEGACY})"
            )));
            *refusal.status_mut() = StatusCode::BAD_REQUEST;
            return Err(refusal);
        };
        response
            .headers_mut()
            .insert("sec-websocket-protocol", HeaderValue::from_static(protocol));
        chosen = Some(protocol);
        Ok(response)
    };
    // A client sends subscriptions, a few KiB at most: nothing near tungstenite's default
    // limits (64 MiB) is needed, nor its 128 KiB buffers for every client.
    let config = WebSocketConfig::default()
        .max_message_size(Some(MAX_CLIENT_MESSAGE))
        .max_frame_size(Some(MAX_CLIENT_MESSAGE))
        .read_buffer_size(READ_BUFFER)
        .write_buffer_size(WRITE_BUFFER);
    let handshake =
        tokio_tungstenite::accept_hdr_async_with_config(stream, negotiate, Some(config));
    let Ok(Ok(mut ws)) = tokio::time::timeout(HANDSHAKE_TIMEOUT, handshake).await else {
        return;
    };
    drop(handshaking);
    let Some(subprotocol) = chosen else {
        return;
    };
    if shared.stopping.load(Ordering::Relaxed) {
        return;
    }
    let Some(client) = shared.register(addr, subprotocol) else {
        // Over the cap: told why, then closed, within the grace of a stop.
        let refusal = Message::text(shared.refusal());
        let _ = tokio::time::timeout(shared.options.close_grace, async {
            ws.send(refusal).await?;
            ws.close(Some(close_frame(CloseCode::Again))).await
        })
        .await;
        return;
    };
    let (mut sink, mut source) = ws.split();
    let read = async {
        while let Some(message) = source.next().await {
            match message {
                Ok(Message::Text(text)) => {
                    if let Some(request) = shared.on_text(&client, text.as_str()) {
                        // In order: the client's next message waits for this answer.
                        shared.answer(&client, request).await;
                    }
                }
                Ok(Message::Binary(_)) => shared.count_cut(client.status(&Status::warning(
                    "not supported by this server (it serves a log, read-only): binary messages",
                ))),
                Ok(Message::Close(_)) => return false,
                Ok(_) => {}
                Err(WsError::Capacity(e)) => shared.cut_off(
                    &client,
                    format!(
                        "{e}: a client's message is at most {MAX_CLIENT_MESSAGE} bytes; \
                         disconnected"
                    ),
                ),
                Err(_) => return false,
            }
            if client.is_closed() {
                return true;
            }
        }
        false
    };
    let write = write(&client, &mut sink, &shared);
    tokio::pin!(write);
    tokio::select! {
        cut = read => {
            if cut {
                // Cut off: no longer read; its status and the close frame, if it takes them.
                let _ = tokio::time::timeout(shared.options.close_grace, &mut write).await;
            }
        }
        () = &mut write => {}
    }
    shared.unregister(&client);
}

/// The close frame of a client the server lets go for breaking a cap (`Policy`) or refuses
/// for now (`Again`): the `status` before it says why.
fn close_frame(code: CloseCode) -> CloseFrame {
    CloseFrame {
        code,
        reason: "see the status message before this close".into(),
    }
}

/// Sends what is queued for `client`, control messages first, until the client is closed or
/// the server stops (then with a close frame).
async fn write(client: &Client, sink: &mut Sink, shared: &Shared) {
    loop {
        let (control, data, closed) = client.take_batch();
        if control.is_empty() && data.is_empty() {
            if closed || shared.stopping.load(Ordering::Relaxed) {
                let cut = lock(&client.queue).cut_off.is_some();
                let frame = cut.then(|| close_frame(CloseCode::Policy));
                let _ = sink.send(Message::Close(frame)).await;
                return;
            }
            client.wake.notified().await;
            continue;
        }
        for m in control {
            if sink.feed(m).await.is_err() {
                return;
            }
        }
        let n = data.len() as u64;
        for m in data {
            if sink.feed(m).await.is_err() {
                return;
            }
        }
        if sink.flush().await.is_err() {
            return;
        }
        client.sent.fetch_add(n, Ordering::Relaxed);
    }
}
