//! A mock TECO drive as a pure CiA 402 node (frames in, frames out, `now` passed in): object
//! dictionary, SDO server, PDO mapping with the remap rules, heartbeat producer, consumer of the
//! master's heartbeat with the 0x6007 reaction, the 402 state machine, a motor and EMCY on faults.
//! Built from `amr_drivers::canopen` pieces used from the device's side.
//!
//! It is one file because the object dictionary is the drive's whole state: the SDO server, the
//! PDOs, the heartbeat reaction, the 402 state machine and the fault injection all read and write
//! the same objects.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use amr_drivers::canopen::cia402::{self, State402, controlword};
use amr_drivers::canopen::emcy::{EMCY_BUS_OFF_RECOVERED, EMCY_HEARTBEAT, Emcy};
use amr_drivers::canopen::frame::{CanFrame, Cob, NodeId};
use amr_drivers::canopen::heartbeat::{HeartbeatConsumer, HeartbeatProducer};
use amr_drivers::canopen::nmt::{NmtCommand, NmtState};
use amr_drivers::canopen::pdo::{self, COB_ID_INVALID, MapEntry, PdoDirection};
use amr_drivers::canopen::sdo::{AbortCode, ObjectAddr, ObjectDictionary, SdoServer, abort_bytes};

use super::motor::Motor;

/// Device type 0x1000 of a CiA 402 servo drive (profile 402, type 0x0002).
pub const DEVICE_TYPE_402_SERVO: u32 = 0x0002_0192;

/// What a mock drive is.
#[derive(Debug, Clone, PartialEq)]
pub struct TecoDriveConfig {
    /// Node id.
    pub node_id: NodeId,
    /// Encoder counts per motor revolution.
    pub encoder_counts_per_rev: u32,
    /// 0x60FF/0x606C units per motor revolution per second.
    pub velocity_units_per_rps: f64,
    /// Encoder position at power-on (put it near ±2³¹ to exercise the wrap).
    pub initial_position_counts: i64,
    /// Standard deviation of the reported position, counts.
    pub encoder_noise_counts: f64,
    /// Fraction of the motion the encoder does not see, 0..1.
    pub slip: f64,
    /// Seed of the noise.
    pub seed: u64,
    /// 0x1017 after boot (0 = no heartbeat until the master sets it).
    pub heartbeat_producer_ms: u16,
    /// 0x6083/0x6084/0x6085 after boot, velocity units/s.
    pub default_acceleration: u32,
    /// 0x1008, long enough to need a segmented upload.
    pub device_name: String,
}

impl TecoDriveConfig {
    /// Defaults matching `config/robot-*.toml` (10000 counts/rev, 10000 units per rev/s).
    pub fn new(node_id: NodeId) -> Self {
        Self {
            node_id,
            encoder_counts_per_rev: 10_000,
            velocity_units_per_rps: 10_000.0,
            initial_position_counts: 0,
            encoder_noise_counts: 0.0,
            slip: 0.0,
            seed: u64::from(node_id),
            heartbeat_producer_ms: 0,
            default_acceleration: 100_000,
            device_name: "TECO mock CiA 402 drive".to_owned(),
        }
    }
}

/// A fault to inject (devices.md §4).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Fault {
    /// Drive fault: EMCY with `code`, state Fault, 0x603F = `code`.
    DriveFault {
        /// EMCY / 0x603F error code (e.g. 0x2310 overcurrent).
        code: u16,
    },
    /// Stop (true) or resume (false) sending heartbeats.
    HeartbeatLoss(bool),
    /// Bus-off: deaf and mute for `duration`, then EMCY 0x8140 (recovered from bus-off).
    BusOff {
        /// How long.
        duration: Duration,
    },
    /// Power cycle: defaults restored, boot-up sent again.
    Reboot,
    /// The next SDO request to `index` is aborted with `code`.
    SdoAbort {
        /// The object index.
        index: u16,
        /// The abort code.
        code: u32,
    },
    /// Delay every SDO response by this much (zero to clear).
    SlowSdo(Duration),
    /// Drop the next `count` frames the drive sends.
    DropFrames(u32),
    /// The digital inputs (0x60FD) read `bits` from now: a switch pressed or released.
    Inputs(u32),
}

