//! The scan-flood drill: one robot sends scans at ten times its LiDAR's rate.

#[allow(clippy::wildcard_imports, reason = "the drills share their parent's imports and helpers")]
use super::*;
use amr_actors::server::localizer::Stall;

/// How long the full scan-flood drill floods.
pub(crate) const FLOOD_FULL: Duration = Duration::from_secs(60);

/// One robot sends scans at ten times its LiDAR's rate (a faulty robot, or one with a stolen key),
/// and the localizer is made slower than that (each scan costs it 8 ms more, as on a loaded host):
/// the server holds a bounded number of scans (the newest replacing the oldest) and its memory
/// stays bounded; the other robot's health and safety reports still arrive, as often and as fresh
/// as before; the formation keeps going, or holds by the integrity rules.
pub(crate) async fn scan_flood(config: &Config, seed: u64, length: Duration, c: &mut Check) {
    let Some(scenario) = config.scenarios.get("turning").cloned() else {
        return c.fail("no turning scenario");
    };
    let Some(sim) = moving_sim(config, seed, scenario, c).await else { return };
    let seen = Arc::new(Mutex::new(FloodSeen::default()));
    let (watched, flooding) = (sim.robots[0].id.clone(), sim.robots[1].id.clone());
    let Ok((probe, _)) =
        Actor::spawn(None, FloodProbe { seen: Arc::clone(&seen), watched, flooding }, ()).await
    else {
        return c.fail("the probe did not start");
    };
    sim.server.ports.uplink.subscribe(probe.clone(), Some);
    let reports = |s: &FloodSeen| s.reports.clone();
    // A baseline of the other robot's reports.
    tokio::time::sleep(Duration::from_secs(5)).await;
    let before = reports(&seen.lock().unwrap_or_else(PoisonError::into_inner));
    let rss0 = rss_kb();
    let slots = &sim.server.ports.scans;
    let dropped0 = slots.dropped();
    let Some(localizer) = sim.server.localizer_actor().await else { return c.fail("no localizer actor") };
    c.inject();
    // 8 ms a scan: at most 125 a second, fewer than the 165 that come. The localizer waits (its
    // mailbox queueing), so that the drill means the same on virtual time as in real time.
    let stall =
        LocalizerMsg::InjectStall { each: Duration::from_millis(8), during: length, how: Stall::Wait };
    if localizer.cast(stall).is_err() {
        c.fail("the localizer actor is gone");
    }
    let flood = flood(&sim, &seen);
    let mut rss_peak = rss0;
    let t0 = Instant::now();
    let mut phases = Vec::new();
    while t0.elapsed() < length {
        tokio::time::sleep(Duration::from_millis(500)).await;
        rss_peak = rss_peak.max(rss_kb());
        if let Some(f) = sim.formation() {
            phases.push(f.phase);
        }
    }
    drop(flood);
    let during = reports(&seen.lock().unwrap_or_else(PoisonError::into_inner))[before.len()..].to_vec();
    probe.stop(None);
    let flooded = seen.lock().unwrap_or_else(PoisonError::into_inner).flood_scans;
    let measured = Flooded {
        length,
        flooded,
        dropped: slots.dropped() - dropped0,
        held_peak: slots.held_peak(),
        rss: (rss0, rss_peak),
        before,
        during,
    };
    measured.judge(c);
    let stopped = phases.iter().find(|p| matches!(p, Phase::Stopped { .. } | Phase::Waiting));
    c.that(stopped.is_none(), format!("the formation kept going or held (no stop): {stopped:?}"));
    // Within 40 s: a formation that went out of shape while robot-b's estimates lagged may be
    // re-forming when the flood ends (9–15 s a time, measured on the full drill), then re-arms.
    c.recovery = c
        .within("the formation running after the flood", Duration::from_secs(40), || {
            sim.formation().is_some_and(|f| f.phase == Phase::Running)
        })
        .await;
    keep_counters(&sim, c);
    sim.shutdown().await;
}

/// The flood: robot-b's latest scan sent again, restamped, nine times for each real one (135 Hz
/// on top of the LiDAR's 15), until dropped.
fn flood(sim: &Sim, seen: &Arc<Mutex<FloodSeen>>) -> crate::AbortOnDrop<()> {
    let (flooder, clock, sink) = (Arc::clone(&sim.robots[1].ports), sim.server.ports.clock, Arc::clone(seen));
    crate::AbortOnDrop(tokio::spawn(async move {
        let mut every = tokio::time::interval(Duration::from_secs_f64(1.0 / 135.0));
        loop {
            every.tick().await;
            let latest = sink.lock().unwrap_or_else(PoisonError::into_inner).latest.clone();
            if let Some(s) = latest {
                let now = clock.now_s();
                flooder.scans.send(amr_msgs::ScanMsg { stamp_s: now, received_s: now, ..s });
            }
        }
    }))
}

