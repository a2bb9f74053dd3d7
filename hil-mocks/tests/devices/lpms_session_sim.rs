#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]
//! The sans-IO LPMS session against the sans-IO mock device, in memory with simulated time
//! (quinn-proto style): deterministic, no sockets, no sleeping.

/// In a module named `lpms` so that `cargo test lpms` selects these tests.
mod lpms {
    use std::time::{Duration, Instant};

    use amr_drivers::lpms::{
        CommandId, DataMode, DeviceError, Event, LinkError, OutputMask, Session, SessionConfig,
    };
    use hil_mocks::lpms::{ConstantYawRate, DeviceSettings, MockDevice, MotionSource};

    const YAW_RATE_RADPS: f64 = -0.4;
    const BIAS_RADPS: f64 = 0.02;
    const NOISE_RADPS: f64 = 0.003;

    struct Sim {
        t0: Instant,
        now: Instant,
        session: Session,
        device: MockDevice,
        motion: ConstantYawRate,
        next_packet_at: Instant,
        /// When true the wire from the device to the host is cut (silence).
        mute: bool,
        log: Vec<Event>,
    }

    impl Sim {
        fn new(config: SessionConfig, seed: u64) -> Self {
            let t0 = Instant::now();
            let device = MockDevice::new(DeviceSettings::default());
            let next_packet_at = t0 + device.stream_period();
            Self {
                t0,
                now: t0,
                session: Session::new(config, t0),
                device,
                motion: ConstantYawRate::new(YAW_RATE_RADPS, BIAS_RADPS, NOISE_RADPS, seed),
                next_packet_at,
                mute: false,
                log: Vec::new(),
            }
        }

        fn deliver(&mut self, bytes: &[u8]) {
            if !self.mute && !bytes.is_empty() {
                self.session.handle_bytes(self.now, bytes);
            }
        }

        /// Moves every pending transmit and event, then advances time to the next timer or packet.
        fn step(&mut self) {
            loop {
                let mut progressed = false;
                while let Some(request) = self.session.poll_transmit() {
                    progressed = true;
                    let t_s = (self.now - self.t0).as_secs_f64();
                    let motion = &mut self.motion;
                    let reply = self.device.handle_bytes(&request, &mut || motion.motion_at(t_s));
                    self.deliver(&reply);
                }
                while let Some(e) = self.session.poll_event() {
                    progressed = true;
                    if e == Event::OpenLink {
                        self.device.reset_link();
                        self.session.link_up(self.now);
                    }
                    self.log.push(e);
                }
                if !progressed {
                    break;
                }
            }
            let timer = self.session.poll_timeout();
            let packet = self.device.is_streaming().then_some(self.next_packet_at);
            let next = [timer, packet].into_iter().flatten().min().unwrap();
            self.now = self.now.max(next);
            if packet == Some(next) {
                self.next_packet_at += self.device.stream_period();
                let m = self.motion.motion_at((self.now - self.t0).as_secs_f64());
                let bytes = self.device.next_data_packet(&m);
                self.deliver(&bytes);
            }
            if timer.is_some_and(|t| t <= self.now) {
                self.session.handle_timeout(self.now);
            }
        }

        /// Steps until `done` holds, at most `max_steps` times.
        fn run_until(&mut self, max_steps: usize, mut done: impl FnMut(&Self) -> bool) {
            for _ in 0..max_steps {
                if done(self) {
                    return;
                }
                self.step();
            }
            panic!("not done after {max_steps} steps; log tail: {:?}", self.events_without_samples());
        }

        fn samples(&self) -> Vec<&amr_drivers::lpms::SensorData> {
            self.log
                .iter()
                .filter_map(|e| match e {
                    Event::Sample(s) => Some(s),
                    _ => None,
                })
                .collect()
        }

        fn events_without_samples(&self) -> Vec<&Event> {
            self.log.iter().filter(|e| !matches!(e, Event::Sample(_))).collect()
        }
    }

    fn config(mode: DataMode, hz: u32) -> SessionConfig {
        SessionConfig {
            stream_hz: hz,
            data_mode: mode,
            outputs: OutputMask::ALL,
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_millis(800),
            ..SessionConfig::default()
        }
    }

