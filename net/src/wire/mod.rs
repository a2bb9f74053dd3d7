//! The link's messages on the wire: one [`Envelope`] per Zenoh sample, encoded with postcard (serde,
//! varints, fixed-width floats: a 271-beam scan is about 2.5 kB, every range an `f64` so the
//! server sees the bits the robot measured, as in one process).
//!
//! Every envelope carries the schema version (first, so a receiver can refuse another version
//! before reading further), the sender's session and its own sequence number (a replayed or
//! reordered sample shows), the robot it is about, the node that sent it, the message's stamp and
//! when it was sent. The body is the fleet's own message types (`amr-msgs`), encoded directly:
//! [`amr_msgs::SCHEMA_VERSION`] is the version here too, and a test there pins the encoding.
//!
//! Decoding never panics: any byte sequence gives an envelope or a [`Reject`] with the reason.

use std::collections::BTreeMap;

use amr_msgs::{Downlink, MAX_BEAMS, SCHEMA_VERSION, ServerStatus, Uplink};
use serde::{Deserialize, Serialize};

/// Largest envelope accepted: a 4 096-beam scan with room to spare.
pub const MAX_ENVELOPE_BYTES: usize = 64 * 1024;
/// Longest health detail on the wire, bytes (longer ones are cut on sending).
pub const MAX_DETAIL_BYTES: usize = 512;

/// One message on the wire.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Envelope {
    /// [`SCHEMA_VERSION`] of the sender.
    pub version: u16,
    /// The sending node's session: the start of its process, nanoseconds of Unix time, so a
    /// restarted sender's session is newer (receivers refuse an older one: [`Freshness`]).
    pub session: u64,
    /// Counts the sender's envelopes on this key within its session, from 1.
    pub seq: u64,
    /// The node that sent it: a robot's id or the server's user name.
    pub origin: String,
    /// The robot the message is from (uplink) or for (downlink).
    pub robot: String,
    /// The message's own stamp, fleet-clock seconds (a scan's acquisition, a command's computation).
    pub stamp_s: f64,
    /// When the bridge sent it, fleet-clock seconds.
    pub sent_s: f64,
    pub body: Body,
}

/// What an envelope carries.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Body {
    Uplink(Uplink),
    Downlink(Downlink),
    /// The server's formation, for operators and tests (`fleet/server/status`).
    Status(ServerStatus),
}

