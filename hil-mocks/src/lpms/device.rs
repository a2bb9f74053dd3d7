//! The mock LPMS-B2 as a pure state machine: request bytes in, reply bytes out, data packets on
//! demand. Built from the driver's own codec pieces (`amr_drivers::lpms`) used from the sensor's side.
//!
//! Behaviour follows the notes (research Part A2): SETs only in command mode (NACK otherwise), ACK
//! for SETs and mode changes, GET replies carry the GET's id; the sensor powers up streaming.

use std::time::Duration;

use amr_drivers::lpms::command::{Command, CommandId, FirmwareVersion, Reply};
use amr_drivers::lpms::data::{
    ConfigRegister, DataMode, OutputMask, STREAM_RATES_HZ, SensorData, encode_sensor_data,
};
use amr_drivers::lpms::frame::{Frame, FrameDecoder};

use super::motion::Motion;

/// Standard gravity, m/s² (to report accelerations in g, as the B2 does; notes A3).
const G_MPS2: f64 = 9.80665;
/// Timestamp ticks per second (notes A3: ×0.0025 s).
const TICKS_PER_S: u32 = 400;

/// What the mock device is when it powers up.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceSettings {
    /// The IMU id it answers with.
    pub imu_id: u16,
    /// Stream rate at power-up, Hz.
    pub stream_hz: u32,
    /// Outputs at power-up.
    pub outputs: OutputMask,
    /// Data mode at power-up.
    pub data_mode: DataMode,
    /// Firmware version reported.
    pub firmware: FirmwareVersion,
    /// Serial number reported.
    pub serial_number: String,
    /// Device name reported.
    pub device_name: String,
}

impl Default for DeviceSettings {
    fn default() -> Self {
        Self {
            imu_id: 1,
            stream_hz: 100,
            outputs: OutputMask::GYRO | OutputMask::ACC | OutputMask::QUATERNION | OutputMask::EULER,
            data_mode: DataMode::Float32,
            firmware: FirmwareVersion { major: 2, minor: 0, build: 5 },
            serial_number: "MOCK-LPMSB2-0001".into(),
            device_name: "LPMSB2-MOCK".into(),
        }
    }
}

/// Faults the device itself applies to what it sends (link faults live in the pty task).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DeviceFaults {
    /// Commands to NACK, with how many more times.
    pub nack: Vec<(CommandId, u32)>,
    /// Replies (not data) still to be swallowed.
    pub drop_replies: u32,
    /// Frames (replies or data) still to be sent with a wrong LRC.
    pub corrupt_lrc: u32,
    /// Frames (replies or data) still to be cut to half their length (after the LRC faults).
    pub truncate: u32,
}

/// Counters and the commands received, for tests.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DeviceStats {
    /// Every valid request, in order.
    pub commands: Vec<CommandId>,
    /// NACKs sent.
    pub nacks: u64,
    /// Data packets produced.
    pub data_packets: u64,
    /// Request frames that did not parse.
    pub bad_requests: u64,
}

/// The mock sensor.
#[derive(Debug)]
pub struct MockDevice {
    settings: DeviceSettings,
    streaming: bool,
    stream_hz: u32,
    outputs: OutputMask,
    data_mode: DataMode,
    timestamp_ticks: u32,
    decoder: FrameDecoder,
    faults: DeviceFaults,
    stats: DeviceStats,
}

impl MockDevice {
    /// A device in its power-up state: streaming.
    pub fn new(settings: DeviceSettings) -> Self {
        Self {
            streaming: true,
            stream_hz: settings.stream_hz,
            outputs: settings.outputs,
            data_mode: settings.data_mode,
            settings,
            timestamp_ticks: 0,
            decoder: FrameDecoder::new(),
            faults: DeviceFaults::default(),
            stats: DeviceStats::default(),
        }
    }

    /// Whether the device streams data packets.
    pub fn is_streaming(&self) -> bool {
        self.streaming
    }

    /// Time between streamed packets.
    pub fn stream_period(&self) -> Duration {
        Duration::from_secs_f64(1.0 / f64::from(self.stream_hz.max(1)))
    }

