//! From `network.toml` and a credentials file to Zenoh configurations: the server's (a router that
//! listens, checks every joining peer's user and password, and enforces who may publish what) and
//! a robot's (a client that connects to the server's endpoints only).
//!
//! Zenoh options used (zenoh-config 1.10 `defaults.rs` and the manual's pages "User-Password
//! authentication" and "Access Control", zenoh.io/docs/manual): `mode`, `listen/endpoints`,
//! `connect/endpoints`, `connect/timeout_ms`, `connect/exit_on_failure`, `scouting/multicast/enabled`,
//! `scouting/gossip/enabled`, `transport/link/tx/lease`, `transport/link/tx/keep_alive`,
//! `transport/auth/usrpwd/{user,password,dictionary_file}` and `access_control`.

use std::fmt;
use std::path::{Path, PathBuf};

use crate::certs::TlsFiles;
use crate::network::NetworkConfig;
use serde_json::json;

/// The key space: `fleet/<robot>/{scan,odom,health,cmd}`, e-stops `fleet/<robot>/estop/<sender>`,
/// liveliness `fleet/<robot>/alive`, the server's status `fleet/server/status`.
pub const PREFIX: &str = "fleet";

/// Why the link could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error("the configuration has no network.toml")]
    NoNetworkConfig,
    #[error("credentials file {path}: {reason}")]
    Credentials { path: PathBuf, reason: String },
    #[error("zenoh configuration `{key}`: {reason}")]
    Config { key: String, reason: String },
    #[error("{0}")]
    Insecure(String),
    #[error("fleet certificates: {0}")]
    Certificates(String),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("starting the bridge actor: {0}")]
    Actor(String),
}

/// One `user:password` line. The password never appears in `Debug` output or logs.
#[derive(Clone, PartialEq, Eq)]
pub struct Credential {
    pub user: String,
    password: String,
}

impl fmt::Debug for Credential {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Credential {{ user: {:?}, password: <redacted> }}", self.user)
    }
}

impl Credential {
    #[must_use]
    pub fn new(user: &str, password: &str) -> Self {
        Credential { user: user.to_owned(), password: password.to_owned() }
    }
}

/// The credentials file: Zenoh's dictionary format, `user:password` per line (blank lines and
/// lines starting with `#` skipped).
#[derive(Clone)]
pub struct Credentials {
    pub path: PathBuf,
    pub entries: Vec<Credential>,
}

impl fmt::Debug for Credentials {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let users: Vec<&str> = self.entries.iter().map(|c| c.user.as_str()).collect();
        write!(f, "Credentials {{ path: {:?}, users: {users:?} }}", self.path)
    }
}

impl Credentials {
    /// Read and check the file. The error names the line, never its contents.
    pub fn load(path: &Path) -> Result<Credentials, NetError> {
        let err = |reason: String| NetError::Credentials { path: path.to_path_buf(), reason };
        let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
        let mut entries: Vec<Credential> = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let Some((user, password)) = line.split_once(':') else {
                return Err(err(format!("line {}: expected user:password", i + 1)));
            };
            if user.is_empty() || password.is_empty() {
                return Err(err(format!("line {}: empty user or password", i + 1)));
            }
            if entries.iter().any(|c| c.user == user) {
                return Err(err(format!("line {}: user `{user}` is listed twice", i + 1)));
            }
            entries.push(Credential::new(user, password));
        }
        Ok(Credentials { path: path.to_path_buf(), entries })
    }

    /// The entry of `user`.
    pub fn of(&self, user: &str) -> Result<&Credential, NetError> {
        self.entries.iter().find(|c| c.user == user).ok_or_else(|| NetError::Credentials {
            path: self.path.clone(),
            reason: format!("no line for user `{user}`"),
        })
    }
}

/// How the peers of the link prove who they are.
#[derive(Debug, Clone)]
pub enum Security {
    /// Mutual TLS (Zenoh's `tls/` transport): every peer presents a certificate of the fleet's CA
    /// and verifies the other's; names are the certificates' common names (`amr fleet certs`
    /// writes the directory, see [`crate::certs`]).
    Tls { dir: PathBuf },
    /// Plain TCP (`--insecure`): peers authenticate with user and password, nothing is
    /// encrypted, and a robot cannot tell the server from whoever answers at its address.
    Insecure { credentials: Credentials },
}

/// Everything a bridge needs: the network section and how peers authenticate.
#[derive(Debug, Clone)]
pub struct NetSettings {
    pub network: NetworkConfig,
    pub security: Security,
    /// Endpoints that replace `network.toml`'s (tests listen on a free loopback port).
    pub listen: Option<Vec<String>>,
    pub connect: Option<Vec<String>>,
}

