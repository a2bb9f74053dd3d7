#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
//! The live view on loopback: a client speaking `foxglove.websocket.v1` gets the server info and
//! the channels, subscribes, and receives a message; a client without the subprotocol is refused.

use std::time::Duration;

use amr_record::encode::Out;
use amr_record::live::SUBPROTOCOL;
use amr_record::{Hub, serve};
use futures_util::{SinkExt, StreamExt};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::http::HeaderValue;

fn out(topic: &str, n: u64) -> Out {
    Out {
        topic: topic.into(),
        schema: amr_record::foxglove::POSE_IN_FRAME,
        log_time_ns: n,
        publish_time_ns: n,
        data: format!("{{\"frame_id\":\"map\",\"n\":{n}}}").into_bytes(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_subscribes_and_receives_messages() {
    let hub = Hub::default();
    hub.publish(&out("/early", 1));
    let server = serve("127.0.0.1:0".parse().unwrap(), hub.clone(), "amr test").await.unwrap();
    let body = async {
        let stream = tokio::net::TcpStream::connect(server.addr).await.unwrap();
        let mut req = format!("ws://{}/", server.addr).into_client_request().unwrap();
        req.headers_mut().insert("Sec-WebSocket-Protocol", HeaderValue::from_static(SUBPROTOCOL));
        let (mut ws, resp) = tokio_tungstenite::client_async(req, stream).await.unwrap();
        assert_eq!(resp.headers().get("Sec-WebSocket-Protocol").unwrap(), SUBPROTOCOL);
        let text = |m: Message| -> serde_json::Value {
            let Message::Text(t) = m else { panic!("expected text, got {m:?}") };
            serde_json::from_str(t.as_str()).unwrap()
        };
        let info = text(ws.next().await.unwrap().unwrap());
        assert_eq!(info["op"], "serverInfo");
        assert_eq!(info["name"], "amr test");
        let adv = text(ws.next().await.unwrap().unwrap());
        assert_eq!(adv["op"], "advertise");
        let ch = &adv["channels"][0];
        assert_eq!(ch["topic"], "/early");
        assert_eq!(ch["schemaName"], "foxglove.PoseInFrame");
        assert_eq!(ch["schemaEncoding"], "jsonschema");
        let schema: serde_json::Value = serde_json::from_str(ch["schema"].as_str().unwrap()).unwrap();
        assert_eq!(schema["title"], "foxglove.PoseInFrame");

        // A channel born after the connection is advertised too.
        hub.publish(&out("/late", 2));
        let adv = text(ws.next().await.unwrap().unwrap());
        assert_eq!(adv["channels"][0]["topic"], "/late");
        let late = adv["channels"][0]["id"].as_u64().unwrap();
        ws.send(Message::text(
            serde_json::json!({ "op": "subscribe", "subscriptions": [{ "id": 7, "channelId": late }] })
                .to_string(),
        ))
        .await
        .unwrap();
        // Publish until the subscription has taken effect and a message arrives.
        let publisher = {
            let hub = hub.clone();
            tokio::spawn(async move {
                for n in 10.. {
                    hub.publish(&out("/early", n));
                    hub.publish(&out("/late", n));
                    tokio::time::sleep(Duration::from_millis(5)).await;
                }
            })
        };
        let frame = loop {
            match ws.next().await.unwrap().unwrap() {
                Message::Binary(b) => break b,
                Message::Text(t) => panic!("unexpected {t}"),
                _ => {}
            }
        };
        publisher.abort();
        assert_eq!(frame[0], 0x01, "message data opcode");
        assert_eq!(u32::from_le_bytes(frame[1..5].try_into().unwrap()), 7, "our subscription id");
        let n = u64::from_le_bytes(frame[5..13].try_into().unwrap());
        let body: serde_json::Value = serde_json::from_slice(&frame[13..]).unwrap();
        assert_eq!(body["n"], n, "the body of the message with that log time");
        // Only the subscribed channel was sent: /early's bodies never arrive.
        ws.close(None).await.unwrap();
    };
    tokio::time::timeout(Duration::from_secs(20), body).await.expect("bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_without_the_subprotocol_is_refused() {
    let server = serve("127.0.0.1:0".parse().unwrap(), Hub::default(), "amr test").await.unwrap();
    let body = async {
        let stream = tokio::net::TcpStream::connect(server.addr).await.unwrap();
        let req = format!("ws://{}/", server.addr).into_client_request().unwrap();
        assert!(tokio_tungstenite::client_async(req, stream).await.is_err());
    };
    tokio::time::timeout(Duration::from_secs(20), body).await.expect("bounded");
}

/// `amr robot --record F --foxglove A`: a recorder on a robot's ports writes the file and feeds the
/// live view at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_robot_recorder_writes_the_file_and_serves_the_live_view() {
    use amr_actors::clock::FleetClock;
    use amr_actors::robot::ports::{ImuReading, RobotPorts, WheelTravel};
    use amr_core::scan::Scan;
    use amr_core::se2::Se2;
    use amr_msgs::{
        Command, Device, DisarmReason, Downlink, Health, HealthReport, OdomMsg, SafetyState, ScanMsg,
    };
    use amr_record::{RecordOptions, RecordSources, Recorder};
    use std::sync::Arc;

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("robot.mcap");
    let clock = FleetClock::start();
    let ports = RobotPorts::new("robot-a", clock);
    let hub = Hub::default();
    let server = serve("127.0.0.1:0".parse().unwrap(), hub.clone(), "amr robot").await.unwrap();
    let mut sources = RecordSources::new(clock);
    sources.robots = vec![Arc::clone(&ports)];
    sources.mounts = vec![("robot-a".into(), Se2::new(0.175, 0.0, 0.0))];
    let options = RecordOptions { file: Some(path.clone()), live: Some(hub), ..RecordOptions::default() };
    let recorder = Recorder::start(options, sources).await.unwrap();

    let feeder = {
        let ports = Arc::clone(&ports);
        tokio::spawn(async move {
            for k in 0u64.. {
                let t = clock.now_s();
                let scan = Arc::new(Scan::new(-2.35, 0.0174, 0.05, 10.0, vec![1.0, f64::NAN, 2.5]));
                ports.scans.send(ScanMsg {
                    robot: "robot-a".into(),
                    seq: k,
                    stamp_s: t,
                    received_s: t,
                    scan,
                    odom: None,
                    odom_frame: 1,
                });
                ports.imu.send(ImuReading { stamp_s: t, yaw_rate_radps: 0.01 });
                ports.wheels.send(WheelTravel { stamp_s: t, dt_s: 0.02, left_m: 0.004, right_m: 0.004 });
                let pose = Se2::new(0.01 * k as f64, 0.0, 0.0);
                ports.odom.send(OdomMsg {
                    seq: k,
                    frame: 1,
                    stamp_s: t,
                    pose,
                    twist: (0.2, 0.0),
                    gyro: true,
                });
                ports.downlink.send(Downlink::Command(Command {
                    seq: k,
                    stamp_s: t,
                    v_mps: 0.2,
                    w_radps: 0.0,
                }));
                if k == 3 {
                    let report =
                        HealthReport { device: Device::Lidar, health: Health::Lost, detail: "gone".into() };
                    ports.health.send(report);
                    ports.safety.send(SafetyState::Disarmed(DisarmReason::DeviceLost));
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        })
    };

    let client = async {
        let stream = tokio::net::TcpStream::connect(server.addr).await.unwrap();
        let mut req = format!("ws://{}/", server.addr).into_client_request().unwrap();
        req.headers_mut().insert("Sec-WebSocket-Protocol", HeaderValue::from_static(SUBPROTOCOL));
        let (mut ws, _) = tokio_tungstenite::client_async(req, stream).await.unwrap();
        loop {
            match ws.next().await.unwrap().unwrap() {
                Message::Text(t) => {
                    let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
                    let imu =
                        v["channels"].as_array().into_iter().flatten().find(|c| c["topic"] == "/robot-a/imu");
                    if let Some(c) = imu {
                        let sub = serde_json::json!({ "op": "subscribe", "subscriptions": [{ "id": 1, "channelId": c["id"] }] });
                        ws.send(Message::text(sub.to_string())).await.unwrap();
                    }
                }
                Message::Binary(b) => {
                    let body: serde_json::Value = serde_json::from_slice(&b[13..]).unwrap();
                    assert_eq!(body["yaw_rate_radps"], 0.01);
                    break;
                }
                _ => {}
            }
        }
    };
    tokio::time::timeout(Duration::from_secs(20), client).await.expect("bounded");
    // Let the feeder pass the health change, then finish.
    tokio::time::sleep(Duration::from_millis(100)).await;
    feeder.abort();
    let stats = recorder.stop().await.unwrap();
    for topic in
        ["/robot-a/scan", "/robot-a/imu", "/robot-a/wheels", "/robot-a/odom", "/tf", "/formation/commands"]
    {
        assert!(stats.per_topic.get(topic).is_some_and(|n| *n >= 3), "{topic}: {stats:?}");
    }
    assert_eq!(stats.per_topic.get("/health"), Some(&2), "{stats:?}");
    let rec = amr_record::read::read_file(&path).unwrap();
    assert!(rec.stopped.is_none());
    assert_eq!(rec.messages.len() as u64, stats.messages);
    let health: Vec<serde_json::Value> = rec
        .messages
        .iter()
        .filter(|m| m.topic == "/health")
        .map(|m| serde_json::from_slice(&m.data).unwrap())
        .collect();
    // Two ports: their relative order is the scheduler's.
    let find = |text: &str| health.iter().find(|h| h["message"] == text).cloned();
    assert_eq!(find("robot-a lidar: lost gone").unwrap()["level"], 4, "ERROR: {health:?}");
    assert_eq!(find("robot-a safety: disarmed:device_lost").unwrap()["level"], 2, "INFO: {health:?}");
}

/// A WebSocket handshake with the subprotocol to `path` on `addr`: the client, or the HTTP status
/// of the refusal.
async fn handshake(
    addr: std::net::SocketAddr,
    path: &str,
) -> Result<
    tokio_tungstenite::WebSocketStream<tokio::net::TcpStream>,
    tokio_tungstenite::tungstenite::http::StatusCode,
> {
    let stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let mut req = format!("ws://{addr}{path}").into_client_request().unwrap();
    req.headers_mut().insert("Sec-WebSocket-Protocol", HeaderValue::from_static(SUBPROTOCOL));
    match tokio_tungstenite::client_async(req, stream).await {
        Ok((ws, _)) => Ok(ws),
        Err(tokio_tungstenite::tungstenite::Error::Http(resp)) => Err(resp.status()),
        Err(e) => panic!("handshake: {e}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_live_view_needs_a_token_off_loopback_and_checks_it() {
    use amr_record::{LiveOptions, serve_with};
    // Off loopback without a token: refused before any socket is opened.
    let e = serve_with("0.0.0.0:0".parse().unwrap(), Hub::default(), "t", LiveOptions::default())
        .await
        .unwrap_err();
    assert_eq!(e.kind(), std::io::ErrorKind::InvalidInput);
    assert!(e.to_string().contains("token"), "{e}");
    // With a token (here on loopback), a client must present it.
    let options = LiveOptions { token: Some("s3cret-token".into()), ..LiveOptions::default() };
    let server = serve_with("127.0.0.1:0".parse().unwrap(), Hub::default(), "t", options).await.unwrap();
    let status =
        |r: Result<_, _>| r.err().map(|s: tokio_tungstenite::tungstenite::http::StatusCode| s.as_u16());
    assert_eq!(status(handshake(server.addr, "/").await), Some(401));
    assert_eq!(status(handshake(server.addr, "/?token=s3cret-tokem").await), Some(401));
    assert_eq!(status(handshake(server.addr, "/?token=s3cret").await), Some(401));
    assert!(handshake(server.addr, "/?token=s3cret-token").await.is_ok());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_live_view_bounds_its_clients_and_their_subscriptions() {
    use amr_record::{LiveOptions, serve_with};
    let hub = Hub::default();
    for k in 0..4 {
        hub.publish(&out(&format!("/t{k}"), k));
    }
    let options = LiveOptions { max_clients: 2, max_subscriptions: 3, ..LiveOptions::default() };
    let server = serve_with("127.0.0.1:0".parse().unwrap(), hub, "t", options).await.unwrap();
    let mut first = handshake(server.addr, "/").await.unwrap();
    let second = handshake(server.addr, "/").await.unwrap();
    assert_eq!(handshake(server.addr, "/").await.err().map(|s| s.as_u16()), Some(503), "a third client");
    // A slot frees when a client leaves (bounded wait: the server notices the close).
    drop(second);
    let mut again = None;
    for _ in 0..100 {
        if let Ok(ws) = handshake(server.addr, "/").await {
            again = Some(ws);
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(again.is_some(), "a client again once one left");
    // Four subscriptions where three are allowed: one refused, with a status error.
    let subs: Vec<serde_json::Value> =
        (1..=4).map(|k| serde_json::json!({ "id": k, "channelId": k })).collect();
    first
        .send(Message::text(serde_json::json!({ "op": "subscribe", "subscriptions": subs }).to_string()))
        .await
        .unwrap();
    let status = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            if let Some(Ok(Message::Text(t))) = first.next().await {
                let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
                if v["op"] == "status" {
                    return v;
                }
            }
        }
    })
    .await
    .expect("a status message");
    assert_eq!(status["level"], 2);
    assert_eq!(status["message"], "1 subscription(s) refused: at most 3 per client");
}

/// Sockets that never complete a handshake, and clients without the token, hold no client slot:
/// with every slot's worth of them open, a client with the token still gets in; an idle socket is
/// closed once the handshake time is up.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_sockets_and_clients_without_the_token_hold_no_slot() {
    use amr_record::{LiveOptions, serve_with};
    use tokio::io::AsyncReadExt as _;
    let options =
        LiveOptions { token: Some("s3cret-token".into()), max_clients: 2, ..LiveOptions::default() };
    let server = serve_with("127.0.0.1:0".parse().unwrap(), Hub::default(), "t", options).await.unwrap();
    let mut idle = Vec::new();
    for _ in 0..4 {
        idle.push(tokio::net::TcpStream::connect(server.addr).await.unwrap());
    }
    for _ in 0..4 {
        assert_eq!(handshake(server.addr, "/?token=wrong").await.err().map(|s| s.as_u16()), Some(401));
    }
    let first = handshake(server.addr, "/?token=s3cret-token").await;
    let second = handshake(server.addr, "/?token=s3cret-token").await;
    assert!(first.is_ok() && second.is_ok(), "the slots went to the clients with the token");
    assert_eq!(
        handshake(server.addr, "/?token=s3cret-token").await.err().map(|s| s.as_u16()),
        Some(503),
        "a third client with the token"
    );
    // The server closes an idle socket after the handshake time (read: end of stream or an error).
    let t0 = std::time::Instant::now();
    let mut buf = [0u8; 16];
    let read = tokio::time::timeout(Duration::from_secs(10), idle[0].read(&mut buf)).await;
    assert!(matches!(read, Ok(Ok(0) | Err(_))), "{read:?}");
    let waited = t0.elapsed();
    assert!(waited >= Duration::from_secs(4), "closed after {waited:?}");
}
