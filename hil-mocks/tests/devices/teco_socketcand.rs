//! Mock TECO drives behind the socketcand server on 127.0.0.1 (real sockets, real time): the
//! greeting as python-can expects it, an outside CiA 402 master driving a drive by hand, and the
//! amr master over the socketcand client transport reading odometry back.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

mod teco {
    use std::time::Duration;

    use amr_drivers::canopen::cia402::{State402, controlword};
    use amr_drivers::canopen::config::BusConfig;
    use amr_drivers::canopen::diff_drive::{
        DiffDrive, DrivesConfig, Geometry, WheelDriveConfig, WheelOdometry,
    };
    use amr_drivers::canopen::frame::{CanFrame, Cob};
    use amr_drivers::canopen::master::{CommLossReaction, Master, MasterConfig, MasterEvent};
    use amr_drivers::canopen::nmt::{NmtCommand, NmtState, sync_frame};
    use amr_drivers::canopen::pdo::{self, PdoDirection, RPDO1_MAP, TPDO1_MAP, TRANSMISSION_SYNC_EVERY};
    use amr_drivers::canopen::sdo::{self, ObjectAddr, SdoRequest};
    use amr_drivers::canopen::shell::{MasterCommand, spawn_master};
    use amr_drivers::canopen::transport::CanTransport;
    use amr_drivers::canopen::transport::socketcand::SocketcandClient;
    use amr_drivers::canopen::{CanopenError, DeviceError};
    use hil_mocks::teco_drive::{Fault, TecoDriveConfig, start_mock_drives};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio::net::TcpStream;

    const STEP: Duration = Duration::from_secs(5);

    async fn read_once(s: &mut TcpStream) -> String {
        let mut buf = [0u8; 256];
        let n = tokio::time::timeout(STEP, s.read(&mut buf)).await.unwrap().unwrap();
        String::from_utf8_lossy(&buf[..n]).into_owned()
    }

    #[tokio::test]
    async fn teco_socketcand_greeting_is_one_element_per_step() {
        let mock = start_mock_drives("127.0.0.1:0", &[1], TecoDriveConfig::new).await.unwrap();
        let mut s = TcpStream::connect(mock.address).await.unwrap();
        // python-can reads the greeting with one recv and compares it exactly.
        assert_eq!(read_once(&mut s).await, "< hi >");
        s.write_all(b"< open can0 >").await.unwrap();
        assert_eq!(read_once(&mut s).await, "< ok >");
        s.write_all(b"< rawmode >").await.unwrap();
        assert_eq!(read_once(&mut s).await, "< ok >");
        // python-can's own spelling of an SDO upload of 0x1000 (hex without padding).
        s.write_all(b"< send 601 8 40 0 10 0 0 0 0 0 >").await.unwrap();
        let mut seen = String::new();
        let found = tokio::time::timeout(STEP, async {
            while !seen.contains("< frame 581 ") {
                let mut buf = [0u8; 512];
                let n = s.read(&mut buf).await.unwrap();
                assert!(n > 0, "closed");
                seen.push_str(&String::from_utf8_lossy(&buf[..n]));
            }
        })
        .await;
        assert!(found.is_ok(), "{seen}");
        assert!(seen.contains(" 4300100092010200 >"), "device type 0x00020192 in {seen}");
    }

    async fn recv_until(c: &mut SocketcandClient, mut pred: impl FnMut(&CanFrame) -> bool) -> CanFrame {
        tokio::time::timeout(STEP, async {
            loop {
                let f = c.recv().await.unwrap();
                if pred(&f) {
                    return f;
                }
            }
        })
        .await
        .expect("frame in time")
    }

    async fn sdo(c: &mut SocketcandClient, node: u8, body: [u8; 8]) -> [u8; 8] {
        c.send(Cob::SdoRequest(node).frame(&body)).await.unwrap();
        let f = recv_until(c, |f| f.cob() == Cob::SdoResponse(node)).await;
        let mut r = [0u8; 8];
        r[..f.data().len()].copy_from_slice(f.data());
        r
    }

