//! Tests of the safety layer: arming, limits, watchdog, drive losses, the estop latch, invariants.

use super::*;

const P: SafetyParams = SafetyParams {
    max_speed_mps: 0.22,
    max_yaw_rate_radps: 0.2,
    max_accel_mps2: 0.05,
    stop_decel_mps2: 0.5,
    track_width_m: 0.33,
    command_timeout_s: 0.2,
    period_s: 0.02,
};

fn cmd(seq: u64, stamp_s: f64, v: f64, w: f64) -> Command {
    Command { seq, stamp_s, v_mps: v, w_radps: w }
}

/// Ticks every 20 ms from `t0` for `n` cycles, offering a command before each if `feed`.
fn run(core: &mut SafetyCore, t0: f64, n: u32, feed: Option<(&mut u64, f64, f64)>) -> Vec<WheelCommand> {
    let mut out = Vec::new();
    let mut feed = feed;
    for k in 0..n {
        let t = t0 + f64::from(k) * 0.02;
        if let Some((seq, v, w)) = feed.as_mut() {
            **seq += 1;
            let _ = core.offer(cmd(**seq, t, *v, *w), t);
        }
        out.push(core.tick(t));
    }
    out
}

#[test]
fn starts_disarmed_and_refuses_commands_until_armed() {
    let mut c = SafetyCore::new(P, 0);
    assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::Startup));
    assert_eq!(c.offer(cmd(1, 0.0, 0.1, 0.0), 0.0), Err(Refusal::NotArmed));
    assert_eq!(c.tick(0.0), WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: false });
    assert_eq!(c.arm(1, c.stops(), 0.0, 0.0), Ok(()));
    assert_eq!(c.offer(cmd(1, 0.0, 0.1, 0.0), 0.0), Ok(()));
}

#[test]
fn limits_speed_and_ramps_each_wheel_at_the_acceleration_limit() {
    let mut c = SafetyCore::new(P, 0);
    assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
    let mut seq = 0;
    let out = run(&mut c, 0.0, 400, Some((&mut seq, 5.0, 0.0)));
    // 0.05 m/s² → 0.001 m/s per 20 ms cycle.
    for w in out.windows(2) {
        assert!((w[1].v_mps - w[0].v_mps).abs() <= 0.001 + 1e-12);
    }
    // The first tick is at the arm time (no time has passed), then 1 mm/s per cycle.
    assert_eq!(out[0].v_mps, 0.0);
    assert!((out[10].v_mps - 0.010).abs() < 1e-9, "{}", out[10].v_mps);
    assert!((out.last().map_or(0.0, |o| o.v_mps) - 0.22).abs() < 1e-12, "capped at max speed");
    // A turn on the spot: each wheel ramps at the limit, the yaw rate is capped.
    let mut c = SafetyCore::new(P, 0);
    assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
    let mut seq = 0;
    let out = run(&mut c, 0.0, 400, Some((&mut seq, 0.0, 9.0)));
    let dw = 0.001 / (P.track_width_m / 2.0);
    assert!((out[1].w_radps - dw).abs() < 1e-9);
    assert!((out.last().map_or(0.0, |o| o.w_radps) - 0.2).abs() < 1e-12);
}