/// Why a sample was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Reject {
    #[error("{0} bytes: larger than the {MAX_ENVELOPE_BYTES}-byte limit")]
    TooLarge(usize),
    #[error("schema version {got}, this build speaks {SCHEMA_VERSION}")]
    Version { got: u16 },
    #[error("malformed: {0}")]
    Malformed(String),
    #[error("{0} trailing bytes after the envelope")]
    Trailing(usize),
    #[error("a scan of {0} beams (at most {MAX_BEAMS})")]
    TooManyBeams(usize),
    #[error("sent on `{key}` but about robot `{robot}`")]
    WrongRobot { key: String, robot: String },
    #[error("from `{origin}`, not from the configured server `{server}`")]
    NotFromServer { origin: String, server: String },
    #[error("an e-stop from `{origin}`, neither the server nor an operator")]
    NotAnOperator { origin: String },
    #[error("an envelope claiming to be from `{origin}` on `{key}`'s key")]
    ForgedOrigin { origin: String, key: String },
    #[error("a {kind} message on a {channel} key")]
    WrongChannel { kind: &'static str, channel: &'static str },
    #[error("envelope {seq} of session {session:#x} is not newer than {last}: replayed or reordered")]
    Replayed { session: u64, seq: u64, last: u64 },
    #[error(
        "session {session:#x} is older than the sender's session {known:#x}: a replay from an earlier run"
    )]
    OldSession { session: u64, known: u64 },
    #[error("session {session:#x} starts in the future (now {now_s:.3} s): refused")]
    FutureSession { session: u64, now_s: f64 },
    #[error("a {kind} stamped {age_s:.3} s ago: older than {MAX_ENABLING_AGE_S} s")]
    Stale { kind: &'static str, age_s: f64 },
    #[error("a {kind} stamped {ahead_s:.3} s ahead of this clock: more than {MAX_ENABLING_AHEAD_S} s")]
    Ahead { kind: &'static str, ahead_s: f64 },
    #[error("non-finite {0}")]
    NotFinite(&'static str),
}

impl Reject {
    /// A short name for counters.
    #[must_use]
    pub fn kind(&self) -> &'static str {
        match self {
            Reject::TooLarge(_) => "too-large",
            Reject::Version { .. } => "version",
            Reject::Malformed(_) | Reject::Trailing(_) | Reject::TooManyBeams(_) | Reject::NotFinite(_) => {
                "malformed"
            }
            Reject::WrongRobot { .. } => "wrong-robot",
            Reject::NotFromServer { .. } => "not-from-server",
            Reject::NotAnOperator { .. } => "not-an-operator",
            Reject::ForgedOrigin { .. } => "forged-origin",
            Reject::WrongChannel { .. } => "wrong-channel",
            Reject::Replayed { .. } | Reject::OldSession { .. } | Reject::FutureSession { .. } => "replayed",
            Reject::Stale { .. } | Reject::Ahead { .. } => "stale",
        }
    }
}

impl Envelope {
    /// Encode (postcard). Only a serde failure, which our types cannot produce, is an error.
    pub fn encode(&self) -> Result<Vec<u8>, postcard::Error> {
        postcard::to_stdvec(self)
    }

    /// Decode and check the version, the size and the shape. Never panics.
    pub fn decode(bytes: &[u8]) -> Result<Envelope, Reject> {
        if bytes.len() > MAX_ENVELOPE_BYTES {
            return Err(Reject::TooLarge(bytes.len()));
        }
        let (version, _) =
            postcard::take_from_bytes::<u16>(bytes).map_err(|e| Reject::Malformed(e.to_string()))?;
        if version != SCHEMA_VERSION {
            return Err(Reject::Version { got: version });
        }
        let (env, rest) =
            postcard::take_from_bytes::<Envelope>(bytes).map_err(|e| Reject::Malformed(e.to_string()))?;
        if !rest.is_empty() {
            return Err(Reject::Trailing(rest.len()));
        }
        if !(env.stamp_s.is_finite() && env.sent_s.is_finite()) {
            return Err(Reject::NotFinite("stamp"));
        }
        if let Body::Uplink(Uplink::Scan(s)) = &env.body
            && s.scan.len() > MAX_BEAMS
        {
            return Err(Reject::TooManyBeams(s.scan.len()));
        }
        Ok(env)
    }
}

fn cut(detail: &str) -> String {
    let mut end = detail.len().min(MAX_DETAIL_BYTES);
    while !detail.is_char_boundary(end) {
        end -= 1;
    }
    detail[..end].to_owned()
}

/// The channel an uplink message travels on: `fleet/<robot>/<channel>`.
#[must_use]
pub fn uplink_channel(u: &Uplink) -> &'static str {
    match u {
        Uplink::Scan(_) => "scan",
        Uplink::Odom { .. } => "odom",
        Uplink::Health { .. } | Uplink::Safety { .. } => "health",
    }
}

/// An uplink message as an envelope body with its stamp (the bridge fills session, seq and sent);
/// a health detail longer than [`MAX_DETAIL_BYTES`] is cut at a character boundary.
#[must_use]
pub fn from_uplink(u: &Uplink) -> (f64, Body) {
    let mut u = u.clone();
    if let Uplink::Health { report, .. } = &mut u
        && report.detail.len() > MAX_DETAIL_BYTES
    {
        report.detail = cut(&report.detail);
    }
    (u.stamp_s(), Body::Uplink(u))
}

/// The uplink message in an envelope received on `fleet/<robot>/<channel>`: from that robot, about
/// that robot, on the channel of its kind, its stamp finite (and an odometry pose and twist
/// finite: the formation steers from it).
pub fn to_uplink(env: Envelope, key_robot: &str, channel: &str) -> Result<Uplink, Reject> {
    if env.robot != key_robot || env.origin != key_robot {
        return Err(Reject::WrongRobot { key: key_robot.to_owned(), robot: env.robot });
    }
    let u = match env.body {
        Body::Uplink(u) => u,
        body => return Err(Reject::WrongChannel { kind: kind_of(&body), channel: static_channel(channel) }),
    };
    if u.robot() != key_robot {
        return Err(Reject::WrongRobot { key: key_robot.to_owned(), robot: u.robot().to_owned() });
    }
    let kind = uplink_channel(&u);
    if kind != channel {
        return Err(Reject::WrongChannel { kind, channel: static_channel(channel) });
    }
    if !u.stamp_s().is_finite() {
        return Err(Reject::NotFinite("stamp"));
    }
    if let Uplink::Odom { msg, .. } = &u
        && ![msg.pose.x, msg.pose.y, msg.pose.theta, msg.twist.0, msg.twist.1].iter().all(|v| v.is_finite())
    {
        return Err(Reject::NotFinite("odometry"));
    }
    Ok(u)
}

