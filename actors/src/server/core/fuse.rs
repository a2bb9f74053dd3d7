//! One fused update of the server core, as named steps: what every configuration shares of a set
//! of scans (each robot's own tracking estimate, the packets, where each robot stands by the own
//! estimates), then per configuration: prepare its pipeline, run it, frame the result, start V's
//! filter where the robots are, localise V, and the estimate with its integrity.

use amr_core::amcl::{Amcl, IntegrityState, UpdateOutcome};
use amr_core::config::AmclMotion;
use amr_core::se2::Se2;
use amr_core::vamr::frame::PacketTimes;
use amr_core::vamr::pipeline::{FusedUpdate, RobotPacket, Source, UpdateError};
use amr_msgs::{Anchored, Estimate, EstimateIntegrity, EstimateSource, FusedFrame, StageTimes};

use super::{
    Channel, Fusion, Held, INITIAL_STD_XY_M, INITIAL_STD_YAW_RAD, Lap, ServerCore, Step, disagreeing,
    mean_pose, observer, true_v_in_first,
};

/// What every configuration's update of one set shares.
struct SetView<'s> {
    set: &'s [Held],
    /// Each robot's own estimate at its scan of the set, when its filter is tracking.
    own: Vec<Option<Se2>>,
    /// Where each robot stands in its observer's frame by the two robots' own tracking estimates.
    relative: Vec<Option<Se2>>,
    /// The first robot's scan: the set's stamp and odometry.
    first: f64,
    first_odom: Se2,
    oldest: f64,
    /// The oracle's V in robot 0's frame (evaluations only).
    true_v_in_reference: Option<Se2>,
    now_s: f64,
}

impl ServerCore {
    pub(super) fn fuse(&mut self, set: &[Held], now_s: f64, lap: &mut dyn FnMut(Lap), step: &mut Step) {
        for (i, h) in set.iter().enumerate() {
            self.fused_stamp[i] = h.stamp_s;
        }
        // The channels are updated one by one against the rest of the core, which they only read.
        let mut channels = std::mem::take(&mut self.channels);
        let own = self.own_estimates(set);
        let oldest = set.iter().map(|h| h.stamp_s).fold(f64::INFINITY, f64::min);
        let packets = self.packets(set);
        let (first, first_odom) = set.first().map_or((oldest, Se2::IDENTITY), |h| (h.stamp_s, h.odom));
        let view = SetView {
            set,
            relative: self.relative_by_own(&own),
            own,
            first,
            first_odom,
            oldest,
            true_v_in_reference: self.oracle.odometry.then(|| true_v_in_first(set, &self.members)).flatten(),
            now_s,
        };
        for ch in &mut channels {
            self.fuse_channel(ch, &view, &packets, lap, step);
        }
        self.channels = channels;
        // The teammate masks of the robots' own filters: where a configuration that tracks the
        // robots in each other's scans placed them (T4's frame before T3's).
        let placed =
            [amr_core::config::Configuration::T4, amr_core::config::Configuration::T3].into_iter().find_map(
                |c| step.fusions.iter().find(|f| f.configuration == c).and_then(|f| f.result.as_ref().ok()),
            );
        if let Some(frame) = placed {
            self.placed = Some(super::Placed { robots: frame.robots.clone(), rx_s: now_s });
        }
    }

    /// Each robot's own estimate at its scan of the set, when its filter is tracking.
    fn own_estimates(&self, set: &[Held]) -> Vec<Option<Se2>> {
        set.iter()
            .enumerate()
            .map(|(i, h)| {
                let tracking = self
                    .robot_filters
                    .get(i)
                    .is_some_and(|f| f.integrity_state() == IntegrityState::Tracking);
                self.corrections.get(i).copied().flatten().filter(|_| tracking).map(|c| c * h.odom)
            })
            .collect()
    }

    fn packets<'s>(&'s self, set: &'s [Held]) -> Vec<RobotPacket<'s>> {
        set.iter()
            .zip(&self.members)
            .enumerate()
            .map(|(i, (h, m))| RobotPacket {
                scan: &h.scan,
                times: PacketTimes { stamp_s: h.stamp_s, received_s: h.rx_s },
                lidar_to_base: m.lidar_to_base,
                chassis: &m.chassis,
                weight: m.weight,
                amcl_pose: self.corrections.get(i).copied().flatten().map(|c| c * h.odom),
                truth: h.truth,
                odom: Some(h.odom),
            })
            .collect()
    }

