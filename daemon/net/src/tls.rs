//! The wall's certificates: `isowall keygen` makes a CA and one certificate per node and for the
//! controller ([`crate::keygen`]); every connection presents one and accepts only peers whose certificate
//! the wall CA signed ([`Identity::server_config`], [`Identity::client_config`]).
//!
//! Files in the certificate folder: `ca.pem` (the CA certificate, on every machine), `ca.key` (the
//! CA's private key: keep it off the wall, it signs new certificates), `NAME.pem` + `NAME.key` for
//! every node NAME and for `controller`. TLS 1.3 only (QUIC), ring provider only.
//!
//! Identities ([`PeerIdentity`], [`peer_identity`]): a node's certificate names the node in its
//! one DNS SAN, and a client connecting to a node checks that name; the controller's certificate
//! has no DNS name at all, only the URI SAN [`CONTROLLER_URI`], which keygen never writes into a
//! node's certificate (a node name cannot be a URI), so no node certificate can act as the
//! controller. Names are compared exactly, byte for byte: TLS's own DNS matching ignores case,
//! which is why a wall's node names must also be unique without regard to case ([`crate::keygen`]
//! refuses names that are not).
//!
//! A private key is loaded only when no one but its owner may read or write it (mode 0600 or
//! 0400): [`Identity::load`] refuses a key open to its group or to others, naming the file.
//!
//! Validity ([`validity_at`]): [`Identity::load`] refuses a certificate or CA that has expired
//! or is not valid yet, naming the file and the date, and warns (tracing) about one that ends
//! within [`EXPIRY_WARNING_DAYS`]; `check-config` says the same of every certificate of the
//! wall it finds ([`certificate_report`]).

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The controller's certificate name (its files are `controller.pem` and `controller.key`).
pub const CONTROLLER: &str = "controller";

/// The controller's identity: the one URI SAN of its certificate (and of no node's).
pub const CONTROLLER_URI: &str = "urn:isowall:controller";

#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("{path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
    #[error("{path}: not a usable PEM {what}: {reason}")]
    Pem { path: PathBuf, what: &'static str, reason: String },
    #[error("certificate generation failed for '{name}': {reason}")]
    Generate { name: String, reason: String },
    #[error("TLS configuration: {0}")]
    Config(String),
    #[error("certificate name {0}")]
    BadName(String),
    #[error("node name '{0}' is the same as '{1}' without regard to case: TLS could not tell them apart")]
    SameName(String, String),
    #[error(
        "{}: a wall CA is already here, and a new one would stop every certificate it signed from \
         working: `--renew` issues the node and controller certificates again from it, `--force` \
         replaces it (then copy every node's new files)", .0.display()
    )]
    CaExists(PathBuf),
    #[error("{}: no wall CA to renew from (run keygen without --renew to make one)", .0.display())]
    NoCa(PathBuf),
    #[error("certificate validity: {0}")]
    Validity(String),
    #[error(
        "{}: the private key is open to its group or to others (mode {mode:04o}): only its owner may \
         read it, `chmod 600 {}`", path.display(), path.display()
    )]
    KeyOpen { path: PathBuf, mode: u32 },
    #[error("{}: the private key does not belong to the certificate {}", key.display(), cert.display())]
    KeyMismatch { cert: PathBuf, key: PathBuf },
    #[error("{}: {what} expired on {until} (UTC): {renew}", path.display())]
    Expired { path: PathBuf, what: &'static str, until: String, renew: &'static str },
    #[error(
        "{}: {what} is not valid before {from} (UTC): is this machine's clock right?", path.display()
    )]
    NotYetValid { path: PathBuf, what: &'static str, from: String },
}

impl TlsError {
    /// What fixes this error where `name`'s certificate was loaded for the wall config at
    /// `config`, where the error itself does not say it: a missing file is copied from where
    /// `keygen` made it (running `keygen` again on a deployed wall would replace its CA).
    pub fn remedy(&self, name: &str, config: &Path) -> Option<String> {
        match self {
            TlsError::Io { error, .. } if error.kind() == std::io::ErrorKind::NotFound => Some(format!(
                "copy ca.pem, {name}.pem and {name}.key into the config's certificate folder from the \
                 machine where `isowall keygen` made them (its keys folder); only for a new wall, \
                 `isowall keygen --config {}` makes them",
                config.display()
            )),
            _ => None,
        }
    }
}

/// A certificate that ends within this many days is warned about.
pub const EXPIRY_WARNING_DAYS: i64 = 30;

