//! `amr`: the one binary of the project. Each subcommand is wiring around the library crates.

mod amcl_cmd;
mod carmen_cmd;
mod cli;
mod config_cmd;
mod eval_cmd;
mod fleet_cmd;
mod localize;
mod mock_cmd;
mod record_cmd;
mod sim_cmd;

use std::process::ExitCode;

use clap::Parser as _;

use cli::{BenchCommand, BenchOptions, Cli, Command, ConfigCommand, FleetCommand, MockCommand, ToolsCommand};
use tracing_subscriber::EnvFilter;

/// Logging for our crates at info, everything else at warn, unless RUST_LOG says otherwise.
const DEFAULT_LOG_FILTER: &str =
    "warn,amr=info,amr_core=info,amr_drivers=info,amr_actors=info,amr_sim=info,hil_mocks=info";

/// Caps the log target where Zenoh dumps its configuration (zenoh 1.10 `api/session.rs`).
const ZENOH_CONFIG_LOG: &str = "zenoh::api::session=info";

fn main() -> ExitCode {
    let cli = Cli::parse();
    init_logging();
    match run(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            #[allow(clippy::print_stderr, reason = "the CLI's own error report")]
            {
                eprintln!("error: {e:#}");
            }
            ExitCode::FAILURE
        }
    }
}

/// Logs to stderr, filtered by RUST_LOG (default [`DEFAULT_LOG_FILTER`]), and to a running
/// recorder.
fn init_logging() {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(DEFAULT_LOG_FILTER));
    // Zenoh prints its whole configuration, passwords included, at debug level when a session
    // opens: that target never goes below info, whatever RUST_LOG asks (credentials stay out of logs).
    let filter = match ZENOH_CONFIG_LOG.parse() {
        Ok(d) => filter.add_directive(d),
        Err(_) => filter,
    };
    // Colour only on a terminal: logs piped to a file or another program stay plain text.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    {
        use tracing_subscriber::prelude::*;
        tracing_subscriber::registry()
            .with(filter)
            .with(tracing_subscriber::fmt::layer().with_writer(std::io::stderr).with_ansi(ansi))
            .with(amr_record::LogLayer::new(record_cmd::log_tap().clone()))
            .init();
    }
}

fn run(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Config(ConfigCommand::Check { dir }) => config_cmd::check(dir),
        Command::Bench(b) => bench_command(b),
        Command::Mock(m) => mock_command(m),
        Command::Tools(t) => tools_command(t),
        Command::Sim { scenario, seed, config, world_only: true, manifest, .. } => fleet_cmd::world_only(
            config,
            &scenario,
            seed,
            &manifest.unwrap_or_else(fleet_cmd::default_manifest),
        ),
        Command::Sim {
            scenario,
            seed,
            configuration,
            duration,
            can,
            json,
            config,
            quiet,
            virtual_time,
            rec,
            map,
            max_error_cm,
            ..
        } => match duration.map(std::time::Duration::try_from_secs_f64) {
            Some(Err(_)) => Err(anyhow::anyhow!("--duration must be a positive number of seconds")),
            d => sim_cmd::sim(sim_cmd::SimArgs {
                scenario,
                seed,
                configuration,
                duration: d.and_then(Result::ok),
                can,
                json,
                config,
                quiet,
                virtual_time,
                rec,
                surveyed_map: map == eval_cmd::MapSource::Surveyed,
                max_error_cm,
            }),
        },
        Command::Robot { config, mock, state_file, net, rec } => {
            let manifest = mock.map(|m| m.unwrap_or_else(fleet_cmd::default_manifest));
            fleet_cmd::robot(&config, manifest.as_deref(), state_file, &net, &rec)
        }
        Command::Replay { file, out, configuration, config, scenario, seed } => {
            record_cmd::replay(&file, out.as_deref(), config, scenario, configuration, seed)
        }
        #[cfg(feature = "drills")]
        Command::Drill { name, .. } if name == "list" => {
            #[allow(clippy::print_stdout, reason = "the command's report")]
            for d in amr_sim::drills::DRILLS {
                let clock = if d.real_time_only().is_some() { "real time only" } else { "" };
                println!("{:16} {:14} {}", d.name, clock, d.about);
            }
            Ok(())
        }
        #[cfg(feature = "drills")]
        Command::Drill { name, seed, soak_seconds, json, config, virtual_time } => {
            let clock = if virtual_time {
                amr_sim::drills::DrillClock::Virtual
            } else {
                amr_sim::drills::DrillClock::Real
            };
            sim_cmd::drill(&sim_cmd::DrillArgs { name, seed, soak_seconds, json, config, clock })
        }
        Command::Fleet(FleetCommand::Certs(args)) => fleet_cmd::certs(&args),
        Command::Estop { robots, reset, user, config, timeout_ms, net } => {
            fleet_cmd::estop(&fleet_cmd::EstopArgs { robots, reset, user, config, timeout_ms, net })
        }
        Command::Server {
            config,
            scenario,
            seed,
            auto_arm,
            auto_arm_hardware,
            progress_file,
            fresh,
            net,
            rec,
        } => fleet_cmd::server(&fleet_cmd::ServerArgs {
            config,
            scenario,
            seed,
            auto_arm,
            auto_arm_hardware,
            progress_file,
            fresh,
            net,
            rec,
        }),
        Command::Eval(args) => eval(args),
        Command::Amcl(args) => amcl_cmd::amcl(args),
        Command::Localize(args) => localize(args),
    }
}