#[test]
fn watchdog_ramps_to_zero_and_needs_a_rearm() {
    let mut c = SafetyCore::new(P, 0);
    assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
    let mut seq = 0;
    let out = run(&mut c, 0.0, 300, Some((&mut seq, 0.2, 0.0)));
    let v0 = out.last().map_or(0.0, |o| o.v_mps);
    assert!(v0 > 0.19);
    // Commands stop at t = 5.98; the watchdog fires once 200 ms have passed.
    let after = run(&mut c, 6.0, 400, None);
    assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::Watchdog));
    // It braked at the stop deceleration (0.5 m/s²: 10 mm/s per cycle), not at the motion
    // limit, and reached zero exactly.
    for w in after.windows(2) {
        assert!(w[0].v_mps - w[1].v_mps <= 0.010 + 1e-12);
    }
    assert_eq!(after.last().map(|o| o.v_mps), Some(0.0));
    // Full speed for the first 10 cycles (the timeout), then down: zero 0.2 s / 0.5 m/s² = 0.4 s
    // (20 cycles) after the watchdog.
    assert!((after[8].v_mps - v0).abs() < 1e-12);
    assert!(after[12].v_mps < v0 - 0.015);
    let first_down = after.iter().position(|o| o.v_mps < v0).unwrap_or(usize::MAX);
    let zero = after.iter().position(|o| o.v_mps == 0.0).unwrap_or(usize::MAX);
    assert!(zero.saturating_sub(first_down) <= 20, "braking from cycle {first_down}, zero at {zero}");
    // A command that was queued during the outage (older seq, or stamped long ago) is refused
    // even after the re-arm.
    assert_eq!(c.offer(cmd(seq + 1, 6.0, 0.2, 0.0), 14.0), Err(Refusal::NotArmed));
    assert_eq!(c.arm(seq + 10, c.stops(), 14.0, 14.0), Ok(()));
    assert_eq!(c.offer(cmd(seq + 1, 13.9, 0.2, 0.0), 14.0), Err(Refusal::Stale));
    assert_eq!(c.offer(cmd(seq + 10, 13.0, 0.2, 0.0), 14.0), Err(Refusal::Expired));
    assert_eq!(c.offer(cmd(seq + 11, 14.0, 0.2, 0.0), 14.0), Ok(()));
    // Replays and reordering are refused.
    assert_eq!(c.offer(cmd(seq + 11, 14.0, 0.2, 0.0), 14.0), Err(Refusal::Stale));
    assert_eq!(c.offer(cmd(seq + 10, 14.0, 0.2, 0.0), 14.0), Err(Refusal::Stale));
    assert_eq!(c.offer(cmd(seq + 12, 14.0, f64::NAN, 0.0), 14.0), Err(Refusal::NotFinite));
}

#[test]
fn slowing_down_while_armed_keeps_the_comfort_limit_a_disarm_brakes_at_the_stop_rate() {
    let mut c = SafetyCore::new(P, 0);
    assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
    let mut seq = 0;
    let out = run(&mut c, 0.0, 300, Some((&mut seq, 0.2, 0.0)));
    let v0 = out.last().map_or(0.0, |o| o.v_mps);
    // Commanded down to 0.1 m/s: 1 mm/s per cycle.
    let down = run(&mut c, 6.0, 10, Some((&mut seq, 0.1, 0.0)));
    assert!((down[9].v_mps - (v0 - 0.010)).abs() < 1e-9, "{} {v0}", down[9].v_mps);
    // A disarm: 10 mm/s per cycle to zero.
    c.disarm(DisarmReason::Requested);
    let stop = run(&mut c, 6.2, 30, None);
    let v1 = down[9].v_mps;
    assert!((stop[0].v_mps - (v1 - 0.010)).abs() < 1e-9, "{} {v1}", stop[0].v_mps);
    let zero_at = stop.iter().position(|o| o.v_mps == 0.0).unwrap_or(usize::MAX);
    assert_eq!(zero_at + 1, (v1 / 0.010).round() as usize, "{v1}");
}

#[test]
fn an_armed_robot_that_never_hears_a_command_stops_at_the_timeout() {
    let mut c = SafetyCore::new(P, 0);
    assert_eq!(c.arm(0, c.stops(), 1.0, 1.0), Ok(()));
    c.tick(1.0);
    c.tick(1.19);
    assert_eq!(c.state(), SafetyState::Armed);
    c.tick(1.21);
    assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::Watchdog));
}

#[test]
fn a_lost_drive_halts_the_output_so_nothing_moves_when_it_returns() {
    let mut c = SafetyCore::new(P, 0);
    assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
    let mut seq = 0;
    run(&mut c, 0.0, 300, Some((&mut seq, 0.2, 0.1)));
    assert!(c.output().0 > 0.19);
    c.halt(DisarmReason::DeviceLost);
    assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::DeviceLost));
    // From the next cycle on, exactly zero (not a ramp from 0.2 m/s).
    assert_eq!(c.tick(6.02), WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: false });
    assert_eq!(c.offer(cmd(seq + 1, 6.02, 0.2, 0.0), 6.02), Err(Refusal::NotArmed));
    // A latched e-stop stays one.
    c.estop();
    c.halt(DisarmReason::DeviceLost);
    assert_eq!(c.state(), SafetyState::EStop);
}