/// What renews a certificate, and the CA.
const RENEW: &str = "`isowall keygen --renew --config FILE` issues the certificates again from the CA (copy \
                     each node its new files)";
const RENEW_CA: &str = "`isowall keygen --force --config FILE` makes a new CA and certificates (copy every \
                        node its new files)";

/// Where `path`'s certificate (`der`; `ca`: the wall CA) stands at `now` (Unix seconds): an
/// error when it has expired or is not valid yet, a warning (`Some`) when it ends within
/// [`EXPIRY_WARNING_DAYS`].
pub fn validity_at(path: &Path, ca: bool, der: &[u8], now: i64) -> Result<Option<String>, TlsError> {
    let what = if ca { "the wall CA" } else { "the certificate" };
    let renew = if ca { RENEW_CA } else { RENEW };
    let (_, x509) = x509_parser::parse_x509_certificate(der).map_err(|e| TlsError::Pem {
        path: path.to_owned(),
        what: "certificate",
        reason: e.to_string(),
    })?;
    let v = x509.validity();
    let day = |t: &x509_parser::time::ASN1Time| t.to_datetime().date().to_string();
    if now < v.not_before.timestamp() {
        return Err(TlsError::NotYetValid { path: path.to_owned(), what, from: day(&v.not_before) });
    }
    let left = v.not_after.timestamp() - now;
    if left < 0 {
        return Err(TlsError::Expired { path: path.to_owned(), what, until: day(&v.not_after), renew });
    }
    // Whole days left, a part of a day counted as one.
    let days = (left + 86_399) / 86_400;
    Ok((left < EXPIRY_WARNING_DAYS * 86_400).then(|| {
        format!(
            "{}: {what} expires on {} (UTC), in {days} day{}: {renew}",
            path.display(),
            day(&v.not_after),
            if days == 1 { "" } else { "s" }
        )
    }))
}

/// The seconds since 1970 now.
pub(crate) fn unix_now() -> i64 {
    let since = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
    i64::try_from(since.as_secs()).unwrap_or(i64::MAX)
}

/// `check-config`'s lines on the certificates of `config`'s wall in its certificate folder, now
/// ([`certificate_report`]).
pub fn check_wall_certificates(config: &isowall_model::WallConfig) -> Result<Vec<String>, String> {
    let names: Vec<String> = config.nodes.iter().map(|n| n.name.clone()).collect();
    certificate_report(&config.cert_dir(), &names, unix_now())
}

/// `check-config`'s lines on the wall's certificates in `dir` (the CA, each of `names`' and the
/// controller's, those present: a folder keygen has not written yet says nothing) at `now`: a
/// warning per certificate that ends soon; an error (every problem, one a line) when one has
/// expired, is not valid yet or cannot be read.
pub fn certificate_report(dir: &Path, names: &[String], now: i64) -> Result<Vec<String>, String> {
    let (mut warnings, mut problems) = (Vec::new(), Vec::new());
    let files = std::iter::once(("ca".to_string(), true))
        .chain(names.iter().map(|n| (n.clone(), false)))
        .chain(std::iter::once((CONTROLLER.to_string(), false)));
    for (name, ca) in files {
        let path = dir.join(format!("{name}.pem"));
        if !path.exists() {
            continue;
        }
        match read_cert(&path).and_then(|der| validity_at(&path, ca, &der, now)) {
            Ok(Some(w)) => warnings.push(w),
            Ok(None) => {}
            Err(e) => problems.push(e.to_string()),
        }
    }
    if problems.is_empty() {
        Ok(warnings)
    } else {
        Err(problems.join("\n"))
    }
}

pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TlsError + '_ {
    move |error| TlsError::Io { path: path.to_owned(), error }
}

/// A certificate name: a node's name or `controller`, by the config's rule
/// ([`isowall_model::names`]).
pub(crate) fn check_name(name: &str) -> Result<(), TlsError> {
    match isowall_model::names::name_problem(name) {
        None => Ok(()),
        Some(problem) => Err(TlsError::BadName(problem)),
    }
}

/// Node names a wall may hold together: each a certificate name, none the same as another (or
/// as `ca` or `controller`, whose files they would take) without regard to case.
pub(crate) fn check_node_names(names: &[String]) -> Result<(), TlsError> {
    for (i, name) in names.iter().enumerate() {
        check_name(name)?;
        if let Some(r) = ["ca", CONTROLLER].into_iter().find(|r| r.eq_ignore_ascii_case(name)) {
            return Err(TlsError::SameName(name.clone(), r.to_string()));
        }
        if let Some(first) = names[..i].iter().find(|n| n.eq_ignore_ascii_case(name)) {
            return Err(TlsError::SameName(name.clone(), first.clone()));
        }
    }
    Ok(())
}

