//! The live view: a Foxglove WebSocket server (`foxglove.websocket.v1`,
//! <https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md>) carrying the recorder's
//! channels. On connect the server sends `serverInfo` and `advertise` (every channel so far; new
//! ones as they appear); the client sends `subscribe` / `unsubscribe`; each message goes to its
//! subscribers as a binary frame: opcode 0x01, the subscription id (u32 LE), the log time in ns
//! (u64 LE), the JSON body. A slow client skips messages (a bounded queue per client), it never
//! slows the recorder.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, PoisonError};

use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::broadcast;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::HeaderValue;

use crate::encode::{Out, schema_text};

/// The WebSocket subprotocol.
pub const SUBPROTOCOL: &str = "foxglove.websocket.v1";
/// Messages queued per client before it starts skipping.
const QUEUE: usize = 1024;

#[derive(Debug, Clone)]
struct Channel {
    id: u32,
    topic: String,
    schema_name: &'static str,
}

#[derive(Debug, Clone)]
enum HubEvent {
    Advertise(Channel),
    Message { channel: u32, log_time_ns: u64, data: Arc<[u8]> },
}

#[derive(Debug)]
struct HubInner {
    channels: Mutex<BTreeMap<String, Channel>>,
    tx: broadcast::Sender<HubEvent>,
}

/// Where the recorder publishes for the live view; cheap to clone.
#[derive(Debug, Clone)]
pub struct Hub(Arc<HubInner>);

impl Default for Hub {
    fn default() -> Self {
        Hub(Arc::new(HubInner { channels: Mutex::default(), tx: broadcast::channel(QUEUE).0 }))
    }
}

impl Hub {
    /// Publish one message: its channel is advertised the first time, the message goes to the
    /// clients subscribed to it.
    pub fn publish(&self, out: &Out) {
        let channel = {
            let mut channels = self.0.channels.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(c) = channels.get(&out.topic) {
                c.id
            } else {
                let c = Channel {
                    id: u32::try_from(channels.len()).unwrap_or(u32::MAX).saturating_add(1),
                    topic: out.topic.clone(),
                    schema_name: out.schema,
                };
                let id = c.id;
                channels.insert(out.topic.clone(), c.clone());
                let _ = self.0.tx.send(HubEvent::Advertise(c));
                id
            }
        };
        if self.0.tx.receiver_count() > 0 {
            let _ = self.0.tx.send(HubEvent::Message {
                channel,
                log_time_ns: out.log_time_ns,
                data: Arc::from(out.data.as_slice()),
            });
        }
    }

    fn snapshot(&self) -> Vec<Channel> {
        self.0.channels.lock().unwrap_or_else(PoisonError::into_inner).values().cloned().collect()
    }
}

/// A running live server; dropping it stops accepting (open connections end with their client).
#[derive(Debug)]
pub struct LiveServer {
    pub addr: SocketAddr,
    pub hub: Hub,
    accept: tokio::task::JoinHandle<()>,
}

impl Drop for LiveServer {
    fn drop(&mut self) {
        self.accept.abort();
    }
}

/// Listen on `addr` (e.g. `127.0.0.1:8765`; port 0 picks one) and serve `hub`'s channels.
pub async fn serve(addr: SocketAddr, hub: Hub, name: &str) -> std::io::Result<LiveServer> {
    let listener = TcpListener::bind(addr).await?;
    let addr = listener.local_addr()?;
    let (h, name) = (hub.clone(), name.to_owned());
    let accept = tokio::spawn(async move {
        loop {
            match listener.accept().await {
                Ok((stream, peer)) => {
                    let (h, name) = (h.clone(), name.clone());
                    tokio::spawn(async move {
                        if let Err(e) = connection(stream, h, &name).await {
                            tracing::debug!(%peer, error = %e, "live: connection ended");
                        }
                    });
                }
                Err(e) => tracing::warn!(error = %e, "live: accept failed"),
            }
        }
    });
    tracing::info!(%addr, "live: Foxglove WebSocket server listening");
    Ok(LiveServer { addr, hub, accept })
}

