//! `muster certs`: the certificates of a federation's hosts, for Zenoh's mutual TLS.
//!
//! One certificate authority per federation (`ca.pem`, and its key `ca.key`, made the
//! first time and reused after, so a robot added later joins the same federation),
//! and per host a key and a certificate whose common name is the host's name, valid
//! for TLS servers and clients (each broker is both), for the host's name, localhost,
//! 127.0.0.1 and any `--san`; and the access file `acl.toml`, every host named in it
//! (offering and requesting unless the file, edited, says less).

use crate::cli::CertsArgs;
use anyhow::{bail, Context};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose, SanType,
};
use std::io::Write;
use std::path::Path;
use std::process::ExitCode;

const CA_NAME: &str = "muster federation CA";

fn ca_params() -> anyhow::Result<CertificateParams> {
    let mut p = CertificateParams::new(Vec::<String>::new())?;
    p.distinguished_name.push(DnType::CommonName, CA_NAME);
    p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    p.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let now = time::OffsetDateTime::now_utc();
    p.not_before = now - time::Duration::days(1);
    p.not_after = now + time::Duration::days(3650);
    Ok(p)
}

/// Writes `text` to a new file (never over an existing one), mode 600 if `secret`.
fn write_new(path: &Path, text: &str, secret: bool) -> anyhow::Result<()> {
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(if secret { 0o600 } else { 0o644 })
        .open(path)
        .with_context(|| format!("writing {} (not overwriting a file)", path.display()))?;
    f.write_all(text.as_bytes())?;
    Ok(())
}

pub fn run(a: CertsArgs) -> anyhow::Result<ExitCode> {
    for h in &a.hosts {
        if !muster_broker::federation::valid_host_name(h) || h == "ca" {
            bail!("host name {h:?}: use 1 to 31 characters of [A-Za-z0-9_-] (not \"ca\")");
        }
    }
    if a.days < 1 {
        bail!("--days must be at least 1");
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    let ca_key_path = a.out.join("ca.key");
    let ca_pem_path = a.out.join("ca.pem");
    let params = ca_params()?;
    let ca_key = if ca_key_path.exists() {
        let pem = std::fs::read_to_string(&ca_key_path)
            .with_context(|| format!("reading {}", ca_key_path.display()))?;
        if !ca_pem_path.exists() {
            bail!(
                "{} exists but {} does not",
                ca_key_path.display(),
                ca_pem_path.display()
            );
        }
        eprintln!("using the authority in {}", a.out.display());
        KeyPair::from_pem(&pem).context("ca.key is not a key in PEM")?
    } else {
        let key = KeyPair::generate()?;
        let cert = params.self_signed(&key)?;
        write_new(&ca_key_path, &key.serialize_pem(), true)?;
        write_new(&ca_pem_path, &cert.pem(), false)?;
        eprintln!(
            "wrote {} and {} (keep ca.key off the hosts)",
            ca_pem_path.display(),
            ca_key_path.display()
        );
        key
    };
    let issuer = Issuer::new(params, ca_key);
    let now = time::OffsetDateTime::now_utc();
    for host in &a.hosts {
        let mut names = vec![host.clone(), "localhost".to_string()];
        names.extend(
            a.san
                .iter()
                .filter(|s| s.parse::<std::net::IpAddr>().is_err())
                .cloned(),
        );
        let mut p = CertificateParams::new(names)?;
        p.subject_alt_names
            .push(SanType::IpAddress(std::net::Ipv4Addr::LOCALHOST.into()));
        for ip in a
            .san
            .iter()
            .filter_map(|s| s.parse::<std::net::IpAddr>().ok())
        {
            p.subject_alt_names.push(SanType::IpAddress(ip));
        }
        p.distinguished_name.push(DnType::CommonName, host.as_str());
        p.key_usages = vec![
            KeyUsagePurpose::DigitalSignature,
            KeyUsagePurpose::KeyEncipherment,
        ];
        p.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        p.not_before = now - time::Duration::days(1);
        p.not_after = now + time::Duration::days(a.days);
        let key = KeyPair::generate()?;
        let cert = p.signed_by(&key, &issuer)?;
        write_new(
            &a.out.join(format!("{host}.key")),
            &key.serialize_pem(),
            true,
        )?;
        write_new(&a.out.join(format!("{host}.pem")), &cert.pem(), false)?;
        println!("{}", a.out.join(host).display());
    }
    let acl = write_acl(&a.out, &a.hosts)?;
    eprintln!(
        "wrote {} (every host offers and requests; edit it to narrow)",
        acl.display()
    );
    eprintln!(
        "copy ca.pem, acl.toml, HOST.pem and HOST.key to each host; start its broker with \
         --tls DIR"
    );
    Ok(ExitCode::SUCCESS)
}

/// Adds `hosts` (offering and requesting) to `DIR/acl.toml`, made if missing; hosts
/// already there keep their roles.
fn write_acl(dir: &Path, hosts: &[String]) -> anyhow::Result<std::path::PathBuf> {
    use muster_broker::federation::{Acl, Role, ACL_FILE};
    let path = dir.join(ACL_FILE);
    let mut acl = if path.exists() {
        Acl::load(&path)?
    } else {
        Acl::default()
    };
    for h in hosts {
        acl.hosts
            .entry(h.clone())
            .or_insert_with(|| [Role::Offer, Role::Request].into());
    }
    let text = format!(
        "# Who may do what in this federation (the same file on every host): a host is\n\
         # its certificate's common name; \"offer\" publishes services, \"request\" asks\n\
         # for other hosts'. A host not named may connect but does nothing.\n{}",
        toml::to_string(&acl)?
    );
    let tmp = dir.join(format!(".{ACL_FILE}.tmp"));
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}