    /// Where each robot stands in its observer's frame by the two robots' own tracking estimates:
    /// where a lost track is looked for again (the slots say where it should be, but a formation
    /// that stopped, coasted or was pushed may stand elsewhere, and holding for a verified V it
    /// would never move back).
    fn relative_by_own(&self, own: &[Option<Se2>]) -> Vec<Option<Se2>> {
        (0..self.members.len())
            .map(|i| {
                let o = observer(&self.members, i);
                if i == 0 {
                    return None;
                }
                Some(own.get(o).copied().flatten()?.inverse() * own.get(i).copied().flatten()?)
            })
            .collect()
    }

    /// One configuration's update of the set.
    fn fuse_channel(
        &self,
        ch: &mut Channel,
        view: &SetView<'_>,
        packets: &[RobotPacket<'_>],
        lap: &mut dyn FnMut(Lap),
        step: &mut Step,
    ) {
        let c = ch.configuration;
        ch.prepare(&view.relative, view.now_s, self.checks.restart_after_ms / 1000.0);
        let result = ch.pipeline.update_with_laps(packets, &mut |stage| lap(Lap::Pipeline(c, stage)));
        if result.is_ok() {
            ch.last_fused_s = Some(view.now_s);
        }
        let u = match result {
            Ok(u) => u,
            Err(e) => {
                let heading_failed = matches!(e, UpdateError::NoHeading { .. });
                step.fusions.push(Fusion {
                    configuration: c,
                    result: Err(e),
                    full_search: false,
                    heading_failed,
                });
                return;
            }
        };
        ch.seq += 1;
        let full_search = u.pairs.iter().any(|p| p.full_search);
        let heading_failed = u.pairs.iter().any(|p| p.heading_source == Source::PreviousHeading);
        let frame = frame_of(ch, &u, view);
        let bases_in_v: Vec<Se2> = frame.robots.iter().map(|(b, _)| *b).collect();
        ch.start_v(&view.own, &bases_in_v, true);
        let v = self.localise_v(ch, &frame, &u, view, step);
        lap(Lap::VirtualAmcl(c));
        if let Some(v) = v {
            step.estimates.push(self.estimate(ch, v, &frame, &bases_in_v, view));
        }
        step.fusions.push(Fusion { configuration: c, result: Ok(frame), full_search, heading_failed });
    }

    /// V by the configuration's filter on the virtual scan (once started), or, in T1, from the
    /// reference robot's own AMCL (the relative poses came from AMCL).
    fn localise_v(
        &self,
        ch: &mut Channel,
        frame: &FusedFrame,
        u: &FusedUpdate,
        view: &SetView<'_>,
        step: &mut Step,
    ) -> Option<Se2> {
        let c = ch.configuration;
        match (&frame.points, ch.filter.as_mut()) {
            (Some(_), Some(_)) if !ch.started => None,
            (Some(points), Some(filter)) => {
                if self.amcl_motion == AmclMotion::Reference {
                    // The reference robot stands where V's odometry was composed from.
                    filter.set_motion_body(view.true_v_in_reference.unwrap_or(u.v_in_reference).inverse());
                }
                let before = filter.integrity_state();
                if matches!(filter.update(frame.v_odom, points, false), UpdateOutcome::Updated { .. }) {
                    step.updated.push(EstimateSource::Fused(c));
                }
                if let Some(now) = filter.integrity().filter(|n| n.state != before) {
                    tracing::info!(
                        configuration = ?c, from = %before, to = %now.state, explained = now.explained,
                        level = now.level, "V's localisation changed state"
                    );
                }
                ch.restart_lost_v(&view.own, &frame.robots, view.now_s);
                ch.filter.as_ref().and_then(|f| f.pose_at(&frame.v_odom))
            }
            _ => self.corrections.first().copied().flatten().map(|c| c * frame.v_odom),
        }
    }

    /// The estimate of V at `v`, each robot anchored by its place in V, with V's integrity (its
    /// filter's, in T1 the reference robot's) and whether the robots' own estimates disagree.
    fn estimate(
        &self,
        ch: &Channel,
        v: Se2,
        frame: &FusedFrame,
        bases_in_v: &[Se2],
        view: &SetView<'_>,
    ) -> Estimate {
        let robots = frame
            .robots
            .iter()
            .map(|(base_in_v, odom)| Some(Anchored { map: v * *base_in_v, odom: *odom, stamp_s: view.first }))
            .collect();
        let judged = match ch.filter.as_ref() {
            Some(f) => f.integrity(),
            None => self.robot_filters.first().and_then(Amcl::integrity),
        };
        let mut integrity = EstimateIntegrity::of(judged);
        integrity.disagrees = disagreeing(v, bases_in_v, &view.own, &self.checks);
        Estimate {
            source: EstimateSource::Fused(ch.configuration),
            stamp_s: view.first,
            v: Some(v),
            robots,
            integrity,
            // V's filter's; T1 has none (V comes from the reference robot's estimate).
            covariance: ch.filter.as_ref().and_then(Amcl::estimate).map(|e| e.covariance),
        }
    }
}

/// V's restarts from the robots' estimates are logged at most this often, s.
const RESTART_LOG_EVERY_S: f64 = 60.0;

impl Channel {
    /// Before the update: each robot's track looked for where the own estimates put it, and, after
    /// a gap in fusion longer than `restart_after_s`, V's filter to start again from the robots'
    /// own estimates (what it carried across the gap on V's odometry alone is not trusted).
    fn prepare(&mut self, relative: &[Option<Se2>], now_s: f64, restart_after_s: f64) {
        for (i, r) in relative.iter().enumerate() {
            if let Some(r) = r {
                self.pipeline.set_expected(i, [r.x, r.y], 0.5);
                self.pipeline.set_expected_heading(i, r.theta);
            }
        }
        if self.last_fused_s.is_some_and(|t| now_s - t > restart_after_s) {
            self.started = false;
            self.last_fused_s = None;
        }
    }

