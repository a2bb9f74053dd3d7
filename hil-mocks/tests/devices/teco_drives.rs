//! The CANopen master (amr-drivers) against two mock TECO drives (hil-mocks) on the in-process
//! bus with paused tokio time: enable, a velocity profile read back as odometry, a drive fault
//! recovered with the verified sequence, heartbeat loss both ways, a reboot reconfigured before
//! enabling, SDO faults.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

mod teco {
    use std::time::Duration;

    use amr_drivers::canopen::cia402::State402;
    use amr_drivers::canopen::config::BusConfig;
    use amr_drivers::canopen::diff_drive::{
        DiffDrive, DrivesConfig, Geometry, WheelDriveConfig, WheelOdometry,
    };
    use amr_drivers::canopen::frame::Cob;
    use amr_drivers::canopen::master::{CommLossReaction, Master, MasterConfig, MasterEvent};
    use amr_drivers::canopen::pdo;
    use amr_drivers::canopen::sdo::{AbortCode, ObjectAddr, SdoRequest, SdoResult};
    use amr_drivers::canopen::shell::{MasterCommand, MasterHandle, spawn_master};
    use amr_drivers::canopen::transport::in_process::{BusOptions, BusPort, InProcessBus};
    use amr_drivers::canopen::{CanopenError, DeviceError, LinkError};
    use hil_mocks::teco_drive::{DriveHandle, DriveSnapshot, Fault, TecoDrive, TecoDriveConfig, spawn_drive};
    use tokio::time::Instant;

    const LEFT: u8 = 1;
    const RIGHT: u8 = 2;
    const MASTER_CONSUMER_MS: u16 = 300;
    const DRIVE_CONSUMER_MS: u32 = 300;

    pub(crate) fn diff_drive() -> DiffDrive {
        DiffDrive::new(
            DrivesConfig {
                left: WheelDriveConfig { node_id: LEFT, inverted: false },
                right: WheelDriveConfig { node_id: RIGHT, inverted: true },
                encoder_counts_per_rev: 10_000,
                gear_ratio: 20.0,
                velocity_units_per_rps: 10_000.0,
                heartbeat_producer_ms: 100,
                heartbeat_consumer_ms: DRIVE_CONSUMER_MS,
                master_consumer_ms: u32::from(MASTER_CONSUMER_MS),
                comm_loss_reaction: CommLossReaction::QuickStop,
                enable_timeout_ms: 2000,
                mode_confirm_attempts: 5,
                quick_stop_decel_mps2: 2.0,
                // Maps 0x60FD into TPDO2: the mock's inputs travel with its position.
                estop_input_bit: Some(16),
                estop_input_active_low: true,
            },
            Geometry { wheel_radius_m: 0.065, track_width_m: 0.33 },
        )
    }

    pub(crate) fn master_config(dd: &DiffDrive) -> MasterConfig {
        MasterConfig {
            can: BusConfig {
                master_node_id: 127,
                master_heartbeat_ms: 100,
                sync_period_ms: 20,
                sdo_timeout_ms: 500,
                boot_timeout_ms: 5000,
                ..BusConfig::default()
            },
            drives: dd.drive_setups(0.5, 0.5, 1.0),
            enable_timeout_ms: 1000,
            mode_confirm_attempts: 5,
            target_hold_ms: 60_000,
        }
    }

    pub(crate) fn drive_config(node: u8) -> TecoDriveConfig {
        TecoDriveConfig {
            // The left counter starts just below 2³¹ so it wraps while driving forwards.
            initial_position_counts: if node == LEFT { i64::from(i32::MAX) - 20_000 } else { 1000 },
            encoder_noise_counts: 2.0,
            ..TecoDriveConfig::new(node)
        }
    }

    struct Rig {
        dd: DiffDrive,
        drives: Vec<DriveHandle>,
        master: MasterHandle,
        odo: WheelOdometry,
        log: Vec<MasterEvent>,
        /// Hears every frame on the bus.
        sniffer: BusPort,
    }

    impl Rig {
        async fn new() -> Self {
            Self::on(InProcessBus::default()).await
        }

