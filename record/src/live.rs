//! The live view: a Foxglove WebSocket server (`foxglove.websocket.v1`,
//! <https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md>) carrying the recorder's
//! channels. On connect the server sends `serverInfo` and `advertise` (every channel so far; new
//! ones as they appear); the client sends `subscribe` / `unsubscribe`; each message goes to its
//! subscribers as a binary frame: opcode 0x01, the subscription id (u32 LE), the log time in ns
//! (u64 LE), the JSON body. A slow client skips messages (a bounded queue per client), it never
//! slows the recorder.
//!
//! Access ([`LiveOptions`]): the protocol has no authentication, so the server binds to loopback
//! unless a token is set; with a token every client must present it (`?token=…` in the URL, or an
//! `Authorization: Bearer …` header). At most [`MAX_CLIENTS`] clients at once (another is refused
//! with HTTP 503) and [`MAX_SUBSCRIPTIONS`] subscriptions per client (more are refused with a
//! `status` error).

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
/// Clients served at once by default.
pub const MAX_CLIENTS: usize = 8;
/// Subscriptions per client by default (the recorder has a few dozen channels at most).
pub const MAX_SUBSCRIPTIONS: usize = 64;

/// Who may connect, and how many.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LiveOptions {
    /// Required from every client when set; needed to bind anywhere but loopback.
    pub token: Option<String>,
    pub max_clients: usize,
    pub max_subscriptions: usize,
}

impl Default for LiveOptions {
    fn default() -> Self {
        LiveOptions { token: None, max_clients: MAX_CLIENTS, max_subscriptions: MAX_SUBSCRIPTIONS }
    }
}

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

/// Listen on `addr` (loopback, e.g. `127.0.0.1:8765`; port 0 picks one) and serve `hub`'s
/// channels with the default bounds and no token.
pub async fn serve(addr: SocketAddr, hub: Hub, name: &str) -> std::io::Result<LiveServer> {
    serve_with(addr, hub, name, LiveOptions::default()).await
}

