//! A drive's (re)start: reset, boot-up, and the configuration written to it by SDO, step by step,
//! before it may be enabled.

#[allow(clippy::wildcard_imports, reason = "a second part of the master: its types and imports")]
use super::*;

impl Master {
    /// Stop drive `i`, then send it a reset-communication and wait for its boot-up.
    ///
    /// Stop first: a reset of communication (CiA 301) leaves the drive's application running, in
    /// whatever state and at whatever target it had, and resets its watchdog of our heartbeat
    /// (0x1016) to off until it is configured again. So a quick stop (0x6040 = 0x0002) and a zero
    /// target (0x60FF = 0) go first, as expedited SDO writes, which a drive takes in
    /// PRE-OPERATIONAL and OPERATIONAL alike (PDOs only in the latter); their confirmations find
    /// no request in flight and are ignored.
    pub(super) fn reset_drive(&mut self, i: usize, now: Instant) {
        let d = &mut self.drives[i];
        d.phase = Phase::WaitingBoot;
        d.state = None;
        d.enable_deadline = None;
        d.sdo.cancel();
        d.current = None;
        d.jobs.clear();
        d.boot_deadline = Some(now + ms(self.config.can.boot_timeout_ms));
        let node = d.setup.node_id;
        let stop = [
            (ObjectAddr::new(0x6040, 0), controlword::QUICK_STOP.to_le_bytes().to_vec()),
            (ObjectAddr::new(0x60FF, 0), 0i32.to_le_bytes().to_vec()),
        ];
        for (addr, data) in stop {
            if let Some(body) = crate::canopen::sdo::expedited_download(addr, &data) {
                self.tx.push_back(Cob::SdoRequest(node).frame(&body));
            }
        }
        self.tx.push_back(NmtCommand::ResetCommunication.frame(node));
    }

    /// A boot-up: forget the drive's state and configure it again before it may be enabled.
    pub(super) fn on_boot(&mut self, i: usize, now: Instant) {
        let node = self.drives[i].setup.node_id;
        tracing::info!(node, "boot-up: configuring");
        self.events.push_back(MasterEvent::BootUp { node });
        self.zero_targets();
        let jobs = self.config_jobs(i);
        let d = &mut self.drives[i];
        d.sdo.cancel();
        d.current = None;
        d.jobs = jobs;
        d.phase = Phase::Configuring;
        d.boot_deadline = None;
        d.state = None;
        d.position = None;
        d.position_fresh = false;
        d.inputs = None;
        d.recovery = Recovery::Idle;
        d.enable_deadline = None;
        d.mode_reads = 0;
        d.retries = 0;
        // Monitoring starts with the first heartbeat (CiA 301), which the drive sends only once
        // 0x1017 is written; a drive dying during configuration shows as SDO timeouts.
        d.consumer.reset(ms(d.setup.heartbeat_consumer_ms));
        self.pump(i, now);
    }

    fn config_jobs(&self, i: usize) -> VecDeque<Job> {
        let s = &self.drives[i].setup;
        let n = s.node_id;
        let w = |index: u16, sub: u8, data: Vec<u8>| {
            Job::Sdo(SdoRequest::Download(ObjectAddr::new(index, sub), data), JobKind::Config)
        };
        let mut jobs = VecDeque::new();
        jobs.push_back(Job::Nmt(NmtCommand::EnterPreOperational));
        jobs.push_back(Job::Sdo(SdoRequest::Upload(ObjectAddr::new(0x1000, 0)), JobKind::DeviceType));
        jobs.push_back(Job::Sdo(SdoRequest::Upload(ObjectAddr::new(0x1008, 0)), JobKind::Optional));
        jobs.push_back(w(0x1017, 0, s.heartbeat_producer_ms.to_le_bytes().to_vec()));
        let consumer = (u32::from(self.config.can.master_node_id) << 16) | u32::from(s.master_consumer_ms);
        jobs.push_back(w(0x1016, 1, consumer.to_le_bytes().to_vec()));
        jobs.push_back(w(0x6007, 0, s.comm_loss_reaction.code().to_le_bytes().to_vec()));
        jobs.push_back(w(0x6083, 0, s.profile_acceleration.to_le_bytes().to_vec()));
        jobs.push_back(w(0x6084, 0, s.profile_deceleration.to_le_bytes().to_vec()));
        jobs.push_back(w(0x6085, 0, s.quick_stop_deceleration.to_le_bytes().to_vec()));
        for (dir, k, map) in [
            (PdoDirection::Receive, 1, &RPDO1_MAP[..]),
            (PdoDirection::Transmit, 1, &TPDO1_MAP[..]),
            (
                PdoDirection::Transmit,
                2,
                if s.digital_inputs { &TPDO2_INPUTS_MAP[..] } else { &TPDO2_MAP[..] },
            ),
        ] {
            for req in pdo::remap_requests(dir, k, n, TRANSMISSION_SYNC_EVERY, map) {
                jobs.push_back(Job::Sdo(req, JobKind::Config));
            }
        }
        jobs.push_back(w(0x60FF, 0, 0i32.to_le_bytes().to_vec()));
        jobs.push_back(w(0x6060, 0, MODE_PROFILE_VELOCITY.to_le_bytes().to_vec()));
        jobs.push_back(Job::Sdo(SdoRequest::Upload(ObjectAddr::new(0x6061, 0)), JobKind::ConfirmMode));
        jobs.push_back(Job::Nmt(NmtCommand::Start));
        jobs.push_back(Job::Finish);
        jobs
    }