#[test]
fn only_an_arm_that_knows_the_last_stop_and_is_fresh_starts_the_robot() {
    // Started after 6 stops (a restart): an arm that carries the count from before the start
    // (queued while this core's actor was being restarted, or sent to the robot's previous
    // run) is refused.
    let mut c = SafetyCore::new(P, 6);
    assert_eq!(c.stops(), 7, "a start is a stop");
    assert_eq!(c.arm(1, 6, 10.0, 10.01), Err(ArmRefusal::BeforeStop));
    // One stamped more than the command timeout before or after this clock, or not finite, is
    // refused whatever it carries.
    assert_eq!(c.arm(1, 7, 10.05, 10.3), Err(ArmRefusal::Expired));
    assert_eq!(c.arm(1, 7, 10.55, 10.3), Err(ArmRefusal::Expired), "from the future");
    assert_eq!(c.arm(1, 7, f64::NAN, 10.3), Err(ArmRefusal::Expired));
    assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::Startup));
    assert_eq!(c.arm(1, 7, 10.25, 10.3), Ok(()));
    let mut seq = 0;
    run(&mut c, 10.3, 100, Some((&mut seq, 0.1, 0.0)));
    // The server's clock runs 2 s ahead and the link is slow. It sends an arm (stamped 14.49 on
    // its clock, 12.49 on the robot's); a drive faults at 12.5 (robot clock); the arm arrives
    // at 12.51. Comparing stamps, it looked newer than the fault (and only the future check
    // refuses it); the counter refuses it whatever the clocks say.
    c.halt(DisarmReason::DeviceLost);
    assert_eq!(c.stops(), 8);
    assert_eq!(c.arm(seq + 1, 7, 12.51, 12.51), Err(ArmRefusal::BeforeStop), "with synchronised clocks");
    assert_eq!(c.arm(seq + 1, 7, 14.49, 12.51), Err(ArmRefusal::Expired), "with the server 2 s ahead");
    let out = run(&mut c, 12.52, 20, Some((&mut seq, 0.1, 0.0)));
    assert!(out.iter().all(|o| o.v_mps == 0.0 && o.w_radps == 0.0));
    // A disarm of any cause is a stop too: a reordered arm from before it is refused.
    assert_eq!(c.arm(seq + 1, 8, 12.95, 12.96), Ok(()));
    c.disarm(DisarmReason::Requested);
    assert_eq!(c.arm(seq + 1, 8, 13.01, 13.01), Err(ArmRefusal::BeforeStop));
    assert_eq!(c.arm(seq + 1, 9, 13.01, 13.02), Ok(()));
    // An e-stop's reset is one: the arm must know of the reset.
    c.estop();
    assert_eq!(c.arm(seq + 1, c.stops(), 14.1, 14.1), Err(ArmRefusal::Latched));
    let at_estop = c.stops();
    assert!(c.reset_estop());
    assert_eq!(c.arm(seq + 1, at_estop, 14.21, 14.21), Err(ArmRefusal::BeforeStop));
    assert_eq!(c.arm(seq + 1, at_estop + 1, 14.21, 14.22), Ok(()));
    // A fault is reset only by `reset_fault` (on the robot), back to the e-stop if one holds.
    c.fault();
    assert!(!c.reset_estop());
    assert!(c.reset_fault(true));
    assert_eq!(c.state(), SafetyState::EStop);
    c.fault();
    assert!(c.reset_fault(false));
    assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::FaultReset));
    assert_eq!(c.arm(seq + 1, c.stops(), 15.0, 15.0), Ok(()));
}

#[test]
fn a_faulted_or_rebooted_drive_halts_other_devices_do_not() {
    let report = |device, health| HealthReport { device, health, detail: String::new() };
    assert!(halts(&report(Device::Drives, Health::Degraded)));
    assert!(halts(&report(Device::Drives, Health::Lost)));
    assert!(halts(&report(Device::Drives, Health::Fault)));
    assert!(halts(&report(Device::CanBus, Health::Lost)));
    assert!(!halts(&report(Device::Drives, Health::Ok)));
    assert!(halts(&report(Device::Drives, Health::Starting)), "reconfigured after a reset");
    assert!(halts(&report(Device::CanBus, Health::Starting)));
    assert!(!halts(&report(Device::CanBus, Health::Degraded)));
    assert!(!halts(&report(Device::Lidar, Health::Lost)));
    assert!(!halts(&report(Device::Imu, Health::Fault)));
}