/// [`serve`] with `options`: an address other than loopback needs a token.
pub async fn serve_with(
    addr: SocketAddr,
    hub: Hub,
    name: &str,
    options: LiveOptions,
) -> std::io::Result<LiveServer> {
    if !addr.ip().is_loopback() && options.token.as_deref().is_none_or(str::is_empty) {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!(
                "the live view has no authentication of its own: bind {addr} only with a token, or use loopback"
            ),
        ));
    }
    let listener = TcpListener::bind(addr).await?;
    let addr = listener.local_addr()?;
    let (h, name) = (hub.clone(), name.to_owned());
    let slots = Arc::new(tokio::sync::Semaphore::new(options.max_clients));
    let options = Arc::new(options);
    let accept = tokio::spawn(async move {
        loop {
            match listener.accept().await {
                Ok((stream, peer)) => {
                    let (h, name, options, slots) =
                        (h.clone(), name.clone(), Arc::clone(&options), Arc::clone(&slots));
                    tokio::spawn(async move {
                        if let Err(e) = connection(stream, h, &name, &options, slots).await {
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

/// The token a client presents: `token=` in the query, or an `Authorization: Bearer` header.
fn presented_token(req: &Request) -> Option<String> {
    let from_query = req
        .uri()
        .query()
        .into_iter()
        .flat_map(|q| q.split('&'))
        .find_map(|kv| kv.strip_prefix("token="))
        .map(str::to_owned);
    from_query.or_else(|| {
        req.headers()
            .get("Authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(|t| t.trim().to_owned())
    })
}

/// Equal, in a time that does not depend on where they differ.
fn same_secret(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn refuse(status: u16, why: &str) -> ErrorResponse {
    let mut e = ErrorResponse::new(Some(why.to_owned()));
    *e.status_mut() = tokio_tungstenite::tungstenite::http::StatusCode::from_u16(status)
        .unwrap_or(tokio_tungstenite::tungstenite::http::StatusCode::BAD_REQUEST);
    e
}

/// Accept the handshake only for our subprotocol, with the token if one is set, and then only if a
/// client slot is free (`take_slot`, asked last: a client that fails the checks never holds one);
/// answer with the subprotocol.
#[allow(clippy::result_large_err, reason = "tungstenite's callback signature")]
fn negotiate(
    req: &Request,
    mut resp: Response,
    token: Option<&str>,
    take_slot: impl FnOnce() -> bool,
) -> Result<Response, ErrorResponse> {
    if let Some(t) = token
        && !presented_token(req).is_some_and(|p| same_secret(p.as_bytes(), t.as_bytes()))
    {
        return Err(refuse(401, "a token is required"));
    }
    let offered = req
        .headers()
        .get_all("Sec-WebSocket-Protocol")
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|p| p.trim() == SUBPROTOCOL);
    if !offered {
        let mut e = ErrorResponse::new(Some(format!("subprotocol {SUBPROTOCOL} required")));
        *e.status_mut() = tokio_tungstenite::tungstenite::http::StatusCode::BAD_REQUEST;
        return Err(e);
    }
    if !take_slot() {
        return Err(refuse(503, "too many live-view clients"));
    }
    resp.headers_mut().insert("Sec-WebSocket-Protocol", HeaderValue::from_static(SUBPROTOCOL));
    Ok(resp)
}

/// How long a client has to complete the WebSocket handshake.
pub const HANDSHAKE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);

async fn connection(
    stream: TcpStream,
    hub: Hub,
    name: &str,
    options: &LiveOptions,
    slots: Arc<tokio::sync::Semaphore>,
) -> Result<(), tokio_tungstenite::tungstenite::Error> {
    let token = options.token.as_deref();
    let mut slot = None;
    let take = || {
        slot = slots.try_acquire_owned().ok();
        slot.is_some()
    };
    #[allow(clippy::result_large_err, reason = "tungstenite's callback signature")]
    let handshake =
        tokio_tungstenite::accept_hdr_async(stream, |req: &Request, resp| negotiate(req, resp, token, take));
    let mut ws = match tokio::time::timeout(HANDSHAKE_TIMEOUT, handshake).await {
        Ok(ws) => ws?,
        Err(_) => {
            return Err(tokio_tungstenite::tungstenite::Error::Io(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                "no WebSocket handshake within 5 s",
            )));
        }
    };
    // Held for as long as the client is connected.
    let _slot = slot;
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
                Some(Ok(Message::Text(t))) => {
                    if let Some(refused) = client_op(t.as_str(), &mut subs, options.max_subscriptions) {
                        let status = json!({ "op": "status", "level": 2, "message": refused });
                        ws.send(Message::text(status.to_string())).await?;
                    }
                }
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
/// anything else is ignored. A subscription beyond `max` is refused: the reason, for a `status`.
fn client_op(text: &str, subs: &mut BTreeMap<u32, u32>, max: usize) -> Option<String> {
    let Ok(v) = serde_json::from_str::<Value>(text) else { return None };
    let as_u32 = |v: &Value| v.as_u64().and_then(|n| u32::try_from(n).ok());
    match v["op"].as_str() {
        Some("subscribe") => {
            let mut refused = 0;
            for s in v["subscriptions"].as_array().into_iter().flatten() {
                if let (Some(id), Some(ch)) = (as_u32(&s["id"]), as_u32(&s["channelId"])) {
                    if subs.len() < max || subs.contains_key(&ch) {
                        subs.insert(ch, id);
                    } else {
                        refused += 1;
                    }
                }
            }
            (refused > 0).then(|| format!("{refused} subscription(s) refused: at most {max} per client"))
        }
        Some("unsubscribe") => {
            for id in v["subscriptionIds"].as_array().into_iter().flatten().filter_map(as_u32) {
                subs.retain(|_, s| *s != id);
            }
            None
        }
        _ => None,
    }
}
