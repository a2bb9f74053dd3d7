//! The fleet's certificates (`amr fleet certs`): one certificate authority per fleet, and a key pair
//! and certificate per robot, for the server and for each operator. The link's mutual TLS
//! ([`crate::settings`]) has every peer verify the other against that CA; the server's access
//! control is keyed on the certificate's name (its subject's common name).
//!
//! The directory's layout, which [`TlsFiles`] reads back:
//!
//! | file | what | who needs it |
//! |---|---|---|
//! | `ca.pem` | the fleet CA's certificate | every machine |
//! | `ca.key` | the CA's private key | nobody on the fleet: keep it offline, it signs new members |
//! | `<name>.pem`, `<name>.key` | a member's certificate and private key | that member only |
//!
//! Keys are ECDSA P-256 (rcgen's default, verified by rustls on ring), written with mode 0600.
//! A member's certificate names it twice: as the subject's common name (what the server's access
//! control matches) and as a DNS subject alternative name. The server's also carries the hosts the
//! robots dial (`--server-hosts`), because a robot checks the name it connected to against the
//! server's certificate (`verify_name_on_connect`): so a robot's certificate, valid for its own
//! name only, cannot pose as the server. Extended key usage is both client and server
//! authentication (webpki checks it on both sides).

use std::collections::BTreeSet;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer,
    KeyPair, KeyUsagePurpose,
};
use time::{Duration, OffsetDateTime};

/// The CA's common name.
pub const CA_NAME: &str = "amr fleet CA";

/// Why certificates could not be made or read.
#[derive(Debug, thiserror::Error)]
pub enum CertError {
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error("certificate for `{name}`: {reason}")]
    Make { name: String, reason: String },
    #[error("{0}")]
    Request(String),
}

fn file_err(path: &Path, reason: impl ToString) -> CertError {
    CertError::File { path: path.to_path_buf(), reason: reason.to_string() }
}

/// What to make.
#[derive(Debug, Clone)]
pub struct CertRequest {
    /// The server's name (network.toml's `server.user`); `None`: members only (joining a fleet).
    pub server: Option<String>,
    /// Host names and addresses the robots dial to reach the server (its certificate is valid for
    /// these and for its name).
    pub server_hosts: Vec<String>,
    pub robots: Vec<String>,
    /// Operators (`amr estop`) and observers: anyone else who joins.
    pub others: Vec<String>,
    /// Names no member may take although no certificate is made for them here: the fleet's server
    /// and its hosts when joining a fleet (a member named so would pass as the server).
    pub reserved: Vec<String>,
    /// How long members' certificates are valid, days (the CA: ten years).
    pub days: u32,
}

/// What was written.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Made {
    /// Whether a new CA was made (else the directory's `ca.pem`/`ca.key` signed).
    pub new_ca: bool,
    /// The members whose certificate and key were written.
    pub members: Vec<String>,
}

