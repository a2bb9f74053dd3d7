//! The fleet as separate processes on one machine: `amr sim --world-only` serves the world and the
//! mock devices, `amr server` runs the fusion server, two `amr robot --mock` processes run the
//! robots, all linked over Zenoh on loopback with mutual TLS (the fleet's certificates made by
//! `amr fleet certs`). The test watches through its own Zenoh session (an observer, whose
//! certificate the server's access control lets only read) and checks: the formation runs; killing
//! the server stops the robots by their own command watchdogs, and a new server re-arms them and
//! resumes the plan; killing a robot process is seen within the liveliness lease and stops the
//! formation (the other robot is disarmed); the restarted robot rejoins; a frozen robot is seen
//! gone when its lease runs out and rejoins when it resumes; after the operator's re-arm the short
//! scenario completes. Every wait is bounded; the processes are killed when the test ends.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use amr_actors::config::ConfigFile;
use amr_actors::config::{ConfigSource, read_files};
use amr_msgs::{SafetyState, ServerStatus, Uplink};
use amr_net::NetSettings;
use amr_net::wire::{Body, Envelope};

/// Children killed when dropped (a failed assertion leaves no process behind).
struct Procs(Vec<(String, Child)>);

impl Procs {
    fn kill(&mut self, name: &str) {
        if let Some(i) = self.0.iter().position(|(n, _)| n == name) {
            let (_, mut c) = self.0.remove(i);
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    fn child(&mut self, name: &str) -> &mut Child {
        &mut self.0.iter_mut().find(|(n, _)| n == name).unwrap().1
    }
}

impl Drop for Procs {
    fn drop(&mut self) {
        for (_, c) in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// On a failed assertion, the end of every process's log goes to the test's output (the temporary
/// directory that holds them is removed with the test): what the server and the robots said is
/// what tells why a wait ran out.
struct LogsOnFailure(PathBuf);

impl Drop for LogsOnFailure {
    #[allow(clippy::print_stderr, reason = "the failed test's output")]
    fn drop(&mut self) {
        if !std::thread::panicking() {
            return;
        }
        let Ok(dir) = std::fs::read_dir(&self.0) else { return };
        let mut logs: Vec<PathBuf> =
            dir.flatten().map(|e| e.path()).filter(|p| p.extension().is_some_and(|x| x == "log")).collect();
        logs.sort();
        for log in logs {
            let text = std::fs::read_to_string(&log).unwrap_or_default();
            let lines: Vec<&str> = text.lines().collect();
            eprintln!("---- {} (last {} of {} lines)", log.display(), lines.len().min(60), lines.len());
            for line in &lines[lines.len().saturating_sub(60)..] {
                eprintln!("{line}");
            }
        }
    }
}

fn spawn(args: &[String], log: &Path, stdin: bool) -> Child {
    let file = std::fs::File::create(log).unwrap();
    Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(args)
        .env("RUST_LOG", "warn,amr_net=info,amr=info")
        .stdin(if stdin { Stdio::piped() } else { Stdio::null() })
        .stdout(Stdio::null())
        .stderr(file)
        .spawn()
        .unwrap()
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The shipped configuration with a short scenario and a 1 s lease, a credentials file (for
/// `--insecure`) and, made by `amr fleet certs`, the fleet's certificates in `dir/certs`.
fn write_config(dir: &Path) -> PathBuf {
    let mut files = read_files(&ConfigSource::Dir(hil_tests::config_dir())).unwrap();
    files.retain(|f| !f.path.starts_with("scenarios/"));
    let scenario = "map = \"paper-site\"\nspacing_m = 0.9\nlaps = 1\nsegments = [{ straight_m = 1.2 }]\n\
                    [start]\nx_m = -2.0\ny_m = 0.0\nyaw_deg = 0.0\n\
                    [limits]\nmax_speed_mps = 0.22\nmax_accel_mps2 = 0.05\nmax_yaw_rate_radps = 0.2\n";
    files.push(ConfigFile { path: "scenarios/short.toml".into(), bytes: scenario.as_bytes().to_vec() });
    let creds = dir.join("credentials");
    std::fs::write(&creds, "server:srv-pw\nrobot-a:a-pw\nrobot-b:b-pw\nobserver:obs-pw\noperator:op-pw\n")
        .unwrap();
    // The robots' command watchdog at 1 s rather than the shipped 200 ms: the four processes here
    // are debug builds sharing two cores with the other tests, and a server starved for 200 ms
    // stopped a robot by its watchdog before the plan began (what this test checks is that the
    // watchdog stops the robots when the server is gone, not how soon; the safety layer's own
    // tests check the timing).
    for f in &mut files {
        let (from, to) = match f.path.as_str() {
            "network.toml" => ("lease_ms = 2000", "lease_ms = 1000"),
            "robot-a.toml" | "robot-b.toml" => ("command_timeout_ms = 200", "command_timeout_ms = 1000"),
            _ => continue,
        };
        let text = String::from_utf8(f.bytes.clone()).unwrap();
        assert!(text.contains(from), "{}: no `{from}`", f.path);
        f.bytes = text.replace(from, to).into_bytes();
    }
    let config = dir.join("config");
    hil_tests::write_dir(&files, &config).unwrap();
    let args = ["fleet", "certs", "--out", "certs", "--config", "config", "--server-hosts", "127.0.0.1"];
    let out = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(args)
        .args(["--operators", "operator,observer"])
        .current_dir(dir)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "amr {args:?}: {said} {}", String::from_utf8_lossy(&out.stderr));
    assert!(said.contains("a new fleet CA signed server, robot-a, robot-b, operator, observer"), "{said}");
    creds
}

#[derive(Debug, Default)]
struct Seen {
    status: Option<ServerStatus>,
    safety_a: Vec<(Instant, SafetyState)>,
}

fn wait_for(seen: &Mutex<Seen>, what: &str, limit: Duration, f: impl Fn(&Seen) -> bool) -> Duration {
    let t0 = Instant::now();
    while t0.elapsed() < limit {
        if f(&seen.lock().unwrap()) {
            return t0.elapsed();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    panic!("{what}: not within {limit:?}; last status {:?}", seen.lock().unwrap().status);
}

#[test]
fn robot_and_server_processes_survive_losing_the_server_and_a_robot_and_finish() {
    let tmp = tempfile::tempdir().unwrap();
    let _logs = LogsOnFailure(tmp.path().to_owned());
    write_config(tmp.path());
    let config = tmp.path().join("config");
    let certs = tmp.path().join("certs");
    let manifest = tmp.path().join("world.json");
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let log = |n: &str| tmp.path().join(format!("{n}.log"));
    let (certs_s, manifest_s) = (certs.to_str().unwrap(), manifest.to_str().unwrap());
    let robot_args = |id: &str| {
        vec![
            "robot".to_owned(),
            "--config".into(),
            config.join(format!("{id}.toml")).display().to_string(),
            "--mock".into(),
            manifest_s.into(),
            "--certs".into(),
            certs_s.into(),
            "--endpoint".into(),
            endpoint.clone(),
            "--state-file".into(),
            tmp.path().join(format!("{id}.safety")).display().to_string(),
        ]
    };
    let run = |v: Vec<String>, name: &str, stdin: bool| spawn(&v, &log(name), stdin);

    let mut procs = Procs(Vec::new());
    let world = vec![
        "sim".to_owned(),
        "--world-only".into(),
        "--config".into(),
        config.display().to_string(),
        "--scenario".into(),
        "short".into(),
        "--manifest".into(),
        manifest_s.into(),
    ];
    procs.0.push(("world".into(), run(world, "world", false)));
    let t0 = Instant::now();
    while !manifest.exists() {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no world manifest: {}",
            std::fs::read_to_string(log("world")).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let server = vec![
        "server".to_owned(),
        "--config".into(),
        config.join("server.toml").display().to_string(),
        "--scenario".into(),
        "short".into(),
        "--auto-arm".into(),
        "--progress-file".into(),
        tmp.path().join("server.progress").display().to_string(),
        "--certs".into(),
        certs_s.into(),
        "--endpoint".into(),
        endpoint.clone(),
    ];
    procs.0.push(("server".into(), run(server.clone(), "server", true)));
    procs.0.push(("robot-a".into(), run(robot_args("robot-a"), "robot-a", false)));
    procs.0.push(("robot-b".into(), run(robot_args("robot-b"), "robot-b", false)));

    // The test's own view: an observer session (read-only by the server's access control).
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let seen = Arc::new(Mutex::new(Seen::default()));
    let _observer = rt.block_on(async {
        let loaded = amr_actors::config::load(&ConfigSource::Dir(config.clone())).unwrap();
        let network = amr_net::network::NetworkConfig::from_set(&loaded).unwrap();
        let mut s = NetSettings::tls(network.as_ref(), Some(&certs)).unwrap();
        s.connect = Some(vec![endpoint.clone()]);
        // The server may not be listening yet: bounded retries.
        let mut session = None;
        for _ in 0..200 {
            match zenoh::open(s.client_config("observer").unwrap()).await {
                Ok(z) => {
                    session = Some(z);
                    break;
                }
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        }
        let session = session.expect("the server admits the observer within 20 s");
        let sink = Arc::clone(&seen);
        let status = session
            .declare_subscriber("fleet/server/status")
            .callback(move |sample| {
                if let Ok(st) = amr_net::decode_status(&sample.payload().to_bytes()) {
                    sink.lock().unwrap().status = Some(st);
                }
            })
            .await
            .unwrap();
        let sink = Arc::clone(&seen);
        let health = session
            .declare_subscriber("fleet/robot-a/health")
            .callback(move |sample| {
                if let Ok(Envelope { body: Body::Uplink(Uplink::Safety { state, .. }), .. }) =
                    Envelope::decode(&sample.payload().to_bytes())
                {
                    sink.lock().unwrap().safety_a.push((Instant::now(), state));
                }
            })
            .await
            .unwrap();
        (session, status, health)
    });
    let phase = |s: &Seen, p: &str| s.status.as_ref().is_some_and(|st| st.phase.starts_with(p));
    let diag = |procs: &mut Procs| {
        for n in ["world", "server", "robot-a", "robot-b"] {
            if let Some(Ok(Some(st))) = procs.0.iter_mut().find(|(m, _)| m == n).map(|(_, c)| c.try_wait()) {
                eprintln!("{n} exited: {st}");
            }
        }
    };

    wait_for(&seen, "formation running", Duration::from_secs(90), |s| phase(s, "Running"));
    wait_for(&seen, "the plan advancing", Duration::from_secs(30), |s| {
        s.status.as_ref().is_some_and(|st| st.plan_s > 2.0)
    });
    diag(&mut procs);

    // Kill the server: each robot's own command watchdog stops it (its log says so).
    procs.kill("server");
    let t0 = Instant::now();
    let watchdog = loop {
        let text = std::fs::read_to_string(log("robot-a")).unwrap_or_default();
        if text.contains("state=Disarmed(Watchdog)") {
            break t0.elapsed();
        }
        assert!(t0.elapsed() < Duration::from_secs(5), "robot-a did not stop by its watchdog:\n{text}");
        std::thread::sleep(Duration::from_millis(20));
    };
    // A new server: the robots' sessions reconnect, it re-arms them and resumes the plan where V is.
    let before = seen.lock().unwrap().status.as_ref().map_or(0.0, |st| st.plan_s);
    seen.lock().unwrap().status = None;
    procs.0.push(("server".into(), run(server, "server-2", true)));
    let restarted = wait_for(&seen, "the new server running", Duration::from_secs(60), |s| {
        phase(s, "Running") && s.status.as_ref().is_some_and(|st| st.alive.len() == 2)
    });
    wait_for(&seen, "the plan resumed", Duration::from_secs(30), |s| {
        s.status.as_ref().is_some_and(|st| st.plan_s > before + 1.0)
    });

    // Kill robot-b's process.
    procs.kill("robot-b");
    let killed = Instant::now();
    let seen_gone = wait_for(&seen, "robot-b seen gone", Duration::from_secs(10), |s| {
        s.status.as_ref().is_some_and(|st| !st.alive.iter().any(|r| r == "robot-b"))
    });
    assert!(seen_gone < Duration::from_secs(2), "the server saw robot-b gone after {seen_gone:?}");
    let stopped = wait_for(&seen, "formation stopped", Duration::from_secs(10), |s| {
        phase(s, "Stopped") || phase(s, "Holding")
    });
    let disarmed = wait_for(&seen, "robot-a disarmed", Duration::from_secs(10), |s| {
        s.safety_a.iter().any(|(t, st)| *t > killed && *st != SafetyState::Armed)
    });

    // Restart it: it rejoins, and after the operator's re-arm the scenario completes.
    procs.0.push(("robot-b".into(), run(robot_args("robot-b"), "robot-b-2", false)));
    let rejoined = wait_for(&seen, "robot-b rejoined", Duration::from_secs(30), |s| {
        s.status.as_ref().is_some_and(|st| st.alive.iter().any(|r| r == "robot-b"))
    });
    // A robot that goes silent without closing its connection (a frozen process, a dead radio):
    // only the lease (1 s here) tells. When it resumes, its session reconnects and it rejoins.
    let pid = procs.child("robot-a").id().to_string();
    let signal = |sig: &str| assert!(Command::new("kill").args([sig, &pid]).status().unwrap().success());
    signal("-STOP");
    let silent = wait_for(&seen, "frozen robot-a seen gone", Duration::from_secs(10), |s| {
        s.status.as_ref().is_some_and(|st| !st.alive.iter().any(|r| r == "robot-a"))
    });
    signal("-CONT");
    assert!(silent < Duration::from_millis(2000), "a silent robot was seen gone after {silent:?}");
    let resumed = wait_for(&seen, "robot-a back", Duration::from_secs(30), |s| {
        s.status.as_ref().is_some_and(|st| st.alive.len() == 2)
    });
    let stdin = procs.child("server").stdin.as_mut().unwrap();
    stdin.write_all(b"rearm\n").unwrap();
    stdin.flush().unwrap();
    wait_for(&seen, "formation running again", Duration::from_secs(60), |s| phase(s, "Running"));
    wait_for(&seen, "scenario finished", Duration::from_secs(90), |s| phase(s, "Finished"));

    // The e-stops of the deployed system: `estop` on the server's stdin reaches every robot over
    // the network, SIGUSR1 is the robot's local one; each latches until reset.
    let latched = |since: Instant, want: SafetyState| {
        move |s: &Seen| s.safety_a.iter().any(|(t, st)| *t >= since && *st == want)
    };
    let reset_state = SafetyState::Disarmed(amr_msgs::DisarmReason::EStopReset);
    let at = Instant::now();
    let stdin = procs.child("server").stdin.as_mut().unwrap();
    stdin.write_all(b"estop\n").unwrap();
    stdin.flush().unwrap();
    let net_estop = wait_for(
        &seen,
        "robot-a e-stopped from the server",
        Duration::from_secs(5),
        latched(at, SafetyState::EStop),
    );
    let at = Instant::now();
    stdin.write_all(b"reset-estop\n").unwrap();
    stdin.flush().unwrap();
    wait_for(
        &seen,
        "robot-a's e-stop reset from the server",
        Duration::from_secs(5),
        latched(at, reset_state),
    );
    let signal = |sig: &str, pid: u32| {
        let ok = std::process::Command::new("kill").args([sig, &pid.to_string()]).status().unwrap().success();
        assert!(ok, "kill {sig} {pid}");
    };
    let robot_a = procs.child("robot-a").id();
    let at = Instant::now();
    signal("-USR1", robot_a);
    let local_estop = wait_for(
        &seen,
        "robot-a e-stopped by SIGUSR1",
        Duration::from_secs(5),
        latched(at, SafetyState::EStop),
    );
    let at = Instant::now();
    signal("-USR2", robot_a);
    wait_for(&seen, "robot-a's e-stop reset by SIGUSR2", Duration::from_secs(5), latched(at, reset_state));
    // An operator's e-stop over the network (`fleet/robot-a/estop/operator`), confirmed by the robot.
    let operator = |reset: bool| {
        let mut args = vec![
            "estop".to_owned(),
            "robot-a".into(),
            "--config".into(),
            config.display().to_string(),
            "--certs".into(),
            certs_s.into(),
            "--endpoint".into(),
            endpoint.clone(),
            "--timeout-ms".into(),
            "5000".into(),
        ];
        if reset {
            args.push("--reset".into());
        }
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_amr")).args(&args).output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(out.status.success(), "amr estop {args:?}: {text} {}", String::from_utf8_lossy(&out.stderr));
        text
    };
    let at = Instant::now();
    let said = operator(false);
    assert!(said.contains("robot-a: e-stop confirmed, now estop"), "{said}");
    let operator_estop = wait_for(
        &seen,
        "robot-a e-stopped by the operator",
        Duration::from_secs(5),
        latched(at, SafetyState::EStop),
    );
    // A restart is not a reset: `kill -9` robot-a while it is e-stopped, start it again and let the
    // server re-arm the formation: it comes back in EStop (from its state file) and refuses the arm.
    procs.kill("robot-a");
    let restarted_at = Instant::now();
    procs.0.push(("robot-a".into(), run(robot_args("robot-a"), "robot-a-3", false)));
    wait_for(
        &seen,
        "restarted robot-a reporting EStop",
        Duration::from_secs(30),
        latched(restarted_at, SafetyState::EStop),
    );
    wait_for(&seen, "restarted robot-a alive", Duration::from_secs(30), |s| {
        s.status.as_ref().is_some_and(|st| st.alive.len() == 2)
    });
    let stdin = procs.child("server").stdin.as_mut().unwrap();
    stdin.write_all(b"rearm\n").unwrap();
    stdin.flush().unwrap();
    std::thread::sleep(Duration::from_secs(3));
    {
        let s = seen.lock().unwrap();
        let since: Vec<SafetyState> =
            s.safety_a.iter().filter(|(t, _)| *t >= restarted_at).map(|(_, st)| *st).collect();
        assert!(!since.contains(&SafetyState::Armed), "armed after a restart with no reset: {since:?}");
        assert_eq!(since.last(), Some(&SafetyState::EStop), "{since:?}");
    }
    let text = std::fs::read_to_string(log("robot-a-3")).unwrap_or_default();
    assert!(text.contains("starting latched"), "{text}");
    let said = operator(true);
    assert!(said.contains("robot-a: e-stop reset confirmed"), "{said}");
    eprintln!(
        "e-stop seen from the server's stdin after {net_estop:?}, from SIGUSR1 after {local_estop:?}, \
         from `amr estop` after {operator_estop:?} (process start included)"
    );
    eprintln!(
        "server killed: robot-a's watchdog stopped it within {watchdog:?}; the new server ran the \
         formation after {restarted:?}; robot-b killed: seen gone after {seen_gone:?}, formation \
         stopped {stopped:?} later, robot-a disarmed {disarmed:?} after that; restarted robot-b \
         rejoined in {rejoined:?}; frozen robot-a seen gone after {silent:?}, back {resumed:?} after \
         resuming; last status {:?}",
        seen.lock().unwrap().status
    );
    let armed_again = seen
        .lock()
        .unwrap()
        .safety_a
        .iter()
        .filter(|(t, s)| *t > killed && *t < restarted_at && *s == SafetyState::Armed)
        .count();
    assert!(armed_again >= 1, "robot-a was re-armed");
}

/// Credentials never reach the logs, even at trace level (Zenoh itself prints its configuration,
/// password included, at debug level when a session opens).
#[test]
fn credentials_stay_out_of_the_logs_at_trace_level() {
    let tmp = tempfile::tempdir().unwrap();
    let creds = write_config(tmp.path());
    std::fs::write(&creds, "server:srv-Zq81xx\nrobot-a:a-Zq81xx\n").unwrap();
    let config = tmp.path().join("config");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let args = |what: &str| -> Vec<String> {
        let (cmd, file) =
            if what == "server" { ("server", "server.toml") } else { ("robot", "robot-a.toml") };
        let config = config.join(file).display().to_string();
        [cmd, "--config", &config, "--insecure", "--credentials", creds.to_str().unwrap()]
            .iter()
            .map(|s| (*s).to_owned())
            .chain(["--endpoint".to_owned(), endpoint.clone()])
            .chain(if what == "server" {
                vec![
                    "--scenario".to_owned(),
                    "short".to_owned(),
                    "--progress-file".to_owned(),
                    tmp.path().join("server.progress").display().to_string(),
                ]
            } else {
                vec!["--state-file".to_owned(), tmp.path().join("robot-a.safety").display().to_string()]
            })
            .collect()
    };
    let mut logs = Vec::new();
    let mut procs = Procs(Vec::new());
    for what in ["server", "robot"] {
        let log = tmp.path().join(format!("{what}.log"));
        let child = Command::new(env!("CARGO_BIN_EXE_amr"))
            .args(args(what))
            .env("RUST_LOG", "trace")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        procs.0.push((what.to_owned(), child));
        logs.push(log);
        std::thread::sleep(Duration::from_millis(500));
    }
    // Bounded: until the robot has reached the server, at most 20 s.
    let t0 = Instant::now();
    while !std::fs::read_to_string(&logs[1]).unwrap_or_default().contains("connected to the server") {
        if t0.elapsed() > Duration::from_secs(20) {
            let tail = |p: &Path| {
                let t = std::fs::read_to_string(p).unwrap_or_default();
                t.lines().filter(|l| !l.contains("TRACE")).take(30).collect::<Vec<_>>().join("\n")
            };
            panic!("the robot never connected:\n{}\n---\n{}", tail(&logs[0]), tail(&logs[1]));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(procs);
    for log in &logs {
        let text = std::fs::read_to_string(log).unwrap();
        assert!(text.contains("TRACE"), "trace logging was on: {}", log.display());
        assert!(!text.contains("Zq81xx"), "a password in {}", log.display());
    }
}

/// `amr server` exits promptly on SIGTERM and on Ctrl-C (SIGINT) while its standard input is open
/// and idle (an operator's terminal; here a pipe the test holds open).
#[test]
fn the_server_exits_promptly_on_a_signal_with_its_stdin_held_open() {
    let tmp = tempfile::tempdir().unwrap();
    let creds = write_config(tmp.path());
    let config = tmp.path().join("config");
    for sig in ["-TERM", "-INT"] {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let log = tmp.path().join(format!("server{sig}.log"));
        let args: Vec<String> = [
            "server",
            "--config",
            config.join("server.toml").to_str().unwrap(),
            "--insecure",
            "--credentials",
            creds.to_str().unwrap(),
            "--endpoint",
            &endpoint,
            "--scenario",
            "short",
            "--progress-file",
            tmp.path().join("server.progress").to_str().unwrap(),
        ]
        .iter()
        .map(|s| (*s).to_owned())
        .collect();
        let mut procs = Procs(vec![("server".into(), spawn(&args, &log, true))]);
        let t0 = Instant::now();
        while !std::fs::read_to_string(&log).unwrap_or_default().contains("server running") {
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "the server did not start: {}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        let child = procs.child("server");
        let pid = child.id().to_string();
        assert!(Command::new("kill").args([sig, &pid]).status().unwrap().success());
        let t0 = Instant::now();
        let status = loop {
            if let Some(st) = child.try_wait().unwrap() {
                break st;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "the server still runs 10 s after kill {sig} with its stdin open: {}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(20));
        };
        assert!(status.success(), "kill {sig}: {status}");
        eprintln!("kill {sig}: exited after {:?}", t0.elapsed());
    }
}