/// The digital inputs (0x60FD) at power-on: bit 16 (manufacturer-specific) high, the e-stop chain
/// closed, as the robot files wire it (`devices.drives.estop_input_bit = 16`, active low).
pub const DEFAULT_INPUTS: u32 = 1 << 16;

/// What a test can observe of a mock drive.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriveSnapshot {
    /// NMT state.
    pub nmt: NmtState,
    /// CiA 402 state.
    pub state: State402,
    /// Last controlword.
    pub controlword: u16,
    /// Target velocity 0x60FF, units.
    pub target_velocity: i32,
    /// Shaft speed, counts/s.
    pub velocity_cps: f64,
    /// Exact encoder position, counts.
    pub position_counts: f64,
    /// Mode display 0x6061.
    pub mode_display: i8,
    /// 0x1016:01 as written.
    pub master_consumer: u32,
    /// 0x6007.
    pub comm_loss_reaction: i16,
    /// Boot-ups sent.
    pub boots: u32,
    /// Times the drive entered Operation enabled.
    pub enables: u32,
    /// Times it entered Operation enabled without its PDO remap and 0x1016 done since the last boot.
    pub enables_unconfigured: u32,
    /// Times the master's heartbeat was found lost.
    pub master_losses: u32,
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct PdoParams {
    cob: u32,
    transmission: u8,
    map: [u32; 8],
    count: u8,
}

impl PdoParams {
    fn new(cob: u32, map: &[MapEntry]) -> Self {
        let mut m = [0u32; 8];
        for (slot, e) in m.iter_mut().zip(map) {
            *slot = e.raw();
        }
        Self { cob, transmission: 255, map: m, count: map.len() as u8 }
    }

    fn valid(&self) -> bool {
        self.cob & COB_ID_INVALID == 0
    }

    fn entries(&self) -> Vec<MapEntry> {
        self.map[..usize::from(self.count.min(8))].iter().map(|r| MapEntry::from_raw(*r)).collect()
    }

    fn synchronous(&self) -> bool {
        (1..=240).contains(&self.transmission)
    }
}

/// Objects that may be mapped, and whether into an RPDO (writable) or a TPDO.
fn mappable(index: u16, receive: bool) -> bool {
    if receive {
        matches!(index, 0x6040 | 0x60FF | 0x6060)
    } else {
        matches!(index, 0x6041 | 0x606C | 0x6064 | 0x6061 | 0x603F | 0x60FD)
    }
}

/// The object dictionary and everything it drives.
#[derive(Debug)]
struct Objects {
    cfg: TecoDriveConfig,
    now: Instant,
    nmt: NmtState,
    state: State402,
    controlword: u16,
    mode: i8,
    mode_display: i8,
    target_velocity: i32,
    accel: u32,
    decel: u32,
    quick_stop_decel: u32,
    comm_loss: i16,
    error_code: u16,
    heartbeat_ms: u16,
    producer: HeartbeatProducer,
    master_consumer_raw: u32,
    consumer: HeartbeatConsumer,
    rpdo1: PdoParams,
    tpdo: [PdoParams; 2],
    motor: Motor,
    last_motion: Instant,
    /// Frames produced by side effects (EMCY), sent by the node.
    out: Vec<CanFrame>,
    remapped: bool,
    stats: DriveSnapshot,
    /// 0x60FD: the wired inputs (physical: kept across a reboot).
    inputs: u32,
}

impl Objects {
    fn boot(cfg: TecoDriveConfig, now: Instant, motor: Motor, stats: DriveSnapshot) -> Self {
        let id = cfg.node_id;
        let rx = PdoDirection::Receive;
        let tx = PdoDirection::Transmit;
        Self {
            now,
            nmt: NmtState::PreOperational,
            state: State402::SwitchOnDisabled,
            controlword: 0,
            mode: 0,
            mode_display: 0,
            target_velocity: 0,
            accel: cfg.default_acceleration,
            decel: cfg.default_acceleration,
            quick_stop_decel: cfg.default_acceleration,
            comm_loss: 0,
            error_code: 0,
            heartbeat_ms: cfg.heartbeat_producer_ms,
            producer: HeartbeatProducer::new(
                Duration::from_millis(u64::from(cfg.heartbeat_producer_ms)),
                now,
            ),
            master_consumer_raw: 0,
            consumer: HeartbeatConsumer::new(Duration::ZERO),
            // Factory mapping differs from the master's, so a skipped remap shows.
            rpdo1: PdoParams::new(rx.default_cob_id(1, id), &[pdo::CONTROLWORD]),
            tpdo: [
                PdoParams::new(tx.default_cob_id(1, id), &[pdo::STATUSWORD]),
                PdoParams::new(tx.default_cob_id(2, id) | COB_ID_INVALID, &[]),
            ],
            motor,
            last_motion: now,
            out: Vec::new(),
            remapped: false,
            stats,
            cfg,
            inputs: DEFAULT_INPUTS,
        }
    }