impl NetSettings {
    /// Mutual TLS with the certificates in `certs` (default: network.toml's `certs_dir`).
    pub fn tls(network: Option<&NetworkConfig>, certs: Option<&Path>) -> Result<NetSettings, NetError> {
        let network = network.ok_or(NetError::NoNetworkConfig)?.clone();
        let dir = certs.map_or_else(|| PathBuf::from(&network.certs_dir), Path::to_path_buf);
        Ok(NetSettings { network, security: Security::Tls { dir }, listen: None, connect: None })
    }

    /// Plain TCP with the credentials at `credentials` (default: network.toml's
    /// `credentials_file`): only behind an explicit `--insecure`.
    pub fn insecure(
        network: Option<&NetworkConfig>,
        credentials: Option<&Path>,
    ) -> Result<NetSettings, NetError> {
        let network = network.ok_or(NetError::NoNetworkConfig)?.clone();
        let path =
            match (credentials, &network.credentials_file) {
                (Some(p), _) => p.to_path_buf(),
                (None, Some(f)) => PathBuf::from(f),
                (None, None) => return Err(NetError::Insecure(
                    "--insecure needs a credentials file (network.toml's credentials_file or --credentials)"
                        .into(),
                )),
            };
        let credentials = Credentials::load(&path)?;
        Ok(NetSettings { network, security: Security::Insecure { credentials }, listen: None, connect: None })
    }

    /// The server's user name.
    #[must_use]
    pub fn server_user(&self) -> &str {
        self.network.server.user.as_str()
    }

    /// The operators' user names (who may e-stop besides the server).
    #[must_use]
    pub fn operators(&self) -> Vec<&str> {
        self.network.server.operators.iter().map(|o| o.as_str()).collect()
    }

    /// Who a robot takes an e-stop or its reset from: the server and the operators.
    #[must_use]
    pub fn estop_senders(&self) -> Vec<String> {
        std::iter::once(self.server_user()).chain(self.operators()).map(str::to_owned).collect()
    }

    /// The endpoints in the transport of [`Security`]: with TLS a `tcp/` endpoint is refused
    /// (plain TCP only behind `--insecure`); insecure, `tls/` endpoints become `tcp/` ones.
    fn endpoints(&self, list: &[String]) -> Result<Vec<String>, NetError> {
        list.iter()
            .map(|e| match (&self.security, e.split_once('/')) {
                (Security::Tls { .. }, Some(("tls", _))) => Ok(e.clone()),
                (Security::Tls { .. }, Some(("tcp", _))) => Err(NetError::Insecure(format!(
                    "`{e}` is plain TCP: use tls/ endpoints, or run with --insecure"
                ))),
                (Security::Insecure { .. }, Some(("tls" | "tcp", rest))) => Ok(format!("tcp/{rest}")),
                _ => Err(NetError::Config {
                    key: "endpoints".into(),
                    reason: format!("`{e}`: expected tls/<host>:<port>"),
                }),
            })
            .collect()
    }

    fn common(&self, mode: &str, me: &str, listen: bool) -> Result<zenoh::Config, NetError> {
        let mut c = zenoh::Config::default();
        set(&mut c, "mode", &json!(mode))?;
        set(&mut c, "scouting/multicast/enabled", &json!(false))?;
        set(&mut c, "scouting/gossip/enabled", &json!(false))?;
        set(&mut c, "transport/link/tx/lease", &json!(self.network.lease_ms.ms()))?;
        set(&mut c, "transport/link/tx/keep_alive", &json!(self.network.keep_alive))?;
        match &self.security {
            Security::Insecure { credentials } => {
                let cred = credentials.of(me)?;
                set(&mut c, "transport/auth/usrpwd/user", &json!(cred.user))?;
                set(&mut c, "transport/auth/usrpwd/password", &json!(cred.password))?;
            }
            Security::Tls { dir } => {
                let files = TlsFiles::of(dir, me).map_err(|e| NetError::Certificates(e.to_string()))?;
                let path = |p: &Path| json!(p.display().to_string());
                set(&mut c, "transport/link/tls/root_ca_certificate", &path(&files.ca))?;
                set(&mut c, "transport/link/tls/enable_mtls", &json!(true))?;
                let side = if listen { "listen" } else { "connect" };
                set(&mut c, &format!("transport/link/tls/{side}_certificate"), &path(&files.cert))?;
                set(&mut c, &format!("transport/link/tls/{side}_private_key"), &path(&files.key))?;
                // A robot checks that the server's certificate is valid for the host it dialled.
                set(&mut c, "transport/link/tls/verify_name_on_connect", &json!(true))?;
                // A link ends when either side's certificate expires (not only new ones fail).
                set(&mut c, "transport/link/tls/close_link_on_expiration", &json!(true))?;
            }
        }
        Ok(c)
    }

