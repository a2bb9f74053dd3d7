//! `amr mock …` (mock devices standalone, for any client: ours, SICK's, a ROS driver) and
//! `amr tools …`.

use std::path::Path;
use std::sync::Arc;

use amr_drivers::sopas::{Dialect, decode_capture};
use anyhow::Context as _;
use hil_mocks::tim551::{MockConfig, RectRoom, Tim551Mock, Variant};

/// The report line a script or test can read (stdout, flushed).
fn announce(line: &str) -> anyhow::Result<()> {
    use std::io::Write as _;
    let mut out = std::io::stdout().lock();
    writeln!(out, "{line}")?;
    out.flush()?;
    Ok(())
}

pub(crate) fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// Serve a mock TiM5xx on `listen` until Ctrl-C.
pub(crate) fn lidar(listen: &str, points: u32, dialect: Option<Dialect>) -> anyhow::Result<()> {
    let variant = match points {
        271 => Variant::Tim551,
        811 => Variant::Tim561,
        other => anyhow::bail!("--points must be 271 (TiM551) or 811 (TiM561/571), not {other}"),
    };
    runtime()?.block_on(async {
        let config = MockConfig { variant, dialect, ..MockConfig::default() };
        let mock = Tim551Mock::spawn(listen, config, Arc::new(RectRoom::default()))
            .await
            .with_context(|| format!("cannot listen on {listen}"))?;
        announce(&format!("mock TiM5xx ({points} points) listening on {}", mock.local_addr))?;
        tokio::signal::ctrl_c().await.context("waiting for Ctrl-C")?;
        tracing::info!(
            connections = mock.handle.connections(),
            scans = mock.handle.scans_sent(),
            "mock LiDAR stopped"
        );
        Ok(())
    })
}

/// Serve a mock LPMS-B2 behind a pseudo-terminal until Ctrl-C.
pub(crate) fn imu(rate_hz: u32) -> anyhow::Result<()> {
    runtime()?.block_on(async {
        let mock = hil_mocks::lpms::start_default_mock_imu(rate_hz).await.context("starting the mock IMU")?;
        announce(&format!("mock LPMS-B2 streaming at {rate_hz} Hz on {}", mock.tty_path().display()))?;
        tokio::signal::ctrl_c().await.context("waiting for Ctrl-C")?;
        Ok(())
    })
}

/// Decode a captured SOPAS telegram and print every field as JSON.
pub(crate) fn sopas_decode(file: &Path) -> anyhow::Result<()> {
    let bytes = std::fs::read(file).with_context(|| format!("cannot read {}", file.display()))?;
    let reply = decode_capture(&bytes)
        .with_context(|| format!("{}: not a SOPAS telegram this decoder accepts", file.display()))?;
    announce(&serde_json::to_string_pretty(&reply)?)
}

/// Serve mock TECO drives (CiA 402) behind a socketcand server until Ctrl-C.
pub(crate) fn drives(listen: &str, nodes: &[u8]) -> anyhow::Result<()> {
    anyhow::ensure!(!nodes.is_empty(), "--nodes needs at least one node id");
    for (i, n) in nodes.iter().enumerate() {
        anyhow::ensure!((1..=127).contains(n), "node id {n} is not a CANopen node id (1..=127)");
        anyhow::ensure!(!nodes[..i].contains(n), "node id {n} is listed twice");
    }
    runtime()?.block_on(async {
        let mock = hil_mocks::teco_drive::start_mock_drives(
            listen,
            nodes,
            hil_mocks::teco_drive::TecoDriveConfig::new,
        )
        .await
        .with_context(|| format!("cannot listen on {listen}"))?;
        announce(&format!("mock TECO drives {nodes:?} on socketcand {} (channel can0)", mock.address))?;
        tokio::signal::ctrl_c().await.context("waiting for Ctrl-C")?;
        Ok(())
    })
}