    /// The config register as GET_CONFIG reports it.
    pub fn config(&self) -> ConfigRegister {
        ConfigRegister::from_settings(self.outputs, self.data_mode, self.stream_hz).unwrap_or_default()
    }

    /// Counters.
    pub fn stats(&self) -> &DeviceStats {
        &self.stats
    }

    /// The faults to apply.
    pub fn faults_mut(&mut self) -> &mut DeviceFaults {
        &mut self.faults
    }

    /// Forgets partial requests (the link was replaced).
    pub fn reset_link(&mut self) {
        self.decoder.clear();
    }

    /// Consumes request bytes; returns the reply bytes. `motion` serves GET_SENSOR_DATA.
    pub fn handle_bytes(&mut self, bytes: &[u8], motion: &mut dyn FnMut() -> Motion) -> Vec<u8> {
        self.decoder.push(bytes);
        let mut out = Vec::new();
        while let Some(next) = self.decoder.next_frame() {
            let Ok(frame) = next else {
                self.stats.bad_requests += 1;
                continue;
            };
            let command = match Command::from_frame(&frame) {
                Ok(c) => c,
                Err(e) => {
                    tracing::debug!(%e, "mock LPMS: bad request");
                    self.stats.bad_requests += 1;
                    if let Some(id) = CommandId::from_code(frame.cmd) {
                        self.stats.commands.push(id);
                    }
                    self.send_reply(Reply::Nack, &mut out);
                    continue;
                }
            };
            self.stats.commands.push(command.id());
            let reply = self.execute(command, motion);
            self.send_reply(reply, &mut out);
        }
        out
    }

    /// The next streamed data packet (advances the timestamp by one period).
    pub fn next_data_packet(&mut self, motion: &Motion) -> Vec<u8> {
        let step = TICKS_PER_S / self.stream_hz.clamp(1, TICKS_PER_S);
        self.timestamp_ticks = self.timestamp_ticks.wrapping_add(step);
        let frame = Frame::new(self.settings.imu_id, CommandId::GetSensorData.code(), self.payload(motion));
        self.stats.data_packets += 1;
        self.encode(&frame)
    }

    /// Seconds of sensor time so far.
    pub fn sensor_time_s(&self) -> f64 {
        f64::from(self.timestamp_ticks) / f64::from(TICKS_PER_S)
    }

    fn execute(&mut self, command: Command, motion: &mut dyn FnMut() -> Motion) -> Reply {
        let id = command.id();
        if let Some(entry) = self.faults.nack.iter_mut().find(|(c, n)| *c == id && *n > 0) {
            entry.1 -= 1;
            return Reply::Nack;
        }
        let is_set = matches!(
            command,
            Command::SetTransmitData(_)
                | Command::SetStreamFreq(_)
                | Command::SetLpbusDataMode(_)
                | Command::WriteRegisters
                | Command::ResetOrientationOffset
        );
        if is_set && self.streaming {
            return Reply::Nack;
        }
        match command {
            Command::GotoCommandMode => {
                self.streaming = false;
                Reply::Ack
            }
            Command::GotoStreamMode => {
                self.streaming = true;
                Reply::Ack
            }
            Command::GetConfig => Reply::Config(self.config()),
            Command::GetStatus => Reply::Status(u32::from(self.streaming)),
            Command::GetSensorData => Reply::SensorData(self.payload(&motion())),
            Command::SetTransmitData(mask) => {
                self.outputs = mask.outputs_only();
                Reply::Ack
            }
            Command::SetStreamFreq(hz) if STREAM_RATES_HZ.contains(&hz) && hz <= TICKS_PER_S => {
                self.stream_hz = hz;
                Reply::Ack
            }
            Command::SetStreamFreq(_) => Reply::Nack,
            Command::SetLpbusDataMode(mode) => {
                self.data_mode = mode;
                Reply::Ack
            }
            Command::WriteRegisters | Command::ResetOrientationOffset => Reply::Ack,
            Command::GetImuId => Reply::ImuId(u32::from(self.settings.imu_id)),
            Command::GetFirmwareVersion => Reply::FirmwareVersion(self.settings.firmware),
            Command::GetSerialNumber => Reply::SerialNumber(self.settings.serial_number.clone()),
            Command::GetDeviceName => Reply::DeviceName(self.settings.device_name.clone()),
        }
    }