/// The subject names of `name`'s certificate: the controller's URI alone, or a node's DNS name.
pub(crate) fn certificate_params(name: &str) -> Result<rcgen::CertificateParams, rcgen::Error> {
    let mut params = rcgen::CertificateParams::default();
    params.subject_alt_names = if name == CONTROLLER {
        vec![rcgen::SanType::URI(CONTROLLER_URI.try_into()?)]
    } else {
        vec![rcgen::SanType::DnsName(name.try_into()?)]
    };
    params.distinguished_name.push(rcgen::DnType::CommonName, name);
    Ok(params)
}

/// Refuses a private key file that its group or others may read or write.
pub(crate) fn key_mode_problem(path: &Path) -> Result<(), TlsError> {
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(path).map_err(io(path))?.permissions().mode() & 0o7777;
    if mode & 0o077 != 0 {
        return Err(TlsError::KeyOpen { path: path.to_owned(), mode });
    }
    Ok(())
}

/// One party's credentials: the wall CA, its certificate chain and private key.
pub struct Identity {
    pub name: String,
    ca: CertificateDer<'static>,
    chain: Vec<CertificateDer<'static>>,
    key: PrivateKeyDer<'static>,
}

fn read_cert(path: &Path) -> Result<CertificateDer<'static>, TlsError> {
    let bytes = std::fs::read(path).map_err(io(path))?;
    CertificateDer::from_pem_slice(&bytes).map_err(|e| TlsError::Pem {
        path: path.to_owned(),
        what: "certificate",
        reason: e.to_string(),
    })
}

fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

impl Identity {
    /// Loads `ca.pem`, `NAME.pem` and `NAME.key` from the certificate folder; the key only when
    /// no one but its owner may read it.
    pub fn load(dir: &Path, name: &str) -> Result<Identity, TlsError> {
        check_name(name)?;
        let (ca_path, cert_path) = (dir.join("ca.pem"), dir.join(format!("{name}.pem")));
        let ca = read_cert(&ca_path)?;
        let cert = read_cert(&cert_path)?;
        let now = unix_now();
        for (path, is_ca, der) in [(&ca_path, true, &ca), (&cert_path, false, &cert)] {
            if let Some(warning) = validity_at(path, is_ca, der, now)? {
                tracing::warn!("{warning}");
            }
        }
        let key_path = dir.join(format!("{name}.key"));
        key_mode_problem(&key_path)?;
        let bytes = std::fs::read(&key_path).map_err(io(&key_path))?;
        let key = PrivateKeyDer::from_pem_slice(&bytes).map_err(|e| TlsError::Pem {
            path: key_path.clone(),
            what: "private key",
            reason: e.to_string(),
        })?;
        Ok(Identity { name: name.to_string(), ca, chain: vec![cert], key })
    }

    fn roots(&self) -> Result<Arc<rustls::RootCertStore>, TlsError> {
        let mut roots = rustls::RootCertStore::empty();
        roots.add(self.ca.clone()).map_err(|e| TlsError::Config(format!("wall CA: {e}")))?;
        Ok(Arc::new(roots))
    }

    /// The TLS 1.3 server side of this identity: it requires a client certificate signed by the
    /// wall CA and speaks only the wall's ALPN ([`crate::transport`] makes it a QUIC endpoint).
    pub fn server_tls(&self) -> Result<rustls::ServerConfig, TlsError> {
        let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(self.roots()?, provider())
            .build()
            .map_err(|e| TlsError::Config(e.to_string()))?;
        let mut tls = rustls::ServerConfig::builder_with_provider(provider())
            .with_protocol_versions(&[&rustls::version::TLS13])
            .map_err(|e| TlsError::Config(e.to_string()))?
            .with_client_cert_verifier(verifier)
            .with_single_cert(self.chain.clone(), self.key.clone_key())
            .map_err(|e| TlsError::Config(e.to_string()))?;
        tls.alpn_protocols = vec![crate::ALPN.to_vec()];
        Ok(tls)
    }

    /// The TLS 1.3 client side of this identity: it presents this certificate and trusts only
    /// the wall CA.
    pub fn client_tls(&self) -> Result<rustls::ClientConfig, TlsError> {
        let mut tls = rustls::ClientConfig::builder_with_provider(provider())
            .with_protocol_versions(&[&rustls::version::TLS13])
            .map_err(|e| TlsError::Config(e.to_string()))?
            .with_root_certificates(self.roots()?)
            .with_client_auth_cert(self.chain.clone(), self.key.clone_key())
            .map_err(|e| TlsError::Config(e.to_string()))?;
        tls.alpn_protocols = vec![crate::ALPN.to_vec()];
        Ok(tls)
    }
}