    fn units_to_cps(&self, units: f64) -> f64 {
        units / self.cfg.velocity_units_per_rps * f64::from(self.cfg.encoder_counts_per_rev)
    }

    /// Run the motor up to `now`.
    fn advance(&mut self, now: Instant) {
        let dt = now.saturating_duration_since(self.last_motion).as_secs_f64();
        self.last_motion = self.last_motion.max(now);
        self.now = self.last_motion;
        let halted = self.controlword & controlword::HALT != 0;
        let (target, accel, decel) = match self.state {
            State402::OperationEnabled if !halted && self.mode_display == 3 => {
                (self.units_to_cps(f64::from(self.target_velocity)), self.accel, self.decel)
            }
            State402::OperationEnabled => (0.0, self.decel, self.decel),
            _ => (0.0, self.quick_stop_decel, self.quick_stop_decel),
        };
        let (a, d) = (self.units_to_cps(f64::from(accel)), self.units_to_cps(f64::from(decel)));
        self.motor.advance(dt, target, a, d);
    }

    fn statusword(&self) -> u16 {
        let mut sw = self.state.statusword_bits() | cia402::SW_REMOTE;
        if matches!(
            self.state,
            State402::ReadyToSwitchOn
                | State402::SwitchedOn
                | State402::OperationEnabled
                | State402::QuickStopActive
        ) {
            sw |= cia402::SW_VOLTAGE_ENABLED;
        }
        let target = self.units_to_cps(f64::from(self.target_velocity));
        if (self.motor.velocity_cps - target).abs() < 1.0 {
            sw |= cia402::SW_TARGET_REACHED;
        }
        if self.motor.velocity_cps.abs() < 1.0 {
            sw |= cia402::SW_PV_SPEED_ZERO;
        }
        sw
    }

    fn velocity_units(&self) -> i32 {
        let v = self.motor.velocity_cps / f64::from(self.cfg.encoder_counts_per_rev.max(1))
            * self.cfg.velocity_units_per_rps;
        v.round() as i32
    }

    fn set_state(&mut self, new: State402) {
        if new == self.state {
            return;
        }
        if new == State402::OperationEnabled {
            self.stats.enables += 1;
            if !self.remapped || self.master_consumer_raw == 0 {
                self.stats.enables_unconfigured += 1;
            }
        }
        if self.state == State402::Fault && new != State402::Fault {
            self.error_code = 0;
            self.out.push(Emcy { code: 0, register: 0, data: [0; 5] }.frame(self.cfg.node_id));
        }
        tracing::debug!(node = self.cfg.node_id, from = ?self.state, to = ?new, "mock drive state");
        self.state = new;
    }

    fn apply_controlword(&mut self, cw: u16) {
        let prev = self.controlword;
        self.controlword = cw;
        let next = cia402::device_transition(self.state, prev, cw);
        self.set_state(next);
    }

    fn fault(&mut self, code: u16) {
        self.error_code = code;
        self.set_state(State402::Fault);
        self.out.push(Emcy { code, register: 0x01, data: [0; 5] }.frame(self.cfg.node_id));
    }

    /// The master's heartbeat stopped: EMCY 0x8130 and the 0x6007 reaction.
    fn comm_lost(&mut self) {
        self.stats.master_losses += 1;
        tracing::info!(
            node = self.cfg.node_id,
            reaction = self.comm_loss,
            "mock drive: master heartbeat lost"
        );
        match self.comm_loss {
            1 => self.fault(EMCY_HEARTBEAT),
            2 => {
                self.out.push(
                    Emcy { code: EMCY_HEARTBEAT, register: 0x10, data: [0; 5] }.frame(self.cfg.node_id),
                );
                self.set_state(State402::SwitchOnDisabled);
            }
            3 => {
                self.out.push(
                    Emcy { code: EMCY_HEARTBEAT, register: 0x10, data: [0; 5] }.frame(self.cfg.node_id),
                );
                if self.state == State402::OperationEnabled {
                    self.set_state(State402::QuickStopActive);
                }
            }
            _ => {
                self.out.push(
                    Emcy { code: EMCY_HEARTBEAT, register: 0x10, data: [0; 5] }.frame(self.cfg.node_id),
                );
            }
        }
    }