fn bench_command(command: BenchCommand) -> anyhow::Result<()> {
    match command {
        BenchCommand::Vamr(opts) => bench(
            opts,
            "the Virtual-AMR pipeline",
            |c, quick| amr_lab::bench::run(&c.vamr, quick),
            amr_lab::bench::markdown,
        ),
        BenchCommand::Localize { logs, only, seeds, nav2, params, config, json, kidnap, runs } => {
            (|| -> anyhow::Result<()> {
                let params = localize::load_params(params.as_deref(), config)?;
                let wants = |k: cli::RunKind| runs.contains(&k);
                anyhow::ensure!(
                    kidnap.is_some() || wants(cli::RunKind::Tracking) || wants(cli::RunKind::Global),
                    "nothing to run: the kidnapped runs need `--kidnap N`"
                );
                let runs = amr_lab::bench_localize::Runs {
                    tracking: wants(cli::RunKind::Tracking),
                    global: wants(cli::RunKind::Global),
                    kidnapped: kidnap.filter(|_| wants(cli::RunKind::Kidnapped)),
                };
                let report =
                    amr_lab::bench_localize::run(&params, &logs, &only, &seeds, nav2.as_deref(), runs)?;
                let text = if json {
                    serde_json::to_string_pretty(&report)? + "\n"
                } else {
                    amr_lab::bench_localize::markdown(&report)
                };
                #[allow(clippy::print_stdout, reason = "the command's report")]
                {
                    print!("{text}");
                }
                Ok(())
            })()
        }
        BenchCommand::Amcl { common, log, nav2, no_large_map } => {
            let extras = amr_lab::bench::AmclExtras { log, nav2, no_large_map };
            bench(
                common,
                "AMCL",
                |c, quick| amr_lab::bench::run_amcl(&c.amcl, &c.vamr, quick, &extras),
                amr_lab::bench::amcl_markdown,
            )
        }
    }
}

fn mock_command(command: MockCommand) -> anyhow::Result<()> {
    match command {
        MockCommand::Lidar { listen, points, dialect } => mock_cmd::lidar(&listen, points, dialect),
        MockCommand::Drives { socketcand, nodes } => mock_cmd::drives(&socketcand, &nodes),
        MockCommand::Imu { rate } => {
            if amr_drivers::lpms::B2_STREAM_RATES_HZ.contains(&rate) {
                mock_cmd::imu(rate)
            } else {
                Err(anyhow::anyhow!(
                    "--rate must be one of {:?}, not {rate}",
                    amr_drivers::lpms::B2_STREAM_RATES_HZ
                ))
            }
        }
    }
}