        async fn on(bus: InProcessBus) -> Self {
            let now = Instant::now().into_std();
            let drives = [LEFT, RIGHT]
                .iter()
                .map(|&n| spawn_drive(TecoDrive::new(drive_config(n), now), bus.port()))
                .collect();
            let dd = diff_drive();
            let master = spawn_master(Master::new(master_config(&dd), now), bus.port());
            let sniffer = bus.port();
            Self { dd, drives, master, odo: WheelOdometry::new(), log: Vec::new(), sniffer }
        }

        fn drive(&self, node: u8) -> &DriveHandle {
            self.drives.iter().find(|d| d.node_id == node).unwrap()
        }

        async fn send(&self, cmd: MasterCommand) {
            self.master.commands.send(cmd).await.unwrap();
        }

        /// Handle events (odometry from every cycle) until `pred` holds; returns the events seen.
        async fn until(
            &mut self,
            within: Duration,
            mut pred: impl FnMut(&MasterEvent) -> bool,
        ) -> Vec<MasterEvent> {
            let mut seen = Vec::new();
            let found = tokio::time::timeout(within, async {
                while let Some(ev) = self.master.events.recv().await {
                    if let MasterEvent::Cycle { positions, .. } = &ev {
                        let l = positions.iter().find(|(n, _)| *n == LEFT).map(|p| p.1);
                        let r = positions.iter().find(|(n, _)| *n == RIGHT).map(|p| p.1);
                        if let (Some(l), Some(r)) = (l, r) {
                            self.odo.update(&self.dd, l, r);
                        }
                    }
                    let hit = pred(&ev);
                    seen.push(ev);
                    if hit {
                        return true;
                    }
                }
                false
            })
            .await;
            let errors: Vec<_> = seen.iter().filter(|e| !matches!(e, MasterEvent::Cycle { .. })).collect();
            assert!(matches!(found, Ok(true)), "not seen within {within:?}; events: {errors:?}");
            self.log.extend(seen.iter().filter(|e| !matches!(e, MasterEvent::Cycle { .. })).cloned());
            seen
        }

        /// Run for `d` of (paused) time, handling events.
        async fn run_for(&mut self, d: Duration) {
            let end = Instant::now() + d;
            let _ = tokio::time::timeout_at(end, self.until(d + Duration::from_secs(1), |_| false)).await;
        }

        async fn enable_both(&mut self) {
            self.send(MasterCommand::Enable).await;
            let mut enabled = [false; 2];
            self.until(Duration::from_secs(3), |e| {
                if let MasterEvent::Enabled { node } = e {
                    enabled[usize::from(*node - 1)] = true;
                }
                enabled == [true, true]
            })
            .await;
        }
    }

    async fn wait_drive(
        d: &DriveHandle,
        within: Duration,
        pred: impl FnMut(&DriveSnapshot) -> bool,
    ) -> DriveSnapshot {
        let mut rx = d.snapshot.clone();
        let s =
            tokio::time::timeout(within, rx.wait_for(pred)).await.expect("drive condition in time").unwrap();
        *s
    }