    fn pdo_mut(&mut self, index: u16) -> Option<(&mut PdoParams, bool)> {
        match index {
            0x1400 | 0x1600 => Some((&mut self.rpdo1, true)),
            0x1800 | 0x1A00 => Some((&mut self.tpdo[0], false)),
            0x1801 | 0x1A01 => Some((&mut self.tpdo[1], false)),
            _ => None,
        }
    }

    fn value_of(&mut self, index: u16) -> Option<u64> {
        Some(match index {
            0x6040 => u64::from(self.controlword),
            0x6041 => u64::from(self.statusword()),
            0x6060 => u64::from(self.mode as u8),
            0x6061 => u64::from(self.mode_display as u8),
            0x603F => u64::from(self.error_code),
            0x6064 => u64::from(self.motor.reported_position() as u32),
            0x606C => u64::from(self.velocity_units() as u32),
            0x60FF => u64::from(self.target_velocity as u32),
            0x60FD => u64::from(self.inputs),
            _ => return None,
        })
    }

    fn store_mapped(&mut self, index: u16, v: u64) {
        match index {
            0x6040 => self.apply_controlword(v as u16),
            0x60FF => self.target_velocity = v as u32 as i32,
            0x6060 => self.set_mode(v as u8 as i8),
            _ => {}
        }
    }

    fn set_mode(&mut self, mode: i8) {
        self.mode = mode;
        // Echoed at once; real drives may lag (python-canopen #131), which the master tolerates.
        self.mode_display = mode;
    }

    /// The TPDO payload of TPDO `k` (0-based) from its current mapping.
    fn tpdo_payload(&mut self, k: usize) -> Option<Vec<u8>> {
        let entries = self.tpdo.get(k)?.entries();
        let values: Option<Vec<u64>> = entries.iter().map(|e| self.value_of(e.addr.index)).collect();
        pdo::pack(&entries, &values?)
    }

    fn apply_rpdo(&mut self, data: &[u8]) {
        let entries = self.rpdo1.entries();
        if let Some(values) = pdo::unpack(&entries, data) {
            for (e, v) in entries.iter().zip(values) {
                self.store_mapped(e.addr.index, v);
            }
        }
    }
}

fn le<const N: usize>(data: &[u8]) -> Result<[u8; N], AbortCode> {
    data.try_into().map_err(|_| AbortCode::LENGTH)
}