    /// What an outside master (python-canopen's BaseNode402, say) does with a real drive.
    #[tokio::test]
    async fn teco_socketcand_outside_master_drives_a_mock_by_hand() {
        let mock = start_mock_drives("127.0.0.1:0", &[1, 2], TecoDriveConfig::new).await.unwrap();
        let mut c = SocketcandClient::connect(&mock.address.to_string(), "can0", STEP).await.unwrap();
        // Reset node 2 and see its boot-up.
        c.send(NmtCommand::ResetNode.frame(2)).await.unwrap();
        recv_until(&mut c, |f| NmtState::decode(f) == Some((2, NmtState::BootUp))).await;
        // Device type, the PDO configuration by SDO, a heartbeat.
        let r = sdo(&mut c, 2, sdo::upload_request(ObjectAddr::new(0x1000, 0))).await;
        assert_eq!(r, [0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0x00]);
        let r = sdo(&mut c, 2, sdo::upload_request(ObjectAddr::new(0x1A00, 1))).await;
        assert_eq!(
            u32::from_le_bytes([r[4], r[5], r[6], r[7]]),
            0x6041_0010,
            "factory TPDO1 maps the statusword"
        );
        let r = sdo(
            &mut c,
            2,
            sdo::expedited_download(ObjectAddr::new(0x1017, 0), &50u16.to_le_bytes()).unwrap(),
        )
        .await;
        assert_eq!(r[0], 0x60);
        recv_until(&mut c, |f| NmtState::decode(f) == Some((2, NmtState::PreOperational))).await;
        // Remap to the profile-velocity set (the remap procedure), synchronous.
        for (dir, map) in [(PdoDirection::Receive, &RPDO1_MAP[..]), (PdoDirection::Transmit, &TPDO1_MAP[..])]
        {
            for req in pdo::remap_requests(dir, 1, 2, TRANSMISSION_SYNC_EVERY, map) {
                let SdoRequest::Download(addr, data) = req else { unreachable!() };
                let r = sdo(&mut c, 2, sdo::expedited_download(addr, &data).unwrap()).await;
                assert_eq!(r[0], 0x60, "{addr}: {r:02x?}");
            }
        }
        // Profile velocity, confirmed on 0x6061.
        sdo(&mut c, 2, sdo::expedited_download(ObjectAddr::new(0x6060, 0), &[3]).unwrap()).await;
        let r = sdo(&mut c, 2, sdo::upload_request(ObjectAddr::new(0x6061, 0))).await;
        assert_eq!((r[0], r[4]), (0x4F, 3));
        c.send(NmtCommand::Start.frame(2)).await.unwrap();
        // Walk the state machine with the controlword in the synchronous RPDO, one SYNC each.
        // SYNC every 10 ms as a master does; at most 1 s.
        let mut state = None;
        let mut sync_period = tokio::time::interval(Duration::from_millis(10));
        for _ in 0..100 {
            sync_period.tick().await;
            let cw = match state {
                Some(State402::SwitchOnDisabled) | None => controlword::SHUTDOWN,
                Some(State402::ReadyToSwitchOn) => controlword::SWITCH_ON,
                _ => controlword::ENABLE_OPERATION,
            };
            let target = if state == Some(State402::OperationEnabled) { 20_000 } else { 0 };
            c.send(Cob::Rpdo(1, 2).frame(&pdo::encode_rpdo1(cw, target))).await.unwrap();
            c.send(sync_frame()).await.unwrap();
            let f = recv_until(&mut c, |f| f.cob() == Cob::Tpdo(1, 2)).await;
            let (sw, velocity) = pdo::decode_tpdo1(f.data()).unwrap();
            state = State402::from_statusword(sw);
            if velocity == 20_000 {
                break;
            }
        }
        assert_eq!(state, Some(State402::OperationEnabled));
        // Velocity followed the target (default ramp 100000 units/s² reaches it in 0.2 s of SYNCs).
        let s = mock.drives[1].now();
        assert_eq!((s.target_velocity, s.velocity_cps), (20_000, 20_000.0));
        assert!(s.position_counts > 0.0);
        assert_eq!(mock.drives[0].now().state, State402::SwitchOnDisabled, "node 1 untouched");
    }