    #[tokio::test(start_paused = true)]
    async fn teco_enable_profile_and_odometry_in_process() {
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        for n in [LEFT, RIGHT] {
            let s = rig.drive(n).now();
            assert_eq!((s.state, s.mode_display), (State402::OperationEnabled, 3));
            assert_eq!(s.master_consumer, (127 << 16) | u32::from(MASTER_CONSUMER_MS));
            assert_eq!(s.enables_unconfigured, 0);
        }
        let truth0: Vec<f64> = rig.drives.iter().map(|d| d.now().position_counts).collect();
        let pose0 = rig.odo.pose();
        // Straight at 0.2 m/s for 2 s and stop; turn on the spot at 0.5 rad/s for 2 s and stop.
        // Ramps at 0.5 m/s² lose at the start what they add at the stop.
        let zero = rig.dd.wheel_targets(0.0, 0.0).to_vec();
        let targets = rig.dd.wheel_targets(0.2, 0.0);
        while rig.sniffer.try_recv().is_some() {}
        rig.send(MasterCommand::SetTargets(targets.to_vec())).await;
        rig.run_for(Duration::from_secs(2)).await;
        // Every SYNC follows exactly one RPDO1 per wheel, so both targets apply at the same SYNC.
        let mut since_sync = Vec::new();
        let mut syncs = 0;
        while let Some(f) = rig.sniffer.try_recv() {
            match f.cob() {
                Cob::Sync => {
                    since_sync.sort_unstable();
                    if syncs > 0 {
                        let expected =
                            if syncs > 1 { vec![targets[0], targets[1]] } else { since_sync.clone() };
                        assert_eq!(since_sync, expected, "RPDOs before SYNC {syncs}");
                    }
                    assert_eq!(since_sync.len(), 2, "one RPDO1 per wheel before SYNC {syncs}");
                    since_sync.clear();
                    syncs += 1;
                }
                Cob::Rpdo(1, node) => {
                    let v = pdo::unpack(&pdo::RPDO1_MAP, f.data()).unwrap();
                    since_sync.push((node, v[1] as u32 as i32));
                }
                _ => {}
            }
        }
        assert!((95..=101).contains(&syncs), "{syncs} SYNCs in 2 s at 20 ms");
        rig.send(MasterCommand::SetTargets(zero.clone())).await;
        rig.run_for(Duration::from_secs(1)).await;
        let mid = rig.odo.pose();
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.0, 0.5).to_vec())).await;
        rig.run_for(Duration::from_secs(2)).await;
        rig.send(MasterCommand::SetTargets(zero)).await;
        rig.run_for(Duration::from_secs(1)).await;
        for d in &rig.drives {
            assert!(d.now().velocity_cps.abs() < 1.0, "stopped: {:?}", d.now());
        }
        // The left counter crossed 2³¹ during the straight run.
        assert!(rig.drive(LEFT).now().position_counts > f64::from(i32::MAX));

        // Truth from the mocks' exact encoder positions.
        let travel: Vec<f64> =
            rig.drives.iter().zip(&truth0).map(|(d, p0)| d.now().position_counts - p0).collect();
        let dl = rig.dd.counts_to_m(rig.dd.drives().left, travel[0].round() as i64);
        let dr = rig.dd.counts_to_m(rig.dd.drives().right, travel[1].round() as i64);
        let yaw_truth = (dr - dl) / 0.33;
        let pose = rig.odo.pose();
        assert!((mid.x_m - pose0.x_m - 0.4).abs() < 0.01, "straight: {mid:?}");
        assert!(mid.y_m.abs() < 1e-3 && mid.yaw_rad.abs() < 1e-3, "straight: {mid:?}");
        assert!((pose.yaw_rad - yaw_truth).abs() < 0.005, "yaw {} vs truth {yaw_truth}", pose.yaw_rad);
        assert!((pose.yaw_rad - 1.0).abs() < 0.02, "turn: {pose:?}");
        assert!(
            (pose.x_m - mid.x_m).abs() < 0.005 && (pose.y_m - mid.y_m).abs() < 0.005,
            "on the spot: {pose:?}"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn teco_drive_fault_reported_and_recovered() {
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.1, 0.0).to_vec())).await;
        rig.run_for(Duration::from_millis(500)).await;
        rig.drive(LEFT).inject(Fault::DriveFault { code: 0x2310 });
        rig.until(Duration::from_secs(1), |e| {
            matches!(
                e,
                MasterEvent::Error(CanopenError::Device(DeviceError::Fault {
                    node: LEFT,
                    error_code: 0x2310
                }))
            )
        })
        .await;
        assert!(rig.log.iter().any(|e| matches!(
            e,
            MasterEvent::Error(CanopenError::Device(DeviceError::Emcy { node: LEFT, code: 0x2310, .. }))
        )));
        // The other wheel is commanded zero at once.
        wait_drive(rig.drive(RIGHT), Duration::from_millis(100), |s| s.target_velocity == 0).await;
        // Holding the controlword does not clear the fault: the drive needs the master's reset.
        rig.run_for(Duration::from_millis(500)).await;
        assert_eq!(rig.drive(LEFT).now().state, State402::Fault);
        rig.send(MasterCommand::Recover(LEFT)).await;
        let seen =
            rig.until(Duration::from_secs(2), |e| matches!(e, MasterEvent::Enabled { node: LEFT })).await;
        let order: Vec<_> = seen
            .iter()
            .filter_map(|e| match e {
                MasterEvent::Recovered { node: LEFT } => Some("recovered"),
                MasterEvent::StateChanged { node: LEFT, state: State402::SwitchOnDisabled } => Some("sod"),
                MasterEvent::Enabled { node: LEFT } => Some("enabled"),
                _ => None,
            })
            .collect();
        assert_eq!(order, ["sod", "recovered", "enabled"]);
        assert!(seen.iter().any(|e| matches!(e, MasterEvent::EmcyReset { node: LEFT })), "EMCY 0x0000 sent");
        // The fault cleared every target: nothing moves until a fresh command.
        rig.run_for(Duration::from_millis(200)).await;
        assert!(rig.drives.iter().all(|d| d.now().target_velocity == 0));
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.1, 0.0).to_vec())).await;
        wait_drive(rig.drive(RIGHT), Duration::from_secs(1), |s| s.target_velocity != 0).await;
    }

    #[tokio::test(start_paused = true)]
    async fn teco_master_heartbeat_stops_then_drives_stop_within_consumer_time() {
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.2, 0.0).to_vec())).await;
        rig.run_for(Duration::from_secs(1)).await;
        let t0 = Instant::now();
        rig.send(MasterCommand::Shutdown).await;
        // Both drives react within their consumer time of the last heartbeat.
        let (a, b) = (rig.drive(LEFT), rig.drive(RIGHT));
        let quick_stop = |s: &DriveSnapshot| s.state == State402::QuickStopActive;
        let wait = Duration::from_secs(2);
        let (sa, sb) = tokio::join!(wait_drive(a, wait, quick_stop), wait_drive(b, wait, quick_stop));
        let dt = Instant::now() - t0;
        assert!(dt <= Duration::from_millis(u64::from(MASTER_CONSUMER_MS)), "{dt:?}");
        assert_eq!((sa.master_losses, sb.master_losses), (1, 1));
        // And the motors actually stop (quick-stop deceleration).
        for d in [a, b] {
            wait_drive(d, Duration::from_secs(2), |s| s.velocity_cps == 0.0).await;
        }
    }

    #[tokio::test(start_paused = true)]
    async fn teco_drive_heartbeat_stops_then_master_reports_and_commands_zero() {
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.2, 0.0).to_vec())).await;
        rig.run_for(Duration::from_millis(500)).await;
        assert_ne!(rig.drive(LEFT).now().target_velocity, 0);
        let t0 = Instant::now();
        rig.drive(RIGHT).inject(Fault::HeartbeatLoss(true));
        rig.until(Duration::from_secs(2), |e| {
            matches!(e, MasterEvent::Error(CanopenError::Link(LinkError::HeartbeatLost { node: RIGHT })))
        })
        .await;
        let dt = Instant::now() - t0;
        assert!(dt <= Duration::from_millis(u64::from(DRIVE_CONSUMER_MS)), "reported after {dt:?}");
        // The healthy wheel is commanded zero in the next cycle.
        wait_drive(rig.drive(LEFT), Duration::from_millis(50), |s| s.target_velocity == 0).await;
        // The master resets the silent drive; it boots, is reconfigured and enabled again.
        rig.until(Duration::from_secs(3), |e| matches!(e, MasterEvent::Enabled { node: RIGHT })).await;
        assert!(rig.log.iter().any(|e| matches!(e, MasterEvent::Configured { node: RIGHT, .. })));
    }

    #[tokio::test(start_paused = true)]
    async fn teco_rebooted_drive_is_reconfigured_before_enabling() {
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        let boots = rig.drive(LEFT).now().boots;
        rig.drive(LEFT).inject(Fault::Reboot);
        let seen =
            rig.until(Duration::from_secs(3), |e| matches!(e, MasterEvent::Enabled { node: LEFT })).await;
        let order: Vec<_> = seen
            .iter()
            .filter_map(|e| match e {
                MasterEvent::BootUp { node: LEFT } => Some("boot-up"),
                MasterEvent::Configured { node: LEFT, device_type: 0x0002_0192 } => Some("configured"),
                MasterEvent::Enabled { node: LEFT } => Some("enabled"),
                _ => None,
            })
            .collect();
        assert_eq!(order, ["boot-up", "configured", "enabled"]);
        let s = rig.drive(LEFT).now();
        assert_eq!(s.boots, boots + 1);
        assert_eq!((s.enables, s.enables_unconfigured), (2, 0));
        assert_eq!(s.master_consumer, (127 << 16) | u32::from(MASTER_CONSUMER_MS));
        assert_eq!(s.comm_loss_reaction, 3);
    }

    #[tokio::test(start_paused = true)]
    async fn teco_sdo_abort_and_slow_replies_are_reported_and_survived() {
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        // An abort during the next configuration: reported with its code, then the master retries.
        rig.drive(RIGHT).inject(Fault::SdoAbort { index: 0x6083, code: 0x0800_0022 });
        rig.drive(RIGHT).inject(Fault::Reboot);
        rig.until(Duration::from_secs(2), |e| {
            matches!(
                e,
                MasterEvent::Error(CanopenError::Device(DeviceError::SdoAbort {
                    node: RIGHT,
                    addr: ObjectAddr { index: 0x6083, sub: 0 },
                    code: AbortCode(0x0800_0022),
                }))
            )
        })
        .await;
        let msg = rig
            .log
            .iter()
            .find_map(|e| match e {
                MasterEvent::Error(e @ CanopenError::Device(DeviceError::SdoAbort { .. })) => {
                    Some(e.to_string())
                }
                _ => None,
            })
            .unwrap();
        assert!(msg.contains("0x6083:00") && msg.contains("because of the present device state"), "{msg}");
        rig.until(Duration::from_secs(3), |e| matches!(e, MasterEvent::Enabled { node: RIGHT })).await;
        // A reply slower than the SDO timeout: a link error for that request; later ones work.
        rig.drive(LEFT).inject(Fault::SlowSdo(Duration::from_millis(800)));
        rig.send(MasterCommand::Sdo(LEFT, SdoRequest::Upload(ObjectAddr::new(0x1000, 0)))).await;
        let seen = rig.until(Duration::from_secs(2), |e| matches!(e, MasterEvent::SdoDone { .. })).await;
        assert!(matches!(
            seen.last(),
            Some(MasterEvent::SdoDone {
                id: 0,
                node: LEFT,
                result: Err(CanopenError::Link(LinkError::SdoTimeout { .. }))
            })
        ));
        rig.drive(LEFT).inject(Fault::SlowSdo(Duration::ZERO));
        rig.run_for(Duration::from_secs(1)).await; // the late reply arrives and is ignored
        // Segmented upload of the device name through the same client.
        rig.send(MasterCommand::Sdo(LEFT, SdoRequest::Upload(ObjectAddr::new(0x1008, 0)))).await;
        let seen = rig.until(Duration::from_secs(2), |e| matches!(e, MasterEvent::SdoDone { .. })).await;
        let name = TecoDriveConfig::new(LEFT).device_name.into_bytes();
        assert_eq!(
            seen.last(),
            Some(&MasterEvent::SdoDone { id: 1, node: LEFT, result: Ok(SdoResult::Read(name)) })
        );
        // The drives stayed enabled throughout.
        assert_eq!(rig.drive(LEFT).now().state, State402::OperationEnabled);
    }

    #[tokio::test(start_paused = true)]
    async fn teco_dropped_frames_and_bus_off_recover() {
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        // A few lost TPDOs and heartbeats do not upset anything.
        rig.drive(LEFT).inject(Fault::DropFrames(5));
        rig.run_for(Duration::from_millis(500)).await;
        assert!(!rig.log.iter().any(|e| matches!(e, MasterEvent::Error(_))), "{:?}", rig.log);
        // Bus-off longer than the consumer time: lost, reset, back.
        rig.drive(LEFT).inject(Fault::BusOff { duration: Duration::from_millis(600) });
        rig.until(Duration::from_secs(1), |e| {
            matches!(e, MasterEvent::Error(CanopenError::Link(LinkError::HeartbeatLost { node: LEFT })))
        })
        .await;
        rig.until(Duration::from_secs(8), |e| matches!(e, MasterEvent::Enabled { node: LEFT })).await;
        assert_eq!(rig.drive(LEFT).now().state, State402::OperationEnabled);
    }

    #[tokio::test(start_paused = true)]
    async fn teco_halt_and_quick_stop_then_enable_again() {
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.2, 0.0).to_vec())).await;
        rig.run_for(Duration::from_secs(1)).await;
        assert!(rig.drive(LEFT).now().velocity_cps > 90_000.0);
        // Halt: ramps to zero and stays enabled.
        rig.send(MasterCommand::Halt(true)).await;
        let s = wait_drive(rig.drive(LEFT), Duration::from_secs(2), |s| s.velocity_cps == 0.0).await;
        assert_eq!(s.state, State402::OperationEnabled);
        assert_ne!(s.controlword & 0x0100, 0, "halt bit set");
        rig.send(MasterCommand::Halt(false)).await;
        wait_drive(rig.drive(LEFT), Duration::from_secs(2), |s| s.velocity_cps > 90_000.0).await;
        // Quick stop: both drives into Quick stop active and stopped.
        rig.send(MasterCommand::QuickStop).await;
        for d in &rig.drives {
            let s = wait_drive(d, Duration::from_secs(2), |s| s.state == State402::QuickStopActive).await;
            assert_eq!(s.controlword, 0x0002);
            wait_drive(d, Duration::from_secs(2), |s| s.velocity_cps == 0.0).await;
        }
        // Enable again: through Switch on disabled back to Operation enabled, at zero: the target set
        // before the drives left Operation enabled no longer applies.
        rig.enable_both().await;
        rig.run_for(Duration::from_millis(500)).await;
        for d in &rig.drives {
            let s = d.now();
            assert!(s.state == State402::OperationEnabled && s.velocity_cps == 0.0, "{s:?}");
        }
        // A target set after re-entry moves them.
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.2, 0.0).to_vec())).await;
        wait_drive(rig.drive(RIGHT), Duration::from_secs(2), |s| s.velocity_cps < -90_000.0).await;
        assert!(!rig.log.iter().any(|e| matches!(e, MasterEvent::Error(_))), "{:?}", rig.log);
    }

    /// NMT Reset Communication (CiA 301) resets the communication objects, not the application: a
    /// drive in Operation enabled runs on at its target (its watchdog of the master's heartbeat,
    /// 0x1016, off and its PDOs unmapped until it is configured again). So a master must stop a
    /// drive before it resets one.
    #[tokio::test(start_paused = true)]
    async fn teco_reset_communication_leaves_the_application_running() {
        use amr_drivers::canopen::nmt::NmtCommand;
        let mut rig = Rig::new().await;
        rig.enable_both().await;
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.2, 0.0).to_vec())).await;
        rig.run_for(Duration::from_secs(1)).await;
        let before = rig.drive(LEFT).now();
        assert!(before.velocity_cps > 90_000.0 && before.master_consumer != 0, "{before:?}");
        // From outside the master, so it has no part in it.
        rig.sniffer.send_now(NmtCommand::ResetCommunication.frame(LEFT));
        let after = wait_drive(rig.drive(LEFT), Duration::from_secs(1), |s| s.boots > before.boots).await;
        assert_eq!(after.state, State402::OperationEnabled, "the application runs on");
        assert!(after.velocity_cps > 90_000.0, "still turning: {after:?}");
    }

    #[tokio::test(start_paused = true)]
    async fn teco_lossy_slow_bus_still_configures_enables_and_drives() {
        // 3 % of frames lost per receiver and 2 ms latency: lost SDO replies time out and the
        // master resets and reconfigures; lost PDOs are made up by the next cycle.
        let bus = InProcessBus::new(BusOptions { latency: Duration::from_millis(2), loss: 0.03, seed: 42 });
        let mut rig = Rig::on(bus).await;
        rig.send(MasterCommand::Enable).await;
        let mut enabled = [false; 2];
        rig.until(Duration::from_secs(30), |e| {
            if let MasterEvent::Enabled { node } = e {
                enabled[usize::from(*node - 1)] = true;
            }
            enabled == [true, true]
        })
        .await;
        rig.send(MasterCommand::SetTargets(rig.dd.wheel_targets(0.1, 0.0).to_vec())).await;
        for d in &rig.drives {
            wait_drive(d, Duration::from_secs(5), |s| s.velocity_cps.abs() > 45_000.0).await;
        }
        for n in [LEFT, RIGHT] {
            let s = rig.drive(n).now();
            assert_eq!((s.enables_unconfigured, s.mode_display), (0, 3));
        }
    }
}