/// A downlink message as an envelope body with its stamp (`sent_s` for those without one).
#[must_use]
pub fn from_downlink(d: &Downlink, sent_s: f64) -> (f64, Body) {
    let stamp = match d {
        Downlink::Command(c) => c.stamp_s,
        Downlink::Arm { stamp_s, .. } => *stamp_s,
        Downlink::Disarm | Downlink::EStop | Downlink::ResetEStop => sent_s,
    };
    (stamp, Body::Downlink(*d))
}

/// The downlink message in an envelope received on `fleet/<robot>/cmd`, if it is for `me` and from
/// the configured server.
pub fn to_downlink(env: Envelope, me: &str, server: &str) -> Result<Downlink, Reject> {
    if env.robot != me {
        return Err(Reject::WrongRobot { key: me.to_owned(), robot: env.robot });
    }
    if env.origin != server {
        return Err(Reject::NotFromServer { origin: env.origin, server: server.to_owned() });
    }
    match env.body {
        Body::Downlink(d) => Ok(d),
        body => Err(Reject::WrongChannel { kind: kind_of(&body), channel: "cmd" }),
    }
}

/// Whether `d` goes on the e-stop key (`fleet/<robot>/estop`) rather than `cmd`.
#[must_use]
pub fn is_estop(d: &Downlink) -> bool {
    matches!(d, Downlink::EStop | Downlink::ResetEStop)
}

/// The e-stop or reset in an envelope received on `fleet/<robot>/estop/<sender>`, if it is for
/// `me` and `sender` (the key's, which the server's access control lets only that authenticated
/// name publish on) is one of `senders` (the server and the operators) and the envelope names the
/// same sender.
pub fn to_estop(env: Envelope, me: &str, sender: &str, senders: &[String]) -> Result<Downlink, Reject> {
    if env.robot != me {
        return Err(Reject::WrongRobot { key: me.to_owned(), robot: env.robot });
    }
    if !senders.iter().any(|s| s == sender) {
        return Err(Reject::NotAnOperator { origin: sender.to_owned() });
    }
    if env.origin != sender {
        return Err(Reject::ForgedOrigin { origin: env.origin, key: sender.to_owned() });
    }
    match env.body {
        Body::Downlink(d) if is_estop(&d) => Ok(d),
        body => Err(Reject::WrongChannel { kind: kind_of(&body), channel: "estop" }),
    }
}

fn kind_of(b: &Body) -> &'static str {
    match b {
        Body::Uplink(u) => match u {
            Uplink::Scan(_) => "scan",
            Uplink::Odom { .. } => "odom",
            Uplink::Health { .. } => "health",
            Uplink::Safety { .. } => "safety",
        },
        Body::Downlink(d) => match d {
            Downlink::Command(_) => "command",
            Downlink::Arm { .. } => "arm",
            Downlink::Disarm => "disarm",
            Downlink::EStop => "estop",
            Downlink::ResetEStop => "reset_estop",
        },
        Body::Status(_) => "status",
    }
}

fn static_channel(c: &str) -> &'static str {
    match c {
        "scan" => "scan",
        "odom" => "odom",
        "health" => "health",
        "cmd" => "cmd",
        "estop" => "estop",
        "status" => "status",
        _ => "unknown",
    }
}

/// How far a sender's session start may lie ahead of the receiver's clock (clocks synchronised
/// by NTP or PTP differ by milliseconds; a session from further ahead would lock the real sender
/// out until then).
pub const MAX_SESSION_AHEAD_S: f64 = 5.0;

/// Oldest arm or e-stop reset a robot takes from the network, by its stamp, s. Messages that
/// stop (disarm, e-stop) are taken whatever their stamp, session or sequence: a stop is never
/// refused (a replayed one stops a robot that must then be reset and armed, which is safe).
pub const MAX_ENABLING_AGE_S: f64 = 2.0;

/// How far ahead of the robot's clock an arm or e-stop reset may be stamped, s: the fleet's clocks
/// are synchronised (NTP, PTP) to milliseconds; a sender further ahead is refused rather than
/// trusted (the robot's safety layer refuses an arm beyond its command timeout either way).
pub const MAX_ENABLING_AHEAD_S: f64 = 0.5;

