//! The mock TiM5xx's device model, pure: what it answers to each command (the real replies of
//! `04_command_vectors.txt` section B) and the LMDscandata telegram it builds for a scan.

use std::time::Duration;

use amr_drivers::sopas::command::CLIENT_PASSWORD_HASH;
use amr_drivers::sopas::scan::Channel;
use amr_drivers::sopas::{Command, ErrorCode, OutputRange, Reply, ScanDataConfig, ScanTelegram, Variable};

use super::source::ScanSource;

/// Which TiM5xx to emulate (notes §3.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Variant {
    /// 1°, 271 points, measurement frequency 0x36 (5.4 kHz).
    Tim551,
    /// 0.3333°, 811 points, 0xA2 (16.2 kHz): TiM561/571.
    Tim561,
}

impl Variant {
    pub fn step_1e4deg(self) -> u16 {
        match self {
            Self::Tim551 => 10_000,
            Self::Tim561 => 3_333,
        }
    }

    pub fn points(self) -> u16 {
        match self {
            Self::Tim551 => 271,
            Self::Tim561 => 811,
        }
    }

    fn measurement_frequency_hecto_hz(self) -> u32 {
        match self {
            Self::Tim551 => 0x36,
            Self::Tim561 => 0xA2,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Tim551 => "TiM551",
            Self::Tim561 => "TiM561",
        }
    }
}

/// Device-wide settings and counters that survive across connections until a reboot.
#[derive(Debug, Clone)]
pub(crate) struct Device {
    pub(crate) variant: Variant,
    pub(crate) serial: u32,
    pub(crate) output_range: OutputRange,
    pub(crate) scan_config: ScanDataConfig,
}

/// Per-connection protocol state.
#[derive(Debug, Clone, Default)]
pub(crate) struct Conn {
    pub(crate) authorized: bool,
    pub(crate) streaming: bool,
}

/// What a command does besides its reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SideEffect {
    None,
    SwitchDialect(amr_drivers::sopas::Dialect),
    Reboot,
}

impl Device {
    pub(crate) fn new(variant: Variant, serial: u32) -> Self {
        Self {
            variant,
            serial,
            output_range: OutputRange::full_field(u32::from(variant.step_1e4deg())),
            // Remission on (8-bit RSSI1), as the TiM551 response image in notes §3.1 shows.
            scan_config: ScanDataConfig { time: 0, ..ScanDataConfig::SICK_SCAN_XD },
        }
    }

    /// The reply to a request, given a ready scan telegram for polls.
    pub(crate) fn answer(
        &mut self,
        conn: &mut Conn,
        cmd: &Command,
        poll: impl FnOnce(&Device) -> ScanTelegram,
    ) -> (Reply, SideEffect) {
        let denied = Reply::Error(ErrorCode::MethodInAccessDenied);
        let reply = match cmd {
            Command::SetAccessMode { level, password_hash } => {
                conn.authorized = *level == 3 && *password_hash == CLIENT_PASSWORD_HASH;
                Reply::AccessMode { granted: conn.authorized }
            }
            Command::ReadByIndex(0) => Reply::IndexIdent {
                index: 0,
                name: self.variant.name().into(),
                version: "V2.60-15.03.19".into(),
            },
            Command::ReadByIndex(_) => Reply::Error(ErrorCode::VariableUnknownIndex),
            Command::Read(v) => match v {
                Variable::ScanData => Reply::ScanData { event: false, telegram: Box::new(poll(self)) },
                Variable::DeviceIdent => {
                    Reply::DeviceIdent { name: self.variant.name().into(), version: "V2.60".into() }
                }
                Variable::SerialNumber => Reply::SerialNumber(format!("{:08}", self.serial % 100_000_000)),
                Variable::FirmwareVersion => Reply::FirmwareVersion("V2.60".into()),
                Variable::DeviceState => Reply::DeviceState(0),
                Variable::OperatingHours => Reply::OperatingHours(0x68C),
                Variable::PowerOnCount => Reply::PowerOnCount(0x79),
                Variable::LocationName => Reply::LocationName("not defined".into()),
                Variable::OutputRange => Reply::OutputRange(self.output_range.clone()),
                Variable::ScanDataConfig => Reply::ScanDataConfig(self.scan_config),
            },
            Command::WriteOutputRange(r) if conn.authorized => {
                let step = u32::from(self.variant.step_1e4deg());
                let ok = r.sectors.len() == 1
                    && r.sectors.iter().all(|s| {
                        s.resolution_1e4deg == step
                            && s.start_1e4deg >= -450_000
                            && s.stop_1e4deg <= 2_250_000
                    });
                if ok {
                    self.output_range = r.clone();
                    Reply::WriteAck("LMPoutputRange".into())
                } else {
                    Reply::Error(ErrorCode::LocalConditionFailed)
                }
            }
            Command::WriteScanDataConfig(c) if conn.authorized => {
                self.scan_config = *c;
                Reply::WriteAck("LMDscandatacfg".into())
            }
            Command::WriteOutputRange(_) | Command::WriteScanDataConfig(_) => {
                Reply::Error(ErrorCode::VariableWriteAccessDenied)
            }
            Command::SetDialect(d) => {
                return (Reply::WriteAck("EIHstCola".into()), SideEffect::SwitchDialect(*d));
            }
            Command::ScanDataEvents(on) => {
                conn.streaming = *on;
                Reply::ScanDataEvents { enabled: *on }
            }
            Command::Run => Reply::Run { ok: true },
            Command::StartMeasurement => Reply::StartMeasurement { status: 0 },
            Command::StopMeasurement => Reply::StopMeasurement { status: 0 },
            Command::Reboot if conn.authorized => return (Reply::Reboot, SideEffect::Reboot),
            Command::WriteEeprom if conn.authorized => Reply::EepromWritten { ok: true },
            Command::Reboot | Command::WriteEeprom => denied,
        };
        (reply, SideEffect::None)
    }

