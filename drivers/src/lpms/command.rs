//! The LPMS-B2 ("legacy", protocol v0) command set: requests the host sends and replies the sensor
//! sends, each to and from a [`Frame`].
//!
//! Ids and payloads: research notes Part A2 (OpenMAT `LpSensor/LpmsRegisterDefinitions.h`,
//! `LpSensorForAndroid/LpmsB2.java`, OpenZen `InternalTypes.h` `EDevicePropertyV0`). Not the IG1 set.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::data::{ConfigRegister, DataMode, OutputMask};
use super::frame::Frame;

/// B2 command ids used here (notes A2 table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum CommandId {
    /// 0: positive reply to a SET or mode change.
    ReplyAck,
    /// 1: negative reply.
    ReplyNack,
    /// 4: read the u32 config register.
    GetConfig,
    /// 5: read the u32 status word.
    GetStatus,
    /// 6: leave streaming, accept commands.
    GotoCommandMode,
    /// 7: start streaming.
    GotoStreamMode,
    /// 9: one data packet (request in command mode; every streamed packet).
    GetSensorData,
    /// 10: select outputs (u32 mask).
    SetTransmitData,
    /// 11: stream rate (u32 Hz).
    SetStreamFreq,
    /// 15: save settings to flash.
    WriteRegisters,
    /// 21: read the IMU id.
    GetImuId,
    /// 47: read the firmware version (3 × u32).
    GetFirmwareVersion,
    /// 75: float or 16-bit data.
    SetLpbusDataMode,
    /// 82: clear the orientation offset.
    ResetOrientationOffset,
    /// 90: read the serial number (24 chars).
    GetSerialNumber,
    /// 91: read the device name (16 chars).
    GetDeviceName,
}

impl CommandId {
    /// Every id in this set.
    pub const ALL: [Self; 16] = [
        Self::ReplyAck,
        Self::ReplyNack,
        Self::GetConfig,
        Self::GetStatus,
        Self::GotoCommandMode,
        Self::GotoStreamMode,
        Self::GetSensorData,
        Self::SetTransmitData,
        Self::SetStreamFreq,
        Self::WriteRegisters,
        Self::GetImuId,
        Self::GetFirmwareVersion,
        Self::SetLpbusDataMode,
        Self::ResetOrientationOffset,
        Self::GetSerialNumber,
        Self::GetDeviceName,
    ];

    /// The wire value.
    pub fn code(self) -> u16 {
        match self {
            Self::ReplyAck => 0,
            Self::ReplyNack => 1,
            Self::GetConfig => 4,
            Self::GetStatus => 5,
            Self::GotoCommandMode => 6,
            Self::GotoStreamMode => 7,
            Self::GetSensorData => 9,
            Self::SetTransmitData => 10,
            Self::SetStreamFreq => 11,
            Self::WriteRegisters => 15,
            Self::GetImuId => 21,
            Self::GetFirmwareVersion => 47,
            Self::SetLpbusDataMode => 75,
            Self::ResetOrientationOffset => 82,
            Self::GetSerialNumber => 90,
            Self::GetDeviceName => 91,
        }
    }

    /// From the wire value; ids outside this set are `None`.
    pub fn from_code(code: u16) -> Option<Self> {
        Self::ALL.into_iter().find(|c| c.code() == code)
    }

    /// Whether the sensor answers with ACK/NACK (SETs and mode changes) rather than a frame of the
    /// same id (GETs).
    pub fn is_acked(self) -> bool {
        !matches!(
            self,
            Self::GetConfig
                | Self::GetStatus
                | Self::GetSensorData
                | Self::GetImuId
                | Self::GetFirmwareVersion
                | Self::GetSerialNumber
                | Self::GetDeviceName
        )
    }
}

impl std::fmt::Display for CommandId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{self:?}({})", self.code())
    }
}

/// A request from the host.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Command {
    /// GOTO_COMMAND_MODE.
    GotoCommandMode,
    /// GOTO_STREAM_MODE.
    GotoStreamMode,
    /// GET_CONFIG.
    GetConfig,
    /// GET_STATUS.
    GetStatus,
    /// GET_SENSOR_DATA.
    GetSensorData,
    /// SET_TRANSMIT_DATA with the output mask.
    SetTransmitData(OutputMask),
    /// SET_STREAM_FREQ with the rate in Hz (sent as-is: OpenMAT `setStreamFrequency`).
    SetStreamFreq(u32),
    /// WRITE_REGISTERS.
    WriteRegisters,
    /// GET_IMU_ID.
    GetImuId,
    /// GET_FIRMWARE_VERSION.
    GetFirmwareVersion,
    /// SET_LPBUS_DATA_MODE.
    SetLpbusDataMode(DataMode),
    /// RESET_ORIENTATION_OFFSET.
    ResetOrientationOffset,
    /// GET_SERIAL_NUMBER.
    GetSerialNumber,
    /// GET_DEVICE_NAME.
    GetDeviceName,
}

