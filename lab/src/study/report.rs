//! The occlusion study's report: the tables of V's and the worst-placed robot's errors, the
//! verdicts on T4, and the plots.

#[allow(clippy::wildcard_imports, reason = "the report reads the study's own types and figures")]
use super::*;

/// The plots of T1's and T4's errors over spacing, one per scenario, listed in `md`.
pub(super) fn study_plots(
    dir: &Path,
    scenarios: &[String],
    rows: &[StudyRow],
    md: &mut String,
) -> anyhow::Result<()> {
    let _ = writeln!(md, "\n## Plots\n");
    for name in scenarios {
        let stem =
            rows.iter().find(|r| r.scenario == *name || name.ends_with(&format!("{}.toml", r.scenario)));
        let Some(stem) = stem.map(|r| r.scenario.clone()) else { continue };
        let mut series = Vec::new();
        for robots in TEAMS {
            for c in [Configuration::T1, Configuration::T4] {
                let points: Vec<(f64, f64)> = rows
                    .iter()
                    .filter(|r| r.scenario == stem && r.robots == robots)
                    .filter_map(|r| Some((r.spacing_m, r.rmse_cm(c)?)))
                    .collect();
                if !points.is_empty() {
                    series.push((format!("{c:?}, {robots} robots"), points));
                }
            }
        }
        let written = crate::plots::write_lines(
            dir,
            &stem,
            &format!("{stem}: trial-level 2D RMSE of V (T1 and T4) over spacing"),
            ("spacing (m)", "2D RMSE (cm)"),
            &series,
        )?;
        for p in written.iter().filter(|p| p.extension().is_some_and(|e| e == "png")) {
            let _ = writeln!(md, "- {}", p.file_name().map(|n| n.to_string_lossy()).unwrap_or_default());
        }
    }
    Ok(())
}

pub(super) fn study_markdown(r: &StudyReport<'_>) -> String {
    let mut md = study_intro(r);
    let run = v_table(r, &mut md);
    worst_robot_table(&run, &mut md);
    md
}

/// The title and what the table of V's errors shows.
fn study_intro(r: &StudyReport<'_>) -> String {
    format!(
        "# amr eval --study occlusion: {} trials per configuration from seed {}, AMCL's map {}\n\n{}\
         Trial-level 2D RMSE of V against the truth, cm (mean ± SD over trials); in brackets, trials that \
         diverged (error above {DIVERGED_M} m at some scan, or no estimate at all). Per robot (robot 0 first): \
         the share of its beams on other robots' bodies (occluded %), the share of the site returns it would \
         have alone that are left (site left %), and the share of its beams that return from the site at all \
         (site %). Δ = T4 − min(T1, T2, T3), ± the standard error of its mean over the trials' paired \
         differences (T4 and the best of T1–T3 on the same trial).\n\n\
         | scenario | motion | robots | spacing m | T1 | T2 | T3 | T4 | Δ cm | occluded % | site left % | site % |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|\n",
        r.trials,
        r.seed,
        match r.map {
            MapSource::Surveyed => "surveyed",
            MapSource::True => "true",
        },
        if r.confirm_trials > r.trials {
            format!(
                "Where those trials leave the criterion below open (the margin within two standard errors of Δ), \
                 the configuration runs {} trials in all, the same first ones and the next: its Δ shows the count.\n\n",
                r.confirm_trials
            )
        } else {
            String::new()
        },
    )
}

/// The table of V's errors per configuration, and the verdicts on T4; the configurations run.
fn v_table<'r>(r: &StudyReport<'r>, md: &mut String) -> Vec<&'r StudyRow> {
    for row in r.rows {
        if let Some(why) = &row.skipped {
            let _ = writeln!(
                md,
                "{} does not fit: {} |||||||",
                row.lead(),
                why.replace('|', "/").lines().next().unwrap_or_default()
            );
            continue;
        }
        let cell = |c: Configuration| {
            row.figures
                .iter()
                .find(|(k, _)| *k == c)
                .map_or("—".into(), |(_, f)| format!("{} ({})", cm(f), f.diverged))
        };
        let _ = writeln!(
            md,
            "{} {} | {} | {} | {} | {} | {} | {} | {} |",
            row.lead(),
            cell(Configuration::T1),
            cell(Configuration::T2),
            cell(Configuration::T3),
            cell(Configuration::T4),
            row.t4_over_best_paired_cm().map_or("—".into(), |d| if row.trials == r.trials {
                with_se(&d)
            } else {
                format!("{} ({} trials)", with_se(&d), row.trials)
            }),
            pct(&row.occluded),
            pct(&row.site_left),
            pct(&row.site_share),
        );
    }
    let run: Vec<&'r StudyRow> = r.rows.iter().filter(|x| x.skipped.is_none()).collect();
    let judged: Vec<(bool, bool)> =
        run.iter().filter_map(|x| x.t4_over_best_paired_cm()).map(|d| over_margin(&d)).collect();
    let worse = judged.iter().filter(|j| j.0).count();
    let beyond_noise = judged.iter().filter(|j| j.1).count();
    let confirmed = run.iter().filter(|x| x.trials > r.trials).count();
    let _ = writeln!(
        md,
        "\n{} configurations run, {} skipped (the formation does not fit the site), {confirmed} of them on {} \
         trials; T4 more than {MARGIN_CM} cm worse than the best of T1–T3 in {worse}, and by more than two \
         standard errors beyond that in {beyond_noise}.",
        run.len(),
        r.rows.len() - run.len(),
        r.confirm_trials,
    );
    run
}

/// The table of the worst-placed robot's errors, and the verdict on T4.
fn worst_robot_table(run: &[&StudyRow], md: &mut String) {
    let _ = writeln!(
        md,
        "\n## The worst-placed robot\n\n\
         V's error is the mean of the robots' errors: errors of opposite sign cancel in it, and a robot whose \
         own estimate drifts counts only 1/N. Here, per trial, the 2D RMSE of the robot each configuration \
         placed worst (where it told that robot it stands), cm, mean ± SD over trials. Δ = T4 − min(T1, T2, T3).\n\n\
         | scenario | motion | robots | spacing m | T1 | T2 | T3 | T4 | Δ cm | T1 / T4 |\n\
         |---|---|---|---|---|---|---|---|---|---|"
    );
    for row in run {
        let cell = |c: Configuration| {
            row.figures
                .iter()
                .find(|(k, _)| *k == c)
                .and_then(|(_, f)| f.worst_robot)
                .map_or("—".into(), |m| format!("{:.2} ± {:.2}", 100.0 * m.mean, 100.0 * m.sd))
        };
        let worst = |c| row.mean_cm(c, |f| f.worst_robot);
        let ratio = match (worst(Configuration::T1), worst(Configuration::T4)) {
            (Some(a), Some(b)) if b > 0.0 => format!("{:.2}", a / b),
            _ => "—".into(),
        };
        let _ = writeln!(
            md,
            "{} {} | {} | {} | {} | {} | {ratio} |",
            row.lead(),
            cell(Configuration::T1),
            cell(Configuration::T2),
            cell(Configuration::T3),
            cell(Configuration::T4),
            row.t4_worst_over_best_cm().map_or("—".into(), |d| format!("{d:+.2}")),
        );
    }
    let worse = run.iter().filter(|x| x.t4_worst_over_best_cm().is_some_and(|d| d > MARGIN_CM)).count();
    let _ = writeln!(
        md,
        "\nFor the worst-placed robot, T4 more than {MARGIN_CM} cm worse than the best of T1–T3 in {worse}."
    );
}