    fn send_reply(&mut self, reply: Reply, out: &mut Vec<u8>) {
        if reply == Reply::Nack {
            self.stats.nacks += 1;
        }
        if self.faults.drop_replies > 0 {
            self.faults.drop_replies -= 1;
            return;
        }
        let frame = reply.to_frame(self.settings.imu_id);
        out.extend(self.encode(&frame));
    }

    fn encode(&mut self, frame: &Frame) -> Vec<u8> {
        let mut bytes = frame.encode().unwrap_or_default();
        if self.faults.corrupt_lrc > 0 && bytes.len() >= 4 {
            self.faults.corrupt_lrc -= 1;
            let lrc_at = bytes.len() - 4;
            bytes[lrc_at] ^= 0x5A;
        } else if self.faults.truncate > 0 {
            self.faults.truncate -= 1;
            bytes.truncate(bytes.len() / 2);
        }
        bytes
    }

    fn payload(&self, m: &Motion) -> Vec<u8> {
        let f = |v: f64| v as f32;
        let [w, x, y, z] = m.orientation_wxyz;
        let roll = (2.0 * (w * x + y * z)).atan2(1.0 - 2.0 * (x * x + y * y));
        let pitch = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0).asin();
        let yaw = (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z));
        let lin_g = m.linear_acc_mps2.map(|a| f(a / G_MPS2));
        let rate = m.angular_velocity_radps.map(f);
        let data = SensorData {
            timestamp_ticks: self.timestamp_ticks,
            gyro_radps: Some(rate),
            // Flat ground: the accelerometer feels gravity on +z on top of the motion.
            acc_g: Some([lin_g[0], lin_g[1], lin_g[2] + 1.0]),
            // A horizontal field of 20 µT seen from a body turned by yaw, 40 µT down.
            mag_ut: Some([f(20.0 * yaw.cos()), f(-20.0 * yaw.sin()), -40.0]),
            angular_velocity_radps: Some(rate),
            quaternion_wxyz: Some(m.orientation_wxyz.map(f)),
            euler_rad: Some([f(roll), f(pitch), f(yaw)]),
            linear_acc_g: Some(lin_g),
            pressure_raw: Some(101.325),
            altitude_m: Some(0.0),
            temperature_c: Some(25.0),
            heave_m: Some(0.0),
        };
        encode_sensor_data(&data, self.outputs, self.data_mode)
    }
}

#[cfg(test)]
mod tests {
    use amr_drivers::lpms::data::decode_sensor_data;

    use super::*;

    fn still() -> Motion {
        Motion {
            angular_velocity_radps: [0.0, 0.0, 0.25],
            orientation_wxyz: [1.0, 0.0, 0.0, 0.0],
            linear_acc_mps2: [0.0; 3],
        }
    }

    fn ask(d: &mut MockDevice, c: Command) -> Vec<Reply> {
        let out = d.handle_bytes(&c.to_frame(1).encode().unwrap(), &mut still);
        let mut dec = FrameDecoder::new();
        dec.push(&out);
        std::iter::from_fn(|| dec.next_frame()).map(|f| Reply::from_frame(&f.unwrap()).unwrap()).collect()
    }

    #[test]
    fn sets_are_refused_while_streaming_and_accepted_in_command_mode() {
        let mut d = MockDevice::new(DeviceSettings::default());
        assert!(d.is_streaming());
        assert_eq!(ask(&mut d, Command::SetStreamFreq(200)), vec![Reply::Nack]);
        assert_eq!(ask(&mut d, Command::GotoCommandMode), vec![Reply::Ack]);
        assert!(!d.is_streaming());
        assert_eq!(ask(&mut d, Command::SetStreamFreq(200)), vec![Reply::Ack]);
        assert_eq!(ask(&mut d, Command::SetStreamFreq(123)), vec![Reply::Nack]);
        assert_eq!(ask(&mut d, Command::SetLpbusDataMode(DataMode::Int16)), vec![Reply::Ack]);
        assert_eq!(ask(&mut d, Command::SetTransmitData(OutputMask::GYRO)), vec![Reply::Ack]);
        let reg = ConfigRegister::from_settings(OutputMask::GYRO, DataMode::Int16, 200).unwrap();
        assert_eq!(ask(&mut d, Command::GetConfig), vec![Reply::Config(reg)]);
        assert_eq!(d.stream_period(), Duration::from_millis(5));
    }

