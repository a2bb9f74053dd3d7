//! The B2 config register and the sensor-data payload (command 9) in float and 16-bit modes.
//!
//! Bit numbers, field order and 16-bit scales: research notes Part A3 (OpenMAT
//! `LpmsRegisterDefinitions.h`, `LpmsIoInterface.cpp::parseSensorData`, `LpmsB2.java::parseSensorData16Bit`,
//! OpenZen `ImuComponent.cpp::parseSensorData`).

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Seconds per timestamp tick: the B2 counts at 400 Hz (notes A3, FW ≥ 1.3.5).
pub const TIMESTAMP_TICK_S: f64 = 0.0025;

/// Output-selection bits of the config register / SET_TRANSMIT_DATA (notes A3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
pub struct OutputMask(pub u32);

impl OutputMask {
    /// Bit 9: barometric pressure.
    pub const PRESSURE: Self = Self(1 << 9);
    /// Bit 10: raw magnetometer.
    pub const MAG: Self = Self(1 << 10);
    /// Bit 11: raw accelerometer.
    pub const ACC: Self = Self(1 << 11);
    /// Bit 12: raw gyroscope.
    pub const GYRO: Self = Self(1 << 12);
    /// Bit 13: temperature.
    pub const TEMPERATURE: Self = Self(1 << 13);
    /// Bit 14: heave motion.
    pub const HEAVE: Self = Self(1 << 14);
    /// Bit 16: angular velocity.
    pub const ANGULAR_VELOCITY: Self = Self(1 << 16);
    /// Bit 17: Euler angles.
    pub const EULER: Self = Self(1 << 17);
    /// Bit 18: quaternion.
    pub const QUATERNION: Self = Self(1 << 18);
    /// Bit 19: altitude.
    pub const ALTITUDE: Self = Self(1 << 19);
    /// Bit 21: linear acceleration.
    pub const LINEAR_ACC: Self = Self(1 << 21);
    /// Every output bit that adds a payload field.
    pub const ALL: Self = Self(
        Self::PRESSURE.0
            | Self::MAG.0
            | Self::ACC.0
            | Self::GYRO.0
            | Self::TEMPERATURE.0
            | Self::HEAVE.0
            | Self::ANGULAR_VELOCITY.0
            | Self::EULER.0
            | Self::QUATERNION.0
            | Self::ALTITUDE.0
            | Self::LINEAR_ACC.0,
    );

    /// Whether every bit of `other` is set.
    pub fn contains(self, other: Self) -> bool {
        self.0 & other.0 == other.0
    }

    /// Only the output bits (drops stream-rate, data-mode and other config bits).
    pub fn outputs_only(self) -> Self {
        Self(self.0 & Self::ALL.0)
    }
}

impl std::ops::BitOr for OutputMask {
    type Output = Self;
    fn bitor(self, rhs: Self) -> Self {
        Self(self.0 | rhs.0)
    }
}

/// LPBUS data mode (SET_LPBUS_DATA_MODE 75: 0 float, 1 int16; config bit 22).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
pub enum DataMode {
    /// Every value an f32 (LE). A robot file spells it `float`.
    #[default]
    #[serde(rename = "float")]
    Float32,
    /// Every value an i16 (LE) with a per-field scale; `int16` in a robot file.
    #[serde(rename = "int16")]
    Int16,
}

impl DataMode {
    /// The SET_LPBUS_DATA_MODE argument.
    pub fn wire_value(self) -> u32 {
        match self {
            Self::Float32 => 0,
            Self::Int16 => 1,
        }
    }

    /// From the SET_LPBUS_DATA_MODE argument; other values are not a mode.
    pub fn from_wire(v: u32) -> Option<Self> {
        match v {
            0 => Some(Self::Float32),
            1 => Some(Self::Int16),
            _ => None,
        }
    }

    fn value_len(self) -> usize {
        match self {
            Self::Float32 => 4,
            Self::Int16 => 2,
        }
    }
}

/// Stream rates the B2 supports, indexed by the config register's bits 0–2 (notes A3).
pub const STREAM_RATES_HZ: [u32; 8] = [5, 10, 25, 50, 100, 200, 400, 800];

/// Config register bit 22: 16-bit data mode.
const CONFIG_16BIT: u32 = 1 << 22;
/// Config register bits 0–2: stream-rate code.
const CONFIG_FREQ_MASK: u32 = 0x7;

/// The u32 config register (GET_CONFIG reply).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct ConfigRegister(pub u32);

impl ConfigRegister {
    /// A register value describing these settings; `None` if `stream_hz` is not a B2 rate.
    pub fn from_settings(outputs: OutputMask, data_mode: DataMode, stream_hz: u32) -> Option<Self> {
        let code = STREAM_RATES_HZ.iter().position(|&r| r == stream_hz)? as u32;
        let mode = if data_mode == DataMode::Int16 { CONFIG_16BIT } else { 0 };
        Some(Self(outputs.outputs_only().0 | mode | code))
    }