    #[tokio::test]
    async fn teco_socketcand_master_enables_and_reads_odometry() {
        let mock = start_mock_drives("127.0.0.1:0", &[1, 2], |n| TecoDriveConfig {
            encoder_noise_counts: 1.0,
            slip: 0.0,
            ..TecoDriveConfig::new(n)
        })
        .await
        .unwrap();
        let dd = diff_drive();
        let config = MasterConfig {
            can: BusConfig {
                master_node_id: 127,
                master_heartbeat_ms: 50,
                sync_period_ms: 10,
                sdo_timeout_ms: 1000,
                boot_timeout_ms: 2000,
                ..BusConfig::default()
            },
            drives: dd.drive_setups(1.0, 1.0, 2.0),
            enable_timeout_ms: 2000,
            mode_confirm_attempts: 5,
            target_hold_ms: 60_000,
        };
        let client = SocketcandClient::connect(&mock.address.to_string(), "can0", STEP).await.unwrap();
        let mut m = spawn_master(Master::new(config, tokio::time::Instant::now().into_std()), client);
        m.commands.send(MasterCommand::Enable).await.unwrap();
        let mut odo = WheelOdometry::new();
        let mut enabled = 0;
        let mut moving_since = None;
        let mut stopped_at = None;
        let result = tokio::time::timeout(Duration::from_secs(10), async {
            while let Some(ev) = m.events.recv().await {
                match ev {
                    MasterEvent::Enabled { .. } => {
                        enabled += 1;
                        if enabled == 2 {
                            let t = dd.wheel_targets(0.1, 0.0).to_vec();
                            m.commands.send(MasterCommand::SetTargets(t)).await.unwrap();
                            moving_since = Some(tokio::time::Instant::now());
                        }
                    }
                    MasterEvent::Cycle { positions, .. } if positions.len() == 2 => {
                        odo.update(&dd, positions[0].1, positions[1].1);
                        if moving_since.is_some_and(|t| t.elapsed() > Duration::from_millis(600))
                            && stopped_at.is_none()
                        {
                            let t = dd.wheel_targets(0.0, 0.0).to_vec();
                            m.commands.send(MasterCommand::SetTargets(t)).await.unwrap();
                            stopped_at = Some(tokio::time::Instant::now());
                        }
                        let still = mock.drives.iter().all(|d| d.now().velocity_cps == 0.0);
                        if stopped_at.is_some_and(|t| t.elapsed() > Duration::from_millis(300)) && still {
                            return true;
                        }
                    }
                    MasterEvent::Error(e) => panic!("{e}"),
                    _ => {}
                }
            }
            false
        })
        .await;
        assert_eq!(result, Ok(true));
        // Odometry from the TPDOs agrees with the mocks' exact encoders (noise 1 count ≈ 2 µm).
        let truth_l = dd.counts_to_m(dd.drives().left, mock.drives[0].now().position_counts.round() as i64);
        let truth_r = dd.counts_to_m(dd.drives().right, mock.drives[1].now().position_counts.round() as i64);
        let pose = odo.pose();
        let truth = (truth_l + truth_r) / 2.0;
        assert!(truth > 0.04, "moved {truth} m");
        assert!((pose.x_m - truth).abs() < 0.002, "odometry {pose:?} vs truth {truth}");
        assert!(pose.yaw_rad.abs() < 0.01, "{pose:?}");
        m.commands.send(MasterCommand::Shutdown).await.unwrap();
    }