/// Refuses replays of one sender (one `Freshness` per sender): an envelope not newer than the last
/// one accepted from the same session (replayed or reordered), one from an older session than the
/// newest seen (a sample recorded in an earlier run of the sender), and a session starting in the
/// future beyond [`MAX_SESSION_AHEAD_S`]. A newer session (the sender restarted) starts afresh.
#[derive(Debug, Default, Clone)]
pub struct Freshness {
    last: Option<(u64, u64)>,
}

impl Freshness {
    /// Accept `env`, received at `now_s` (fleet clock, Unix seconds), if it is fresh.
    pub fn check(&mut self, env: &Envelope, now_s: f64) -> Result<(), Reject> {
        let session_s = env.session as f64 / 1e9;
        if session_s > now_s + MAX_SESSION_AHEAD_S {
            return Err(Reject::FutureSession { session: env.session, now_s });
        }
        match self.last {
            Some((known, _)) if env.session < known => {
                Err(Reject::OldSession { session: env.session, known })
            }
            Some((session, last)) if session == env.session && env.seq <= last => {
                Err(Reject::Replayed { session, seq: env.seq, last })
            }
            _ => {
                self.last = Some((env.session, env.seq));
                Ok(())
            }
        }
    }
}

/// Refuses an arm or e-stop reset stamped more than [`MAX_ENABLING_AGE_S`] before `now_s` or more
/// than [`MAX_ENABLING_AHEAD_S`] after it (or not finite); every other downlink passes (commands have the safety layer's own, tighter, age limit).
pub fn check_enabling_age(env: &Envelope, now_s: f64) -> Result<(), Reject> {
    let kind = match &env.body {
        Body::Downlink(Downlink::Arm { .. }) => "arm",
        Body::Downlink(Downlink::ResetEStop) => "reset_estop",
        _ => return Ok(()),
    };
    let age_s = now_s - env.stamp_s;
    if !(age_s.is_finite() && age_s <= MAX_ENABLING_AGE_S) {
        return Err(Reject::Stale { kind, age_s });
    }
    if -age_s > MAX_ENABLING_AHEAD_S {
        return Err(Reject::Ahead { kind, ahead_s: -age_s });
    }
    Ok(())
}

/// The checks a robot's bridge applies to what it receives, per key, with the replay records they
/// keep: commands and arms on `fleet/<robot>/cmd` ([`DownlinkGate::on_cmd`]), e-stops and resets
/// on `fleet/<robot>/estop/<sender>` ([`DownlinkGate::on_estop`]). Pure: the clocks are passed in.
#[derive(Debug, Default, Clone)]
pub struct DownlinkGate {
    /// The server's envelopes on `cmd`.
    cmd: Freshness,
    /// Each sender's envelopes on its e-stop key.
    per_sender: BTreeMap<String, Freshness>,
}

impl DownlinkGate {
    /// An envelope received on `fleet/<me>/cmd`: for `me` and from `server` (checked before it may
    /// touch the replay record), then an arm checked for age ([`check_enabling_age`], on the fleet
    /// clock) and anything but a disarm for replay ([`Freshness`], on the wall clock). A disarm is
    /// taken whatever its session, sequence or stamp: a stop is never refused.
    pub fn on_cmd(
        &mut self,
        env: &Envelope,
        me: &str,
        server: &str,
        now_fleet_s: f64,
        now_wall_s: f64,
    ) -> Result<Downlink, Reject> {
        let d = to_downlink(env.clone(), me, server)?;
        if d != Downlink::Disarm {
            check_enabling_age(env, now_fleet_s)?;
            self.cmd.check(env, now_wall_s)?;
        }
        Ok(d)
    }

    /// An envelope received on `fleet/<me>/estop/<sender>` (`sender`: the key's last segment): for
    /// `me`, from one of `senders`, naming `sender` ([`to_estop`]). An e-stop is taken whatever its
    /// session, sequence or stamp; a reset is checked for age and for replay against `sender`'s own
    /// record.
    pub fn on_estop(
        &mut self,
        env: &Envelope,
        me: &str,
        sender: &str,
        senders: &[String],
        now_fleet_s: f64,
        now_wall_s: f64,
    ) -> Result<Downlink, Reject> {
        let d = to_estop(env.clone(), me, sender, senders)?;
        if d == Downlink::EStop {
            return Ok(d);
        }
        check_enabling_age(env, now_fleet_s)?;
        self.per_sender.entry(sender.to_owned()).or_default().check(env, now_wall_s)?;
        Ok(d)
    }
}

#[cfg(test)]
mod tests;