    /// Stream rate from bits 0–2.
    pub fn stream_hz(self) -> u32 {
        STREAM_RATES_HZ[(self.0 & CONFIG_FREQ_MASK) as usize]
    }

    /// Data mode from bit 22.
    pub fn data_mode(self) -> DataMode {
        if self.0 & CONFIG_16BIT != 0 { DataMode::Int16 } else { DataMode::Float32 }
    }

    /// The output bits.
    pub fn outputs(self) -> OutputMask {
        OutputMask(self.0).outputs_only()
    }
}

/// One decoded sensor-data packet. Fields absent from the output mask are `None`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SensorData {
    /// Sensor timestamp counter (400 Hz ticks, [`TIMESTAMP_TICK_S`]).
    pub timestamp_ticks: u32,
    /// Raw gyroscope, rad/s.
    pub gyro_radps: Option<[f32; 3]>,
    /// Raw accelerometer, g (the libraries apply no scaling; notes A3).
    pub acc_g: Option<[f32; 3]>,
    /// Raw magnetometer, µT.
    pub mag_ut: Option<[f32; 3]>,
    /// Angular velocity, rad/s.
    pub angular_velocity_radps: Option<[f32; 3]>,
    /// Orientation quaternion w, x, y, z.
    pub quaternion_wxyz: Option<[f32; 4]>,
    /// Euler angles x, y, z, rad.
    pub euler_rad: Option<[f32; 3]>,
    /// Linear acceleration, g.
    pub linear_acc_g: Option<[f32; 3]>,
    /// Pressure as sent; the unit is unverified (notes A3: libraries apply no scaling).
    pub pressure_raw: Option<f32>,
    /// Altitude, m.
    pub altitude_m: Option<f32>,
    /// Temperature, °C.
    pub temperature_c: Option<f32>,
    /// Heave, m.
    pub heave_m: Option<f32>,
}

impl SensorData {
    /// Sensor time of this sample in seconds since the counter's zero.
    pub fn timestamp_s(&self) -> f64 {
        f64::from(self.timestamp_ticks) * TIMESTAMP_TICK_S
    }
}

/// A sensor-data payload that does not match the configured layout.
#[derive(Debug, Clone, PartialEq, Eq, Error, Serialize, Deserialize)]
#[error(
    "sensor-data payload is {actual} bytes, the output mask {mask:#010x} in {mode:?} mode needs {expected}"
)]
pub struct DataLengthError {
    /// Length the mask and mode require.
    pub expected: usize,
    /// Length received.
    pub actual: usize,
    /// Output mask used.
    pub mask: u32,
    /// Data mode used.
    pub mode: DataMode,
}

/// The payload fields in wire order: mask bit, value count, 16-bit divisor (notes A3 table).
const FIELDS: [(OutputMask, usize, f32); 11] = [
    (OutputMask::GYRO, 3, 1000.0),
    (OutputMask::ACC, 3, 1000.0),
    (OutputMask::MAG, 3, 100.0),
    (OutputMask::ANGULAR_VELOCITY, 3, 1000.0),
    (OutputMask::QUATERNION, 4, 10000.0),
    (OutputMask::EULER, 3, 10000.0),
    (OutputMask::LINEAR_ACC, 3, 1000.0),
    (OutputMask::PRESSURE, 1, 100.0),
    (OutputMask::ALTITUDE, 1, 10.0),
    (OutputMask::TEMPERATURE, 1, 100.0),
    (OutputMask::HEAVE, 1, 1000.0),
];

/// Payload length for this mask and mode: 4 timestamp bytes plus every enabled field.
pub fn payload_len(mask: OutputMask, mode: DataMode) -> usize {
    4 + FIELDS
        .iter()
        .filter(|(bit, _, _)| mask.contains(*bit))
        .map(|(_, n, _)| n * mode.value_len())
        .sum::<usize>()
}

/// Decodes a command-9 payload. A length that does not match the mask is an error, never a guess.
pub fn decode_sensor_data(
    payload: &[u8],
    mask: OutputMask,
    mode: DataMode,
) -> Result<SensorData, DataLengthError> {
    let expected = payload_len(mask, mode);
    if payload.len() != expected {
        return Err(DataLengthError { expected, actual: payload.len(), mask: mask.0, mode });
    }
    let mut values = payload[4..].chunks_exact(mode.value_len()).map(|c| match c {
        [a, b, c, d] => f32::from_le_bytes([*a, *b, *c, *d]),
        [a, b] => f32::from(i16::from_le_bytes([*a, *b])),
        _ => f32::NAN,
    });
    let mut out = SensorData {
        timestamp_ticks: u32::from_le_bytes([payload[0], payload[1], payload[2], payload[3]]),
        ..SensorData::default()
    };
    for (bit, n, divisor) in FIELDS {
        if !mask.contains(bit) {
            continue;
        }
        let divisor = if mode == DataMode::Int16 { divisor } else { 1.0 };
        let mut v = [0.0f32; 4];
        for slot in v.iter_mut().take(n) {
            *slot = values.next().unwrap_or(f32::NAN) / divisor;
        }
        let v3 = [v[0], v[1], v[2]];
        match bit {
            OutputMask::GYRO => out.gyro_radps = Some(v3),
            OutputMask::ACC => out.acc_g = Some(v3),
            OutputMask::MAG => out.mag_ut = Some(v3),
            OutputMask::ANGULAR_VELOCITY => out.angular_velocity_radps = Some(v3),
            OutputMask::QUATERNION => out.quaternion_wxyz = Some(v),
            OutputMask::EULER => out.euler_rad = Some(v3),
            OutputMask::LINEAR_ACC => out.linear_acc_g = Some(v3),
            OutputMask::PRESSURE => out.pressure_raw = Some(v[0]),
            OutputMask::ALTITUDE => out.altitude_m = Some(v[0]),
            OutputMask::TEMPERATURE => out.temperature_c = Some(v[0]),
            _ => out.heave_m = Some(v[0]),
        }
    }
    Ok(out)
}

