//! Tests of the localisation benchmark's counts, scores and report.

use super::*;
use IntegrityState::{Lost, Tracking, Uncertain};

const ON_ERROR: PoseError = PoseError { m: 0.1, rad: 0.02 };
const ON: Option<PoseError> = Some(ON_ERROR);
const OFF: Option<PoseError> = Some(PoseError { m: 2.0, rad: 0.02 });

#[test]
fn counts_tell_detected_losses_from_false_alarms_and_driving_off() {
    let (on, off) = (ON, OFF);
    let scans = [
        (on, Tracking),
        (on, Tracking),
        (on, Tracking),
        // A loss of four scans, reported lost at its second: detected; two of its scans
        // reported tracking (a server would drive on them).
        (off, Tracking),
        (off, Lost),
        (off, Lost),
        (off, Tracking),
        (on, Uncertain),
        // A brief excursion reported tracking throughout.
        (off, Tracking),
        (on, Tracking),
        (on, Tracking),
        (on, Tracking),
        // Lost while on, after three on scans: a false alarm.
        (on, Lost),
        (None, Lost),
    ];
    let c = integrity_counts(&scans, 7);
    assert_eq!((c.losses, c.detected, c.recovered), (1, 1, 1));
    assert_eq!(c.excursions, 1);
    assert_eq!(c.false_lost, 1);
    assert_eq!(c.uncertain_on, 1);
    assert_eq!(c.lost_on, 1);
    assert_eq!(c.on, 8);
    assert_eq!(c.tracking_off, 3);
    assert_eq!(c.reseeds, 7);
}

/// An estimate within 0.5 m of the robot but turned by more than 10° is off as one metres away
/// is: a filter that reports `lost` there is not a false alarm, and one that reports `tracking`
/// there is tracking while off.
#[test]
fn an_estimate_facing_the_wrong_way_is_off() {
    let turned_error = PoseError { m: 0.2, rad: 120f64.to_radians() };
    assert!(turned_error.off() && !ON_ERROR.off());
    let turned = Some(turned_error);
    assert!(!PoseError { m: 0.5, rad: 10f64.to_radians() - 1e-9 }.off());
    assert!(PoseError { m: 0.5, rad: 10f64.to_radians() + 1e-6 }.off());
    let scans = [
        (ON, Tracking),
        (ON, Tracking),
        (ON, Tracking),
        (turned, Tracking),
        (turned, Lost),
        (turned, Lost),
        (ON, Lost),
    ];
    let c = integrity_counts(&scans, 0);
    assert_eq!((c.false_lost, c.losses, c.detected, c.tracking_off, c.on), (0, 1, 1, 1, 4));
}

/// A percentile is the sorted sample at its rank, rounded; NaN for none.
#[test]
fn percentiles_take_the_rounded_rank() {
    let v = [1.0, 2.0, 3.0, 4.0];
    assert_eq!(percentile(&v, 0.5), 3.0);
    assert_eq!(percentile(&v, 0.05), 1.0);
    assert_eq!(percentile(&v, 0.95), 4.0);
    assert!(percentile(&[], 0.5).is_nan());
}

/// Without logs the report is its tables' headers, and a skipped log says why.
#[test]
fn the_report_heads_its_tables_and_names_skipped_logs() {
    let r = Report { seeds: vec![1, 2], logs: Vec::new(), skipped: vec![("b".into(), "no odometry".into())] };
    let md = markdown(&r);
    assert!(md.starts_with("AMCL on recorded logs against their references (seeds [1, 2];"), "{md}");
    assert!(
        md.contains("\n| log | run | RMSE | P95 | max | heading RMSE (°) | off (%) | from | update ms |")
    );
    assert!(md.contains("\n| log | pose | scans | median | P5 | P95 | uncertain (%) | lost (%) |\n"));
    assert!(md.ends_with("\nb: not run, no odometry.\n"), "{md}");
}

/// A kidnapping's outcome counts from the kidnapping's scan: when the filter stopped reporting
/// `Tracking`, when it reported `Lost`, and when it tracked again within 0.5 m after that; the
/// next kidnapping ends the window.
#[test]
fn kidnap_outcomes_count_doubt_loss_and_return_from_the_kidnapping() {
    let (on, off) = (ON, OFF);
    let states = [
        (on, Tracking),
        (off, Tracking),
        (off, Uncertain),
        (off, Uncertain),
        (off, Lost),
        (on, Lost),
        (on, Tracking),
        // The second kidnapping: absorbed, never doubted.
        (on, Tracking),
        (on, Tracking),
    ];
    let judged: Vec<Judged> = states.iter().enumerate().map(|(i, (e, s))| (i, *e, *s)).collect();
    let jump = amr_core::se2::Se2::new(3.0, 4.0, 0.5);
    let kidnaps =
        [amr_core::amcl::log::Kidnap { scan: 1, jump }, amr_core::amcl::log::Kidnap { scan: 7, jump }];
    let out = kidnap_outcomes(&judged, &kidnaps);
    let first = &out[0];
    assert!(first.carried_off && !first.brief);
    assert_eq!((first.doubted_after, first.lost_after, first.tracked_after), (Some(1), Some(3), Some(5)));
    assert!((first.jump_m - 5.0).abs() < 1e-9);
    // Two scans on before the next kidnapping: not back.
    assert_eq!(first.back_after, None);
    let second = &out[1];
    assert!(!second.carried_off && !second.brief);
    assert_eq!((second.doubted_after, second.lost_after, second.tracked_after), (None, None, None));
    assert_eq!(second.back_after, None, "never off");
}

/// A localiser that reports no state (nav2's) is back when its estimate is within 0.5 m on
/// `DETECT_WITHIN` scans in a row after being off: a brief return does not count.
#[test]
fn back_after_counts_a_lasting_return_whatever_the_state() {
    let (on, off) = (ON, OFF);
    let errors = [on, off, off, off, on, off, on, on, on, off];
    let judged: Vec<Judged> = errors.iter().enumerate().map(|(i, e)| (i + 10, *e, Tracking)).collect();
    let kidnaps = [amr_core::amcl::log::Kidnap { scan: 10, jump: amr_core::se2::Se2::new(2.0, 0.0, 1.0) }];
    let k = kidnap_outcomes(&judged, &kidnaps)[0];
    assert!(k.carried_off);
    assert_eq!((k.back_after, k.doubted_after, k.lost_after, k.tracked_after), (Some(6), None, None, None));
}
