//! `amr bench localize`'s report: a row per log and run, the kidnappings, and how the integrity
//! measure separates the reference poses from displaced ones.

#[allow(clippy::wildcard_imports, reason = "the report reads the benchmark's own types")]
use super::*;

fn cm(s: &Score) -> (f64, f64, f64) {
    s.translation.map_or((f64::NAN, f64::NAN, f64::NAN), |t| (t.rmse * 100.0, t.p95 * 100.0, t.max * 100.0))
}

fn row(out: &mut String, name: &str, what: &str, s: &Score, run: Option<&Run>) {
    let (rmse, p95, max) = cm(s);
    let t = run.map_or("–".to_owned(), |r| format!("{:.2} / {:.2}", r.update_median_ms, r.update_p95_ms));
    let i = run.map_or("– | – | – | – | – | – | –".to_owned(), |r| {
        let c = &r.integrity;
        format!(
            "{}/{} | {}/{} | {} | {} | {} / {} / {} | {} | {}",
            c.detected,
            c.losses,
            c.recovered,
            c.losses,
            c.excursions,
            c.false_lost,
            c.uncertain_on,
            c.lost_on,
            c.on,
            c.tracking_off,
            c.reseeds
        )
    });
    let conv = s.converged_from.map_or("never".to_owned(), |c| c.to_string());
    let _ = writeln!(
        out,
        "| {name} | {what} | {rmse:.1} | {p95:.1} | {max:.1} | {:.2} | {:.1} | {conv} | {t} | {i} |",
        s.heading_rmse_deg,
        s.diverged_share * 100.0
    );
}

pub fn markdown(r: &Report) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "AMCL on recorded logs against their references (seeds {:?}; one row per seed). Errors in cm; \
         'off' is the share of scans more than 0.5 m off; 'from' is the first scan from which every \
         scan is within 0.5 m; times are per filter update (median / P95, ms). Integrity (a scan \
         is off there when its estimate is more than 0.5 m or {OFF_HEADING_DEG}° off, else on): \
         losses (runs of at least {DETECT_WITHIN} off scans) reported lost within {DETECT_WITHIN} \
         scans, losses recovered, brief excursions (shorter runs), false alarms (turned lost with \
         the estimate on for {DETECT_WITHIN} scans), scans on reported uncertain / lost / all scans on, \
         scans off reported tracking (what a server would drive on), updates that re-seeded \
         particles.\n",
        r.seeds
    );
    let _ = writeln!(
        out,
        "| log | run | RMSE | P95 | max | heading RMSE (°) | off (%) | from | update ms | detected | recovered | brief | false lost | uncertain / lost / on | tracking while off | re-seeds |"
    );
    let _ = writeln!(out, "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for l in &r.logs {
        row(&mut out, &l.name, "odometry alone", &l.odometry_only, None);
        if let Some(n) = &l.nav2 {
            row(&mut out, &l.name, "nav2 (its CSV)", n, None);
        }
        for (s, run) in r.seeds.iter().zip(&l.tracking) {
            row(&mut out, &l.name, &format!("tracking, seed {s}"), &run.score, Some(run));
        }
        for (s, run) in r.seeds.iter().zip(&l.global) {
            row(&mut out, &l.name, &format!("global, seed {s}"), &run.score, Some(run));
        }
        for (s, run) in r.seeds.iter().zip(&l.kidnapped) {
            row(&mut out, &l.name, &format!("kidnapped, seed {s}"), &run.score, Some(run));
        }
    }
    kidnap_table(r, &mut out);
    separation_table(r, &mut out);
    for (name, why) in &r.skipped {
        let _ = writeln!(out, "\n{name}: not run, {why}.");
    }
    out
}

/// The kidnappings: how many carried the estimate off, how soon each was reported lost and
/// tracked again.
fn kidnap_table(r: &Report, out: &mut String) {
    let kidnaps: Vec<(&str, u64, &KidnapOutcome)> = r
        .logs
        .iter()
        .flat_map(|l| {
            r.seeds
                .iter()
                .zip(&l.kidnapped)
                .flat_map(move |(s, run)| run.kidnaps.iter().map(move |k| (l.name.as_str(), *s, k)))
        })
        .collect();
    if kidnaps.is_empty() {
        return;
    }
    let n = kidnaps.len();
    let off: Vec<&KidnapOutcome> =
        kidnaps.iter().filter(|(_, _, k)| k.carried_off).map(|(_, _, k)| *k).collect();
    let lost3 = off.iter().filter(|k| k.lost_after.is_some_and(|a| a < DETECT_WITHIN)).count();
    let doubted3 = off.iter().filter(|k| k.doubted_after.is_some_and(|a| a < DETECT_WITHIN)).count();
    let back10 = off.iter().filter(|k| k.tracked_after.is_some_and(|a| a < 10)).count();
    let back = off.iter().filter(|k| k.tracked_after.is_some()).count();
    let brief = kidnaps.iter().filter(|(_, _, k)| k.brief).count();
    let _ = writeln!(
        out,
        "\nKidnappings (odometry teleported 1-5 m, any heading): {n} in all, {} of which carried the \
         estimate off (more than 0.5 m or {OFF_HEADING_DEG}° for at least {DETECT_WITHIN} scans in a \
         row; {brief} more went off for fewer scans, the others the filter absorbed); of those \
         carried off, reported \
         lost within {DETECT_WITHIN} scans: {lost3} (no longer tracking, uncertain or lost: \
         {doubted3}); tracking again within 10 scans: {back10}; at all: {back}; the estimate back \
         on ({DETECT_WITHIN} scans in a row, whatever the state) within 10 scans: \
         {within10}; at all: {again}. Scans counted from the kidnapping's (0).\n",
        off.len(),
        within10 = back_within(&off, 10),
        again = back_within(&off, usize::MAX),
    );
    nav2_kidnap_table(r, out);
    let _ = writeln!(
        out,
        "| log | seed | scan | jump (m, °) | carried off | not tracking after | lost after | tracking after | back after |"
    );
    let _ = writeln!(out, "|---|---|---|---|---|---|---|---|---|");
    let show = |a: Option<usize>| a.map_or("never".to_owned(), |a| a.to_string());
    for (name, s, k) in kidnaps {
        let _ = writeln!(
            out,
            "| {name} | {s} | {} | {:.1}, {:.0} | {} | {} | {} | {} | {} |",
            k.scan,
            k.jump_m,
            k.jump_deg,
            if k.carried_off {
                "yes"
            } else if k.brief {
                "briefly"
            } else {
                "no"
            },
            show(k.doubted_after),
            show(k.lost_after),
            show(k.tracked_after),
            show(k.back_after)
        );
    }
}