/// A frame that is not a well-formed request or reply of this set.
#[derive(Debug, Clone, PartialEq, Eq, Error, Serialize, Deserialize)]
pub enum CommandError {
    /// The command id is not in the B2 set handled here.
    #[error("unknown LPBUS command id {0}")]
    UnknownCommand(u16),
    /// The id is known but not valid in this direction (e.g. an ACK sent as a request).
    #[error("command {0} is not valid in this direction")]
    WrongDirection(CommandId),
    /// The payload length does not fit the command.
    #[error("command {command}: payload of {actual} bytes, expected {expected}")]
    BadLength {
        /// The command.
        command: CommandId,
        /// Bytes the command carries.
        expected: usize,
        /// Bytes received.
        actual: usize,
    },
    /// The argument is outside the command's domain (e.g. data mode 7).
    #[error("command {command}: invalid argument {value}")]
    BadArgument {
        /// The command.
        command: CommandId,
        /// The argument.
        value: u32,
    },
}

fn u32_arg(command: CommandId, data: &[u8]) -> Result<u32, CommandError> {
    match data {
        [a, b, c, d] => Ok(u32::from_le_bytes([*a, *b, *c, *d])),
        _ => Err(CommandError::BadLength { command, expected: 4, actual: data.len() }),
    }
}

fn no_arg(command: CommandId, data: &[u8]) -> Result<(), CommandError> {
    if data.is_empty() {
        Ok(())
    } else {
        Err(CommandError::BadLength { command, expected: 0, actual: data.len() })
    }
}

impl Command {
    /// The command's id.
    pub fn id(self) -> CommandId {
        match self {
            Self::GotoCommandMode => CommandId::GotoCommandMode,
            Self::GotoStreamMode => CommandId::GotoStreamMode,
            Self::GetConfig => CommandId::GetConfig,
            Self::GetStatus => CommandId::GetStatus,
            Self::GetSensorData => CommandId::GetSensorData,
            Self::SetTransmitData(_) => CommandId::SetTransmitData,
            Self::SetStreamFreq(_) => CommandId::SetStreamFreq,
            Self::WriteRegisters => CommandId::WriteRegisters,
            Self::GetImuId => CommandId::GetImuId,
            Self::GetFirmwareVersion => CommandId::GetFirmwareVersion,
            Self::SetLpbusDataMode(_) => CommandId::SetLpbusDataMode,
            Self::ResetOrientationOffset => CommandId::ResetOrientationOffset,
            Self::GetSerialNumber => CommandId::GetSerialNumber,
            Self::GetDeviceName => CommandId::GetDeviceName,
        }
    }

    /// The request frame addressed to `imu_id`.
    pub fn to_frame(self, imu_id: u16) -> Frame {
        let data = match self {
            Self::SetTransmitData(mask) => mask.0.to_le_bytes().to_vec(),
            Self::SetStreamFreq(hz) => hz.to_le_bytes().to_vec(),
            Self::SetLpbusDataMode(mode) => mode.wire_value().to_le_bytes().to_vec(),
            _ => Vec::new(),
        };
        Frame::new(imu_id, self.id().code(), data)
    }

    /// Parses a request frame (the mock's side).
    pub fn from_frame(frame: &Frame) -> Result<Self, CommandError> {
        let id = CommandId::from_code(frame.cmd).ok_or(CommandError::UnknownCommand(frame.cmd))?;
        let d = frame.data.as_slice();
        let cmd = match id {
            CommandId::ReplyAck | CommandId::ReplyNack => return Err(CommandError::WrongDirection(id)),
            CommandId::SetTransmitData => Self::SetTransmitData(OutputMask(u32_arg(id, d)?)),
            CommandId::SetStreamFreq => Self::SetStreamFreq(u32_arg(id, d)?),
            CommandId::SetLpbusDataMode => {
                let v = u32_arg(id, d)?;
                Self::SetLpbusDataMode(
                    DataMode::from_wire(v).ok_or(CommandError::BadArgument { command: id, value: v })?,
                )
            }
            other => {
                no_arg(other, d)?;
                match other {
                    CommandId::GotoCommandMode => Self::GotoCommandMode,
                    CommandId::GotoStreamMode => Self::GotoStreamMode,
                    CommandId::GetConfig => Self::GetConfig,
                    CommandId::GetStatus => Self::GetStatus,
                    CommandId::GetSensorData => Self::GetSensorData,
                    CommandId::WriteRegisters => Self::WriteRegisters,
                    CommandId::GetImuId => Self::GetImuId,
                    CommandId::GetFirmwareVersion => Self::GetFirmwareVersion,
                    CommandId::ResetOrientationOffset => Self::ResetOrientationOffset,
                    CommandId::GetSerialNumber => Self::GetSerialNumber,
                    _ => Self::GetDeviceName,
                }
            }
        };
        Ok(cmd)
    }
}