/// Make the certificates of `req` in `out`. A directory that already holds `ca.pem` and `ca.key`
/// keeps its CA, which signs the new members (a robot joining a fleet); a member whose files
/// exist is refused rather than overwritten.
pub fn make(out: &Path, req: &CertRequest) -> Result<Made, CertError> {
    let names: Vec<&String> = req.server.iter().chain(&req.robots).chain(&req.others).collect::<Vec<_>>();
    let mut seen = BTreeSet::new();
    for n in &names {
        amr_core::config::RobotId::new(n).map_err(|e| CertError::Request(format!("name `{n}`: {e}")))?;
        if !seen.insert(n.as_str()) {
            return Err(CertError::Request(format!("`{n}` is named twice")));
        }
        if Some(*n) != req.server.as_ref() && req.server_hosts.iter().chain(&req.reserved).any(|h| h == *n) {
            return Err(CertError::Request(format!(
                "`{n}` is the server's name or one of its hosts: its certificate would pass as the server's"
            )));
        }
    }
    if req.days == 0 {
        return Err(CertError::Request("--days must be at least 1".into()));
    }
    std::fs::create_dir_all(out).map_err(|e| file_err(out, e))?;
    for n in &names {
        for ext in ["pem", "key"] {
            let p = out.join(format!("{n}.{ext}"));
            if p.exists() {
                return Err(file_err(&p, "exists; remove it first to make a new one"));
            }
        }
    }
    let now = OffsetDateTime::now_utc();
    let (ca_pem, ca_key) = (out.join("ca.pem"), out.join("ca.key"));
    let (issuer, new_ca) = if ca_pem.exists() || ca_key.exists() {
        let cert = read(&ca_pem)?;
        let key = KeyPair::from_pem(&read(&ca_key)?).map_err(|e| file_err(&ca_key, e))?;
        (Issuer::from_ca_cert_pem(&cert, key).map_err(|e| file_err(&ca_pem, e))?, false)
    } else {
        let key = KeyPair::generate().map_err(|e| make_err(CA_NAME, e))?;
        let mut p = CertificateParams::default();
        p.distinguished_name = dn(CA_NAME);
        p.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        p.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        p.not_before = now - Duration::hours(1);
        p.not_after = now + Duration::days(3653);
        let cert = p.self_signed(&key).map_err(|e| make_err(CA_NAME, e))?;
        write(&ca_pem, &cert.pem(), false)?;
        write(&ca_key, &key.serialize_pem(), true)?;
        (Issuer::new(p, key), true)
    };
    let mut members = Vec::new();
    for n in names {
        let mut sans = vec![n.clone()];
        if Some(n) == req.server.as_ref() {
            sans.extend(req.server_hosts.iter().filter(|h| *h != n).cloned());
        }
        let mut p = CertificateParams::new(sans).map_err(|e| make_err(n, e))?;
        p.distinguished_name = dn(n);
        p.is_ca = IsCa::ExplicitNoCa;
        p.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        p.extended_key_usages =
            vec![ExtendedKeyUsagePurpose::ServerAuth, ExtendedKeyUsagePurpose::ClientAuth];
        p.use_authority_key_identifier_extension = true;
        p.not_before = now - Duration::hours(1);
        p.not_after = now + Duration::days(i64::from(req.days));
        let key = KeyPair::generate().map_err(|e| make_err(n, e))?;
        let cert = p.signed_by(&key, &issuer).map_err(|e| make_err(n, e))?;
        write(&out.join(format!("{n}.pem")), &cert.pem(), false)?;
        write(&out.join(format!("{n}.key")), &key.serialize_pem(), true)?;
        members.push(n.clone());
    }
    Ok(Made { new_ca, members })
}

fn make_err(name: &str, e: rcgen::Error) -> CertError {
    CertError::Make { name: name.to_owned(), reason: e.to_string() }
}

fn dn(common_name: &str) -> DistinguishedName {
    let mut d = DistinguishedName::new();
    d.push(DnType::OrganizationName, "amr fleet");
    d.push(DnType::CommonName, common_name);
    d
}

fn read(path: &Path) -> Result<String, CertError> {
    std::fs::read_to_string(path).map_err(|e| file_err(path, e))
}

/// Write a new file; private keys readable by their owner only.
fn write(path: &Path, text: &str, private: bool) -> Result<(), CertError> {
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt as _;
        o.mode(if private { 0o600 } else { 0o644 });
    }
    #[cfg(not(unix))]
    let _ = private;
    let mut f = o.open(path).map_err(|e| file_err(path, e))?;
    f.write_all(text.as_bytes()).map_err(|e| file_err(path, e))
}

/// One member's files in a certificates directory, checked to exist and to name that member.
#[derive(Debug, Clone)]
pub struct TlsFiles {
    pub ca: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
}

impl TlsFiles {
    /// `dir/ca.pem`, `dir/<name>.pem` and `dir/<name>.key`; the certificate's common name must be
    /// `name` (the server's access control goes by it, so a mix-up is caught here, not as a
    /// refusal later).
    pub fn of(dir: &Path, name: &str) -> Result<TlsFiles, CertError> {
        let files = TlsFiles {
            ca: dir.join("ca.pem"),
            cert: dir.join(format!("{name}.pem")),
            key: dir.join(format!("{name}.key")),
        };
        for p in [&files.ca, &files.key] {
            if !p.is_file() {
                return Err(file_err(p, "missing (make the fleet's certificates with `amr fleet certs`)"));
            }
        }
        let cn = common_name(&read(&files.cert)?).map_err(|e| file_err(&files.cert, e))?;
        if cn != name {
            return Err(file_err(&files.cert, format!("is `{cn}`'s certificate, not `{name}`'s")));
        }
        Ok(files)
    }
}