    /// Events until `pred`, within `within` of real time.
    async fn until(
        events: &mut tokio::sync::mpsc::Receiver<MasterEvent>,
        within: Duration,
        mut pred: impl FnMut(&MasterEvent) -> bool,
    ) -> Vec<MasterEvent> {
        let mut seen = Vec::new();
        let found = tokio::time::timeout(within, async {
            while let Some(ev) = events.recv().await {
                let hit = pred(&ev);
                if !matches!(ev, MasterEvent::Cycle { .. }) {
                    seen.push(ev);
                }
                if hit {
                    return true;
                }
            }
            false
        })
        .await;
        assert_eq!(found, Ok(true), "events: {seen:?}");
        seen
    }

    /// The master's configuration for two drives (consumer times 500 ms, heartbeats 50 ms).
    fn two_drive_master() -> MasterConfig {
        let setups = vec![1u8, 2]
            .into_iter()
            .map(|n| amr_drivers::canopen::master::DriveSetup {
                node_id: n,
                heartbeat_producer_ms: 50,
                heartbeat_consumer_ms: 500,
                master_consumer_ms: 500,
                comm_loss_reaction: CommLossReaction::QuickStop,
                profile_acceleration: 100_000,
                profile_deceleration: 100_000,
                quick_stop_deceleration: 200_000,
                digital_inputs: false,
            })
            .collect();
        MasterConfig {
            can: BusConfig {
                master_node_id: 127,
                master_heartbeat_ms: 50,
                sync_period_ms: 10,
                sdo_timeout_ms: 1000,
                boot_timeout_ms: 2000,
                ..BusConfig::default()
            },
            drives: setups,
            enable_timeout_ms: 2000,
            mode_confirm_attempts: 5,
            target_hold_ms: 60_000,
        }
    }

    /// Mock drives 1 and 2 behind socketcand and an enabled amr master talking to them over it.
    async fn enabled_pair() -> (hil_mocks::teco_drive::MockDrives, amr_drivers::canopen::shell::MasterHandle)
    {
        let mock = start_mock_drives("127.0.0.1:0", &[1, 2], TecoDriveConfig::new).await.unwrap();
        let client = SocketcandClient::connect(&mock.address.to_string(), "can0", STEP).await.unwrap();
        let mut m =
            spawn_master(Master::new(two_drive_master(), tokio::time::Instant::now().into_std()), client);
        m.commands.send(MasterCommand::Enable).await.unwrap();
        let mut enabled = [false; 2];
        until(&mut m.events, STEP, |e| {
            if let MasterEvent::Enabled { node } = e {
                enabled[usize::from(*node - 1)] = true;
            }
            enabled == [true, true]
        })
        .await;
        (mock, m)
    }

    /// The robots' drive layer (config/robot-*.toml values, heartbeats as in `two_drive_master`).
    fn diff_drive() -> DiffDrive {
        DiffDrive::new(
            DrivesConfig {
                left: WheelDriveConfig { node_id: 1, inverted: false },
                right: WheelDriveConfig { node_id: 2, inverted: true },
                encoder_counts_per_rev: 10_000,
                gear_ratio: 20.0,
                velocity_units_per_rps: 10_000.0,
                heartbeat_producer_ms: 50,
                heartbeat_consumer_ms: 500,
                master_consumer_ms: 500,
                comm_loss_reaction: CommLossReaction::QuickStop,
                enable_timeout_ms: 2000,
                mode_confirm_attempts: 5,
                quick_stop_decel_mps2: 2.0,
                estop_input_bit: None,
                estop_input_active_low: true,
            },
            Geometry { wheel_radius_m: 0.065, track_width_m: 0.33 },
        )
    }

    /// Over real TCP the deadline is the consumer time plus this much for scheduling on a shared
    /// machine (the in-process tests, in paused time, hold the consumer time exactly).
    const SLACK: Duration = Duration::from_millis(250);