impl ObjectDictionary for Objects {
    fn read(&mut self, addr: ObjectAddr) -> Result<Vec<u8>, AbortCode> {
        let ObjectAddr { index, sub } = addr;
        let v = match (index, sub) {
            (0x1000, 0) => DEVICE_TYPE_402_SERVO.to_le_bytes().to_vec(),
            (0x1001, 0) => vec![u8::from(self.state.is_fault())],
            (0x1008, 0) => self.cfg.device_name.as_bytes().to_vec(),
            (0x1016, 0) => vec![1],
            (0x1016, 1) => self.master_consumer_raw.to_le_bytes().to_vec(),
            (0x1016, _) => return Err(AbortCode::NO_SUBINDEX),
            (0x1017, 0) => self.heartbeat_ms.to_le_bytes().to_vec(),
            (0x1018, 0) => vec![4],
            (0x1018, 1) => 0x0000_0A5Du32.to_le_bytes().to_vec(),
            (0x1018, 2..=4) => u32::from(self.cfg.node_id).to_le_bytes().to_vec(),
            (0x1400 | 0x1800 | 0x1801 | 0x1600 | 0x1A00 | 0x1A01, _) => {
                let comm = matches!(index, 0x1400 | 0x1800 | 0x1801);
                let Some((p, _)) = self.pdo_mut(index) else { return Err(AbortCode::NO_OBJECT) };
                match (comm, sub) {
                    (true, 0) => vec![2],
                    (true, 1) => p.cob.to_le_bytes().to_vec(),
                    (true, 2) => vec![p.transmission],
                    (false, 0) => vec![p.count],
                    (false, 1..=8) => p.map[usize::from(sub) - 1].to_le_bytes().to_vec(),
                    _ => return Err(AbortCode::NO_SUBINDEX),
                }
            }
            (0x6007, 0) => self.comm_loss.to_le_bytes().to_vec(),
            (0x603F..=0x6041, 0) => (self.value_of(index).unwrap_or(0) as u16).to_le_bytes().to_vec(),
            (0x6060 | 0x6061, 0) => vec![self.value_of(index).unwrap_or(0) as u8],
            (0x6064 | 0x606C | 0x60FD | 0x60FF, 0) => {
                (self.value_of(index).unwrap_or(0) as u32).to_le_bytes().to_vec()
            }
            (0x6083, 0) => self.accel.to_le_bytes().to_vec(),
            (0x6084, 0) => self.decel.to_le_bytes().to_vec(),
            (0x6085, 0) => self.quick_stop_decel.to_le_bytes().to_vec(),
            (0x6502, 0) => (1u32 << 2).to_le_bytes().to_vec(), // profile velocity supported
            (0x1000 | 0x1001 | 0x1008 | 0x1017 | 0x6007 | 0x6040..=0x6085 | 0x6502, _) => {
                return Err(AbortCode::NO_SUBINDEX);
            }
            _ => return Err(AbortCode::NO_OBJECT),
        };
        Ok(v)
    }

    fn write(&mut self, addr: ObjectAddr, data: &[u8]) -> Result<(), AbortCode> {
        let ObjectAddr { index, sub } = addr;
        match (index, sub) {
            (
                0x1000 | 0x1001 | 0x1008 | 0x1018 | 0x6041 | 0x6061 | 0x6064 | 0x606C | 0x603F | 0x60FD
                | 0x6502,
                _,
            ) => Err(AbortCode::READ_ONLY),
            (0x1017, 0) => {
                self.heartbeat_ms = u16::from_le_bytes(le(data)?);
                self.producer.set_period(Duration::from_millis(u64::from(self.heartbeat_ms)), self.now);
                Ok(())
            }
            (0x1016, 1) => {
                self.master_consumer_raw = u32::from_le_bytes(le(data)?);
                self.consumer.reset(Duration::from_millis(u64::from(self.master_consumer_raw & 0xFFFF)));
                Ok(())
            }
            (0x1400 | 0x1800 | 0x1801, 1 | 2) | (0x1600 | 0x1A00 | 0x1A01, 0..=8) => {
                self.write_pdo(addr, data)
            }
            (0x6007, 0) => {
                self.comm_loss = i16::from_le_bytes(le(data)?);
                Ok(())
            }
            (0x6040, 0) => {
                self.apply_controlword(u16::from_le_bytes(le(data)?));
                Ok(())
            }
            (0x6060, 0) => {
                let [m] = le::<1>(data)?;
                if m as i8 != 3 && m != 0 {
                    return Err(AbortCode::VALUE_RANGE); // only profile velocity is offered
                }
                self.set_mode(m as i8);
                Ok(())
            }
            (0x60FF, 0) => {
                self.target_velocity = i32::from_le_bytes(le(data)?);
                Ok(())
            }
            (0x6083, 0) => {
                self.accel = u32::from_le_bytes(le(data)?);
                Ok(())
            }
            (0x6084, 0) => {
                self.decel = u32::from_le_bytes(le(data)?);
                Ok(())
            }
            (0x6085, 0) => {
                self.quick_stop_decel = u32::from_le_bytes(le(data)?);
                Ok(())
            }
            (0x1016 | 0x1017 | 0x6007 | 0x6040 | 0x6060 | 0x60FF | 0x6083..=0x6085, _) => {
                Err(AbortCode::NO_SUBINDEX)
            }
            _ => Err(AbortCode::NO_OBJECT),
        }
    }
}

