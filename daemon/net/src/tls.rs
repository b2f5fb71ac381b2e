//! The wall's certificates: `isowall keygen` makes a CA and one certificate per node and for the
//! controller ([`crate::keygen`]); every connection presents one and accepts only peers whose certificate
//! the wall CA signed ([`Identity::server_config`], [`Identity::client_config`]).
//!
//! Files in the certificate folder: `ca.pem` (the CA certificate, on every machine), `ca.key` (the
//! CA's private key: keep it off the wall, it signs new certificates), `NAME.pem` + `NAME.key` for
//! every node NAME and for `controller`. A node's certificate names the node (DNS SAN), and a
//! client connecting to a node checks that name. TLS 1.3 only (QUIC), ring provider only.
//!
//! A private key is loaded only when no one but its owner may read or write it (mode 0600 or
//! 0400): [`Identity::load`] refuses a key open to its group or to others, naming the file.

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The controller's certificate name.
pub const CONTROLLER: &str = "controller";

#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a usable PEM {what}: {reason}")]
    Pem { path: PathBuf, what: &'static str, reason: String },
    #[error("certificate generation failed for '{name}': {reason}")]
    Generate { name: String, reason: String },
    #[error("TLS configuration: {0}")]
    Config(String),
    #[error("certificate name {0}")]
    BadName(String),
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
}

pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TlsError + '_ {
    move |source| TlsError::Io { path: path.to_owned(), source }
}

/// A certificate name: a node's name or `controller`, by the config's rule
/// ([`isowall_wall::names`]).
pub(crate) fn check_name(name: &str) -> Result<(), TlsError> {
    match isowall_wall::names::name_problem(name) {
        None => Ok(()),
        Some(problem) => Err(TlsError::BadName(problem)),
    }
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
        let ca = read_cert(&dir.join("ca.pem"))?;
        let cert = read_cert(&dir.join(format!("{name}.pem")))?;
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

    /// A QUIC server configuration that requires a client certificate signed by the wall CA.
    pub fn server_config(&self) -> Result<quinn::ServerConfig, TlsError> {
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
        let quic = quinn::crypto::rustls::QuicServerConfig::try_from(tls)
            .map_err(|e| TlsError::Config(e.to_string()))?;
        let mut config = quinn::ServerConfig::with_crypto(Arc::new(quic));
        config.transport_config(Arc::new(crate::transport::transport_config()));
        Ok(config)
    }

    /// A QUIC client configuration that presents this identity and trusts only the wall CA.
    pub fn client_config(&self) -> Result<quinn::ClientConfig, TlsError> {
        let mut tls = rustls::ClientConfig::builder_with_provider(provider())
            .with_protocol_versions(&[&rustls::version::TLS13])
            .map_err(|e| TlsError::Config(e.to_string()))?
            .with_root_certificates(self.roots()?)
            .with_client_auth_cert(self.chain.clone(), self.key.clone_key())
            .map_err(|e| TlsError::Config(e.to_string()))?;
        tls.alpn_protocols = vec![crate::ALPN.to_vec()];
        let quic = quinn::crypto::rustls::QuicClientConfig::try_from(tls)
            .map_err(|e| TlsError::Config(e.to_string()))?;
        let mut config = quinn::ClientConfig::new(Arc::new(quic));
        config.transport_config(Arc::new(crate::transport::transport_config()));
        Ok(config)
    }
}

/// Whether the peer of `connection` presented a certificate (already verified against the wall CA
/// by the handshake) that names `name`: a daemon uses it to accept only the controller's
/// certificate as a controller, not another node's.
pub fn peer_is(connection: &quinn::Connection, name: &str) -> bool {
    let Some(identity) = connection.peer_identity() else { return false };
    let Ok(chain) = identity.downcast::<Vec<CertificateDer<'static>>>() else { return false };
    let Some(leaf) = chain.first() else { return false };
    let Ok(cert) = webpki::EndEntityCert::try_from(leaf) else { return false };
    let Ok(server_name) = rustls::pki_types::ServerName::try_from(name) else { return false };
    cert.verify_is_valid_for_subject_name(&server_name).is_ok()
}