/// Firmware version from GET_FIRMWARE_VERSION: three u32 on the wire in the order build, minor,
/// major (notes A2, `LpmsB2.java`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FirmwareVersion {
    /// Major version.
    pub major: u32,
    /// Minor version.
    pub minor: u32,
    /// Build number.
    pub build: u32,
}

/// Length of the GET_SERIAL_NUMBER reply text (notes A2).
pub const SERIAL_NUMBER_LEN: usize = 24;
/// Length of the GET_DEVICE_NAME reply text (notes A2).
pub const DEVICE_NAME_LEN: usize = 16;

/// A reply from the sensor. Streamed data packets are `SensorData` replies too.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum Reply {
    /// ACK (0).
    Ack,
    /// NACK (1).
    Nack,
    /// GET_CONFIG.
    Config(ConfigRegister),
    /// GET_STATUS.
    Status(u32),
    /// GET_IMU_ID.
    ImuId(u32),
    /// GET_FIRMWARE_VERSION.
    FirmwareVersion(FirmwareVersion),
    /// GET_SERIAL_NUMBER, NUL padding removed.
    SerialNumber(String),
    /// GET_DEVICE_NAME, NUL padding removed.
    DeviceName(String),
    /// Command 9: the raw payload, decoded with the config in force (see `data`).
    SensorData(Vec<u8>),
}

fn text_arg(command: CommandId, data: &[u8], len: usize) -> Result<String, CommandError> {
    if data.len() != len {
        return Err(CommandError::BadLength { command, expected: len, actual: data.len() });
    }
    let end = data.iter().position(|&b| b == 0).unwrap_or(data.len());
    Ok(String::from_utf8_lossy(&data[..end]).into_owned())
}

fn text_bytes(s: &str, len: usize) -> Vec<u8> {
    let mut v: Vec<u8> = s.bytes().take(len).collect();
    v.resize(len, 0);
    v
}

impl Reply {
    /// The id the reply frame carries.
    pub fn id(&self) -> CommandId {
        match self {
            Self::Ack => CommandId::ReplyAck,
            Self::Nack => CommandId::ReplyNack,
            Self::Config(_) => CommandId::GetConfig,
            Self::Status(_) => CommandId::GetStatus,
            Self::ImuId(_) => CommandId::GetImuId,
            Self::FirmwareVersion(_) => CommandId::GetFirmwareVersion,
            Self::SerialNumber(_) => CommandId::GetSerialNumber,
            Self::DeviceName(_) => CommandId::GetDeviceName,
            Self::SensorData(_) => CommandId::GetSensorData,
        }
    }

    /// The reply frame from sensor `imu_id` (the mock's side). Text longer than its field is cut.
    pub fn to_frame(&self, imu_id: u16) -> Frame {
        let data = match self {
            Self::Ack | Self::Nack => Vec::new(),
            Self::Config(c) => c.0.to_le_bytes().to_vec(),
            Self::Status(v) | Self::ImuId(v) => v.to_le_bytes().to_vec(),
            Self::FirmwareVersion(v) => {
                [v.build, v.minor, v.major].iter().flat_map(|x| x.to_le_bytes()).collect()
            }
            Self::SerialNumber(s) => text_bytes(s, SERIAL_NUMBER_LEN),
            Self::DeviceName(s) => text_bytes(s, DEVICE_NAME_LEN),
            Self::SensorData(p) => p.clone(),
        };
        Frame::new(imu_id, self.id().code(), data)
    }