/// Who a peer is, by the certificate it presented (the handshake verified it against the wall CA).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum PeerIdentity {
    /// The controller's certificate: the URI SAN [`CONTROLLER_URI`] and no DNS name.
    Controller,
    /// A node's certificate: exactly one DNS SAN, its name as written (case kept), and no URI.
    Node(String),
}

impl std::fmt::Display for PeerIdentity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PeerIdentity::Controller => f.write_str(CONTROLLER),
            PeerIdentity::Node(n) => write!(f, "node `{n}`"),
        }
    }
}

/// The identity a DER certificate carries, or why it carries none of the wall's.
pub fn certificate_identity(der: &CertificateDer<'_>) -> Result<PeerIdentity, String> {
    let cert = webpki::EndEntityCert::try_from(der).map_err(|e| format!("not a certificate: {e:?}"))?;
    let uris: Vec<&str> = cert.valid_uri_names().collect();
    let dns: Vec<&str> = cert.valid_dns_names().collect();
    match (uris.as_slice(), dns.as_slice()) {
        ([uri], []) if *uri == CONTROLLER_URI => Ok(PeerIdentity::Controller),
        ([], [name]) => Ok(PeerIdentity::Node((*name).to_string())),
        _ => Err(format!(
            "its certificate names neither the controller nor one node (URIs {uris:?}, DNS names {dns:?})"
        )),
    }
}

/// The identity of `connection`'s peer (its leaf certificate), or why it has none of the wall's.
pub fn peer_identity(connection: &quinn::Connection) -> Result<PeerIdentity, String> {
    let identity = connection.peer_identity().ok_or("it presented no certificate")?;
    let chain = identity
        .downcast::<Vec<CertificateDer<'static>>>()
        .map_err(|_| "its certificate chain is not X.509".to_string())?;
    certificate_identity(chain.first().ok_or("its certificate chain is empty")?)
}

/// Whether the peer of `connection` is `name`, compared exactly: [`CONTROLLER`] for the
/// controller's certificate ([`PeerIdentity::Controller`]), else the node `name`'s. A daemon uses
/// it to accept only the controller's certificate as a controller, and each node's as itself.
pub fn peer_is(connection: &quinn::Connection, name: &str) -> bool {
    match peer_identity(connection) {
        Ok(PeerIdentity::Controller) => name == CONTROLLER,
        Ok(PeerIdentity::Node(n)) => n == name && name != CONTROLLER,
        Err(_) => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leaf(dir: &Path, name: &str) -> CertificateDer<'static> {
        read_cert(&dir.join(format!("{name}.pem"))).unwrap()
    }

    #[test]
    fn the_controller_and_each_node_have_distinct_exact_identities() {
        let dir = tempfile::tempdir().unwrap();
        crate::keygen::keygen(
            dir.path(),
            "w",
            &["node0".into(), "Node-1".into()],
            crate::keygen::CaMode::New,
            30,
        )
        .unwrap();
        assert_eq!(certificate_identity(&leaf(dir.path(), CONTROLLER)), Ok(PeerIdentity::Controller));
        assert_eq!(certificate_identity(&leaf(dir.path(), "node0")), Ok(PeerIdentity::Node("node0".into())));
        // Case is kept: `Node-1` is not `node-1`.
        assert_eq!(
            certificate_identity(&leaf(dir.path(), "Node-1")),
            Ok(PeerIdentity::Node("Node-1".into()))
        );
        // The CA's own certificate is neither.
        assert!(certificate_identity(&leaf(dir.path(), "ca")).is_err());
    }

    #[test]
    fn keygen_refuses_names_that_differ_only_in_case_before_writing_anything() {
        for names in [vec!["Controller"], vec!["node0", "NODE0"], vec!["CA"], vec!["controller"]] {
            let dir = tempfile::tempdir().unwrap();
            let names: Vec<String> = names.into_iter().map(String::from).collect();
            let e =
                crate::keygen::keygen(dir.path(), "w", &names, crate::keygen::CaMode::New, 30).unwrap_err();
            assert!(matches!(e, TlsError::SameName(..)), "{names:?}: {e}");
            assert!(e.to_string().contains("without regard to case"), "{e}");
            assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "{names:?}: files written");
        }
    }
}
