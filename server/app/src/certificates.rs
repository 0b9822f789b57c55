//! A site's certificates for zenoh over TLS (`vsgraphs-server certificates`): a certificate
//! authority, the server's certificate (for the names robots reach it by) and one certificate
//! per robot whose common name is the robot's id, which the server's access rules check
//! against the id it publishes under. Files are PEM: `ca.pem` and `ca-key.pem`, `server.pem`
//! and `server-key.pem`, `robot-ID.pem` and `robot-ID-key.pem`. An authority already in the
//! folder is kept, so robots can be added later; keys are written readable by their owner only.

use anyhow::{ensure, Context};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};
use std::path::{Path, PathBuf};

/// Files written.
#[derive(Debug, Default)]
pub struct Written {
    pub files: Vec<PathBuf>,
}

/// Makes (or reuses) the authority in `dir` and signs a server certificate for `hosts` (DNS
/// names or IP addresses) and one certificate per robot id.
pub fn make(dir: &Path, hosts: &[String], robots: &[String]) -> anyhow::Result<Written> {
    for id in robots {
        vsgraphs_proto::keys::validate_robot_id(id).map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut written = Written::default();
    let ca_pem = dir.join("ca.pem");
    let ca_key_pem = dir.join("ca-key.pem");
    let issuer = if ca_pem.exists() && ca_key_pem.exists() {
        let key = KeyPair::from_pem(&read(&ca_key_pem)?)
            .with_context(|| format!("reading {}", ca_key_pem.display()))?;
        Issuer::from_ca_cert_pem(&read(&ca_pem)?, key)
            .with_context(|| format!("reading {}", ca_pem.display()))?
    } else {
        let key = KeyPair::generate()?;
        let mut params = CertificateParams::new(Vec::<String>::new())?;
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params
            .distinguished_name
            .push(DnType::CommonName, "vsgraphs site authority");
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        let certificate = params.self_signed(&key)?;
        save(&ca_pem, &certificate.pem(), false, &mut written)?;
        save(&ca_key_pem, &key.serialize_pem(), true, &mut written)?;
        Issuer::new(params, key)
    };
    let mut leaf = |name: &str, sans: Vec<String>, file: &str| -> anyhow::Result<()> {
        let key = KeyPair::generate()?;
        let mut params = CertificateParams::new(sans)?;
        params.distinguished_name.push(DnType::CommonName, name);
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        let certificate = params.signed_by(&key, &issuer)?;
        save(
            &dir.join(format!("{file}.pem")),
            &certificate.pem(),
            false,
            &mut written,
        )?;
        save(
            &dir.join(format!("{file}-key.pem")),
            &key.serialize_pem(),
            true,
            &mut written,
        )
    };
    if !hosts.is_empty() {
        leaf("vsgraphs server", hosts.to_vec(), "server")?;
    }
    for id in robots {
        // A robot also listens as a zenoh peer: its certificate names the robot alone.
        leaf(id, vec![id.clone()], &format!("robot-{id}"))?;
    }
    ensure!(
        !written.files.is_empty(),
        "nothing to make: the authority exists and no --host or --robot was given"
    );
    Ok(written)
}

fn read(path: &Path) -> anyhow::Result<String> {
    std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))
}

fn save(path: &Path, pem: &str, secret: bool, written: &mut Written) -> anyhow::Result<()> {
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    if secret {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o600);
    }
    #[cfg(not(unix))]
    let _ = secret;
    let mut file = options
        .open(path)
        .with_context(|| format!("writing {}", path.display()))?;
    std::io::Write::write_all(&mut file, pem.as_bytes())
        .with_context(|| format!("writing {}", path.display()))?;
    written.files.push(path.to_owned());
    Ok(())
}