    /// Parses a reply frame (the host's side).
    pub fn from_frame(frame: &Frame) -> Result<Self, CommandError> {
        let id = CommandId::from_code(frame.cmd).ok_or(CommandError::UnknownCommand(frame.cmd))?;
        let d = frame.data.as_slice();
        Ok(match id {
            CommandId::ReplyAck => no_arg(id, d).map(|()| Self::Ack)?,
            CommandId::ReplyNack => no_arg(id, d).map(|()| Self::Nack)?,
            CommandId::GetConfig => Self::Config(ConfigRegister(u32_arg(id, d)?)),
            CommandId::GetStatus => Self::Status(u32_arg(id, d)?),
            CommandId::GetImuId => Self::ImuId(u32_arg(id, d)?),
            CommandId::GetFirmwareVersion => match d {
                [b0, b1, b2, b3, n0, n1, n2, n3, m0, m1, m2, m3] => Self::FirmwareVersion(FirmwareVersion {
                    build: u32::from_le_bytes([*b0, *b1, *b2, *b3]),
                    minor: u32::from_le_bytes([*n0, *n1, *n2, *n3]),
                    major: u32::from_le_bytes([*m0, *m1, *m2, *m3]),
                }),
                _ => return Err(CommandError::BadLength { command: id, expected: 12, actual: d.len() }),
            },
            CommandId::GetSerialNumber => Self::SerialNumber(text_arg(id, d, SERIAL_NUMBER_LEN)?),
            CommandId::GetDeviceName => Self::DeviceName(text_arg(id, d, DEVICE_NAME_LEN)?),
            CommandId::GetSensorData => Self::SensorData(d.to_vec()),
            other => return Err(CommandError::WrongDirection(other)),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all_commands() -> Vec<Command> {
        vec![
            Command::GotoCommandMode,
            Command::GotoStreamMode,
            Command::GetConfig,
            Command::GetStatus,
            Command::GetSensorData,
            Command::SetTransmitData(OutputMask::GYRO | OutputMask::QUATERNION),
            Command::SetStreamFreq(200),
            Command::WriteRegisters,
            Command::GetImuId,
            Command::GetFirmwareVersion,
            Command::SetLpbusDataMode(DataMode::Int16),
            Command::SetLpbusDataMode(DataMode::Float32),
            Command::ResetOrientationOffset,
            Command::GetSerialNumber,
            Command::GetDeviceName,
        ]
    }

    #[test]
    fn every_command_round_trips_through_the_wire() {
        for cmd in all_commands() {
            let bytes = cmd.to_frame(1).encode().unwrap();
            let mut d = super::super::frame::FrameDecoder::new();
            d.push(&bytes);
            let frame = d.next_frame().unwrap().unwrap();
            assert_eq!(Command::from_frame(&frame), Ok(cmd));
        }
    }

    #[test]
    fn every_reply_round_trips_through_the_wire() {
        let replies = vec![
            Reply::Ack,
            Reply::Nack,
            Reply::Config(ConfigRegister(0x0040_1804)),
            Reply::Status(3),
            Reply::ImuId(7),
            Reply::FirmwareVersion(FirmwareVersion { major: 2, minor: 0, build: 5 }),
            Reply::SerialNumber("LPMSB2-000123".into()),
            Reply::DeviceName("LPMSB2".into()),
            Reply::SensorData(vec![1, 0, 0, 0]),
        ];
        for r in replies {
            let bytes = r.to_frame(9).encode().unwrap();
            let mut d = super::super::frame::FrameDecoder::new();
            d.push(&bytes);
            let frame = d.next_frame().unwrap().unwrap();
            assert_eq!(frame.id, 9);
            assert_eq!(Reply::from_frame(&frame), Ok(r));
        }
    }

    #[test]
    fn ids_are_the_b2_set_not_the_ig1_set() {
        assert_eq!(CommandId::GetImuId.code(), 21);
        assert_eq!(CommandId::SetStreamFreq.code(), 11);
        assert_eq!(CommandId::SetTransmitData.code(), 10);
        assert_eq!(CommandId::WriteRegisters.code(), 15);
        assert_eq!(CommandId::from_code(30), None);
        for id in CommandId::ALL {
            assert_eq!(CommandId::from_code(id.code()), Some(id));
        }
    }

    #[test]
    fn bad_arguments_are_errors() {
        let f = Frame::new(1, 75, 7u32.to_le_bytes().to_vec());
        assert!(matches!(Command::from_frame(&f), Err(CommandError::BadArgument { value: 7, .. })));
        let f = Frame::new(1, 10, vec![1, 2]);
        assert!(matches!(
            Command::from_frame(&f),
            Err(CommandError::BadLength { expected: 4, actual: 2, .. })
        ));
        assert_eq!(
            Command::from_frame(&Frame::new(1, 0, vec![])),
            Err(CommandError::WrongDirection(CommandId::ReplyAck))
        );
        assert_eq!(Reply::from_frame(&Frame::new(1, 1234, vec![])), Err(CommandError::UnknownCommand(1234)));
        assert!(Reply::from_frame(&Frame::new(1, 47, vec![0; 11])).is_err());
    }
}
