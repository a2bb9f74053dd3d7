//! The LMDscandata telegram (`sRA`/`sSN LMDscandata`): every field of the notes' §3 table (SICK TI
//! §5.3, Wireshark `dissect_binary_scan_data`), and the [`Scan`] derived from it in robot units.

use serde::Serialize;

use super::args::{ArgReader, ArgWriter};
use super::error::DecodeError;
use super::framing::Dialect;

/// Upper bound on channel, encoder and data counts accepted from a telegram: a TiM5xx sends at
/// most 811 points and 2 channels; anything far beyond is a corrupt count, not data.
const MAX_COUNT: u16 = 4096;
const MAX_CHANNELS: u16 = 8;

/// One encoder block (field 14: position u32 + speed u16).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Encoder {
    pub position: u32,
    pub speed: u16,
}

/// One output channel (fields 16–22 or the 8-bit equivalent).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Channel<T> {
    /// `DIST1`, `RSSI1`, …
    pub content: String,
    pub scale_factor: f32,
    pub scale_offset: f32,
    /// Device frame, 1/10000°, 90° = straight ahead.
    pub start_angle_1e4deg: i32,
    pub step_1e4deg: u16,
    pub data: Vec<T>,
}

/// Field 24 when present: sensor mounting position (WS, TI).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PositionBlock {
    pub x: f32,
    pub y: f32,
    pub z: f32,
    pub rot_x: f32,
    pub rot_y: f32,
    pub rot_z: f32,
    pub rotation_type: u8,
    pub transmit_device_name: u8,
}

/// Field 27 when present: the device's clock (TI; the TiM781S sample counts from 1970 at boot).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct DeviceTime {
    pub year: u16,
    pub month: u8,
    pub day: u8,
    pub hour: u8,
    pub minute: u8,
    pub second: u8,
    pub microsecond: u32,
}

/// Field 28 when present.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct EventInfo {
    /// 4 chars, e.g. `FDIN`.
    pub kind: String,
    pub encoder_position: u32,
    pub event_time_us: u32,
    pub angle_1e4deg: i32,
}

/// Every field of an LMDscandata telegram body, as sent.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScanTelegram {
    pub version: u16,
    pub device_number: u16,
    pub serial: u32,
    pub device_status: [u8; 2],
    pub telegram_counter: u16,
    pub scan_counter: u16,
    /// Device tick at the end of the scan ("time since start-up", TI); the generation time.
    pub time_since_startup_us: u32,
    pub time_of_transmission_us: u32,
    pub input_status: [u8; 2],
    pub output_status: [u8; 2],
    /// Reserved / layer angle (0 on a TiM5xx).
    pub reserved_layer_angle: u16,
    /// 1/100 Hz (`5DC` = 15 Hz).
    pub scan_frequency_centi_hz: u32,
    /// 100 Hz units (`36` = 5.4 kHz).
    pub measurement_frequency_hecto_hz: u32,
    pub encoders: Vec<Encoder>,
    pub channels_16bit: Vec<Channel<u16>>,
    pub channels_8bit: Vec<Channel<u8>>,
    pub position: Option<PositionBlock>,
    pub device_name: Option<String>,
    pub comment: Option<String>,
    pub time: Option<DeviceTime>,
    pub event: Option<EventInfo>,
}

fn count(r: &mut ArgReader<'_>, what: &'static str, max: u16) -> Result<u16, DecodeError> {
    let n = r.u16(what)?;
    if n > max {
        return Err(DecodeError::OutOfRange { what, value: n.into() });
    }
    Ok(n)
}

fn channel_header<T>(r: &mut ArgReader<'_>) -> Result<Channel<T>, DecodeError> {
    Ok(Channel {
        content: r.fixed("channel content", 5)?,
        scale_factor: r.f32("scale factor")?,
        scale_offset: r.f32("scale offset")?,
        start_angle_1e4deg: r.i32("start angle")?,
        step_1e4deg: r.u16("angular step")?,
        data: Vec::new(),
    })
}