/// Of `off`, the kidnappings whose estimate was back within `scans` scans.
fn back_within(off: &[&KidnapOutcome], scans: usize) -> usize {
    off.iter().filter(|k| k.back_after.is_some_and(|a| a < scans)).count()
}

/// nav2 beside ours on the same kidnapped logs, where its estimates were given: per log and seed,
/// the kidnappings that carried the estimate off, and of those the ones back within 10 scans and
/// at all.
fn nav2_kidnap_table(r: &Report, out: &mut String) {
    if r.logs.iter().all(|l| l.nav2_kidnapped.is_empty()) {
        return;
    }
    let _ = writeln!(
        out,
        "nav2 (its CSVs) on the same kidnapped logs: kidnappings carried off / back within 10 \
         scans / at all (back: {DETECT_WITHIN} scans in a row within 0.5 m and {OFF_HEADING_DEG}°).\n"
    );
    let _ = writeln!(out, "| log | seed | ours | nav2 |");
    let _ = writeln!(out, "|---|---|---|---|");
    let counts = |ks: &[KidnapOutcome]| {
        let off: Vec<&KidnapOutcome> = ks.iter().filter(|k| k.carried_off).collect();
        (off.len(), back_within(&off, 10), back_within(&off, usize::MAX))
    };
    let mut sums = [(0, 0, 0); 2];
    for l in &r.logs {
        for (s, nav2) in &l.nav2_kidnapped {
            let Some(ours) =
                r.seeds.iter().zip(&l.kidnapped).find(|(x, _)| *x == s).map(|(_, run)| &run.kidnaps)
            else {
                continue;
            };
            let (a, b) = (counts(ours), counts(nav2));
            for (sum, c) in sums.iter_mut().zip([a, b]) {
                *sum = (sum.0 + c.0, sum.1 + c.1, sum.2 + c.2);
            }
            let _ = writeln!(
                out,
                "| {} | {s} | {} / {} / {} | {} / {} / {} |",
                l.name, a.0, a.1, a.2, b.0, b.1, b.2
            );
        }
    }
    let [a, b] = sums;
    let _ = writeln!(out, "| all | | {} / {} / {} | {} / {} / {} |\n", a.0, a.1, a.2, b.0, b.1, b.2);
}

/// How the integrity measure separates the reference poses from displaced ones.
fn separation_table(r: &Report, out: &mut String) {
    let _ = writeln!(
        out,
        "\nIntegrity measure (share of the scan explained by the map) at the reference poses and \
         displaced from them (direction and sign drawn per scan); 'uncertain' and 'lost' are the \
         shares of scans below the monitor's ratios × the scan's level (each range band's share \
         explained at the references, weighted by the scan's endpoints in it): false alarms on \
         the reference row, detections on the others.\n"
    );
    let _ = writeln!(out, "| log | pose | scans | median | P5 | P95 | uncertain (%) | lost (%) |");
    let _ = writeln!(out, "|---|---|---|---|---|---|---|---|");
    for l in &r.logs {
        for s in &l.separation {
            let _ = writeln!(
                out,
                "| {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.1} | {:.1} |",
                l.name,
                s.displacement,
                s.scans,
                s.median,
                s.p5,
                s.p95,
                s.below_uncertain * 100.0,
                s.below_lost * 100.0
            );
        }
    }
    let Some(first) = r.logs.first() else { return };
    let _ = writeln!(
        out,
        "\nShare of the endpoints explained at the reference poses by their range from the sensor \
         (in brackets: the share of the log's endpoints in the band).\n"
    );
    let head: Vec<&str> = first.by_range.iter().map(|b| b.band.as_str()).collect();
    let _ = writeln!(out, "| log | {} |", head.join(" | "));
    let _ = writeln!(out, "|---|{}", "---|".repeat(head.len()));
    for l in &r.logs {
        let total: u64 = l.by_range.iter().map(|b| b.endpoints).sum::<u64>().max(1);
        let cells: Vec<String> = l
            .by_range
            .iter()
            .map(|b| {
                if b.endpoints == 0 {
                    "–".to_owned()
                } else {
                    format!("{:.2} ({:.0} %)", b.explained, 100.0 * b.endpoints as f64 / total as f64)
                }
            })
            .collect();
        let _ = writeln!(out, "| {} | {} |", l.name, cells.join(" | "));
    }
}
