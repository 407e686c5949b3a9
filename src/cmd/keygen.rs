//! `muster keygen`: a key pair for a remote user or the broker.

use crate::cli::KeygenArgs;
use anyhow::Context;
use muster_shared::udp::access::{access_line, new_web_token, valid_user_name, web_line};
use muster_shared::udp::crypto::KeyPair;
use std::process::ExitCode;

pub fn run(a: KeygenArgs) -> anyhow::Result<ExitCode> {
    let name = match (&a.user, a.broker) {
        (Some(u), _) => {
            if !valid_user_name(u) {
                anyhow::bail!("--user {u:?}: use 1 to 24 characters of [A-Za-z0-9_-]");
            }
            u.clone()
        }
        (None, _) => "broker".to_string(),
    };
    std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    let path = a.out.join(format!("{name}.key"));
    let key = KeyPair::generate()?;
    key.write(&name, &path)
        .with_context(|| "not overwriting an existing key file".to_string())?;
    eprintln!("wrote {}", path.display());
    if a.broker {
        println!("{}", hex::encode(key.public));
        eprintln!(
            "start the broker with --key {}; users may pin it with --broker-key",
            path.display()
        );
    } else {
        println!("{}", access_line(&name, &key.public, &a.allow, a.operator));
        if a.web {
            let token = new_web_token();
            let path = a.out.join(format!("{name}.web"));
            muster_shared::udp::crypto::write_secret(&path, &format!("{token}\n"))
                .with_context(|| format!("writing {} (not overwriting one)", path.display()))?;
            eprintln!(
                "wrote {} (the web token: sign in to `muster web` as {name} with it)",
                path.display()
            );
            println!("{}", web_line(&name, &token));
        }
        eprintln!("add the line(s) above to the broker's access file, then `kill -HUP` the broker");
    }
    Ok(ExitCode::SUCCESS)
}