#[test]
fn estop_latches_until_reset_and_a_fault_never_clears() {
    let mut c = SafetyCore::new(P, 0);
    assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
    let mut seq = 0;
    run(&mut c, 0.0, 100, Some((&mut seq, 0.2, 0.0)));
    c.estop();
    assert_eq!(c.output(), (0.0, 0.0));
    assert_eq!(c.tick(2.0), WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: true });
    assert_eq!(c.arm(1000, c.stops(), 2.0, 2.0), Err(ArmRefusal::Latched), "arming does not clear an e-stop");
    assert_eq!(c.offer(cmd(1001, 2.0, 0.1, 0.0), 2.0), Err(Refusal::NotArmed));
    assert!(c.reset_estop());
    assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::EStopReset));
    assert!(!c.tick(2.02).quick_stop);
    assert_eq!(c.arm(1000, c.stops(), 2.04, 2.04), Ok(()));
    c.fault();
    assert!(!c.reset_estop());
    assert_eq!(c.arm(2000, c.stops(), 3.0, 3.0), Err(ArmRefusal::Latched));
    c.estop();
    assert_eq!(c.state(), SafetyState::Fault);
    assert!(c.tick(3.0).quick_stop);
}

#[test]
fn the_harness_applies_inputs_and_latches_as_the_actor_does() {
    use crate::config::{ConfigSource, load};
    let config = load(&ConfigSource::Embedded).unwrap();
    let robot = config.robots.iter().find(|r| r.id.as_str() == "robot-a").unwrap();
    let mut h = SafetyHarness::new(robot);
    assert_eq!((h.state(), h.stops()), (SafetyState::Disarmed(DisarmReason::Startup), 1));
    let link = |d: Downlink| SafetyInput::Link(d);
    assert!(!h.apply(link(Downlink::Arm { seq: 1, stops: 0, stamp_s: 10.0 }), 10.0).taken);
    assert!(h.apply(link(Downlink::Arm { seq: 1, stops: 1, stamp_s: 10.0 }), 10.0).taken);
    assert!(h.apply(link(Downlink::Command(cmd(1, 10.0, 0.2, 0.0))), 10.0).taken);
    assert!(h.tick(10.02).v_mps > 0.0);
    // A network e-stop stops at once; with a local one too, a network reset clears only its own.
    let stop = h.apply(link(Downlink::EStop), 10.03);
    assert_eq!(stop.output, Some(WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: true }));
    assert!(h.apply(SafetyInput::Control(SafetyControl::EStop), 10.04).taken);
    assert!(!h.apply(link(Downlink::ResetEStop), 10.05).taken);
    assert_eq!(h.state(), SafetyState::EStop);
    assert!(h.apply(SafetyInput::Control(SafetyControl::ResetEStop), 10.06).taken);
    assert_eq!(h.state(), SafetyState::Disarmed(DisarmReason::EStopReset));
    // An escalation faults before the next cycle; only a reset on the robot clears it, and a
    // restart keeps it.
    h.escalate();
    assert!(h.tick(10.08).quick_stop);
    assert_eq!(h.state(), SafetyState::Fault);
    assert!(!h.apply(link(Downlink::ResetEStop), 10.1).taken);
    assert!(h.restart(10.12).is_some_and(|o| o.quick_stop));
    assert_eq!(h.state(), SafetyState::Fault);
    assert!(h.apply(SafetyInput::Control(SafetyControl::ResetEStop), 10.14).taken);
    assert_eq!(h.state(), SafetyState::Disarmed(DisarmReason::FaultReset));
    assert_eq!(h.restart(10.16), None);
    // A pressed e-stop input holds until released, whatever the resets.
    assert!(h.estop_input(true, 10.2).taken);
    assert!(!h.apply(SafetyInput::Control(SafetyControl::ResetEStop), 10.22).taken);
    assert!(!h.estop_input(false, 10.24).taken);
    assert!(h.apply(SafetyInput::Control(SafetyControl::ResetEStop), 10.26).taken);
    // A lost drive halts; a lidar does not.
    let report = |device, health| HealthReport { device, health, detail: String::new() };
    assert!(h.apply(SafetyInput::Health(report(Device::Drives, Health::Lost)), 10.3).taken);
    assert!(!h.apply(SafetyInput::Health(report(Device::Lidar, Health::Lost)), 10.3).taken);
    assert_eq!(h.state(), SafetyState::Disarmed(DisarmReason::DeviceLost));
}