impl Objects {
    /// A write to a PDO's communication (COB-ID, transmission type) or mapping parameters.
    fn write_pdo(&mut self, addr: ObjectAddr, data: &[u8]) -> Result<(), AbortCode> {
        let ObjectAddr { index, sub } = addr;
        match (index, sub) {
            (0x1400 | 0x1800 | 0x1801, 1) => {
                let cob = u32::from_le_bytes(le(data)?);
                let Some((p, _)) = self.pdo_mut(index) else { return Err(AbortCode::NO_OBJECT) };
                // CiA 301: the COB-ID may only change while the PDO is invalid.
                if p.valid() && cob & COB_ID_INVALID == 0 && cob != p.cob {
                    return Err(AbortCode::VALUE_RANGE);
                }
                p.cob = cob;
                Ok(())
            }
            (0x1400 | 0x1800 | 0x1801, 2) => {
                let [t] = le::<1>(data)?;
                let Some((p, _)) = self.pdo_mut(index) else { return Err(AbortCode::NO_OBJECT) };
                p.transmission = t;
                Ok(())
            }
            (0x1600 | 0x1A00 | 0x1A01, 0) => {
                let [n] = le::<1>(data)?;
                let Some((p, _)) = self.pdo_mut(index) else { return Err(AbortCode::NO_OBJECT) };
                if p.valid() {
                    return Err(AbortCode::DEVICE_STATE);
                }
                if n > 8 {
                    return Err(AbortCode::VALUE_RANGE);
                }
                let bits: u32 = p.map[..usize::from(n)].iter().map(|r| r & 0xFF).sum();
                if bits > 64 {
                    return Err(AbortCode(0x0604_0042));
                }
                p.count = n;
                if n > 0 {
                    self.remapped = true;
                }
                Ok(())
            }
            (0x1600 | 0x1A00 | 0x1A01, 1..=8) => {
                let raw = u32::from_le_bytes(le(data)?);
                let Some((p, receive)) = self.pdo_mut(index) else { return Err(AbortCode::NO_OBJECT) };
                if p.valid() || p.count != 0 {
                    return Err(AbortCode::DEVICE_STATE);
                }
                if !mappable((raw >> 16) as u16, receive) {
                    return Err(AbortCode(0x0604_0041));
                }
                p.map[usize::from(sub) - 1] = raw;
                Ok(())
            }
            _ => Err(AbortCode::NO_OBJECT),
        }
    }
}

/// The mock drive.
#[derive(Debug)]
pub struct TecoDrive {
    od: Objects,
    sdo: SdoServer,
    /// Frames to send and the earliest time each may go (slow SDO replies).
    tx: VecDeque<(Instant, CanFrame)>,
    pending_rpdo: Option<Vec<u8>>,
    last_async: [Option<Vec<u8>>; 2],
    heartbeat_silent: bool,
    bus_off_until: Option<Instant>,
    sdo_abort: Option<(u16, AbortCode)>,
    sdo_delay: Duration,
    drop_next: u32,
}

impl TecoDrive {
    /// Power on at `now`: the boot-up message is the first frame.
    pub fn new(cfg: TecoDriveConfig, now: Instant) -> Self {
        let motor =
            Motor::new(cfg.initial_position_counts as f64, cfg.slip, cfg.encoder_noise_counts, cfg.seed);
        let stats = DriveSnapshot {
            nmt: NmtState::PreOperational,
            state: State402::SwitchOnDisabled,
            controlword: 0,
            target_velocity: 0,
            velocity_cps: 0.0,
            position_counts: 0.0,
            mode_display: 0,
            master_consumer: 0,
            comm_loss_reaction: 0,
            boots: 0,
            enables: 0,
            enables_unconfigured: 0,
            master_losses: 0,
        };
        let mut d = Self {
            od: Objects::boot(cfg, now, motor, stats),
            sdo: SdoServer::new(),
            tx: VecDeque::new(),
            pending_rpdo: None,
            last_async: [None, None],
            heartbeat_silent: false,
            bus_off_until: None,
            sdo_abort: None,
            sdo_delay: Duration::ZERO,
            drop_next: 0,
        };
        d.boot_up(now, false);
        d
    }

    /// The node id.
    pub fn node_id(&self) -> NodeId {
        self.od.cfg.node_id
    }