    /// The server: a router listening on its endpoints, admitting only peers that authenticate
    /// (certificate of the fleet's CA, or a user of the credentials file), with access control
    /// (see [`access_control`]).
    pub fn server_config(&self, robots: &[String]) -> Result<zenoh::Config, NetError> {
        let mut c = self.common("router", self.server_user(), true)?;
        let listen = self.endpoints(self.listen.as_deref().unwrap_or(&self.network.server.listen))?;
        set(&mut c, "listen/endpoints", &json!(listen))?;
        set(&mut c, "connect/endpoints", &json!([]))?;
        let names = match &self.security {
            Security::Insecure { credentials } => {
                set(
                    &mut c,
                    "transport/auth/usrpwd/dictionary_file",
                    &json!(credentials.path.display().to_string()),
                )?;
                Names::Usernames
            }
            Security::Tls { .. } => Names::Certificates,
        };
        set(&mut c, "access_control", &access_control(names, robots, &self.operators()))?;
        Ok(c)
    }

    /// A client of the server's endpoints as `user`: a robot (user = its id), or an observer
    /// (operator tools, tests) that may read everything and, by the server's access control,
    /// publish nothing a robot or the server reads. A Zenoh client's `open` fails while no router
    /// admits it: the robot's bridge retries in the background (see `bridge`).
    pub fn client_config(&self, user: &str) -> Result<zenoh::Config, NetError> {
        let mut c = self.common("client", user, false)?;
        let connect = self.endpoints(self.connect.as_deref().unwrap_or(&self.network.server.connect))?;
        set(&mut c, "connect/endpoints", &json!(connect))?;
        set(&mut c, "listen/endpoints", &json!([]))?;
        Ok(c)
    }
}

fn set(c: &mut zenoh::Config, key: &str, value: &serde_json::Value) -> Result<(), NetError> {
    c.insert_json5(key, &value.to_string())
        .map_err(|e| NetError::Config { key: key.to_owned(), reason: e.to_string() })
}

/// What the server's access control matches a peer's name on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Names {
    /// The certificate's common name (mutual TLS).
    Certificates,
    /// The user of user/password authentication (`--insecure`).
    Usernames,
}

/// Every kind of message the access control knows (zenoh-config 1.10 `AclMessage`).
const ALL_MESSAGES: [&str; 9] = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
];

