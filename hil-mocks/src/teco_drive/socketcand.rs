//! A socketcand server in front of the in-process bus, so outside tools (python-can's `socketcand`
//! interface, a CiA 402 master) can join the simulated bus. Greeting behaviour as devices.md §2:
//! `< hi >` alone, then wait for `< open CH >` → `< ok >`, wait for `< rawmode >` → `< ok >`
//! (python-can reads each with a single `recv` and compares exactly); then frames both ways.

use std::net::SocketAddr;
use std::time::Duration;

use amr_drivers::canopen::transport::in_process::InProcessBus;
use amr_drivers::canopen::transport::socketcand::{Element, ElementDecoder, encode_frame};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::Instant;

/// How long a client may take for each handshake step.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// Serve `bus` to every client that connects to `listener`, on any channel name.
pub fn serve(listener: TcpListener, bus: InProcessBus) -> tokio::task::JoinHandle<()> {
    serve_with(listener, bus, SocketcandControl::default())
}

/// Faults of the socketcand server (devices.md §4: the link to the bus breaks).
#[derive(Debug, Clone)]
pub struct SocketcandControl {
    drop: tokio::sync::broadcast::Sender<()>,
    refuse_until: std::sync::Arc<std::sync::Mutex<Option<Instant>>>,
    accepted: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl Default for SocketcandControl {
    fn default() -> Self {
        SocketcandControl {
            drop: tokio::sync::broadcast::channel(4).0,
            refuse_until: std::sync::Arc::default(),
            accepted: std::sync::Arc::default(),
        }
    }
}

impl SocketcandControl {
    /// Close every client connection now, and accept-and-close new ones for `refuse_for`.
    pub fn drop_connections(&self, refuse_for: Duration) {
        *self.refuse_until.lock().unwrap_or_else(std::sync::PoisonError::into_inner) =
            Some(Instant::now() + refuse_for);
        let _ = self.drop.send(());
    }

    /// Connections accepted so far (refused ones included).
    pub fn accepted(&self) -> u64 {
        self.accepted.load(std::sync::atomic::Ordering::Relaxed)
    }

    fn refusing(&self) -> bool {
        self.refuse_until
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .is_some_and(|t| Instant::now() < t)
    }
}

/// [`serve`] with a fault control.
pub fn serve_with(
    listener: TcpListener,
    bus: InProcessBus,
    control: SocketcandControl,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let start = Instant::now();
        // Bounded by the listener: one pass per accepted connection.
        loop {
            match listener.accept().await {
                Ok((stream, peer)) => {
                    control.accepted.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    if control.refusing() {
                        drop(stream);
                        continue;
                    }
                    let bus = bus.clone();
                    let mut dropped = control.drop.subscribe();
                    tokio::spawn(async move {
                        let served = tokio::select! {
                            r = client(stream, bus, start) => r,
                            _ = dropped.recv() => Ok(()),
                        };
                        if let Err(e) = served {
                            tracing::debug!(%peer, %e, "socketcand client ended");
                        }
                    });
                }
                Err(e) => {
                    tracing::warn!(%e, "socketcand accept failed");
                    return;
                }
            }
        }
    })
}

async fn next_element(
    stream: &mut TcpStream,
    dec: &mut ElementDecoder,
    buf: &mut [u8],
) -> std::io::Result<Element> {
    // Bounded by the stream: each pass consumes an element or reads bytes.
    loop {
        while let Some(r) = dec.next_element() {
            match r {
                Ok(e) => return Ok(e),
                Err(err) => tracing::debug!(%err, "socketcand server: dropped"),
            }
        }
        let n = stream.read(buf).await?;
        if n == 0 {
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        dec.push(&buf[..n]);
    }
}

async fn expect(
    stream: &mut TcpStream,
    dec: &mut ElementDecoder,
    buf: &mut [u8],
    want: fn(&Element) -> bool,
) -> std::io::Result<()> {
    let e = tokio::time::timeout(HANDSHAKE_TIMEOUT, next_element(stream, dec, buf))
        .await
        .map_err(|_| std::io::Error::from(std::io::ErrorKind::TimedOut))??;
    if want(&e) {
        Ok(())
    } else {
        let _ = stream.write_all(b"< error unexpected command >").await;
        Err(std::io::Error::new(std::io::ErrorKind::InvalidData, format!("unexpected {e:?}")))
    }
}

async fn client(mut stream: TcpStream, bus: InProcessBus, start: Instant) -> std::io::Result<()> {
    let _ = stream.set_nodelay(true);
    let mut dec = ElementDecoder::new();
    let mut buf = vec![0u8; 4096];
    stream.write_all(b"< hi >").await?;
    expect(&mut stream, &mut dec, &mut buf, |e| matches!(e, Element::Open(_))).await?;
    stream.write_all(b"< ok >").await?;
    expect(&mut stream, &mut dec, &mut buf, |e| matches!(e, Element::Rawmode)).await?;
    stream.write_all(b"< ok >").await?;
    let mut port = bus.port();
    let (mut rd, mut wr) = stream.into_split();
    // Bounded by the connection and the bus: each pass moves one frame or chunk.
    loop {
        tokio::select! {
            n = rd.read(&mut buf) => {
                let n = n?;
                if n == 0 {
                    return Ok(());
                }
                dec.push(&buf[..n]);
                while let Some(r) = dec.next_element() {
                    match r {
                        Ok(Element::Send(frame)) => port.send_now(frame),
                        Ok(other) => tracing::debug!(?other, "socketcand server: ignored"),
                        Err(err) => tracing::debug!(%err, "socketcand server: dropped"),
                    }
                }
            }
            frame = amr_drivers::canopen::transport::CanTransport::recv(&mut port) => {
                let Ok(frame) = frame else { return Ok(()) };
                let t = Instant::now() - start;
                let line = encode_frame(&frame, t.as_secs(), t.subsec_micros());
                wr.write_all(line.as_bytes()).await?;
            }
        }
    }
}

/// Bind `addr` and serve `bus` with `control`; returns the bound address and the server task.
pub async fn bind_with(
    addr: &str,
    bus: InProcessBus,
    control: SocketcandControl,
) -> std::io::Result<(SocketAddr, tokio::task::JoinHandle<()>)> {
    let listener = TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    Ok((local, serve_with(listener, bus, control)))
}

/// Bind `addr` and serve `bus`; returns the bound address and the server task.
pub async fn bind(
    addr: &str,
    bus: InProcessBus,
) -> std::io::Result<(SocketAddr, tokio::task::JoinHandle<()>)> {
    let listener = TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    Ok((local, serve(listener, bus)))
}
