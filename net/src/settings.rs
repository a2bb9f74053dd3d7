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

use crate::network::NetworkConfig;
use serde_json::json;

/// The key space: `fleet/<robot>/{scan,odom,health,cmd}`, liveliness `fleet/<robot>/alive`, the
/// server's status `fleet/server/status`.
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

/// Everything a bridge needs: the network section and the credentials.
#[derive(Debug, Clone)]
pub struct NetSettings {
    pub network: NetworkConfig,
    pub credentials: Credentials,
    /// Endpoints that replace `network.toml`'s (tests listen on a free loopback port).
    pub listen: Option<Vec<String>>,
    pub connect: Option<Vec<String>>,
}

impl NetSettings {
    /// The configuration's network section with the credentials at `credentials` (default: the
    /// file `network.toml` names).
    pub fn new(network: Option<&NetworkConfig>, credentials: Option<&Path>) -> Result<NetSettings, NetError> {
        let network = network.ok_or(NetError::NoNetworkConfig)?.clone();
        let path = credentials.map_or_else(|| PathBuf::from(&network.credentials_file), Path::to_path_buf);
        let credentials = Credentials::load(&path)?;
        Ok(NetSettings { network, credentials, listen: None, connect: None })
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

    fn common(&self, mode: &str, me: &Credential) -> Result<zenoh::Config, NetError> {
        let mut c = zenoh::Config::default();
        set(&mut c, "mode", &json!(mode))?;
        set(&mut c, "scouting/multicast/enabled", &json!(false))?;
        set(&mut c, "scouting/gossip/enabled", &json!(false))?;
        set(&mut c, "transport/link/tx/lease", &json!(self.network.lease_ms.ms()))?;
        set(&mut c, "transport/link/tx/keep_alive", &json!(self.network.keep_alive))?;
        set(&mut c, "transport/auth/usrpwd/user", &json!(me.user))?;
        set(&mut c, "transport/auth/usrpwd/password", &json!(me.password))?;
        Ok(c)
    }

    /// The server: a router listening on its endpoints, admitting only the users of the credentials
    /// file, with access control (see [`access_control`]).
    pub fn server_config(&self, robots: &[String]) -> Result<zenoh::Config, NetError> {
        let me = self.credentials.of(self.server_user())?;
        let mut c = self.common("router", me)?;
        let listen = self.listen.clone().unwrap_or_else(|| self.network.server.listen.clone());
        set(&mut c, "listen/endpoints", &json!(listen))?;
        set(&mut c, "connect/endpoints", &json!([]))?;
        set(
            &mut c,
            "transport/auth/usrpwd/dictionary_file",
            &json!(self.credentials.path.display().to_string()),
        )?;
        let users: Vec<&str> = self.credentials.entries.iter().map(|e| e.user.as_str()).collect();
        let operators = self.operators();
        set(&mut c, "access_control", &access_control(self.server_user(), &users, robots, &operators))?;
        Ok(c)
    }

    /// A client of the server's endpoints as `user`: a robot (user = its id), or an observer
    /// (operator tools, tests) that may read everything and, by the server's access control,
    /// publish nothing a robot or the server reads. A Zenoh client's `open` fails while no router
    /// admits it: the robot's bridge retries in the background (see `bridge`).
    pub fn client_config(&self, user: &str) -> Result<zenoh::Config, NetError> {
        let me = self.credentials.of(user)?;
        let mut c = self.common("client", me)?;
        let connect = self.connect.clone().unwrap_or_else(|| self.network.server.connect.clone());
        set(&mut c, "connect/endpoints", &json!(connect))?;
        set(&mut c, "listen/endpoints", &json!([]))?;
        Ok(c)
    }
}

fn set(c: &mut zenoh::Config, key: &str, value: &serde_json::Value) -> Result<(), NetError> {
    c.insert_json5(key, &value.to_string())
        .map_err(|e| NetError::Config { key: key.to_owned(), reason: e.to_string() })
}

/// The server's access control: every joined user but the server may not publish commands or the
/// server's status. A robot or an observer may not publish e-stops, and may publish (and hold a
/// liveliness token) only under its own robot's keys. An operator may publish e-stops and resets
/// (`fleet/<robot>/estop`) and nothing a robot publishes. So a robot cannot command or stop another
/// robot or pose as it, and an observer publishes nothing a robot or the server reads. Rules match
/// on the authenticated user name (Zenoh "usernames" subjects), and the server's own publications
/// are local, so no rule stops them.
#[must_use]
pub fn access_control(
    server: &str,
    users: &[&str],
    robots: &[String],
    operators: &[&str],
) -> serde_json::Value {
    let mut rules = Vec::new();
    let mut subjects = Vec::new();
    let mut policies = Vec::new();
    for (i, user) in users.iter().filter(|u| **u != server).enumerate() {
        let mut keys = vec![format!("{PREFIX}/*/cmd"), format!("{PREFIX}/server/**")];
        if operators.contains(user) {
            keys.extend(["scan", "odom", "health", "alive"].map(|ch| format!("{PREFIX}/*/{ch}")));
        } else {
            keys.push(format!("{PREFIX}/*/estop"));
            keys.extend(robots.iter().filter(|r| r.as_str() != *user).map(|r| format!("{PREFIX}/{r}/**")));
        }
        let (rule, subject) = (format!("r{i}"), format!("s{i}"));
        rules.push(json!({
            "id": rule,
            "permission": "deny",
            "flows": ["ingress"],
            "messages": ["put", "delete", "liveliness_token"],
            "key_exprs": keys,
        }));
        subjects.push(json!({ "id": subject, "usernames": [user] }));
        policies.push(json!({ "rules": [rule], "subjects": [subject] }));
    }
    json!({
        "enabled": !rules.is_empty(),
        "default_permission": "allow",
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
    fn access_control_denies_commands_and_other_robots_keys_to_every_user_but_the_server() {
        let robots = vec!["robot-a".to_owned(), "robot-b".to_owned()];
        let users = ["server", "robot-a", "robot-b", "observer", "operator"];
        let acl = access_control("server", &users, &robots, &["operator"]);
        let rules = acl["rules"].as_array().unwrap();
        assert_eq!(rules.len(), 4, "one per user but the server");
        let keys = |i: usize| -> Vec<String> {
            rules[i]["key_exprs"].as_array().unwrap().iter().map(|k| k.as_str().unwrap().to_owned()).collect()
        };
        assert_eq!(keys(0), ["fleet/*/cmd", "fleet/server/**", "fleet/*/estop", "fleet/robot-b/**"]);
        assert_eq!(
            keys(2),
            ["fleet/*/cmd", "fleet/server/**", "fleet/*/estop", "fleet/robot-a/**", "fleet/robot-b/**"]
        );
        // The operator: e-stops only (nothing a robot publishes, no commands).
        assert_eq!(
            keys(3),
            [
                "fleet/*/cmd",
                "fleet/server/**",
                "fleet/*/scan",
                "fleet/*/odom",
                "fleet/*/health",
                "fleet/*/alive"
            ]
        );
        assert_eq!(acl["subjects"][1]["usernames"][0], "robot-b");
        // Zenoh accepts it.
        let mut c = zenoh::Config::default();
        set(&mut c, "access_control", &acl).unwrap();
    }
}