    #[test]
    fn both_data_modes_stream_every_packet_with_the_motion_sources_values() {
        for (mode, hz) in [(DataMode::Float32, 100), (DataMode::Int16, 400), (DataMode::Float32, 25)] {
            let mut sim = Sim::new(config(mode, hz), 3);
            sim.run_until(100_000, |s| s.samples().len() >= 2000);
            let ready = sim.log.iter().find_map(|e| match e {
                Event::Ready(i) => Some(i.clone()),
                _ => None,
            });
            let info = ready.unwrap();
            assert_eq!((info.config.stream_hz(), info.config.data_mode()), (hz, mode));
            let step = 400 / hz;
            let samples = sim.samples();
            for pair in samples.windows(2) {
                assert_eq!(pair[1].timestamp_ticks.wrapping_sub(pair[0].timestamp_ticks), step);
            }
            // The mean gyro z over 2000 samples is the true rate plus the bias (noise averages out).
            let mean = samples.iter().map(|s| f64::from(s.gyro_radps.unwrap()[2])).sum::<f64>()
                / samples.len() as f64;
            assert!((mean - (YAW_RATE_RADPS + BIAS_RADPS)).abs() < 0.001, "{mode:?}: mean gyro z {mean}");
            for s in &samples {
                let q = s.quaternion_wxyz.unwrap();
                let yaw_q = 2.0 * f64::from(q[3]).atan2(f64::from(q[0]));
                let yaw_e = f64::from(s.euler_rad.unwrap()[2]);
                let d = (yaw_q - yaw_e + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                    - std::f64::consts::PI;
                assert!(d.abs() < 1e-3, "quaternion and Euler yaw disagree by {d}");
                assert!((s.acc_g.unwrap()[2] - 1.0).abs() < 1e-3);
            }
            assert_eq!(sim.session.stats().protocol_errors, 0);
            assert_eq!(sim.session.stats().link_downs, 0);
        }
    }

    #[test]
    fn the_same_seed_gives_the_same_record() {
        let record = |seed| {
            let mut sim = Sim::new(config(DataMode::Int16, 100), seed);
            sim.run_until(10_000, |s| s.samples().len() >= 300);
            sim.samples().into_iter().cloned().collect::<Vec<_>>()
        };
        assert_eq!(record(11), record(11));
        assert_ne!(record(11), record(12));
    }

    #[test]
    fn a_nack_gives_an_exact_event_log_and_start_up_completes_on_the_same_link() {
        let mut sim = Sim::new(config(DataMode::Float32, 100), 1);
        sim.device.faults_mut().nack.push((CommandId::SetTransmitData, 2));
        sim.run_until(10_000, |s| !s.samples().is_empty());
        let log: Vec<String> = sim
            .events_without_samples()
            .iter()
            .map(|e| match e {
                Event::Ready(_) => "Ready".to_string(),
                other => format!("{other:?}"),
            })
            .collect();
        let nack =
            format!("{:?}", Event::DeviceError(DeviceError::Nack { command: CommandId::SetTransmitData }));
        assert_eq!(log, vec!["OpenLink".to_string(), nack.clone(), nack, "Ready".to_string()]);
        // Two backoffs (100 ms, 200 ms) passed on the same link.
        assert!(sim.now - sim.t0 >= Duration::from_millis(300));
    }

    #[test]
    fn lost_replies_are_retried_and_silence_takes_the_link_down_then_it_recovers() {
        let mut sim = Sim::new(config(DataMode::Float32, 100), 1);
        sim.device.faults_mut().drop_replies = 3;
        sim.run_until(10_000, |s| !s.samples().is_empty());
        let gotos =
            sim.device.stats().commands.iter().take_while(|c| **c == CommandId::GotoCommandMode).count();
        assert_eq!(gotos, 4, "three lost replies, the fourth attempt succeeds");
        assert_eq!(sim.session.stats().link_downs, 0);

        sim.mute = true;
        sim.run_until(10_000, |s| s.log.iter().any(|e| matches!(e, Event::LinkDown(_))));
        assert!(matches!(sim.log.last(), Some(Event::LinkDown(LinkError::DataTimeout { .. }))));
        let samples_before = sim.samples().len();
        // Silent through several reopen cycles; then the wire works again.
        sim.run_until(100_000, |s| s.session.stats().link_downs >= 3);
        sim.mute = false;
        sim.run_until(100_000, |s| s.samples().len() > samples_before + 10);
        assert_eq!(sim.session.stats().ready, 2);
        let downs: Vec<&Event> = sim.log.iter().filter(|e| matches!(e, Event::LinkDown(_))).collect();
        assert!(matches!(
            downs[1],
            Event::LinkDown(LinkError::ReplyTimeout { command: CommandId::GotoCommandMode, .. })
        ));
    }
}
