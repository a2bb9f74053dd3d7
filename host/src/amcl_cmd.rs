//! `amr amcl`: our AMCL as a ROS 2 node in nav2_amcl's place (wiring around
//! `amr_record::ros2::amcl_node`).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use amr_record::ros2::amcl_node::{AmclNodeConfig, run};
use anyhow::Context as _;

use crate::record_cmd::{Ros2NodeArgs, Ros2Transport};

/// `amr amcl`'s options.
#[derive(Debug, Clone, clap::Args)]
pub(crate) struct AmclArgs {
    /// The ROS 2 transport: `zenoh` (rmw_zenoh, Jazzy and later) or `dds` (DDS/RTPS: Humble's and
    /// Foxy's default).
    #[arg(long, value_enum, value_name = "TRANSPORT", num_args = 0..=1, default_value = "zenoh", default_missing_value = "zenoh")]
    pub ros2: Ros2Transport,
    /// nav2's params file: its `amcl: ros__parameters:` section, by nav2_amcl's names (frames,
    /// topics, `transform_tolerance`, `tf_broadcast`, `set_initial_pose` and `initial_pose`
    /// included); what nav2 has not (our slip tail, the integrity monitor) from the
    /// configuration's amcl.toml.
    #[arg(long, value_name = "NAV2_PARAMS.yaml")]
    pub params: PathBuf,
    #[command(flatten)]
    pub node: Ros2NodeArgs,
    /// The configuration directory whose amcl.toml supplies what nav2 has not (default:
    /// ./config if present, else the embedded one).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Seed of the filter's random draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Stop after this many seconds (and at Ctrl-C or SIGTERM in any case).
    #[arg(long, value_name = "SECONDS")]
    pub duration: Option<f64>,
}

pub(crate) fn amcl(args: AmclArgs) -> anyhow::Result<()> {
    let duration = match args.duration.map(Duration::try_from_secs_f64) {
        Some(Err(_)) => anyhow::bail!("--duration must be a positive number of seconds"),
        d => d.and_then(Result::ok),
    };
    let n = crate::localize::load_nav2(&args.params, args.config.clone())?;
    let config = AmclNodeConfig { frames: n.frames, params: n.params, seed: args.seed };
    crate::mock_cmd::runtime()?.block_on(async move {
        let node = Arc::new(args.node.open(args.ros2, "amcl").await?);
        let stop = async move {
            let signal = async {
                if let Err(e) = crate::fleet_cmd::stop_signal().await {
                    tracing::warn!(error = %e, "no signal handler: runs until killed");
                    std::future::pending::<()>().await;
                }
            };
            match duration {
                Some(d) => tokio::select! {
                    () = tokio::time::sleep(d) => {}
                    () = signal => {}
                },
                None => signal.await,
            }
        };
        tracing::info!(scan = %config.frames.scan_topic, map = %config.frames.map_topic, "amcl: waiting for the map, scans and /tf");
        let stats = run(Arc::clone(&node), config, stop).await.context("the amcl node")?;
        tracing::info!(
            scans = stats.scans,
            used = stats.used,
            poses = stats.poses,
            without_map = stats.without_map,
            without_odometry = stats.without_odometry,
            unusable = stats.unusable,
            "amcl stopped"
        );
        if let Ok(node) = Arc::try_unwrap(node)
            && let Err(e) = node.close().await
        {
            tracing::debug!(error = %e, "closing the ROS 2 node");
        }
        Ok(())
    })
}