/// One input to the safety layer, as the state-machine property test draws them.
#[derive(Debug, Clone)]
enum Op {
    /// A command `ahead` numbers after the last one sent (0: a replay), stamped `age_s` ago.
    Command {
        ahead: u64,
        age_s: f64,
        v: f64,
        w: f64,
    },
    /// An arm whose floor is `ahead` numbers after the last command sent, stamped `age_s` ago
    /// (negative: ahead of the robot's clock), carrying a stop counter `behind` stops old.
    Arm {
        ahead: u64,
        age_s: f64,
        behind: u64,
    },
    Disarm,
    /// The drives lost or faulted.
    Halt,
    EStop,
    ResetEStop,
    Fault,
    /// A reset of a fault on the robot (`held`: an e-stop still holds).
    ResetFault {
        held: bool,
    },
    /// The safety actor restarted: a new core.
    Restart,
    Tick {
        dt_s: f64,
    },
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        6 => (0u64..3, 0.0..0.4f64, -1.0..1.0f64, -1.0..1.0f64)
            .prop_map(|(ahead, age_s, v, w)| Op::Command { ahead, age_s, v, w }),
        3 => (0u64..3, -0.3..0.3f64, prop_oneof![3 => Just(0u64), 1 => 1u64..3])
            .prop_map(|(ahead, age_s, behind)| Op::Arm { ahead, age_s, behind }),
        1 => Just(Op::Disarm),
        1 => Just(Op::Halt),
        1 => Just(Op::EStop),
        1 => Just(Op::ResetEStop),
        1 => Just(Op::Fault),
        1 => any::<bool>().prop_map(|held| Op::ResetFault { held }),
        1 => Just(Op::Restart),
        12 => (0.0..0.1f64).prop_map(|dt_s| Op::Tick { dt_s }),
    ]
}

fn wheels((v, w): (f64, f64)) -> [f64; 2] {
    [v - w * P.track_width_m / 2.0, v + w * P.track_width_m / 2.0]
}

use proptest::prelude::*;