    /// The telegram for scan number `index` (counted from boot), sent at `sent` after boot.
    pub(crate) fn telegram(
        &self,
        source: &dyn ScanSource,
        index: u64,
        scan_period: Duration,
        sent: Duration,
        telegram_counter: u16,
        initial_tick_us: u32,
    ) -> ScanTelegram {
        let sector = self.output_range.sectors.first().copied();
        let start = sector.map_or(-450_000, |s| s.start_1e4deg);
        let step = self.variant.step_1e4deg();
        let stop = sector.map_or(2_250_000, |s| s.stop_1e4deg);
        let n = (((stop - start) / i32::from(step)) + 1).clamp(1, i32::from(self.variant.points())) as usize;
        let angles: Vec<f64> = (0..n)
            .map(|i| ((f64::from(start) + i as f64 * f64::from(step)) / 1e4 - 90.0).to_radians())
            .collect();
        let end_of_scan = scan_period.saturating_mul(u32::try_from(index).unwrap_or(u32::MAX));
        let sample = source.scan(end_of_scan, &angles);
        let dist: Vec<u16> = (0..n)
            .map(|i| {
                let r = sample.ranges_m.get(i).copied().unwrap_or(0.0);
                if r.is_finite() && r > 0.0 { (r * 1000.0).round().min(65_535.0) as u16 } else { 0 }
            })
            .collect();
        let tick = |d: Duration| initial_tick_us.wrapping_add(d.as_micros() as u32);
        let header = |content: &str| Channel::<u16> {
            content: content.into(),
            scale_factor: 1.0,
            scale_offset: 0.0,
            start_angle_1e4deg: start,
            step_1e4deg: step,
            data: Vec::new(),
        };
        let mut channels_16bit = vec![Channel { data: dist, ..header("DIST1") }];
        let mut channels_8bit = Vec::new();
        if self.scan_config.remission != 0 {
            let rssi: Vec<u8> =
                (0..n).map(|i| sample.rssi.as_ref().and_then(|r| r.get(i).copied()).unwrap_or(0)).collect();
            if self.scan_config.resolution == 0 {
                let h = header("RSSI1");
                channels_8bit.push(Channel {
                    content: h.content,
                    scale_factor: h.scale_factor,
                    scale_offset: h.scale_offset,
                    start_angle_1e4deg: h.start_angle_1e4deg,
                    step_1e4deg: h.step_1e4deg,
                    data: rssi,
                });
            } else {
                channels_16bit
                    .push(Channel { data: rssi.into_iter().map(u16::from).collect(), ..header("RSSI1") });
            }
        }
        ScanTelegram {
            version: 1,
            device_number: 1,
            serial: self.serial,
            device_status: [0, 0],
            telegram_counter,
            scan_counter: index as u16,
            time_since_startup_us: tick(end_of_scan),
            time_of_transmission_us: tick(sent.max(end_of_scan)),
            input_status: [0, 0],
            output_status: [0, 0],
            reserved_layer_angle: 0,
            scan_frequency_centi_hz: (1e6 / scan_period.as_micros().max(1) as f64 * 100.0).round() as u32,
            measurement_frequency_hecto_hz: self.variant.measurement_frequency_hecto_hz(),
            encoders: Vec::new(),
            channels_16bit,
            channels_8bit,
            position: None,
            device_name: Some("not defined".into()),
            comment: None,
            time: None,
            event: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use amr_drivers::sopas::{Dialect, Scan};

    use super::super::source::RectRoom;
    use super::*;

    fn no_poll(_: &Device) -> ScanTelegram {
        unreachable!("not a poll")
    }

    #[test]
    fn writes_need_the_client_login_and_a_matching_resolution() {
        let mut d = Device::new(Variant::Tim551, 1);
        let mut conn = Conn::default();
        let range = Command::WriteOutputRange(OutputRange::full_field(0x2710));
        assert_eq!(
            d.answer(&mut conn, &range, no_poll).0,
            Reply::Error(ErrorCode::VariableWriteAccessDenied)
        );
        let wrong = Command::SetAccessMode { level: 3, password_hash: 0x1234_5678 };
        assert_eq!(d.answer(&mut conn, &wrong, no_poll).0, Reply::AccessMode { granted: false });
        let login = Command::SetAccessMode { level: 3, password_hash: CLIENT_PASSWORD_HASH };
        assert_eq!(d.answer(&mut conn, &login, no_poll).0, Reply::AccessMode { granted: true });
        assert_eq!(d.answer(&mut conn, &range, no_poll).0, Reply::WriteAck("LMPoutputRange".into()));
        let tim561_range = Command::WriteOutputRange(OutputRange::full_field(0xD05));
        assert_eq!(
            d.answer(&mut conn, &tim561_range, no_poll).0,
            Reply::Error(ErrorCode::LocalConditionFailed)
        );
        let (reply, effect) = d.answer(&mut conn, &Command::Reboot, no_poll);
        assert_eq!((reply, effect), (Reply::Reboot, SideEffect::Reboot));
        let (reply, effect) = d.answer(&mut conn, &Command::SetDialect(Dialect::ColaA), no_poll);
        assert_eq!(
            (reply, effect),
            (Reply::WriteAck("EIHstCola".into()), SideEffect::SwitchDialect(Dialect::ColaA))
        );
    }

    #[test]
    fn telegrams_have_the_variant_geometry_and_round_trip() {
        let room = RectRoom::default();
        let period = Duration::from_nanos(1_000_000_000 / 15);
        for (variant, n, step) in [(Variant::Tim551, 271, 10_000u16), (Variant::Tim561, 811, 3_333)] {
            let d = Device::new(variant, 7);
            let t = d.telegram(&room, 70_000, period, period * 70_001, 3, u32::MAX - 1_000);
            assert_eq!(t.channels_16bit[0].data.len(), n);
            assert_eq!(t.channels_16bit[0].step_1e4deg, step);
            assert_eq!(t.channels_8bit[0].content, "RSSI1");
            assert_eq!(t.scan_counter, 70_000u64 as u16);
            assert_eq!(t.scan_frequency_centi_hz, 1500);
            // 70 000 scans ≈ 4667 s: the tick has wrapped past u32::MAX.
            assert!(t.time_since_startup_us < 1_000_000_000);
            for dialect in [Dialect::ColaA, Dialect::ColaB] {
                let reply = Reply::ScanData { event: true, telegram: Box::new(t.clone()) };
                let back = Reply::decode(dialect, &reply.encode(dialect).unwrap()).unwrap();
                assert_eq!(back, reply);
            }
            let scan = Scan::from_telegram(&t).unwrap();
            let ahead = scan.angles_rad.iter().position(|a| a.abs() < 1e-3).unwrap();
            assert!((scan.ranges_m[ahead] - 4.0).abs() < 1e-3);
        }
    }
}