    /// Start queued jobs while the SDO client is free.
    pub(super) fn pump(&mut self, i: usize, now: Instant) {
        // Bounded: every pass pops a job.
        while self.drives[i].sdo.is_idle() {
            let Some(job) = self.drives[i].jobs.pop_front() else { return };
            let node = self.drives[i].setup.node_id;
            match job {
                Job::Nmt(cmd) => self.tx.push_back(cmd.frame(node)),
                Job::Finish => {
                    let d = &mut self.drives[i];
                    d.phase = Phase::Operational;
                    d.configurations += 1;
                    if self.goal == Goal::Enabled {
                        d.enable_deadline = Some(now + ms(self.config.enable_timeout_ms));
                    }
                    let device_type = d.device_type;
                    tracing::info!(node, device_type, "drive configured");
                    self.events.push_back(MasterEvent::Configured { node, device_type });
                }
                Job::Sdo(req, kind) => {
                    let d = &mut self.drives[i];
                    let body = d.sdo.start(now, req.clone());
                    let frame = d.sdo.frame(body);
                    d.current = Some((kind, req));
                    self.tx.push_back(frame);
                }
            }
        }
    }

    pub(super) fn sdo_step(&mut self, i: usize, now: Instant, step: SdoStep) {
        let node = self.drives[i].setup.node_id;
        let (result, abort) = match step {
            SdoStep::Send(body) => {
                let f = self.drives[i].sdo.frame(body);
                self.tx.push_back(f);
                return;
            }
            SdoStep::Done { result, abort } => (result, abort),
        };
        if let Some(body) = abort {
            let f = self.drives[i].sdo.frame(body);
            self.tx.push_back(f);
        }
        let Some((kind, req)) = self.drives[i].current.take() else { return };
        let addr = req.addr();
        let retry = matches!(kind, JobKind::Config | JobKind::DeviceType | JobKind::ConfirmMode)
            && result == Err(SdoFailure::Timeout)
            && self.drives[i].retries < SDO_RETRIES;
        if retry {
            // A lost frame costs one timeout, not a whole reconfiguration.
            tracing::debug!(node, %addr, "SDO timeout during configuration; retrying");
            let d = &mut self.drives[i];
            d.retries += 1;
            d.jobs.push_front(Job::Sdo(req, kind));
            self.pump(i, now);
            return;
        }
        self.drives[i].retries = 0;
        let to_error = |addr: ObjectAddr, f: SdoFailure| -> CanopenError {
            match f {
                SdoFailure::Aborted(code) => DeviceError::SdoAbort { node, addr, code }.into(),
                SdoFailure::Protocol(code) => LinkError::SdoProtocol { node, addr, code }.into(),
                SdoFailure::Timeout => LinkError::SdoTimeout { node, addr }.into(),
            }
        };
        match (kind, result) {
            (JobKind::User(id), result) => {
                let result = result.map_err(|f| to_error(addr, f));
                self.events.push_back(MasterEvent::SdoDone { id, node, result });
            }
            (JobKind::Optional, _) => {}
            (JobKind::DeviceType, Ok(SdoResult::Read(v))) => {
                let mut b = [0u8; 4];
                let n = v.len().min(4);
                b[..n].copy_from_slice(&v[..n]);
                self.drives[i].device_type = u32::from_le_bytes(b);
            }
            (JobKind::ConfirmMode, Ok(SdoResult::Read(v))) => {
                let displayed = v.first().map_or(0, |b| *b as i8);
                if displayed != MODE_PROFILE_VELOCITY {
                    let d = &mut self.drives[i];
                    d.mode_reads += 1;
                    if d.mode_reads < self.config.mode_confirm_attempts {
                        d.jobs.push_front(Job::Sdo(
                            SdoRequest::Upload(ObjectAddr::new(0x6061, 0)),
                            JobKind::ConfirmMode,
                        ));
                    } else {
                        self.error(
                            DeviceError::ModeNotConfirmed {
                                node,
                                requested: MODE_PROFILE_VELOCITY,
                                displayed,
                            }
                            .into(),
                        );
                        self.reset_drive(i, now);
                        return;
                    }
                }
            }
            (JobKind::Config | JobKind::DeviceType | JobKind::ConfirmMode, Ok(_)) => {}
            (JobKind::Config | JobKind::DeviceType | JobKind::ConfirmMode, Err(f)) => {
                tracing::warn!(node, ?f, "configuration step failed; resetting the drive");
                self.error(to_error(addr, f));
                let d = &mut self.drives[i];
                d.jobs.clear();
                self.reset_drive(i, now);
                return;
            }
        }
        self.pump(i, now);
    }
}