/// The subject's common name of a PEM certificate.
pub fn common_name(pem: &str) -> Result<String, String> {
    let (_, pem) = x509_parser::pem::parse_x509_pem(pem.as_bytes()).map_err(|e| format!("not PEM: {e}"))?;
    let cert = pem.parse_x509().map_err(|e| format!("not a certificate: {e}"))?;
    let cn = cert.subject().iter_common_name().next().ok_or("has no common name")?;
    cn.as_str().map(str::to_owned).map_err(|e| format!("its common name is not text: {e}"))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    fn req() -> CertRequest {
        CertRequest {
            server: Some("server".into()),
            server_hosts: vec!["127.0.0.1".into(), "localhost".into()],
            robots: vec!["robot-a".into(), "robot-b".into()],
            others: vec!["operator".into()],
            reserved: vec![],
            days: 30,
        }
    }

    #[test]
    fn a_fleet_is_made_read_back_and_extended_without_overwriting() {
        let dir = tempfile::tempdir().unwrap();
        let made = make(dir.path(), &req()).unwrap();
        assert!(made.new_ca);
        assert_eq!(made.members, ["server", "robot-a", "robot-b", "operator"]);
        let files = TlsFiles::of(dir.path(), "robot-a").unwrap();
        assert_eq!(common_name(&std::fs::read_to_string(&files.cert).unwrap()).unwrap(), "robot-a");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt as _;
            let mode = std::fs::metadata(&files.key).unwrap().permissions().mode();
            assert_eq!(mode & 0o077, 0, "a private key readable by others: {mode:o}");
        }
        // Files swapped: robot-b's certificate under robot-a's name is caught.
        std::fs::copy(dir.path().join("robot-b.pem"), dir.path().join("robot-a.pem")).unwrap();
        let e = TlsFiles::of(dir.path(), "robot-a").unwrap_err().to_string();
        assert!(e.contains("`robot-b`'s certificate"), "{e}");
        assert!(TlsFiles::of(dir.path(), "robot-c").is_err());
        // Made again: refused, nothing overwritten.
        let ca = std::fs::read(dir.path().join("ca.pem")).unwrap();
        assert!(make(dir.path(), &req()).unwrap_err().to_string().contains("exists"));
        // A new robot joins: the fleet's CA signs it.
        let join = CertRequest {
            server: None,
            server_hosts: vec![],
            robots: vec!["robot-c".into()],
            others: vec![],
            reserved: vec!["server".into(), "localhost".into()],
            days: 30,
        };
        // Joining, no member may be named like the server or one of its hosts.
        for name in ["server", "localhost"] {
            let mut bad = join.clone();
            bad.robots.push(name.into());
            let e = make(dir.path(), &bad).unwrap_err().to_string();
            assert!(e.contains("pass as the server"), "{e}");
        }
        let made = make(dir.path(), &join).unwrap();
        assert!(!made.new_ca);
        assert_eq!(std::fs::read(dir.path().join("ca.pem")).unwrap(), ca);
        TlsFiles::of(dir.path(), "robot-c").unwrap();
    }

    #[test]
    fn bad_requests_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut r = req();
        r.robots.push("Robot A".into());
        assert!(make(dir.path(), &r).unwrap_err().to_string().contains("Robot A"));
        let mut r = req();
        r.others.push("robot-a".into());
        assert!(make(dir.path(), &r).unwrap_err().to_string().contains("twice"));
        let mut r = req();
        r.server_hosts.push("robot-b".into());
        assert!(make(dir.path(), &r).unwrap_err().to_string().contains("pass as the server"));
        assert!(!dir.path().join("ca.pem").exists(), "a refused request wrote nothing");
    }
}