proptest! {
    #![proptest_config(ProptestConfig { cases: 500, ..ProptestConfig::default() })]

    /// Whatever the sequence of commands, arms, e-stops, faults, restarts and time steps, the
    /// output stays within the limits, changes no faster than the ramp of the state it is in,
    /// never grows while the robot is not armed, is zero in e-stop and fault, and is zero once
    /// the watchdog and a stop have had their time after the last fresh command; the stop
    /// counter counts every stop, and only an arm carrying it starts the robot.
    #[test]
    fn safety_core_invariants_hold_for_any_input_sequence(ops in proptest::collection::vec(op(), 1..200)) {
        let mut core = SafetyCore::new(P, 0);
        let mut now = 0.0f64;
        // The stops counted (start, disarm, halt, e-stop or its reset, fault or its reset,
        // restart), and whether an arm that knew the last one was accepted since.
        let mut stops = 1u64;
        let mut armed_since_stop = false;
        let mut sent = 0u64;
        // When the robot last had something that lets it move: an accepted arm or command.
        let mut fresh_at = f64::NEG_INFINITY;
        let mut prev = (0.0f64, 0.0f64);
        // Whether the output may jump this cycle (a quick stop or dropped drives set it to zero).
        let mut jumped = false;
        for op in ops {
            let armed_before = core.state() == SafetyState::Armed;
            match op {
                Op::Command { ahead, age_s, v, w } => {
                    sent += ahead;
                    let c = cmd(sent, now - age_s, v, w);
                    if core.offer(c, now).is_ok() {
                        prop_assert!(armed_before, "a command was accepted while not armed");
                        fresh_at = now;
                    }
                }
                Op::Arm { ahead, age_s, behind } => {
                    let was = core.state();
                    let stamp = now - age_s;
                    let ok = core.arm(sent + ahead, stops.wrapping_sub(behind), stamp, now).is_ok();
                    let may = matches!(was, SafetyState::Armed | SafetyState::Disarmed(_))
                        && age_s.abs() <= P.command_timeout_s
                        && behind == 0;
                    prop_assert_eq!(ok, may);
                    if ok && was != SafetyState::Armed {
                        fresh_at = now;
                        armed_since_stop = true;
                    }
                }
                Op::Disarm => {
                    core.disarm(DisarmReason::Requested);
                    stops += 1;
                    armed_since_stop = false;
                }
                Op::Halt => {
                    core.halt(DisarmReason::DeviceLost);
                    stops += 1;
                    armed_since_stop = false;
                    jumped = true;
                }
                Op::EStop => {
                    core.estop();
                    stops += 1;
                    armed_since_stop = false;
                    jumped = true;
                }
                Op::ResetEStop => {
                    let was = core.state();
                    prop_assert_eq!(core.reset_estop(), was == SafetyState::EStop);
                    if was == SafetyState::EStop {
                        stops += 1;
                    }
                }
                Op::Fault => {
                    core.fault();
                    stops += 1;
                    armed_since_stop = false;
                    jumped = true;
                }
                Op::ResetFault { held } => {
                    let was = core.state();
                    prop_assert_eq!(core.reset_fault(held), was == SafetyState::Fault);
                    if was == SafetyState::Fault {
                        stops += 1;
                        let want = if held { SafetyState::EStop } else { SafetyState::Disarmed(DisarmReason::FaultReset) };
                        prop_assert_eq!(core.state(), want);
                    }
                }
                Op::Restart => {
                    // A new core from the counter the ports keep.
                    core = SafetyCore::new(P, core.stops());
                    stops += 1;
                    armed_since_stop = false;
                    jumped = true;
                }
                Op::Tick { dt_s } => {
                    now += dt_s;
                    let state_before = core.state();
                    let out = core.tick(now);
                    if state_before == SafetyState::Armed && core.state() != SafetyState::Armed {
                        // The watchdog disarmed: a stop event.
                        stops += 1;
                    }
                    let (v, w) = (out.v_mps, out.w_radps);
                    prop_assert!(v.abs() <= P.max_speed_mps + 1e-9 && w.abs() <= P.max_yaw_rate_radps + 1e-9, "{v} {w}");
                    if matches!(core.state(), SafetyState::EStop | SafetyState::Fault) {
                        prop_assert!(out.quick_stop && v == 0.0 && w == 0.0);
                    }
                    let (a, b) = (wheels(prev), wheels((v, w)));
                    if !jumped {
                        // The tick clamps dt to ten periods.
                        let dt = dt_s.min(10.0 * P.period_s);
                        let rate = if core.state() == SafetyState::Armed { P.max_accel_mps2 } else { P.stop_decel_mps2 };
                        for k in 0..2 {
                            prop_assert!((b[k] - a[k]).abs() <= rate * dt + 1e-9, "wheel {k}: {} -> {} in {dt} s", a[k], b[k]);
                        }
                    }
                    if state_before != SafetyState::Armed && core.state() != SafetyState::Armed {
                        for k in 0..2 {
                            prop_assert!(b[k].abs() <= a[k].abs() + 1e-9, "wheel {k} sped up while not armed: {} -> {}", a[k], b[k]);
                        }
                    }
                    // Watchdog, then a stop from at most the top wheel speed, then one cycle.
                    let top_wheel = P.max_speed_mps + P.max_yaw_rate_radps * P.track_width_m / 2.0;
                    if now - fresh_at > P.command_timeout_s + top_wheel / P.stop_decel_mps2 + 11.0 * P.period_s {
                        prop_assert!(v == 0.0 && w == 0.0, "still moving {v} {w} {} s after the last fresh command", now - fresh_at);
                    }
                    // No motion after a fault, e-stop, halt or restart without a newer re-arm
                    // (a disarm or the watchdog only ramps down what was moving).
                    if !armed_since_stop && core.state() != SafetyState::Armed {
                        for k in 0..2 {
                            prop_assert!(b[k].abs() <= a[k].abs() + 1e-9, "wheel {k} sped up with no arm since the stop");
                        }
                    }
                    if jumped && !armed_since_stop {
                        prop_assert!(v == 0.0 && w == 0.0, "moving right after a halt, e-stop, fault or restart: {v} {w}");
                    }
                    prev = (v, w);
                    jumped = false;
                }
            }
            prop_assert_eq!(core.stops(), stops, "the stop counter");
        }
    }
}