fn write_channel_header<T>(w: &mut ArgWriter, c: &Channel<T>) -> Result<u16, DecodeError> {
    w.fixed(&c.content);
    w.f32(c.scale_factor);
    w.f32(c.scale_offset);
    w.i32(c.start_angle_1e4deg);
    w.u16(c.step_1e4deg);
    let n = u16::try_from(c.data.len())
        .map_err(|_| DecodeError::OutOfRange { what: "number of data", value: c.data.len() as i64 })?;
    w.u16(n);
    Ok(n)
}

/// A count of channels, then each channel: its header, its count of data, the data.
fn channels<T>(
    r: &mut ArgReader<'_>,
    what: &'static str,
    mut value: impl FnMut(&mut ArgReader<'_>) -> Result<T, DecodeError>,
) -> Result<Vec<Channel<T>>, DecodeError> {
    let n = count(r, what, MAX_CHANNELS)?;
    let mut out = Vec::new();
    for _ in 0..n {
        let mut c = channel_header::<T>(r)?;
        let n = count(r, "number of data", MAX_COUNT)?;
        for _ in 0..n {
            c.data.push(value(r)?);
        }
        out.push(c);
    }
    Ok(out)
}

/// An optional block: its 16-bit presence flag, then the block when present.
fn optional<T>(
    r: &mut ArgReader<'_>,
    flag: &'static str,
    block: impl FnOnce(&mut ArgReader<'_>) -> Result<T, DecodeError>,
) -> Result<Option<T>, DecodeError> {
    if r.flag16(flag)? { block(r).map(Some) } else { Ok(None) }
}

impl PositionBlock {
    fn decode(r: &mut ArgReader<'_>) -> Result<Self, DecodeError> {
        Ok(PositionBlock {
            x: r.f32("position x")?,
            y: r.f32("position y")?,
            z: r.f32("position z")?,
            rot_x: r.f32("rotation x")?,
            rot_y: r.f32("rotation y")?,
            rot_z: r.f32("rotation z")?,
            rotation_type: r.u8("rotation type")?,
            transmit_device_name: r.u8("transmit device name")?,
        })
    }
}

impl DeviceTime {
    fn decode(r: &mut ArgReader<'_>) -> Result<Self, DecodeError> {
        Ok(DeviceTime {
            year: r.u16("year")?,
            month: r.u8("month")?,
            day: r.u8("day")?,
            hour: r.u8("hour")?,
            minute: r.u8("minute")?,
            second: r.u8("second")?,
            microsecond: r.u32("microsecond")?,
        })
    }
}

impl EventInfo {
    fn decode(r: &mut ArgReader<'_>) -> Result<Self, DecodeError> {
        Ok(EventInfo {
            kind: r.fixed("event type", 4)?,
            encoder_position: r.u32("event encoder position")?,
            event_time_us: r.u32("event time")?,
            angle_1e4deg: r.i32("event angle")?,
        })
    }
}

impl ScanTelegram {
    /// Decodes the arguments after `sRA LMDscandata` / `sSN LMDscandata`. Every count is taken
    /// from the telegram and must match the data; bytes left over are an error.
    pub(crate) fn decode(r: &mut ArgReader<'_>) -> Result<Self, DecodeError> {
        let version = r.u16("version")?;
        let device_number = r.u16("device number")?;
        let serial = r.u32("serial number")?;
        let device_status = [r.u8("device status")?, r.u8("device status")?];
        let telegram_counter = r.u16("telegram counter")?;
        let scan_counter = r.u16("scan counter")?;
        let time_since_startup_us = r.u32("time since start-up")?;
        let time_of_transmission_us = r.u32("time of transmission")?;
        let input_status = [r.u8("input status")?, r.u8("input status")?];
        let output_status = [r.u8("output status")?, r.u8("output status")?];
        let reserved_layer_angle = r.u16("reserved")?;
        let scan_frequency_centi_hz = r.u32("scan frequency")?;
        let measurement_frequency_hecto_hz = r.u32("measurement frequency")?;
        let n_enc = count(r, "number of encoders", MAX_CHANNELS)?;
        let mut encoders = Vec::new();
        for _ in 0..n_enc {
            encoders.push(Encoder { position: r.u32("encoder position")?, speed: r.u16("encoder speed")? });
        }
        let channels_16bit = channels(r, "number of 16-bit channels", |r| r.u16("16-bit data"))?;
        let channels_8bit = channels(r, "number of 8-bit channels", |r| r.u8("8-bit data"))?;
        let position = optional(r, "position present", PositionBlock::decode)?;
        let device_name = optional(r, "name present", |r| r.string("device name"))?;
        let comment = optional(r, "comment present", |r| r.string("comment"))?;
        let time = optional(r, "time present", DeviceTime::decode)?;
        let event = optional(r, "event present", EventInfo::decode)?;
        r.finish()?;
        Ok(Self {
            version,
            device_number,
            serial,
            device_status,
            telegram_counter,
            scan_counter,
            time_since_startup_us,
            time_of_transmission_us,
            input_status,
            output_status,
            reserved_layer_angle,
            scan_frequency_centi_hz,
            measurement_frequency_hecto_hz,
            encoders,
            channels_16bit,
            channels_8bit,
            position,
            device_name,
            comment,
            time,
            event,
        })
    }

    /// Encodes the body (device side; the mock builds its telegrams with this).
    pub(crate) fn encode(&self, w: &mut ArgWriter) -> Result<(), DecodeError> {
        w.u16(self.version);
        w.u16(self.device_number);
        w.u32(self.serial);
        self.device_status.iter().for_each(|b| w.u8(*b));
        w.u16(self.telegram_counter);
        w.u16(self.scan_counter);
        w.u32(self.time_since_startup_us);
        w.u32(self.time_of_transmission_us);
        self.input_status.iter().for_each(|b| w.u8(*b));
        self.output_status.iter().for_each(|b| w.u8(*b));
        w.u16(self.reserved_layer_angle);
        w.u32(self.scan_frequency_centi_hz);
        w.u32(self.measurement_frequency_hecto_hz);
        w.u16(self.encoders.len() as u16);
        for e in &self.encoders {
            w.u32(e.position);
            w.u16(e.speed);
        }
        w.u16(self.channels_16bit.len() as u16);
        for c in &self.channels_16bit {
            write_channel_header(w, c)?;
            c.data.iter().for_each(|v| w.u16(*v));
        }
        w.u16(self.channels_8bit.len() as u16);
        for c in &self.channels_8bit {
            write_channel_header(w, c)?;
            c.data.iter().for_each(|v| w.u8(*v));
        }
        w.flag16(self.position.is_some());
        if let Some(p) = &self.position {
            for v in [p.x, p.y, p.z, p.rot_x, p.rot_y, p.rot_z] {
                w.f32(v);
            }
            w.u8(p.rotation_type);
            w.u8(p.transmit_device_name);
        }
        w.flag16(self.device_name.is_some());
        if let Some(n) = &self.device_name {
            w.string(n);
        }
        w.flag16(self.comment.is_some());
        if let Some(c) = &self.comment {
            w.string(c);
        }
        w.flag16(self.time.is_some());
        if let Some(t) = &self.time {
            w.u16(t.year);
            for v in [t.month, t.day, t.hour, t.minute, t.second] {
                w.u8(v);
            }
            w.u32(t.microsecond);
        }
        w.flag16(self.event.is_some());
        if let Some(e) = &self.event {
            w.fixed(&e.kind);
            w.u32(e.encoder_position);
            w.u32(e.event_time_us);
            w.i32(e.angle_1e4deg);
        }
        Ok(())
    }

    /// Decodes a telegram body given in a dialect (the bytes after `sSN LMDscandata`).
    pub fn decode_args(dialect: Dialect, args: &[u8]) -> Result<Self, DecodeError> {
        Self::decode(&mut ArgReader::new(dialect, args))
    }
}

/// One scan in robot units: ranges in metres, beam angles in the robot frame (device angle − 90°,
/// radians; sick_tim `angle_min = start − π/2`, sick_scan_xd `setScanAngleShift(-M_PI/2)`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Scan {
    pub serial: u32,
    pub device_status: [u8; 2],
    pub telegram_counter: u16,
    pub scan_counter: u16,
    /// Device tick at the end of the scan (µs since start-up).
    pub generation_tick_us: u32,
    /// Device tick when the telegram was sent.
    pub transmission_tick_us: u32,
    pub scan_frequency_hz: f64,
    pub measurement_frequency_hz: f64,
    /// Angle of the first beam, robot frame.
    pub angle_min_rad: f64,
    pub angle_increment_rad: f64,
    /// One angle per beam, robot frame.
    pub angles_rad: Vec<f64>,
    /// DIST × scale + offset, mm → m; 0 means no return (sick_tim maps it to +inf).
    pub ranges_m: Vec<f32>,
    /// RSSI1 (16- or 8-bit channel) when the device sends it.
    pub rssi: Option<Vec<u16>>,
}

impl Scan {
    /// Derives the robot-unit scan; errors without a `DIST` channel or when channel counts differ.
    pub fn from_telegram(t: &ScanTelegram) -> Result<Self, DecodeError> {
        let dist = t
            .channels_16bit
            .iter()
            .find(|c| c.content.starts_with("DIST"))
            .ok_or(DecodeError::NoDistanceChannel)?;
        let n = dist.data.len();
        let rssi16 = t.channels_16bit.iter().find(|c| c.content.starts_with("RSSI"));
        let rssi8 = t.channels_8bit.iter().find(|c| c.content.starts_with("RSSI"));
        let rssi: Option<Vec<u16>> = match (rssi16, rssi8) {
            (Some(c), _) => Some(c.data.clone()),
            (None, Some(c)) => Some(c.data.iter().map(|v| u16::from(*v)).collect()),
            (None, None) => None,
        };
        if let Some(r) = &rssi
            && r.len() != n
        {
            return Err(DecodeError::CountMismatch {
                what: format!("DIST has {n} values, RSSI {}", r.len()),
            });
        }
        let deg = std::f64::consts::PI / 180.0;
        let angle_min_rad = (f64::from(dist.start_angle_1e4deg) / 1e4 - 90.0) * deg;
        let angle_increment_rad = f64::from(dist.step_1e4deg) / 1e4 * deg;
        let angles_rad = (0..n).map(|i| angle_min_rad + i as f64 * angle_increment_rad).collect();
        let ranges_m = dist
            .data
            .iter()
            .map(|&v| (f32::from(v) * dist.scale_factor + dist.scale_offset) / 1000.0)
            .collect();
        let mut measurement_frequency_hz = f64::from(t.measurement_frequency_hecto_hz) * 100.0;
        if t.measurement_frequency_hecto_hz > 10_000 {
            // sick_scan_xd divides by 100 here ("firmware inconsistency", notes §3 field 13).
            measurement_frequency_hz /= 100.0;
        }
        Ok(Self {
            serial: t.serial,
            device_status: t.device_status,
            telegram_counter: t.telegram_counter,
            scan_counter: t.scan_counter,
            generation_tick_us: t.time_since_startup_us,
            transmission_tick_us: t.time_of_transmission_us,
            scan_frequency_hz: f64::from(t.scan_frequency_centi_hz) / 100.0,
            measurement_frequency_hz,
            angle_min_rad,
            angle_increment_rad,
            angles_rad,
            ranges_m,
            rssi,
        })
    }
}