    /// A boot-up: after a power-on or NMT Reset Node everything starts afresh; after NMT Reset
    /// Communication (`keep_application`) only the communication objects do (CiA 301: NMT state,
    /// 0x1016, 0x1017, the PDOs), while the application — the CiA 402 state machine, its mode,
    /// target and ramps, and the motor — runs on as it was.
    fn boot_up(&mut self, now: Instant, keep_application: bool) {
        let (motor, inputs) = (self.od.motor.clone(), self.od.inputs);
        let mut stats = self.od.stats;
        stats.boots += 1;
        let o = &self.od;
        let app = keep_application.then_some((
            o.state,
            o.controlword,
            o.mode,
            o.mode_display,
            o.target_velocity,
            (o.accel, o.decel, o.quick_stop_decel),
            o.comm_loss,
            o.error_code,
        ));
        self.od = Objects::boot(self.od.cfg.clone(), now, motor, stats);
        if let Some((state, cw, mode, display, target, (accel, decel, quick), comm_loss, error)) = app {
            let o = &mut self.od;
            (o.state, o.controlword, o.mode, o.mode_display, o.target_velocity) =
                (state, cw, mode, display, target);
            (o.accel, o.decel, o.quick_stop_decel, o.comm_loss, o.error_code) =
                (accel, decel, quick, comm_loss, error);
        }
        self.od.inputs = inputs;
        self.sdo = SdoServer::new();
        self.pending_rpdo = None;
        self.last_async = [None, None];
        self.heartbeat_silent = false;
        self.send(now, NmtState::BootUp.heartbeat(self.node_id()));
    }

    fn send(&mut self, at: Instant, frame: CanFrame) {
        self.tx.push_back((at, frame));
    }

    fn flush_out(&mut self, now: Instant) {
        for f in std::mem::take(&mut self.od.out) {
            self.send(now, f);
        }
    }

    fn bus_off(&self, now: Instant) -> bool {
        self.bus_off_until.is_some_and(|t| now < t)
    }

    /// The next frame due at `now`.
    pub fn poll_transmit(&mut self, now: Instant) -> Option<CanFrame> {
        // Bounded: each pass removes a frame.
        loop {
            let pos = self.tx.iter().position(|(at, _)| *at <= now)?;
            let (_, frame) = self.tx.remove(pos)?;
            if self.bus_off(now) {
                continue;
            }
            if self.drop_next > 0 {
                self.drop_next -= 1;
                tracing::debug!(node = self.node_id(), ?frame, "mock drive: frame dropped");
                continue;
            }
            return Some(frame);
        }
    }

