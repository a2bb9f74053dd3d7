//! Drills of the link and the server: one robot's scans late at the start, the link lost, the server
//! crashed and restarted.

#[allow(clippy::wildcard_imports, reason = "the drills share their parent's imports and helpers")]
use super::*;

/// How late robot-b's scans reach the server in [`late_scans`]: past the fusion's sync gate (its
/// scans pair with nothing of robot-a's) and its age gate.
const LATE_BY: Duration = Duration::from_millis(300);
/// How long they come late, from the start of the job.
const LATE_FOR: Duration = Duration::from_secs(8);

/// One robot's LiDAR scans reach the server late from the start of the job (a loaded host or
/// network between that LiDAR and the server), its odometry and health on time: nothing can be
/// fused, so V has no verified estimate, and the formation must not start on the scenario's
/// start pose alone. Once the scans come on time, V is started where the robots' own estimates
/// put it, verified, and the formation starts by itself; every verified estimate of V is within
/// 10 cm of the truth.
pub(crate) async fn late_scans(config: &Config, seed: u64, c: &mut Check) {
    let Some(scenario) = one_leg(config) else { return c.fail("no straight scenario") };
    let options = drill_options(scenario, seed, c);
    let sim = match Sim::start(config, options).await {
        Ok(s) => s,
        Err(e) => return c.fail(format!("setup: {e}")),
    };
    let Some(late) = sim.robots.get(1).map(|r| r.id.clone()) else {
        sim.shutdown().await;
        return c.fail("the drill needs two robots");
    };
    sim.link.set_scan_delay(&late, LATE_BY);
    c.inject();
    c.throughout(
        &format!(
            "{late}'s scans {} ms late: the formation does not start, every target zero",
            LATE_BY.as_millis()
        ),
        LATE_FOR,
        || {
            !matches!(phase(&sim), Some(Phase::Arming { .. } | Phase::Running | Phase::Holding { .. }))
                && all_targets_zero(&sim)
        },
    )
    .await;
    let verified_while_late = sim.report().samples.iter().filter(|s| s.verified).count();
    c.eq("verified estimates of V while the scans came late", verified_while_late, 0);
    sim.link.set_scan_delay(&late, Duration::ZERO);
    let on_time = c.since_injection();
    c.recovery = c
        .within(
            "scans on time: V verified, the formation running, the wheels turning",
            Duration::from_secs(20),
            || phase(&sim) == Some(Phase::Running) && all_turning(&sim),
        )
        .await
        .map(|t| t.saturating_sub(on_time));
    let verified = || sim.report().samples.iter().filter(|s| s.verified).count();
    c.within(
        "more than 20 verified estimates of V after the scans came on time",
        Duration::from_secs(10),
        || verified() > 20,
    )
    .await;
    let report = sim.report();
    let verified = report.samples.iter().filter(|s| s.verified).count();
    for f in report.failures(0.10, false) {
        c.fail(f);
    }
    c.counters.insert("verified_estimates".into(), verified as u64);
    keep_counters(&sim, c);
    sim.shutdown().await;
}

/// Drill 8: the link between the robots and the server is lost — held, as a stalled transport
/// would: nothing passes, and the backlog (the commands the server sent meanwhile) is delivered
/// late when it returns, the worst case for stale commands.
///
/// (a) Each robot's watchdog disarms it within 350 ms; (b) the ramp starts within 350 ms and every
/// target is zero within 5.35 s, no target ever growing; the server notices the silence (the
/// fusion's 0.5 s) and stops the formation. The link returns: the late commands are all refused
/// (counted), no robot arms, the wheels stay still and the formation stays stopped for 1.5 s; (c)
/// after the operator's re-arm the formation runs again and the wheels turn. (d) The formation's
/// phases after the fault are exactly Stopped, Waiting, Arming, Running, and no actor failed.
pub(crate) async fn link_lost(config: &Config, seed: u64, c: &mut Check) {
    let Some(scenario) = one_leg(config) else { return c.fail("no straight scenario") };
    let Some(sim) = moving_sim(config, seed, scenario, c).await else { return };
    let n = sim.robots.len();
    let ids: Vec<String> = sim.robots.iter().map(|r| r.id.clone()).collect();
    let (p0, marks0, s0) = (sim.phases().len(), marks(&sim), sim.server.events.len());
    let refused0: Vec<u64> = (0..n).map(|i| refused(&sim, i)).collect();
    c.inject();
    for id in &ids {
        sim.link.set_held(id, true);
    }
    let all: Vec<usize> = (0..n).collect();
    watchdog_stop(&sim, c, &all).await;
    c.that(
        c.counters.get("formation_stopped_ms").is_some_and(|t| *t <= 2000),
        format!(
            "the formation stopped within 2 s (the robots' scans stopped): {:?} ms",
            c.counters.get("formation_stopped_ms")
        ),
    );
    tokio::time::sleep(Duration::from_millis(500)).await;
    // The link returns with its backlog.
    let late0 = sim.link.late();
    for id in &ids {
        sim.link.set_held(id, false);
    }
    let returned = c.since_injection();
    c.throughout(
        "after the link returns: nobody armed, every target zero, the formation stopped",
        Duration::from_millis(1500),
        || none_armed(&sim) && all_targets_zero(&sim) && matches!(phase(&sim), Some(Phase::Stopped { .. })),
    )
    .await;
    c.that(all_still(&sim), "the wheels at rest");
    c.that(sim.link.late() > late0, "the held backlog was delivered");
    for i in 0..n {
        let late = refused(&sim, i) - refused0[i];
        c.that(late >= 1, format!("{}: the late commands refused ({late})", ids[i]));
    }
    // The operator re-arms.
    rearm_and_run(&sim, c).await;
    c.counters.insert("link_returned_ms".into(), ms(returned));
    c.eq(
        "formation phases after the fault",
        phases_from(&sim, p0),
        vec!["Stopped", "Waiting", "Arming", "Running"],
    );
    c.eq("robot supervision events", robot_events(&sim, &marks0), vec![]);
    c.events = event_lines(&sim, p0, &marks0, s0);
    keep_counters(&sim, c);
    sim.shutdown().await;
}

