//! The wall's certificates: `isowall keygen` makes a CA and one certificate per node and for the
//! controller ([`keygen`]); every connection presents one and accepts only peers whose certificate
//! the wall CA signed ([`Identity::server_config`], [`Identity::client_config`]).
//!
//! Files in the certificate folder: `ca.pem` (the CA certificate, on every machine), `ca.key` (the
//! CA's private key: keep it off the wall, it signs new certificates), `NAME.pem` + `NAME.key` for
//! every node NAME and for `controller`. A node's certificate names the node (DNS SAN), and a
//! client connecting to a node checks that name. TLS 1.3 only (QUIC), ring provider only.

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
    #[error("'{0}' cannot name a certificate: use letters, digits, '-' and '.' only")]
    BadName(String),
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TlsError + '_ {
    move |source| TlsError::Io { path: path.to_owned(), source }
}

fn check_name(name: &str) -> Result<(), TlsError> {
    let ok = !name.is_empty()
        && name.len() <= 63
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '.')
        && !name.starts_with(['-', '.']);
    if ok {
        Ok(())
    } else {
        Err(TlsError::BadName(name.to_string()))
    }
}

/// Writes a new wall CA and a certificate + key for each of `names` and for the controller into
/// `dir` (created if needed). Existing files are overwritten; returns the files written.
pub fn keygen(dir: &Path, wall: &str, names: &[String]) -> Result<Vec<PathBuf>, TlsError> {
    use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair, KeyUsagePurpose};
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let gen_err = |name: &str| {
        let name = name.to_string();
        move |e: rcgen::Error| TlsError::Generate { name, reason: e.to_string() }
    };
    let ca_key = KeyPair::generate().map_err(gen_err("ca"))?;
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).map_err(gen_err("ca"))?;
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params.distinguished_name.push(DnType::CommonName, format!("Isowall wall CA: {wall}"));
    ca_params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::DigitalSignature];
    let ca_cert = ca_params.self_signed(&ca_key).map_err(gen_err("ca"))?;
    let mut written = Vec::new();
    let mut write = |name: &str, text: String| -> Result<(), TlsError> {
        let path = dir.join(name);
        std::fs::write(&path, text).map_err(io(&path))?;
        if name.ends_with(".key") {
            // Private keys: readable by their owner only.
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).map_err(io(&path))?;
        }
        written.push(path);
        Ok(())
    };
    write("ca.pem", ca_cert.pem())?;
    write("ca.key", ca_key.serialize_pem())?;
    let issuer = Issuer::new(ca_params, ca_key);
    let mut all: Vec<&str> = names.iter().map(String::as_str).collect();
    all.push(CONTROLLER);
    for name in all {
        check_name(name)?;
        let key = KeyPair::generate().map_err(gen_err(name))?;
        let mut params = CertificateParams::new(vec![name.to_string()]).map_err(gen_err(name))?;
        params.distinguished_name.push(DnType::CommonName, name);
        let cert = params.signed_by(&key, &issuer).map_err(gen_err(name))?;
        write(&format!("{name}.pem"), cert.pem())?;
        write(&format!("{name}.key"), key.serialize_pem())?;
    }
    Ok(written)
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
    /// Loads `ca.pem`, `NAME.pem` and `NAME.key` from the certificate folder.
    pub fn load(dir: &Path, name: &str) -> Result<Identity, TlsError> {
        check_name(name)?;
        let ca = read_cert(&dir.join("ca.pem"))?;
        let cert = read_cert(&dir.join(format!("{name}.pem")))?;
        let key_path = dir.join(format!("{name}.key"));
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
