//! `amr mock lidar`, `amr mock imu` and `amr tools sopas-decode` as a user runs them. Every wait is
//! bounded; the mocks are killed at the end of each test.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// Kills the child when dropped, so a failed assertion leaves no mock running.
struct Running(Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Start `amr args…` and wait (at most 10 s) for its first stdout line.
fn start(args: &[&str]) -> (Running, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(args)
        .env_remove("RUST_LOG")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let line = rx.recv_timeout(Duration::from_secs(10)).expect("the mock announces itself");
    (Running(child), line.trim().to_owned())
}

/// Read from `r` on a thread until `done(bytes)` or 5 s.
fn read_until(mut r: impl Read + Send + 'static, done: fn(&[u8]) -> bool) -> Vec<u8> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut buf = Vec::new();
        let mut chunk = [0u8; 4096];
        while let Ok(n) = r.read(&mut chunk) {
            if n == 0 {
                break;
            }
            buf.extend_from_slice(&chunk[..n]);
            if done(&buf) {
                break;
            }
        }
        let _ = tx.send(buf);
    });
    rx.recv_timeout(Duration::from_secs(5)).unwrap_or_default()
}

#[test]
fn mock_lidar_answers_sopas_on_tcp() {
    let (_mock, line) = start(&["mock", "lidar", "--listen", "127.0.0.1:0", "--points", "811"]);
    assert!(line.starts_with("mock TiM5xx (811 points) listening on 127.0.0.1:"), "{line}");
    let addr = line.rsplit(' ').next().unwrap();
    let mut tcp = std::net::TcpStream::connect(addr).unwrap();
    tcp.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    tcp.write_all(b"\x02sRN DeviceIdent\x03").unwrap();
    let reply = read_until(tcp, |b| b.contains(&0x03));
    let text = String::from_utf8_lossy(&reply);
    assert!(text.starts_with("\u{2}sRA DeviceIdent "), "{text:?}");
    assert!(text.contains("TiM"), "the device names itself: {text:?}");
}

#[test]
fn mock_imu_streams_lpbus_frames_on_its_tty() {
    let (_mock, line) = start(&["mock", "imu", "--rate", "50"]);
    let path = line.rsplit(' ').next().unwrap().to_owned();
    assert!(line.starts_with("mock LPMS-B2 streaming at 50 Hz on "), "{line}");
    assert!(Path::new(&path).exists(), "{path}");
    let tty = std::fs::File::open(&path).unwrap();
    // Enough bytes for a few frames.
    let bytes = read_until(tty, |b| b.len() > 400);
    let mut decoder = amr_drivers::lpms::frame::FrameDecoder::new();
    decoder.push(&bytes);
    let mut data_frames = 0;
    while let Some(frame) = decoder.next_frame() {
        if frame.is_ok_and(|f| f.cmd == 9) {
            data_frames += 1;
        }
    }
    assert!(
        data_frames >= 2,
        "sensor-data frames (cmd 9) with valid LRCs, got {data_frames} in {} bytes",
        bytes.len()
    );
}

#[test]
fn sopas_decode_prints_every_field_as_json() {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../drivers/tests/data/sopas");
    let out = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["tools", "sopas-decode"])
        .arg(data.join("03_tim781s_colaB_sSN_LMDscandata.frame2.bin"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let oracle: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(data.join("expected_decoded.json")).unwrap()).unwrap();
    let expect = &oracle["03_tim781s_colaB_sSN_LMDscandata.frame2.bin"];
    let t = &json["ScanData"]["telegram"];
    for key in
        ["serial", "telegram_counter", "scan_counter", "time_since_startup_us", "time_of_transmission_us"]
    {
        assert_eq!(t[key], expect[key], "{key}");
    }
    // A file that is not a telegram: a clear error, exit 1.
    let bad = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["tools", "sopas-decode"])
        .arg(data.join("README.md"))
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("not a SOPAS telegram"));
}

#[test]
fn mock_drives_answer_sdo_over_socketcand() {
    let (_mock, line) = start(&["mock", "drives", "--socketcand", "127.0.0.1:0", "--nodes", "1,2"]);
    assert!(line.starts_with("mock TECO drives [1, 2] on socketcand 127.0.0.1:"), "{line}");
    let addr = line.split(' ').find(|w| w.starts_with("127.0.0.1:")).unwrap();
    let mut tcp = std::net::TcpStream::connect(addr).unwrap();
    tcp.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let mut expect = |send: Option<&[u8]>, want: &str| {
        if let Some(bytes) = send {
            tcp.write_all(bytes).unwrap();
        }
        let got = read_until(tcp.try_clone().unwrap(), |b| b.ends_with(b">"));
        let text = String::from_utf8_lossy(&got).into_owned();
        assert!(text.contains(want), "expected `{want}`, got {text:?}");
        text
    };
    expect(None, "< hi >");
    expect(Some(b"< open can0 >"), "< ok >");
    expect(Some(b"< rawmode >"), "< ok >");
    // SDO upload of 0x1000 (device type) from node 2; the reply comes on 0x582 with command 0x43.
    tcp.write_all(b"< send 602 8 40 0 10 0 0 0 0 0 >").unwrap();
    let mut reply = String::new();
    for _ in 0..20 {
        let got = read_until(tcp.try_clone().unwrap(), |b| b.ends_with(b">"));
        reply += &String::from_utf8_lossy(&got);
        if reply.contains("< frame 582 ") {
            break;
        }
    }
    let frame =
        reply.split("< frame 582 ").nth(1).unwrap_or_else(|| panic!("no SDO reply from node 2 in {reply:?}"));
    let data = frame.split_whitespace().nth(1).unwrap();
    assert!(
        data.to_ascii_lowercase().starts_with("43001000"),
        "expedited 4-byte upload of 0x1000:00: {data}"
    );
    // Bad node lists are refused before anything starts.
    let bad =
        Command::new(env!("CARGO_BIN_EXE_amr")).args(["mock", "drives", "--nodes", "1,1"]).output().unwrap();
    assert_eq!(bad.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("listed twice"));
}