    #[test]
    fn data_packets_follow_the_config_and_count_time() {
        let mut d = MockDevice::new(DeviceSettings::default());
        ask(&mut d, Command::GotoCommandMode);
        ask(&mut d, Command::SetTransmitData(OutputMask::GYRO | OutputMask::QUATERNION));
        ask(&mut d, Command::SetLpbusDataMode(DataMode::Int16));
        let mut dec = FrameDecoder::new();
        for i in 1..=3u32 {
            dec.push(&d.next_data_packet(&still()));
            let f = dec.next_frame().unwrap().unwrap();
            let s = decode_sensor_data(&f.data, d.config().outputs(), DataMode::Int16).unwrap();
            assert_eq!(s.timestamp_ticks, 4 * i);
            assert_eq!(s.gyro_radps, Some([0.0, 0.0, 0.25]));
            assert_eq!(s.quaternion_wxyz, Some([1.0, 0.0, 0.0, 0.0]));
        }
    }

    #[test]
    fn faults_nack_drop_and_corrupt_what_they_say() {
        let mut d = MockDevice::new(DeviceSettings::default());
        d.faults_mut().nack.push((CommandId::GetImuId, 1));
        assert_eq!(ask(&mut d, Command::GetImuId), vec![Reply::Nack]);
        assert_eq!(ask(&mut d, Command::GetImuId), vec![Reply::ImuId(1)]);
        d.faults_mut().drop_replies = 1;
        assert_eq!(ask(&mut d, Command::GetImuId), vec![]);
        d.faults_mut().corrupt_lrc = 1;
        let out = d.handle_bytes(&Command::GetImuId.to_frame(1).encode().unwrap(), &mut still);
        let mut dec = FrameDecoder::new();
        dec.push(&out);
        assert!(matches!(dec.next_frame(), Some(Err(_))));
        assert_eq!(d.stats().nacks, 1);
    }

    #[test]
    fn identity_status_and_polled_data_answer_in_command_mode() {
        let mut d = MockDevice::new(DeviceSettings::default());
        assert_eq!(ask(&mut d, Command::GotoCommandMode), vec![Reply::Ack]);
        assert_eq!(ask(&mut d, Command::GetStatus), vec![Reply::Status(0)]);
        assert_eq!(
            ask(&mut d, Command::GetSerialNumber),
            vec![Reply::SerialNumber("MOCK-LPMSB2-0001".into())]
        );
        assert_eq!(ask(&mut d, Command::GetDeviceName), vec![Reply::DeviceName("LPMSB2-MOCK".into())]);
        assert_eq!(
            ask(&mut d, Command::GetFirmwareVersion),
            vec![Reply::FirmwareVersion(FirmwareVersion { major: 2, minor: 0, build: 5 })]
        );
        let replies = ask(&mut d, Command::GetSensorData);
        let [Reply::SensorData(payload)] = replies.as_slice() else {
            panic!("expected one data reply: {replies:?}")
        };
        let s = decode_sensor_data(payload, d.config().outputs(), d.config().data_mode()).unwrap();
        assert_eq!(s.gyro_radps, Some([0.0, 0.0, 0.25]));
        assert_eq!(s.acc_g, Some([0.0, 0.0, 1.0]));
        assert_eq!(ask(&mut d, Command::WriteRegisters), vec![Reply::Ack]);
        assert_eq!(ask(&mut d, Command::ResetOrientationOffset), vec![Reply::Ack]);
        assert_eq!(ask(&mut d, Command::GotoStreamMode), vec![Reply::Ack]);
        assert!(d.is_streaming());
    }
}