fn advertise(channels: &[Channel]) -> Message {
    let list: Vec<Value> = channels
        .iter()
        .map(|c| {
            json!({
                "id": c.id, "topic": c.topic, "encoding": "json", "schemaName": c.schema_name,
                "schemaEncoding": "jsonschema", "schema": schema_text(c.schema_name)
            })
        })
        .collect();
    Message::text(json!({ "op": "advertise", "channels": list }).to_string())
}

/// Accept the handshake only for our subprotocol, and answer with it.
#[allow(clippy::result_large_err, reason = "tungstenite's callback signature")]
fn negotiate(req: &Request, mut resp: Response) -> Result<Response, ErrorResponse> {
    let offered = req
        .headers()
        .get_all("Sec-WebSocket-Protocol")
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|p| p.trim() == SUBPROTOCOL);
    if offered {
        resp.headers_mut().insert("Sec-WebSocket-Protocol", HeaderValue::from_static(SUBPROTOCOL));
        Ok(resp)
    } else {
        let mut e = ErrorResponse::new(Some(format!("subprotocol {SUBPROTOCOL} required")));
        *e.status_mut() = tokio_tungstenite::tungstenite::http::StatusCode::BAD_REQUEST;
        Err(e)
    }
}

async fn connection(
    stream: TcpStream,
    hub: Hub,
    name: &str,
) -> Result<(), tokio_tungstenite::tungstenite::Error> {
    let mut ws = tokio_tungstenite::accept_hdr_async(stream, negotiate).await?;
    // Subscribe before the snapshot: a channel born in between is advertised twice, never missed.
    let mut rx = hub.0.tx.subscribe();
    ws.send(Message::text(
        json!({ "op": "serverInfo", "name": name, "capabilities": [], "supportedEncodings": ["json"] })
            .to_string(),
    ))
    .await?;
    ws.send(advertise(&hub.snapshot())).await?;
    // channel id → subscription id
    let mut subs: BTreeMap<u32, u32> = BTreeMap::new();
    loop {
        tokio::select! {
            incoming = ws.next() => match incoming {
                Some(Ok(Message::Text(t))) => client_op(t.as_str(), &mut subs),
                Some(Ok(Message::Close(_))) | None => return Ok(()),
                Some(Ok(_)) => {}
                Some(Err(e)) => return Err(e),
            },
            ev = rx.recv() => match ev {
                Ok(HubEvent::Advertise(c)) => ws.send(advertise(&[c])).await?,
                Ok(HubEvent::Message { channel, log_time_ns, data }) => {
                    if let Some(sub) = subs.get(&channel) {
                        let mut frame = Vec::with_capacity(13 + data.len());
                        frame.push(0x01);
                        frame.extend_from_slice(&sub.to_le_bytes());
                        frame.extend_from_slice(&log_time_ns.to_le_bytes());
                        frame.extend_from_slice(&data);
                        ws.send(Message::binary(frame)).await?;
                    }
                }
                Err(broadcast::error::RecvError::Lagged(n)) => tracing::debug!(skipped = n, "live: client lagging"),
                Err(broadcast::error::RecvError::Closed) => return Ok(()),
            },
        }
    }
}

/// `subscribe` {subscriptions: [{id, channelId}]} and `unsubscribe` {subscriptionIds: [..]};
/// anything else is ignored.
fn client_op(text: &str, subs: &mut BTreeMap<u32, u32>) {
    let Ok(v) = serde_json::from_str::<Value>(text) else { return };
    let as_u32 = |v: &Value| v.as_u64().and_then(|n| u32::try_from(n).ok());
    match v["op"].as_str() {
        Some("subscribe") => {
            for s in v["subscriptions"].as_array().into_iter().flatten() {
                if let (Some(id), Some(ch)) = (as_u32(&s["id"]), as_u32(&s["channelId"])) {
                    subs.insert(ch, id);
                }
            }
        }
        Some("unsubscribe") => {
            for id in v["subscriptionIds"].as_array().into_iter().flatten().filter_map(as_u32) {
                subs.retain(|_, s| *s != id);
            }
        }
        _ => {}
    }
}