    #[tokio::test]
    async fn teco_socketcand_drive_heartbeat_lost_is_reported_and_the_other_wheel_stopped() {
        let (mock, mut m) = enabled_pair().await;
        let dd = diff_drive();
        m.commands.send(MasterCommand::SetTargets(dd.wheel_targets(0.1, 0.0).to_vec())).await.unwrap();
        wait_drive(&mock.drives[0], |s| s.target_velocity != 0).await;
        let t0 = std::time::Instant::now();
        mock.drives[1].inject(Fault::HeartbeatLoss(true));
        until(&mut m.events, STEP, |e| {
            matches!(
                e,
                MasterEvent::Error(CanopenError::Link(amr_drivers::canopen::LinkError::HeartbeatLost {
                    node: 2
                }))
            )
        })
        .await;
        let dt = t0.elapsed();
        assert!(dt <= Duration::from_millis(500) + SLACK, "reported after {dt:?}");
        wait_drive(&mock.drives[0], |s| s.target_velocity == 0).await;
        m.commands.send(MasterCommand::Shutdown).await.unwrap();
    }

    #[tokio::test]
    async fn teco_socketcand_master_silent_then_drives_quick_stop() {
        let (mock, m) = enabled_pair().await;
        let t0 = std::time::Instant::now();
        m.commands.send(MasterCommand::Shutdown).await.unwrap();
        for d in &mock.drives {
            wait_drive(d, |s| s.state == State402::QuickStopActive).await;
        }
        let dt = t0.elapsed();
        assert!(dt <= Duration::from_millis(500) + SLACK, "quick stop after {dt:?}");
    }

    /// Wait (at most 5 s) until a mock drive's published state satisfies `pred`.
    async fn wait_drive(
        d: &hil_mocks::teco_drive::DriveHandle,
        pred: impl FnMut(&hil_mocks::teco_drive::DriveSnapshot) -> bool,
    ) {
        let mut rx = d.snapshot.clone();
        let reached = tokio::time::timeout(STEP, rx.wait_for(pred)).await;
        assert!(matches!(reached, Ok(Ok(_))), "drive state not reached within {STEP:?}: {:?}", d.now());
    }

    #[tokio::test]
    async fn teco_socketcand_fault_recovery_and_reboot() {
        let (mock, mut m) = enabled_pair().await;
        // Drive fault: reported, then the verified reset brings it back.
        mock.drives[0].inject(Fault::DriveFault { code: 0x4310 });
        until(&mut m.events, STEP, |e| {
            matches!(
                e,
                MasterEvent::Error(CanopenError::Device(DeviceError::Fault { node: 1, error_code: 0x4310 }))
            )
        })
        .await;
        m.commands.send(MasterCommand::Recover(1)).await.unwrap();
        let seen = until(&mut m.events, STEP, |e| matches!(e, MasterEvent::Enabled { node: 1 })).await;
        assert!(seen.contains(&MasterEvent::Recovered { node: 1 }), "{seen:?}");
        // Reboot: boot-up, reconfigured, then enabled — in that order.
        mock.drives[1].inject(Fault::Reboot);
        let seen = until(&mut m.events, STEP, |e| matches!(e, MasterEvent::Enabled { node: 2 })).await;
        let order: Vec<_> = seen
            .iter()
            .filter_map(|e| match e {
                MasterEvent::BootUp { node: 2 } => Some("boot-up"),
                MasterEvent::Configured { node: 2, .. } => Some("configured"),
                MasterEvent::Enabled { node: 2 } => Some("enabled"),
                _ => None,
            })
            .collect();
        assert_eq!(order, ["boot-up", "configured", "enabled"]);
        assert_eq!(mock.drives[1].now().enables_unconfigured, 0);
        m.commands.send(MasterCommand::Shutdown).await.unwrap();
    }
}