/// Encodes a command-9 payload (the mock's side). Fields enabled in `mask` but `None` in `data` are
/// sent as zero; in 16-bit mode values are scaled, rounded and saturated to i16.
pub fn encode_sensor_data(data: &SensorData, mask: OutputMask, mode: DataMode) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload_len(mask, mode));
    out.extend_from_slice(&data.timestamp_ticks.to_le_bytes());
    let v3 = |v: Option<[f32; 3]>| v.map(|a| a.to_vec()).unwrap_or_else(|| vec![0.0; 3]);
    let v1 = |v: Option<f32>| vec![v.unwrap_or(0.0)];
    for (bit, _, divisor) in FIELDS {
        if !mask.contains(bit) {
            continue;
        }
        let values = match bit {
            OutputMask::GYRO => v3(data.gyro_radps),
            OutputMask::ACC => v3(data.acc_g),
            OutputMask::MAG => v3(data.mag_ut),
            OutputMask::ANGULAR_VELOCITY => v3(data.angular_velocity_radps),
            OutputMask::QUATERNION => {
                data.quaternion_wxyz.map(|a| a.to_vec()).unwrap_or_else(|| vec![0.0; 4])
            }
            OutputMask::EULER => v3(data.euler_rad),
            OutputMask::LINEAR_ACC => v3(data.linear_acc_g),
            OutputMask::PRESSURE => v1(data.pressure_raw),
            OutputMask::ALTITUDE => v1(data.altitude_m),
            OutputMask::TEMPERATURE => v1(data.temperature_c),
            _ => v1(data.heave_m),
        };
        for v in values {
            match mode {
                DataMode::Float32 => out.extend_from_slice(&v.to_le_bytes()),
                DataMode::Int16 => {
                    // `as` saturates and maps NaN to 0, which is what a device clamping would do.
                    let q = (v * divisor).round() as i16;
                    out.extend_from_slice(&q.to_le_bytes());
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_full_float_payload_is_108_bytes() {
        // Notes A3: "Max 32-bit payload with everything on = 4+12·6+16+4·4 = 108 bytes".
        assert_eq!(payload_len(OutputMask::ALL, DataMode::Float32), 108);
        assert_eq!(payload_len(OutputMask::ALL, DataMode::Int16), 56);
        assert_eq!(payload_len(OutputMask::default(), DataMode::Float32), 4);
    }

    #[test]
    fn config_register_round_trips_settings() {
        let mask = OutputMask::GYRO | OutputMask::QUATERNION;
        let reg = ConfigRegister::from_settings(mask, DataMode::Int16, 100).unwrap();
        assert_eq!(reg.stream_hz(), 100);
        assert_eq!(reg.data_mode(), DataMode::Int16);
        assert_eq!(reg.outputs(), mask);
        assert_eq!(reg.0 & 0x7, 4);
        assert!(ConfigRegister::from_settings(mask, DataMode::Float32, 99).is_none());
    }

    #[test]
    fn a_short_payload_is_an_error() {
        let err = decode_sensor_data(&[0; 15], OutputMask::GYRO, DataMode::Float32).unwrap_err();
        assert_eq!((err.expected, err.actual), (16, 15));
        assert!(decode_sensor_data(&[0; 17], OutputMask::GYRO, DataMode::Float32).is_err());
    }

    #[test]
    fn int16_values_are_scaled_per_field() {
        let mut p = 7u32.to_le_bytes().to_vec();
        for v in [1000i16, -2000, 3, 1234, 4] {
            p.extend_from_slice(&v.to_le_bytes());
        }
        let d = decode_sensor_data(
            &p,
            OutputMask::GYRO | OutputMask::TEMPERATURE | OutputMask::ALTITUDE,
            DataMode::Int16,
        )
        .unwrap();
        assert_eq!(d.timestamp_ticks, 7);
        assert_eq!(d.gyro_radps, Some([1.0, -2.0, 0.003]));
        // Wire order: altitude (bit 19, /10) before temperature (bit 13, /100).
        assert_eq!(d.altitude_m, Some(123.4));
        assert_eq!(d.temperature_c, Some(0.04));
    }
}