    /// When [`TecoDrive::handle_timeout`] (or a delayed frame) is next due.
    pub fn poll_timeout(&self) -> Option<Instant> {
        [
            self.od.producer.poll_timeout(),
            self.od.consumer.poll_timeout(),
            self.bus_off_until,
            self.tx.iter().map(|(at, _)| *at).min(),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Timers at `now`: heartbeat, master-heartbeat consumer, end of bus-off, event TPDOs.
    pub fn handle_timeout(&mut self, now: Instant) {
        self.od.advance(now);
        if let Some(t) = self.bus_off_until
            && now >= t
        {
            self.bus_off_until = None;
            let emcy = Emcy { code: EMCY_BUS_OFF_RECOVERED, register: 0x10, data: [0; 5] };
            self.send(now, emcy.frame(self.node_id()));
        }
        if self.od.producer.due(now) && !self.heartbeat_silent {
            self.send(now, self.od.nmt.heartbeat(self.node_id()));
        }
        if self.od.consumer.check(now) {
            self.od.comm_lost();
        }
        self.async_tpdos(now);
        self.flush_out(now);
    }

    /// Event-driven TPDOs (transmission type 254/255): sent when their content changes.
    fn async_tpdos(&mut self, now: Instant) {
        if self.od.nmt != NmtState::Operational {
            return;
        }
        for k in 0..2 {
            let p = &self.od.tpdo[k];
            if !p.valid() || p.synchronous() || p.count == 0 {
                continue;
            }
            let cob = p.cob;
            // Position noise would make TPDOs with 0x6064 change every time: compare without it.
            let Some(payload) = self.od.tpdo_payload(k) else { continue };
            if self.last_async[k].as_ref() != Some(&payload) {
                self.last_async[k] = Some(payload.clone());
                if let Ok(f) = CanFrame::new((cob & 0x7FF) as u16, &payload) {
                    self.send(now, f);
                }
            }
        }
    }

    fn sync(&mut self, now: Instant) {
        if self.od.nmt != NmtState::Operational {
            return;
        }
        if let Some(data) = self.pending_rpdo.take() {
            self.od.apply_rpdo(&data);
        }
        for k in 0..2 {
            let p = &self.od.tpdo[k];
            if !p.valid() || !p.synchronous() {
                continue;
            }
            let cob = p.cob;
            if let Some(payload) = self.od.tpdo_payload(k)
                && let Ok(f) = CanFrame::new((cob & 0x7FF) as u16, &payload)
            {
                self.send(now, f);
            }
        }
    }

    /// A frame from the bus at `now`.
    pub fn handle_frame(&mut self, now: Instant, frame: &CanFrame) {
        if self.bus_off(now) {
            return;
        }
        self.od.advance(now);
        let me = self.node_id();
        match frame.cob() {
            Cob::Nmt => {
                if let Some((cmd, node)) = NmtCommand::decode(frame)
                    && (node == 0 || node == me)
                {
                    match cmd {
                        NmtCommand::Start => self.od.nmt = NmtState::Operational,
                        NmtCommand::Stop => self.od.nmt = NmtState::Stopped,
                        NmtCommand::EnterPreOperational => self.od.nmt = NmtState::PreOperational,
                        NmtCommand::ResetNode => self.boot_up(now, false),
                        NmtCommand::ResetCommunication => self.boot_up(now, true),
                    }
                }
            }
            Cob::Sync => self.sync(now),
            Cob::Rpdo(1, n) if n == me => {
                let p = &self.od.rpdo1;
                if self.od.nmt == NmtState::Operational && p.valid() && frame.id() == (p.cob & 0x7FF) {
                    if p.synchronous() {
                        self.pending_rpdo = Some(frame.data().to_vec());
                    } else {
                        self.od.apply_rpdo(frame.data());
                    }
                }
            }
            Cob::SdoRequest(n) if n == me && self.od.nmt != NmtState::Stopped => {
                let mut body = [0u8; 8];
                body[..frame.data().len()].copy_from_slice(frame.data());
                let initiate = matches!(body[0] >> 5, 1 | 2);
                let addr = ObjectAddr::new(u16::from_le_bytes([body[1], body[2]]), body[3]);
                let reply = match self.sdo_abort {
                    Some((index, code)) if initiate && index == addr.index => {
                        self.sdo_abort = None;
                        Some(abort_bytes(addr, code))
                    }
                    _ => self.sdo.handle_request(frame.data(), &mut self.od),
                };
                if let Some(r) = reply {
                    let f = Cob::SdoResponse(me).frame(&r);
                    self.send(now + self.sdo_delay, f);
                }
            }
            Cob::Heartbeat(n) => {
                let master = ((self.od.master_consumer_raw >> 16) & 0x7F) as u8;
                if master != 0 && n == master && self.od.master_consumer_raw & 0xFFFF != 0 {
                    self.od.consumer.received(now);
                }
            }
            _ => {}
        }
        self.async_tpdos(now);
        self.flush_out(now);
    }

    /// Inject a fault at `now`.
    pub fn inject(&mut self, now: Instant, fault: Fault) {
        self.od.advance(now);
        tracing::info!(node = self.node_id(), ?fault, "mock drive: fault");
        match fault {
            Fault::DriveFault { code } => self.od.fault(code),
            Fault::HeartbeatLoss(on) => self.heartbeat_silent = on,
            Fault::BusOff { duration } => self.bus_off_until = Some(now + duration),
            Fault::Reboot => self.boot_up(now, false),
            Fault::SdoAbort { index, code } => self.sdo_abort = Some((index, AbortCode(code))),
            Fault::SlowSdo(d) => self.sdo_delay = d,
            Fault::DropFrames(n) => self.drop_next = n,
            Fault::Inputs(bits) => self.od.inputs = bits,
        }
        self.flush_out(now);
    }

    /// What a test can see.
    pub fn snapshot(&self) -> DriveSnapshot {
        DriveSnapshot {
            nmt: self.od.nmt,
            state: self.od.state,
            controlword: self.od.controlword,
            target_velocity: self.od.target_velocity,
            velocity_cps: self.od.motor.velocity_cps,
            position_counts: self.od.motor.position_counts,
            mode_display: self.od.mode_display,
            master_consumer: self.od.master_consumer_raw,
            comm_loss_reaction: self.od.comm_loss,
            ..self.od.stats
        }
    }
}

#[cfg(test)]
mod tests;
