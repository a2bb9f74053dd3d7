//! `network.toml`: how the robots and the fusion server reach each other when they run as separate
//! processes (Eclipse Zenoh). The server listens; every robot connects to it. Discovery is
//! by these endpoints only: multicast scouting and gossip stay off.
//!
//! Keys are not part of the configuration (it is embedded in the binary and kept in version
//! control): `certs_dir` names the directory of the fleet's certificates that each machine keeps
//! to itself (its own key only), and `credentials_file`, used only with `--insecure`, a file of
//! `user:password` lines (Zenoh's dictionary format).

use serde::Deserialize;

use amr_actors::config::{Config, ConfigError};
use amr_core::config::value::Millis;
use amr_core::config::{ConfigFileType, RobotId, Violation, parse_file, rule};

/// The link's settings.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkConfig {
    pub server: NetworkServer,
    /// A peer whose session is silent this long is gone: Zenoh's transport lease, which is also
    /// when the server sees a robot's liveliness token vanish. At most [`MAX_LEASE_MS`].
    pub lease_ms: Millis,
    /// Keep-alive messages per lease (Zenoh's `keep_alive`, default 4).
    pub keep_alive: u32,
    /// The fleet's certificates (`amr fleet certs`): `ca.pem` and this machine's `<name>.pem` and
    /// `<name>.key`. `amr robot|server|estop --certs DIR` overrides it.
    pub certs_dir: String,
    /// Only with `--insecure` (plain TCP): `user:password` per line. The server reads every line
    /// (who may join); a robot reads its own (user = its id). `--credentials FILE` overrides it.
    #[serde(default)]
    pub credentials_file: Option<String>,
}

/// The fusion server's identity and endpoints.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkServer {
    /// Its Zenoh user name; the only peer allowed to command a robot.
    pub user: RobotId,
    /// Zenoh endpoints the server listens on (`tcp/<address>:<port>`).
    pub listen: Vec<String>,
    /// Zenoh endpoints the robots connect to.
    pub connect: Vec<String>,
    /// Users besides the server that may e-stop a robot and reset its e-stop (on
    /// `fleet/<robot>/estop`, e.g. with `amr estop`), and nothing else.
    #[serde(default)]
    pub operators: Vec<RobotId>,
}

/// Longest lease allowed, ms: the server must see a robot gone within 2 s of its process or its
/// link dying.
pub const MAX_LEASE_MS: u32 = 2000;

impl ConfigFileType for NetworkConfig {
    fn validate(&self) -> Result<(), Violation> {
        rule(
            (100..=MAX_LEASE_MS).contains(&self.lease_ms.ms()),
            "lease_ms",
            format!("must be in 100..={MAX_LEASE_MS} ms (got {})", self.lease_ms.ms()),
        )?;
        rule(
            (1..=10).contains(&self.keep_alive),
            "keep_alive",
            format!("must be in 1..=10 (got {})", self.keep_alive),
        )?;
        rule(!self.server.listen.is_empty(), "server.listen", "needs at least one endpoint".to_owned())?;
        rule(!self.server.connect.is_empty(), "server.connect", "needs at least one endpoint".to_owned())?;
        for (i, o) in self.server.operators.iter().enumerate() {
            rule(
                o != &self.server.user,
                format!("server.operators[{i}]"),
                format!("`{}` is the server's own user", o.as_str()),
            )?;
        }
        for (key, list) in [("server.listen", &self.server.listen), ("server.connect", &self.server.connect)]
        {
            for (i, e) in list.iter().enumerate() {
                rule(
                    endpoint(e),
                    format!("{key}[{i}]"),
                    format!("`{e}`: expected tls/<host>:<port> (or tcp/, used only with --insecure)"),
                )?;
            }
        }
        rule(!self.certs_dir.is_empty(), "certs_dir", "must name a directory".to_owned())?;
        rule(
            self.credentials_file.as_ref().is_none_or(|f| !f.is_empty()),
            "credentials_file",
            "must name a file".to_owned(),
        )
    }
}

impl NetworkConfig {
    /// The set's `network.toml`, parsed and checked; `None` when the set has none.
    pub fn from_set(config: &Config) -> Result<Option<NetworkConfig>, ConfigError> {
        config.network.as_ref().map(|f| parse_file::<NetworkConfig>(&f.path, f.text()?)).transpose()
    }
}

/// `tls/<host>:<port>` or `tcp/<host>:<port>` with a port number.
fn endpoint(e: &str) -> bool {
    e.strip_prefix("tls/")
        .or_else(|| e.strip_prefix("tcp/"))
        .and_then(|rest| rest.rsplit_once(':'))
        .is_some_and(|(host, port)| !host.is_empty() && port.parse::<u16>().is_ok())
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"
lease_ms = 2000
keep_alive = 4
certs_dir = "/etc/amr/fleet-certs"
[server]
user = "server"
listen = ["tls/0.0.0.0:7447"]
connect = ["tls/192.168.0.10:7447"]
"#;

    #[test]
    fn a_good_file_parses() {
        let n: NetworkConfig = parse_file("network.toml", GOOD).unwrap();
        assert_eq!(n.lease_ms.ms(), 2000);
        assert_eq!(n.server.user.as_str(), "server");
    }

    #[test]
    fn a_long_lease_and_a_non_tcp_endpoint_are_refused() {
        let e = parse_file::<NetworkConfig>("network.toml", &GOOD.replace("2000", "5000")).unwrap_err();
        assert_eq!(e.key, "lease_ms");
        let e = parse_file::<NetworkConfig>("network.toml", &GOOD.replace("tls/0.0.0.0", "udp/0.0.0.0"))
            .unwrap_err();
        assert_eq!(e.key, "server.listen[0]");
        assert_eq!(e.line, Some(7));
        let e =
            parse_file::<NetworkConfig>("network.toml", &GOOD.replace(":7447\"]\nconnect", "\"]\nconnect"))
                .unwrap_err();
        assert!(e.rule.contains("expected tls/<host>:<port>"), "{e}");
    }
}
