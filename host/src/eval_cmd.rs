//! `amr eval`: the arguments of the paper's experiments in simulation, and the Foxglove live view
//! the trials are served to; amr-lab runs them and writes the reports.

use std::path::{Path, PathBuf};

use amr_lab::eval::{Outputs, Plan};
use anyhow::Context as _;

/// AMCL's map in an evaluation (`--map`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum MapSource {
    /// A simulated survey of the site, as SLAM builds maps (the localiser never sees the world
    /// it is simulated in).
    Surveyed,
    /// The site's own map (the paper's site: the rendering of the polygons the world ray-casts).
    True,
}

impl From<MapSource> for amr_lab::eval::MapSource {
    fn from(m: MapSource) -> Self {
        match m {
            MapSource::Surveyed => amr_lab::eval::MapSource::Surveyed,
            MapSource::True => amr_lab::eval::MapSource::True,
        }
    }
}

/// A study over many configurations (`--study`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum Study {
    /// T1–T4 over robot spacing, team size and sites, with the occlusion each robot suffers.
    Occlusion,
}

/// Which parameter a sensitivity study varies (paper Tables 6–7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum Sweep {
    /// ε_d, the correspondence distance gate (Table 6).
    Eps,
    /// Δθ, the angular increment (Table 7).
    Step,
}

impl From<Sweep> for amr_lab::eval::Sweep {
    fn from(s: Sweep) -> Self {
        match s {
            Sweep::Eps => amr_lab::eval::Sweep::Eps,
            Sweep::Step => amr_lab::eval::Sweep::Step,
        }
    }
}

/// `amr eval` without `--sweep`, `--budget` or `--study`: T1–T4 on `plan`, written under `dir`,
/// each trial recorded to `record` and served live on `live` if given. Returns the report's
/// directory.
pub(crate) fn run(
    plan: &Plan<'_>,
    dir: &Path,
    record: Option<&Path>,
    live: Option<std::net::SocketAddr>,
) -> anyhow::Result<PathBuf> {
    // The live view's server runs on its own runtime while the trials run here.
    let live = match live {
        Some(addr) => {
            let rt = crate::mock_cmd::runtime()?;
            let hub = amr_record::Hub::default();
            let server = rt
                .block_on(amr_record::serve(addr, hub.clone(), "amr eval"))
                .with_context(|| format!("serving the Foxglove live view on {addr}"))?;
            tracing::info!(address = %server.addr, "Foxglove live view (simulated time, faster than real time)");
            Some((rt, server, hub))
        }
        None => None,
    };
    let hub = live.as_ref().map(|(_, _, h)| h.clone());
    amr_lab::eval::run(plan, Outputs { dir, record, live: hub })
}