    /// V's filter, lost, starts again where the robots' own tracking estimates put V (none
    /// tracking: it stays lost, and the formation holds). Its virtual scan no longer fits the map
    /// at its estimate, and V is not searched for elsewhere (`virtual_params`).
    fn restart_lost_v(&mut self, own: &[Option<Se2>], robots: &[(Se2, Se2)], now_s: f64) {
        let lost = self.filter.as_ref().is_some_and(|f| f.integrity_state() == IntegrityState::Lost);
        if lost && own.iter().any(Option::is_some) {
            let bases_in_v: Vec<Se2> = robots.iter().map(|(b, _)| *b).collect();
            // A virtual scan that stays poor restarts V every few frames: said once a minute at most.
            let say = self.last_restart_s.is_none_or(|t| now_s - t >= RESTART_LOG_EVERY_S);
            if say {
                tracing::info!(configuration = ?self.configuration, "V's filter lost: it starts again from the robots' own estimates");
                self.last_restart_s = Some(now_s);
            }
            self.started = false;
            self.start_v(own, &bases_in_v, say);
        }
    }

    /// V's filter, not started yet, starts where the robots' own tracking estimates put V (their
    /// mean); none tracking yet: V waits, with no estimate. `say`: log where it starts.
    fn start_v(&mut self, own: &[Option<Se2>], bases_in_v: &[Se2], say: bool) {
        let c = self.configuration;
        if let Some(filter) = self.filter.as_mut().filter(|_| !self.started) {
            let start = mean_pose(own.iter().zip(bases_in_v).filter_map(|(o, b)| o.map(|o| o * b.inverse())));
            if let Some(v0) = start {
                if say {
                    tracing::info!(configuration = ?c, x = v0.x, y = v0.y, theta = v0.theta, "V's filter starts where the robots' own estimates put it");
                }
                filter.init_pose(v0, INITIAL_STD_XY_M, INITIAL_STD_YAW_RAD);
                self.started = true;
            }
        }
    }
}

/// The pipeline's result as the frame the server hands on.
fn frame_of(ch: &Channel, u: &FusedUpdate, view: &SetView<'_>) -> FusedFrame {
    let points =
        u.virtual_scan.as_ref().map(|v| std::sync::Arc::new(v.points.iter().map(|(p, _)| *p).collect()));
    FusedFrame {
        seq: ch.seq,
        configuration: ch.configuration,
        stamp_s: view.first,
        oldest_stamp_s: view.oldest,
        v_odom: view.first_odom * view.true_v_in_reference.unwrap_or(u.v_in_reference),
        points,
        robots: u.bases_in_v.iter().zip(view.set).map(|(b, h)| (*b, h.odom)).collect(),
        times: StageTimes { acquisition_sync_s: view.now_s - view.oldest, ..StageTimes::default() },
    }
}
