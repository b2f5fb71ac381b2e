//! `isowall keygen`: the wall CA and a certificate + key for every node and for the controller
//! (the files are listed in [`crate::tls`]). It is safe to run beside a working wall:
//!
//! - every name is checked first, by the config's own rule ([`isowall_model::names`]), before any
//!   key is made or any file written;
//! - an existing CA is never replaced unless asked ([`CaMode::Replace`], `--force`): every
//!   certificate it signed would stop working. [`CaMode::Renew`] (`--renew`) keeps it and issues
//!   the node and controller certificates again from it (with new keys), e.g. before they expire;
//! - every file is written atomically: a temporary file in the same folder, created with its final
//!   mode (0600 for private keys, 0644 for certificates; never wider for a moment), synced, then
//!   renamed over the old one, so a reader sees the old file or the new one, never a part;
//! - certificates are valid from an hour before they are made (the clocks of a wall differ a
//!   little) for `days` days ([`DEFAULT_DAYS`]: two years); a new CA for [`CA_DAYS`]. A
//!   certificate may not outlive the CA that signs it.

use crate::tls::{
    certificate_params, check_node_names, io, key_mode_problem, unix_now, TlsError, CONTROLLER,
};
use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair, KeyUsagePurpose};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::CertificateDer;
use std::path::{Path, PathBuf};
use time::OffsetDateTime;

/// Days a node's or the controller's certificate is valid by default (two years).
pub const DEFAULT_DAYS: u32 = 730;
/// Days a new wall CA is valid (ten years), and so the longest a certificate may be asked for.
pub const CA_DAYS: u32 = 3650;
/// Certificates start this long before they are made, for clocks that lag the controller's.
const BACKDATE_SECONDS: i64 = 3600;

/// What keygen does with the CA in the folder.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CaMode {
    /// Make a new CA; refuse if the folder already holds one.
    New,
    /// Make a new CA even if the folder holds one (`--force`): its certificates stop working.
    Replace,
    /// Keep the folder's CA and issue the node and controller certificates again from it.
    Renew,
}

/// What keygen wrote.
#[derive(Debug)]
pub struct KeygenReport {
    /// The files written, in the order written.
    pub files: Vec<PathBuf>,
    /// The last day the node and controller certificates are valid (UTC, `YYYY-MM-DD`).
    pub valid_until: String,
    /// The last day the CA is valid.
    pub ca_valid_until: String,
}

/// Writes the wall's certificates into `dir` (created if needed) for the nodes `names` and the
/// controller: a new CA (see [`CaMode`]) and, signed by it, a certificate and key per name, valid
/// for `days` days from now. Nothing is written unless every name is good and the CA may be made
/// or used.
pub fn keygen(
    dir: &Path,
    wall: &str,
    names: &[String],
    mode: CaMode,
    days: u32,
) -> Result<KeygenReport, TlsError> {
    check_node_names(names)?;
    if !(1..=CA_DAYS).contains(&days) {
        return Err(TlsError::Validity(format!("--days {days} is outside 1..={CA_DAYS}")));
    }
    let gen_err = |name: &str| {
        let name = name.to_string();
        move |e: rcgen::Error| TlsError::Generate { name, reason: e.to_string() }
    };
    let now = unix_now();
    let not_before = date_time(now - BACKDATE_SECONDS)?;
    let not_after = date_time(now + i64::from(days) * 86_400)?;
    let ca_pem_path = dir.join("ca.pem");
    let ca_key_path = dir.join("ca.key");

    // Every file's contents are made before the first is written.
    let mut files: Vec<(PathBuf, String, u32)> = Vec::new();
    let (issuer, ca_not_after) = match mode {
        CaMode::Renew => {
            let (issuer, ca_not_after) = existing_ca(&ca_pem_path, &ca_key_path)?;
            if ca_not_after < not_after {
                return Err(TlsError::Validity(format!(
                    "{}: the CA is valid until {}, before certificates of {days} days would end ({}): \
                     ask for fewer --days, or make a new CA with --force (and copy every node's new files)",
                    ca_pem_path.display(),
                    ca_not_after.date(),
                    not_after.date()
                )));
            }
            (issuer, ca_not_after)
        }
        CaMode::New | CaMode::Replace => {
            if mode == CaMode::New {
                if let Some(p) = [&ca_pem_path, &ca_key_path].into_iter().find(|p| p.exists()) {
                    return Err(TlsError::CaExists(p.clone()));
                }
            }
            let ca_not_after = date_time(now + i64::from(CA_DAYS) * 86_400)?;
            let ca_key = KeyPair::generate().map_err(gen_err("ca"))?;
            let mut params = CertificateParams::new(Vec::<String>::new()).map_err(gen_err("ca"))?;
            params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
            params.distinguished_name.push(DnType::CommonName, format!("Isowall wall CA: {wall}"));
            params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::DigitalSignature];
            params.not_before = not_before;
            params.not_after = ca_not_after;
            let cert = params.self_signed(&ca_key).map_err(gen_err("ca"))?;
            files.push((ca_pem_path.clone(), cert.pem(), CERT_MODE));
            files.push((ca_key_path.clone(), ca_key.serialize_pem(), KEY_MODE));
            (Issuer::new(params, ca_key), ca_not_after)
        }
    };
    let mut all: Vec<&str> = names.iter().map(String::as_str).collect();
    all.push(CONTROLLER);
    for name in all {
        let key = KeyPair::generate().map_err(gen_err(name))?;
        let mut params = certificate_params(name).map_err(gen_err(name))?;
        params.not_before = not_before;
        params.not_after = not_after;
        let cert = params.signed_by(&key, &issuer).map_err(gen_err(name))?;
        files.push((dir.join(format!("{name}.pem")), cert.pem(), CERT_MODE));
        files.push((dir.join(format!("{name}.key")), key.serialize_pem(), KEY_MODE));
    }

    std::fs::create_dir_all(dir).map_err(io(dir))?;
    for (path, text, mode) in &files {
        write_atomically(path, text.as_bytes(), *mode)?;
    }
    // The renames themselves reach the disk.
    std::fs::File::open(dir).and_then(|d| d.sync_all()).map_err(io(dir))?;
    Ok(KeygenReport {
        files: files.into_iter().map(|(p, _, _)| p).collect(),
        valid_until: not_after.date().to_string(),
        ca_valid_until: ca_not_after.date().to_string(),
    })
}

