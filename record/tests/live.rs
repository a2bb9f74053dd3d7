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