/// The server's access control, an allow list: whatever it does not allow is denied.
///
/// - Every peer that joined may subscribe to the fleet's keys and receive them (observers, tools).
/// - A robot may publish only its own scan, odometry and health, and hold only its own liveliness
///   token.
/// - An operator may publish e-stops and resets on its own key (`fleet/<robot>/estop/<name>`),
///   nothing else.
/// - Nobody but the server publishes commands or the server's status: the server's own
///   publications are local to its router and pass no ingress rule.
///
/// Zenoh allows a message when an allow rule's key expression *includes* the message's key
/// (zenoh 1.10, `PolicyEnforcer::policy_decision_point`), and a put may carry a wildcard key that
/// reaches every subscriber it intersects. An allow list is safe against that (`fleet/**` is
/// included in no robot's keys), where a deny list of other robots' keys is not: `fleet/**`
/// is included in none of them either, so it would pass.
#[must_use]
pub fn access_control(names: Names, robots: &[String], operators: &[&str]) -> serde_json::Value {
    let name_key = match names {
        Names::Certificates => "cert_common_names",
        Names::Usernames => "usernames",
    };
    let mut rules = vec![
        json!({
            "id": "join-read", "permission": "allow", "flows": ["ingress"],
            "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": [format!("{PREFIX}/**")],
        }),
        json!({
            "id": "join-receive", "permission": "allow", "flows": ["egress"],
            "messages": ALL_MESSAGES, "key_exprs": [format!("{PREFIX}/**")],
        }),
    ];
    let protocol = match names {
        Names::Certificates => "tls",
        Names::Usernames => "tcp",
    };
    let mut subjects = vec![json!({ "id": "joined", "link_protocols": [protocol] })];
    let mut policies = vec![json!({ "rules": ["join-read", "join-receive"], "subjects": ["joined"] })];
    for (i, r) in robots.iter().enumerate() {
        let (rule, token, subject) = (format!("robot{i}"), format!("robot{i}-alive"), format!("robot{i}"));
        let own = ["scan", "odom", "health"].map(|ch| format!("{PREFIX}/{r}/{ch}"));
        rules.push(json!({
            "id": rule, "permission": "allow", "flows": ["ingress"], "messages": ["put", "delete"],
            "key_exprs": own,
        }));
        rules.push(json!({
            "id": token, "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
            "key_exprs": [format!("{PREFIX}/{r}/alive")],
        }));
        subjects.push(json!({ "id": subject, name_key: [r] }));
        policies.push(json!({ "rules": [rule, token], "subjects": [subject] }));
    }
    // Each operator on its own key: a robot takes the sender's name from the key, so no operator
    // can speak for the server or another operator.
    for (i, o) in operators.iter().enumerate() {
        let (rule, subject) = (format!("estop{i}"), format!("operator{i}"));
        rules.push(json!({
            "id": rule, "permission": "allow", "flows": ["ingress"], "messages": ["put"],
            "key_exprs": [format!("{PREFIX}/*/estop/{o}")],
        }));
        subjects.push(json!({ "id": subject, name_key: [o] }));
        policies.push(json!({ "rules": [rule], "subjects": [subject] }));
    }
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    #[test]
    fn a_credentials_file_is_checked_and_never_shows_a_password() {
        let dir = std::env::temp_dir().join(format!("amr-net-cred-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("creds");
        std::fs::write(&p, "# fleet\nserver:s3cret-server\n\nrobot-a:s3cret-a\n").unwrap();
        let c = Credentials::load(&p).unwrap();
        assert_eq!(c.of("robot-a").unwrap().user, "robot-a");
        let shown = format!("{c:?} {:?}", c.of("server").unwrap());
        assert!(!shown.contains("s3cret"), "{shown}");
        assert!(c.of("robot-b").is_err());
        std::fs::write(&p, "server:x\nserver:y\n").unwrap();
        let e = Credentials::load(&p).unwrap_err().to_string();
        assert!(e.contains("line 2") && !e.contains(":y"), "{e}");
        std::fs::write(&p, "server-without-password\n").unwrap();
        assert!(Credentials::load(&p).unwrap_err().to_string().contains("expected user:password"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn access_control_is_an_allow_list_keyed_on_the_chosen_names() {
        let robots = vec!["robot-a".to_owned(), "robot-b".to_owned()];
        let acl = access_control(Names::Certificates, &robots, &["operator", "night-shift"]);
        assert_eq!(acl["default_permission"], "deny");
        let rule =
            |id: &str| acl["rules"].as_array().unwrap().iter().find(|r| r["id"] == id).unwrap().clone();
        let keys = |id: &str| -> Vec<String> {
            rule(id)["key_exprs"].as_array().unwrap().iter().map(|k| k.as_str().unwrap().to_owned()).collect()
        };
        assert_eq!(keys("robot0"), ["fleet/robot-a/scan", "fleet/robot-a/odom", "fleet/robot-a/health"]);
        assert_eq!(keys("robot1-alive"), ["fleet/robot-b/alive"]);
        assert_eq!(keys("estop0"), ["fleet/*/estop/operator"]);
        assert_eq!(keys("estop1"), ["fleet/*/estop/night-shift"]);
        assert_eq!(acl["subjects"][4]["cert_common_names"], serde_json::json!(["night-shift"]));
        // Nobody is allowed to publish commands or the server's status (only the server's local
        // publications make them), and every allow rule but the join rules is ingress only.
        for r in acl["rules"].as_array().unwrap() {
            for k in r["key_exprs"].as_array().unwrap() {
                let k = k.as_str().unwrap();
                assert!(!k.ends_with("/cmd") && !k.starts_with("fleet/server"), "{r}");
            }
        }
        assert_eq!(rule("join-read")["messages"].as_array().unwrap().len(), 3, "reading only");
        assert_eq!(acl["subjects"][1]["cert_common_names"][0], "robot-a");
        assert_eq!(acl["subjects"][0]["link_protocols"][0], "tls");
        let insecure = access_control(Names::Usernames, &robots, &["operator"]);
        assert_eq!(insecure["subjects"][3]["usernames"][0], "operator");
        // Zenoh accepts both.
        for acl in [acl, insecure] {
            let mut c = zenoh::Config::default();
            set(&mut c, "access_control", &acl).unwrap();
        }
    }
}