/// Certificates: everyone may read them.
const CERT_MODE: u32 = 0o644;
/// Private keys: their owner only, from the moment the file exists.
const KEY_MODE: u32 = 0o600;

/// Writes `contents` to `path` through a temporary file beside it, created with `mode` and
/// renamed over `path` once synced.
fn write_atomically(path: &Path, contents: &[u8], mode: u32) -> Result<(), TlsError> {
    use std::io::Write;
    use std::os::unix::fs::PermissionsExt;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut tmp = tempfile::Builder::new()
        .prefix(".keygen-")
        .permissions(std::fs::Permissions::from_mode(mode))
        .tempfile_in(dir)
        .map_err(io(dir))?;
    tmp.write_all(contents).and_then(|()| tmp.as_file().sync_all()).map_err(io(path))?;
    tmp.persist(path).map_err(|e| TlsError::Io { path: path.to_owned(), error: e.error })?;
    Ok(())
}

/// The folder's CA, to sign with: its certificate and key (the key private to its owner and
/// matching the certificate), and the end of its validity.
fn existing_ca(
    pem_path: &Path,
    key_path: &Path,
) -> Result<(Issuer<'static, KeyPair>, OffsetDateTime), TlsError> {
    if !pem_path.exists() || !key_path.exists() {
        let missing = if pem_path.exists() { key_path } else { pem_path };
        return Err(TlsError::NoCa(missing.to_owned()));
    }
    let bytes = std::fs::read(pem_path).map_err(io(pem_path))?;
    let pem_err = |what, reason: String| TlsError::Pem { path: pem_path.to_owned(), what, reason };
    let der = CertificateDer::from_pem_slice(&bytes).map_err(|e| pem_err("certificate", e.to_string()))?;
    let (_, x509) =
        x509_parser::parse_x509_certificate(&der).map_err(|e| pem_err("certificate", e.to_string()))?;
    let ca_not_after = date_time(x509.validity().not_after.timestamp())?;
    key_mode_problem(key_path)?;
    let key_text = std::fs::read_to_string(key_path).map_err(io(key_path))?;
    let key = KeyPair::from_pem(&key_text).map_err(|e| TlsError::Pem {
        path: key_path.to_owned(),
        what: "private key",
        reason: e.to_string(),
    })?;
    if rcgen::PublicKeyData::subject_public_key_info(&key) != x509.public_key().raw {
        return Err(TlsError::KeyMismatch { cert: pem_path.to_owned(), key: key_path.to_owned() });
    }
    let issuer = Issuer::from_ca_cert_der(&der, key).map_err(|e| pem_err("CA certificate", e.to_string()))?;
    Ok((issuer, ca_not_after))
}