/// What the scan flood measured.
struct Flooded {
    length: Duration,
    /// Flood scans the localizer took.
    flooded: u64,
    /// Scans the slots dropped.
    dropped: u64,
    held_peak: u64,
    /// Resident memory at the start and at its peak, kB.
    rss: (u64, u64),
    /// The other robot's reports (received, age at the server), before and during the flood.
    before: Vec<(f64, f64)>,
    during: Vec<(f64, f64)>,
}

impl Flooded {
    /// The counters and the verdicts: the flood reached the server, memory stayed bounded, old
    /// scans were dropped, the other robot's reports kept coming as often and as fresh.
    fn judge(&self, c: &mut Check) {
        let rate = |r: &[(f64, f64)]| match (r.first(), r.last()) {
            (Some(a), Some(b)) if b.0 > a.0 => r.len() as f64 / (b.0 - a.0),
            _ => 0.0,
        };
        let worst = |r: &[(f64, f64)]| r.iter().map(|(_, age)| *age).fold(0.0, f64::max);
        let (before, during, (rss0, rss_peak)) = (&self.before, &self.during, self.rss);
        c.counters.insert("flood_scans_seen_by_server".into(), self.flooded);
        c.counters.insert("scans_dropped".into(), self.dropped);
        c.counters.insert("scans_held_peak".into(), self.held_peak);
        c.counters.insert("rss_start_kb".into(), rss0);
        c.counters.insert("rss_peak_kb".into(), rss_peak);
        c.counters.insert("reports_per_10s_before".into(), (rate(before) * 10.0) as u64);
        c.counters.insert("reports_per_10s_during".into(), (rate(during) * 10.0) as u64);
        c.counters.insert("report_age_ms_worst_before".into(), (worst(before) * 1000.0) as u64);
        c.counters.insert("report_age_ms_worst_during".into(), (worst(during) * 1000.0) as u64);
        // What reached the server: what the localizer took and what the slots dropped.
        let per_s = (self.flooded + self.dropped) as f64 / self.length.as_secs_f64();
        c.that(per_s > 100.0, format!("the robot flooded: {per_s:.0} scans/s reached the server"));
        c.that(
            self.held_peak <= 2 * amr_actors::link::SCANS_PER_ROBOT as u64,
            format!("the server held at most {} scans at once", self.held_peak),
        );
        c.that(
            rss_peak.saturating_sub(rss0) < 200_000,
            format!("memory grew by {} kB (< 200 MB)", rss_peak.saturating_sub(rss0)),
        );
        c.that(
            self.dropped > 0,
            format!("the slots dropped old scans ({}): the localizer could not keep up", self.dropped),
        );
        // Their rate varies with the changes among them; the periodic re-sends alone are most of it.
        c.that(
            rate(during) >= 0.5 * rate(before) && !during.is_empty(),
            format!(
                "the other robot's reports kept coming: {:.2}/s before, {:.2}/s during",
                rate(before),
                rate(during)
            ),
        );
        c.that(
            worst(during) <= worst(before).max(0.05) * 2.0,
            format!(
                "and as fresh: worst age {:.0} ms before, {:.0} ms during",
                worst(before) * 1000.0,
                worst(during) * 1000.0
            ),
        );
    }
}

/// The process's resident memory, kB (0 where /proc is not there).
fn rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find_map(|l| {
                l.strip_prefix("VmRSS:").and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            })
        })
        .unwrap_or(0)
}

#[derive(Debug, Default)]
struct FloodSeen {
    /// The first robot's health and safety reports: (received, age at the server).
    reports: Vec<(f64, f64)>,
    /// The second robot's latest scan, and how many of its scans the server took.
    latest: Option<amr_msgs::ScanMsg>,
    flood_scans: u64,
}

/// Watches the server's uplink for the flood drill.
#[derive(Debug)]
struct FloodProbe {
    seen: Arc<Mutex<FloodSeen>>,
    /// The robot whose reports are timed, and the one flooding.
    watched: String,
    flooding: String,
}

impl Actor for FloodProbe {
    type Msg = (amr_msgs::Uplink, f64);
    type State = ();
    type Arguments = ();

    async fn pre_start(&self, _myself: ActorRef<Self::Msg>, (): ()) -> Result<(), ActorProcessingErr> {
        Ok(())
    }

    async fn handle(
        &self,
        _myself: ActorRef<Self::Msg>,
        (u, rx): Self::Msg,
        (): &mut (),
    ) -> Result<(), ActorProcessingErr> {
        let mut s = self.seen.lock().unwrap_or_else(PoisonError::into_inner);
        match &u {
            amr_msgs::Uplink::Health { stamp_s, .. } | amr_msgs::Uplink::Safety { stamp_s, .. }
                if u.robot() == self.watched =>
            {
                s.reports.push((rx, rx - stamp_s));
            }
            amr_msgs::Uplink::Scan(scan) if scan.robot == self.flooding => {
                s.flood_scans += 1;
                s.latest = Some(scan.clone());
            }
            _ => {}
        }
        Ok(())
    }
}
