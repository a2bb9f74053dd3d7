//! `amr sim` and `amr drill`: wiring around amr-sim.

use std::path::PathBuf;
use std::time::Duration;

use amr_actors::config::load;
use amr_core::config::Configuration;
use amr_sim::{Sim, SimCan, SimOptions};
use anyhow::Context;
use hil_mocks::world::Noise;

use crate::mock_cmd::runtime;

/// `amr sim` options.
#[derive(Debug, Clone)]
pub(crate) struct SimArgs {
    pub scenario: String,
    pub seed: u64,
    pub configuration: Option<Configuration>,
    pub duration: Option<Duration>,
    pub can: SimCan,
    pub json: Option<PathBuf>,
    pub config: Option<PathBuf>,
    pub quiet: bool,
    pub virtual_time: bool,
    pub rec: crate::record_cmd::RecordArgs,
    pub surveyed_map: bool,
    pub max_error_cm: f64,
}

pub(crate) fn parse_can(s: &str) -> Result<SimCan, String> {
    match s {
        "socketcand" => Ok(SimCan::Socketcand),
        "in-process" => Ok(SimCan::InProcess),
        _ => Err(format!("`{s}`: expected socketcand or in-process")),
    }
}

/// Run the whole system against the mocks and print the report; an error when the run failed
/// (`SimReport::failures`).
pub(crate) fn sim(args: SimArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.max_error_cm.is_finite() && args.max_error_cm > 0.0,
        "--max-error-cm must be a positive number of centimetres"
    );
    let config = load(&crate::config_cmd::source_for(args.config.clone()))?;
    let chosen = config.scenario(&args.scenario)?;
    let options = SimOptions {
        scenario_name: chosen.stem.clone(),
        map: amr_actors::config::is_path(&args.scenario)
            .then(|| (chosen.map_name.clone(), chosen.map.clone())),
        scenario: chosen.scenario,
        seed: args.seed,
        noise: Noise::TYPICAL,
        can: if args.virtual_time { SimCan::VirtualTime } else { args.can },
        configuration: args.configuration,
        max_duration: args.duration,
        surveyed_map: args.surveyed_map,
    };
    // Virtual time: one thread, tokio's clock paused and advanced only when every task waits,
    // devices over in-memory pipes: as fast as the machine allows, and the same seed gives the
    // same run.
    let rt = if args.virtual_time {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
            .context("starting the virtual-time runtime")?
    } else {
        runtime()?
    };
    rt.block_on(async move {
        let sim = Sim::start(&config, options)
            .await
            .with_context(|| format!("starting the simulation of {}", args.scenario))?;
        // Attached before the robots' devices have booted: the recording holds every scan.
        let mut sources = amr_record::RecordSources::server(&sim.server.ports, &sim.setup);
        sources.metadata.insert("scenario".into(), args.scenario.clone());
        sources.robots = sim.robots.iter().map(|r| std::sync::Arc::clone(&r.ports)).collect();
        sources.formation = Some(std::sync::Arc::clone(&sim.server.formation));
        let recording = args.rec.start(sources).await?;
        if let Some(r) = &recording {
            r.ros2_inputs(sim.server.control()).await?;
        }
        let quiet = args.quiet;
        tokio::select! {
            () = sim.run(|s| {
                if !quiet {
                    #[allow(clippy::print_stderr, reason = "live status on the terminal")]
                    {
                        eprintln!("{}", s.status_line());
                    }
                }
            }) => {}
            r = tokio::signal::ctrl_c() => {
                r.context("waiting for Ctrl-C")?;
                tracing::info!("interrupted: stopping");
            }
        }
        let report = sim.report();
        if let Some(r) = recording {
            r.stop().await?;
        }
        sim.shutdown().await;
        #[allow(clippy::print_stdout, reason = "the command's report")]
        {
            print!("\n{}", report.to_text());
        }
        if let Some(path) = &args.json {
            std::fs::write(path, serde_json::to_string_pretty(&report)? + "\n")
                .with_context(|| format!("writing {}", path.display()))?;
        }
        // A run cut short by --duration has not finished its plan on purpose.
        let failures = report.failures(args.max_error_cm / 100.0, args.duration.is_none());
        anyhow::ensure!(failures.is_empty(), "the run failed: {}", failures.join("; "));
        Ok(())
    })
}