fn date_time(unix_seconds: i64) -> Result<OffsetDateTime, TlsError> {
    OffsetDateTime::from_unix_timestamp(unix_seconds)
        .map_err(|e| TlsError::Validity(format!("the time {unix_seconds} s after 1970: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::PermissionsExt;

    fn names(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    fn mode(p: &Path) -> u32 {
        std::fs::metadata(p).unwrap().permissions().mode() & 0o777
    }

    fn not_after(p: &Path) -> i64 {
        let der = CertificateDer::from_pem_slice(&std::fs::read(p).unwrap()).unwrap();
        x509_parser::parse_x509_certificate(&der).unwrap().1.validity().not_after.timestamp()
    }

    #[test]
    fn keys_are_private_certificates_expire_and_no_temporary_file_is_left() {
        let dir = tempfile::tempdir().unwrap();
        let r = keygen(dir.path(), "w", &names(&["node0"]), CaMode::New, 30).unwrap();
        assert_eq!(r.files.len(), 6);
        for f in &r.files {
            if f.extension().unwrap() == "key" {
                assert_eq!(mode(f), 0o600, "{}", f.display());
            } else {
                // 0644 less the umask: readable, writable by its owner alone.
                assert_eq!(mode(f) & 0o622, 0o600, "{}: {:o}", f.display(), mode(f));
            }
        }
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left.len(), 6, "{left:?}");
        let now = unix_now();
        let end = not_after(&dir.path().join("node0.pem"));
        assert!((end - (now + 30 * 86_400)).abs() < 120, "node0 ends {end}, now {now}");
        let ca_end = not_after(&dir.path().join("ca.pem"));
        assert!((ca_end - (now + i64::from(CA_DAYS) * 86_400)).abs() < 120);
    }

    #[test]
    fn an_existing_ca_is_kept_unless_forced_and_renewal_keeps_it() {
        let dir = tempfile::tempdir().unwrap();
        keygen(dir.path(), "w", &names(&["node0"]), CaMode::New, 30).unwrap();
        let read = |n: &str| std::fs::read(dir.path().join(n)).unwrap();
        let (ca, ca_key, node) = (read("ca.pem"), read("ca.key"), read("node0.pem"));
        let e = keygen(dir.path(), "w", &names(&["node0"]), CaMode::New, 30).unwrap_err();
        assert!(matches!(&e, TlsError::CaExists(p) if p.ends_with("ca.pem")), "{e}");
        assert!(e.to_string().contains("--renew") && e.to_string().contains("--force"), "{e}");
        assert_eq!((read("ca.pem"), read("node0.pem")), (ca.clone(), node.clone()), "nothing replaced");

        keygen(dir.path(), "w", &names(&["node0", "node1"]), CaMode::Renew, 60).unwrap();
        assert_eq!((read("ca.pem"), read("ca.key")), (ca.clone(), ca_key), "the CA is kept");
        assert_ne!(read("node0.pem"), node, "node0 is issued again");
        let end = not_after(&dir.path().join("node1.pem"));
        assert!((end - (unix_now() + 60 * 86_400)).abs() < 120);

        keygen(dir.path(), "w", &names(&["node0"]), CaMode::Replace, 30).unwrap();
        assert_ne!(read("ca.pem"), ca, "--force replaces the CA");
    }

    #[test]
    fn renewal_needs_a_matching_private_ca_that_outlives_the_certificates() {
        let dir = tempfile::tempdir().unwrap();
        let e = keygen(dir.path(), "w", &names(&["node0"]), CaMode::Renew, 30).unwrap_err();
        assert!(matches!(&e, TlsError::NoCa(p) if p.ends_with("ca.pem")), "{e}");
        // A CA that ends in 10 days signs no certificate for 30.
        let ca_key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.not_after = date_time(unix_now() + 10 * 86_400).unwrap();
        let cert = params.self_signed(&ca_key).unwrap();
        write_atomically(&dir.path().join("ca.pem"), cert.pem().as_bytes(), CERT_MODE).unwrap();
        write_atomically(&dir.path().join("ca.key"), ca_key.serialize_pem().as_bytes(), KEY_MODE).unwrap();
        let e = keygen(dir.path(), "w", &names(&["node0"]), CaMode::Renew, 30).unwrap_err();
        assert!(e.to_string().contains("the CA is valid until"), "{e}");
        keygen(dir.path(), "w", &names(&["node0"]), CaMode::Renew, 9).unwrap();
        keygen(dir.path(), "w", &names(&["node0"]), CaMode::Replace, 30).unwrap();
        let key = dir.path().join("ca.key");
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o644)).unwrap();
        let e = keygen(dir.path(), "w", &names(&["node0"]), CaMode::Renew, 30).unwrap_err();
        assert!(matches!(&e, TlsError::KeyOpen { .. }), "{e}");
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
        // Another CA's key beside this CA's certificate.
        let other = tempfile::tempdir().unwrap();
        keygen(other.path(), "o", &[], CaMode::New, 30).unwrap();
        std::fs::copy(other.path().join("ca.key"), &key).unwrap();
        let e = keygen(dir.path(), "w", &names(&["node0"]), CaMode::Renew, 30).unwrap_err();
        assert!(matches!(&e, TlsError::KeyMismatch { .. }), "{e}");
    }

    #[test]
    fn bad_names_and_days_write_nothing() {
        for (list, days) in [(vec!["node0", "node_1"], 30), (vec![&*"a".repeat(64)], 30), (vec!["n"], 0)] {
            let dir = tempfile::tempdir().unwrap();
            let keys = dir.path().join("keys");
            assert!(keygen(&keys, "w", &names(&list), CaMode::New, days).is_err(), "{list:?} {days}");
            assert!(!keys.exists(), "{list:?}: the folder was made");
        }
        let dir = tempfile::tempdir().unwrap();
        let e = keygen(dir.path(), "w", &[], CaMode::New, CA_DAYS + 1).unwrap_err();
        assert!(e.to_string().contains("outside 1..=3650"), "{e}");
    }

    #[test]
    fn expired_certificates_are_refused_and_ending_ones_warned_about() {
        use crate::tls::{certificate_report, validity_at, Identity};
        let dir = tempfile::tempdir().unwrap();
        // `keygen --days 1`: loading and check-config warn about node0's and the controller's.
        keygen(dir.path(), "w", &names(&["node0"]), CaMode::New, 1).unwrap();
        let (node_pem, ca_pem) = (dir.path().join("node0.pem"), dir.path().join("ca.pem"));
        let der = |p: &Path| CertificateDer::from_pem_slice(&std::fs::read(p).unwrap()).unwrap();
        let now = unix_now();
        let w = validity_at(&node_pem, false, &der(&node_pem), now).unwrap().expect("a warning");
        assert!(w.contains("node0.pem: the certificate expires on") && w.contains("in 1 day:"), "{w}");
        assert!(w.contains("--renew"), "{w}");
        assert_eq!(validity_at(&ca_pem, true, &der(&ca_pem), now).unwrap(), None, "the CA ends in 10 years");
        let warned = certificate_report(dir.path(), &names(&["node0"]), now).unwrap();
        assert_eq!(warned.len(), 2, "{warned:?}");
        assert!(Identity::load(dir.path(), "node0").is_ok(), "ending soon still loads");
        // Two days later: refused, naming the file and the date.
        let e = validity_at(&node_pem, false, &der(&node_pem), now + 2 * 86_400).unwrap_err();
        assert!(matches!(&e, TlsError::Expired { path, .. } if *path == node_pem), "{e}");
        assert!(e.to_string().contains("expired on") && e.to_string().contains("--renew"), "{e}");
        let e = certificate_report(dir.path(), &names(&["node0"]), now + 2 * 86_400).unwrap_err();
        assert_eq!(e.lines().count(), 2, "{e}");
        // The CA, 11 years on: refused, with the way to a new one.
        let e = validity_at(&ca_pem, true, &der(&ca_pem), now + 11 * 365 * 86_400).unwrap_err();
        assert!(e.to_string().contains("the wall CA expired on") && e.to_string().contains("--force"), "{e}");
        // A certificate the CA signed that ended yesterday is refused at load, and one valid only
        // from tomorrow too.
        let (issuer, _) = existing_ca(&ca_pem, &dir.path().join("ca.key")).unwrap();
        for (from, to, says) in [(-10, -1, "expired on"), (1, 10, "is not valid before")] {
            let key = KeyPair::generate().unwrap();
            let mut params = certificate_params("node0").unwrap();
            params.not_before = date_time(now + from * 86_400).unwrap();
            params.not_after = date_time(now + to * 86_400).unwrap();
            let cert = params.signed_by(&key, &issuer).unwrap();
            write_atomically(&node_pem, cert.pem().as_bytes(), CERT_MODE).unwrap();
            write_atomically(&dir.path().join("node0.key"), key.serialize_pem().as_bytes(), KEY_MODE)
                .unwrap();
            let e = Identity::load(dir.path(), "node0").err().expect("refused").to_string();
            assert!(e.contains("node0.pem") && e.contains(says), "{e}");
        }
    }
}