/// Drill 9: the server crashes (its whole tree killed at once) and a new one starts on the same
/// link after 1 s.
///
/// (a) Each robot's watchdog disarms it within 350 ms; (b) every target is zero within 5.35 s, no
/// target ever growing; the robots stay disarmed and still while no server runs. The new server
/// hears from every robot (its AMCL localises each on its scans: reconnected) within 5 s, but does
/// not arm them: for 2 s nobody is armed and the wheels stay still. (c) After the operator's
/// re-arm the formation runs and the wheels turn, resumed where V is (not at the plan's start), and
/// V's error against the truth is under 15 cm 3 s later. (d) The phases after the crash are
/// exactly Waiting, Arming, Running (the new server's); the robots' supervisors saw nothing, the
/// new server's started its three children.
///
/// The new server starts its AMCL from the last fused estimate of V (with the robots at their
/// slots around it) and its plan where V is (see [`Sim::restart_server`]).
pub(crate) async fn server_restart(config: &Config, seed: u64, c: &mut Check) {
    let Some(scenario) = one_leg(config) else { return c.fail("no straight scenario") };
    let Some(mut sim) = moving_sim(config, seed, scenario, c).await else { return };
    let n = sim.robots.len();
    let (p0, marks0) = (sim.phases().len(), marks(&sim));
    let plan_before = sim.formation().map_or(0.0, |f| f.plan_s);
    c.inject();
    sim.crash_server();
    c.within("the server's tree dead", Duration::from_secs(1), || !sim.server.is_running()).await;
    let all: Vec<usize> = (0..n).collect();
    watchdog_stop(&sim, c, &all).await;
    c.throughout("no server: nobody armed, every target zero", Duration::from_secs(1), || {
        none_armed(&sim) && all_targets_zero(&sim)
    })
    .await;
    let restarted = c.since_injection();
    if let Err(e) = sim.restart_server().await {
        c.fail(format!("restart: {e}"));
        return sim.shutdown().await;
    }
    let s0 = 0;
    c.within(
        "reconnected: the new server localises every robot on its scans",
        Duration::from_secs(5),
        || sim.server.ports.stats.own_estimates.iter().all(|e| ServerStats::get(e) >= 1),
    )
    .await;
    c.throughout(
        "the new server does not arm by itself: nobody armed, wheels still",
        Duration::from_secs(2),
        || none_armed(&sim) && all_targets_zero(&sim),
    )
    .await;
    c.that(all_still(&sim), "the wheels at rest");
    c.that(
        matches!(phase(&sim), Some(Phase::Waiting)),
        format!("the new formation waits: {:?}", phase(&sim)),
    );
    rearm_and_run(&sim, c).await;
    let plan_after = sim.formation().map_or(0.0, |f| f.plan_s);
    c.that(
        plan_after > 0.5 * plan_before,
        format!("resumed where V is: plan at {plan_after:.1} s (it was at {plan_before:.1} s at the crash)"),
    );
    tokio::time::sleep(Duration::from_secs(3)).await;
    let report = sim.report();
    match report.samples.last() {
        Some(s) => {
            let e = s.e_x_m.hypot(s.e_y_m);
            c.counters.insert("v_error_mm.after_restart".into(), (e * 1000.0) as u64);
            c.that(e < 0.15, format!("V's error after the restart {:.1} cm (< 15 cm)", e * 100.0));
        }
        None => c.fail("no fused estimate after the restart"),
    }
    c.counters.insert("server_restarted_ms".into(), ms(restarted));
    c.eq("formation phases after the crash", phases_from(&sim, p0), vec!["Waiting", "Arming", "Running"]);
    c.eq("robot supervision events", robot_events(&sim, &marks0), vec![]);
    let started = |ch: &str| EventKind::Started { child: ch.into() };
    c.eq(
        "the new server's supervision events",
        sim.server.events.kinds("server"),
        vec![started("localizer"), started("formation")],
    );
    c.events = event_lines(&sim, p0, &marks0, s0);
    keep_counters(&sim, c);
    sim.shutdown().await;
}