/// `amr drill`'s arguments.
#[cfg(feature = "drills")]
pub(crate) struct DrillArgs {
    pub name: String,
    pub seed: u64,
    pub soak_seconds: u64,
    pub json: Option<PathBuf>,
    pub config: Option<PathBuf>,
    pub clock: amr_sim::drills::DrillClock,
}

/// `amr drill NAME|all`: run drills, print the table (and JSON), fail if any failed.
#[cfg(feature = "drills")]
pub(crate) fn drill(args: &DrillArgs) -> anyhow::Result<()> {
    use amr_sim::drills::{DRILLS, DrillClock};
    let (name, seed, soak_seconds, clock) = (args.name.as_str(), args.seed, args.soak_seconds, args.clock);
    let config = load(&crate::config_cmd::source_for(args.config.clone()))?;
    let names: Vec<&str> = if name == "all" {
        DRILLS
            .iter()
            .filter(|d| clock == DrillClock::Real || d.real_time_only().is_none())
            .map(|d| d.name)
            .collect()
    } else if let Some(d) = DRILLS.iter().find(|d| d.name == name) {
        if let (DrillClock::Virtual, Some(why)) = (clock, d.real_time_only()) {
            anyhow::bail!("drill `{name}` runs in real time only ({why}): run it without --virtual-time");
        }
        vec![name]
    } else {
        let known: Vec<&str> = DRILLS.iter().map(|d| d.name).collect();
        anyhow::bail!("no drill `{name}` (have: all, {})", known.join(", "));
    };
    let least = amr_sim::drills::SOAK_MIN.as_secs();
    if names.contains(&"soak") && soak_seconds < least {
        anyhow::bail!(
            "--soak-seconds {soak_seconds} is too short: the soak injects a fault every 3-6 s and must see \
             at least 3 of 3 kinds, so it needs at least {least} s (default 600)"
        );
    }
    // Virtual time: one thread, its clock paused and advanced only when every task waits.
    let rt = match clock {
        DrillClock::Real => runtime()?,
        DrillClock::Virtual => tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
            .context("starting the virtual-time runtime")?,
    };
    let outcomes = rt.block_on(async {
        let mut out = Vec::new();
        for n in names {
            tracing::info!(drill = n, "running");
            if n == "soak" {
                out.push(
                    amr_sim::drills::soak(&config, seed, Duration::from_secs(soak_seconds), clock).await,
                );
            } else if let Some(o) = amr_sim::drills::run_on(n, &config, seed, clock).await {
                out.push(o);
            }
        }
        out
    });
    #[allow(clippy::print_stdout, reason = "the command's report")]
    {
        print!("{}", amr_sim::drills::table(&outcomes));
    }
    match &args.json {
        Some(path) if path == std::path::Path::new("-") => {
            #[allow(clippy::print_stdout, reason = "the command's report")]
            {
                println!("{}", serde_json::to_string_pretty(&outcomes)?);
            }
        }
        Some(path) => std::fs::write(path, serde_json::to_string_pretty(&outcomes)? + "\n")
            .with_context(|| format!("writing {}", path.display()))?,
        None => {}
    }
    let failed: Vec<&str> = outcomes.iter().filter(|o| !o.passed).map(|o| o.name.as_str()).collect();
    anyhow::ensure!(failed.is_empty(), "drills failed: {}", failed.join(", "));
    Ok(())
}

/// `amr tools can-check --iface vcan0`: the robot on a kernel CAN interface, with can-utils'
/// `cansend` as a third party (`amr_sim::kernel_can`); one PASS/FAIL line per check.
#[cfg(feature = "drills")]
pub(crate) fn can_check(
    iface: &str,
    cansend: &std::path::Path,
    seed: u64,
    config: Option<PathBuf>,
) -> anyhow::Result<()> {
    let config = load(&crate::config_cmd::source_for(config))?;
    let lines = runtime()?.block_on(amr_sim::kernel_can::run(&config, seed, iface, cansend));
    #[allow(clippy::print_stdout, reason = "the command's report")]
    for l in &lines {
        println!("{} {}: {}", if l.passed { "PASS" } else { "FAIL" }, l.name, l.detail);
    }
    let failed: Vec<&str> = lines.iter().filter(|l| !l.passed).map(|l| l.name.as_str()).collect();
    anyhow::ensure!(failed.is_empty(), "kernel CAN checks failed: {}", failed.join(", "));
    Ok(())
}