fn tools_command(command: ToolsCommand) -> anyhow::Result<()> {
    match command {
        ToolsCommand::SopasDecode { file } => mock_cmd::sopas_decode(&file),
        ToolsCommand::CarmenPrepare { log, out, name } => carmen_cmd::prepare_log(&log, &out, name),
        ToolsCommand::CarmenKidnap { log, every, seed, out } => {
            carmen_cmd::kidnap_log(&log, every, seed, &out)
        }
        #[cfg(feature = "drills")]
        ToolsCommand::CanCheck { iface, cansend, seed, config } => {
            sim_cmd::can_check(&iface, &cansend, seed, config)
        }
    }
}

/// `amr eval`: the paper's experiments, the study, the budget or a sweep; prints the report.
fn eval(args: cli::EvalArgs) -> anyhow::Result<()> {
    let cli::EvalArgs {
        scenario,
        map,
        trials,
        seed,
        out,
        config,
        robots,
        sweep,
        budget,
        study,
        study_scenarios,
        confirm_trials,
        record,
        foxglove,
    } = args;
    let config = amr_actors::config::load(&config_cmd::source_for(config))?;
    let plan =
        amr_lab::eval::Plan { config: &config, scenario: &scenario, map: map.into(), robots, trials, seed };
    let report = match sweep {
        None if study.is_some() => {
            let scenarios: Vec<String> = if study_scenarios.is_empty() {
                amr_lab::study::STUDY_SCENARIOS.iter().map(|s| (*s).to_owned()).collect()
            } else {
                study_scenarios
            };
            let study = amr_lab::study::Occlusion {
                config: &config,
                scenarios: &scenarios,
                map: map.into(),
                trials,
                confirm_trials,
                seed,
            };
            amr_lab::study::occlusion(&study, &out)?
        }
        None if budget => amr_lab::study::budget(&plan, &out)?,
        Some(which) => amr_lab::eval::sweep(&plan, which.into(), &out)?,
        None => eval_cmd::run(&plan, &out, record.as_deref(), foxglove)?.join("report.md"),
    };
    #[allow(clippy::print_stdout, reason = "the command's report")]
    {
        print!("{}", std::fs::read_to_string(&report)?);
        println!("\nwritten to {}", report.display());
    }
    Ok(())
}

/// `amr localize`: one pose per scan of a log or bag, as CSV.
fn localize(args: cli::LocalizeArgs) -> anyhow::Result<()> {
    let cli::LocalizeArgs { map, log, bag, ros2, initial, params, nav2_params, out, seed, kidnap } = args;
    let params = match nav2_params {
        Some(f) => localize::load_nav2_params(&f, None)?,
        None => localize::load_params(params.as_deref(), None)?,
    };
    let input = match (log, bag) {
        (_, Some(bag)) => localize::Input::Bag(bag, ros2.options()),
        (Some(log), None) => localize::Input::Carmen(log),
        (None, None) => anyhow::bail!("give --log or --bag"),
    };
    let s = localize::run(&localize::Options { map, input, initial, params, out, seed, kidnap })?;
    tracing::info!(
        scans = s.scans,
        poses = s.poses,
        skipped = s.skipped,
        without_odometry = s.scans_without_odometry,
        "localised the log"
    );
    Ok(())
}

/// Load the configuration, run a benchmark and print its report as Markdown or JSON.
fn bench<R: serde::Serialize>(
    opts: BenchOptions,
    what: &str,
    run: impl FnOnce(&amr_actors::config::Config, bool) -> anyhow::Result<R>,
    markdown: fn(&R) -> String,
) -> anyhow::Result<()> {
    let config = amr_actors::config::load(&config_cmd::source_for(opts.config))?;
    tracing::info!(quick = opts.quick, "benchmarking {what}");
    let report = run(&config, opts.quick)?;
    let text = if opts.json { serde_json::to_string_pretty(&report)? + "\n" } else { markdown(&report) };
    #[allow(clippy::print_stdout, reason = "the command's report")]
    {
        print!("{text}");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn cli_definition_is_consistent() {
        Cli::command().debug_assert();
    }

    #[test]
    fn default_filter_parses() {
        assert!(EnvFilter::try_new(DEFAULT_LOG_FILTER).is_ok());
        assert!(ZENOH_CONFIG_LOG.parse::<tracing_subscriber::filter::Directive>().is_ok());
    }
}
