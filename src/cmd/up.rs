//! `muster up --synthetic`: the demo on synthetic systems (the default, the paper's
//! robots on the simulator, is in `up_paper.rs`).
//!
//! Starts a broker and synthetic systems as child processes (three tracker-like data
//! services on `t1`, one delivery-like command service with a task queue on `d1`),
//! then acts as a user: lists, requests a data service, links tracker to delivery.
//! Runs until Ctrl-C (or `--duration`), then stops its children cleanly.

use super::children::Children;
use super::standbys::Standbys;
use crate::cli::UpArgs;
use anyhow::Context as _;
use muster_shared::types::ServiceId;
use muster_shared::udp::access::{access_line, new_web_token, web_line};
use muster_shared::udp::crypto::KeyPair;
use muster_shared::Instance;
use muster_users::{ConnectOptions, RemoteOptions, UserClient, UserError, UserEvent};
use std::net::SocketAddr;
use std::process::{ExitCode, Stdio};
use std::time::{Duration, Instant};

/// A guest key and an access file letting it list and request everything, for the
/// remote users (UDP) and the web console of this run.
pub(super) struct Guest {
    pub(super) dir: std::path::PathBuf,
    /// The broker's key file: the standby taking over must present the same key.
    pub(super) broker_key: std::path::PathBuf,
    key: KeyPair,
    /// Where the broker serves remote users (`None`: `--no-udp`).
    pub(super) addr: Option<SocketAddr>,
}

impl Guest {
    pub(super) fn new(inst: &Instance, udp: Option<SocketAddr>) -> anyhow::Result<Self> {
        // Resolve port 0, and fall back to a free port if the asked one is taken (another
        // `muster up` on this machine): the demo must start on a fresh machine.
        let addr = match udp.map(|a| (a, std::net::UdpSocket::bind(a))) {
            None => None,
            Some((_, Ok(s))) => Some(s.local_addr()?),
            Some((addr, Err(e))) => {
                let free = std::net::UdpSocket::bind((addr.ip(), 0))?.local_addr()?;
                eprintln!("muster up: udp {addr} unavailable ({e}); remote users use {free}");
                Some(free)
            }
        };
        let dir = std::env::temp_dir().join(format!("muster-up-{inst}-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let key = KeyPair::generate()?;
        key.write("guest", &dir.join("guest.key"))?;
        let broker_key = dir.join("broker.key");
        KeyPair::generate()?.write("broker", &broker_key)?;
        let token = new_web_token();
        muster_shared::udp::crypto::write_secret(&dir.join("guest.web"), &format!("{token}\n"))?;
        std::fs::write(
            dir.join("access"),
            access_line("guest", &key.public, &["*".to_string()], false)
                + "\n"
                + &web_line("guest", &token)
                + "\n",
        )?;
        Ok(Guest {
            dir,
            broker_key,
            key,
            addr,
        })
    }

    /// The broker's arguments for this guest: room for the web console's users, and the
    /// UDP address, access file and key (without UDP, only the first).
    pub(super) fn broker_args(&self) -> Vec<String> {
        // The web console is one user per person signed in, all in one process.
        let mut args = vec!["--max-users-per-process".to_string(), "1024".to_string()];
        let Some(addr) = self.addr else {
            return args;
        };
        args.extend([
            "--udp".to_string(),
            addr.to_string(),
            "--access".to_string(),
            self.dir.join("access").display().to_string(),
            "--key".to_string(),
            self.broker_key.display().to_string(),
        ]);
        args
    }

    /// Starts `muster web` for the guest on `listen` (another free port if that one is
    /// taken) and says where it is and how to sign in.
    pub(super) fn start_web(
        &self,
        children: &mut Children,
        inst: &Instance,
        listen: SocketAddr,
    ) -> anyhow::Result<()> {
        use std::io::BufRead;
        let listen = match std::net::TcpListener::bind(listen) {
            Ok(l) => l.local_addr()?,
            Err(e) => {
                let free = std::net::TcpListener::bind((listen.ip(), 0))?.local_addr()?;
                eprintln!("muster up: web {listen} unavailable ({e}); the console uses {free}");
                free
            }
        };
        let access = self.dir.join("access").display().to_string();
        // Another program may take the port between the look above and the console's
        // own bind: then any free port.
        let mut at = None;
        for listen in [listen, SocketAddr::new(listen.ip(), 0)] {
            let listen_s = listen.to_string();
            let child = children.spawn(
                inst,
                "web console",
                &[
                    "web", "--listen", &listen_s, "--access", &access, "--wait", "60s",
                ],
                Stdio::piped(),
            )?;
            let stdout = child.stdout.take().context("the web console's output")?;
            let mut line = String::new();
            std::io::BufReader::new(stdout).read_line(&mut line)?;
            if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) {
                at = Some(v);
                break;
            }
            eprintln!("muster up: the web console did not start on {listen}");
        }
        let at = at.context("the web console did not start")?;
        out!(
            "== web console: {} (sign in as guest with the token in {}) ==",
            at["url"].as_str().unwrap_or_default(),
            self.dir.join("guest.web").display()
        );
        Ok(())
    }
}

impl Drop for Guest {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The demo's tracker-like system: three data services.
const TRACKER: [&str; 10] = [
    "system",
    "synthetic",
    "--name",
    "t1",
    "--services",
    "3",
    "--kind",
    "data",
    "--quota",
    "10",
];
/// The demo's delivery-like system: one command service with a task queue.
const DELIVERY: [&str; 11] = [
    "system",
    "synthetic",
    "--name",
    "d1",
    "--services",
    "1",
    "--kind",
    "command",
    "--quota",
    "1",
    "--queue",
];

pub fn run(inst: &Instance, a: UpArgs) -> anyhow::Result<ExitCode> {
    if a.hosts {
        return run_hosts(inst, a);
    }
    if !a.synthetic {
        return super::up_paper::run(inst, a);
    }
    let mut children = Children::default();
    let guest = Guest::new(inst, (!a.no_udp).then_some(a.udp))?;
    let broker_args = guest.broker_args();
    let mut sys_udp: Vec<&str> = Vec::new();
    if guest.addr.is_some() {
        sys_udp.extend(["--udp", "127.0.0.1:0"]);
    }
    let broker: Vec<&str> = std::iter::once("broker")
        .chain(broker_args.iter().map(String::as_str))
        .collect();
    children.spawn(inst, "broker", &broker, Stdio::inherit())?;
    let standbys = (!a.no_standby).then(|| Standbys::start(inst, broker_args.clone()));
    children.spawn(
        inst,
        "tracker system t1",
        &TRACKER.iter().chain(&sys_udp).copied().collect::<Vec<_>>(),
        Stdio::inherit(),
    )?;
    children.spawn(
        inst,
        "delivery system d1",
        &DELIVERY.iter().chain(&sys_udp).copied().collect::<Vec<_>>(),
        Stdio::inherit(),
    )?;
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(10),
        handle_signals: true,
        watch_list: false,
    };
    let mut client = UserClient::connect(inst, &opts)?;
    let end = a.duration.map(|d| Instant::now() + d);
    let shown = wait_for_services(&mut client, 4, Duration::from_secs(10))
        .and_then(|()| remote_list(&guest));
    if !a.no_web {
        guest.start_web(&mut children, inst, a.web)?;
    }
    let ids = (ServiceId::new("t1", "s0"), ServiceId::new("d1", "s0"));
    match shown.and_then(|()| demo(&mut client, end, ids)) {
        Ok(()) | Err(UserError::Interrupted) => {}
        Err(e) => return Err(e.into()),
    }
    client.close();
    if let Some(s) = standbys {
        s.stop();
    }
    children.stop();
    super::children::leave_no_fence(inst);
    out!("muster up: stopped");
    Ok(ExitCode::SUCCESS)
}

pub(super) fn wait_for_services(
    client: &mut UserClient,
    n: usize,
    wait: Duration,
) -> Result<(), UserError> {
    let deadline = Instant::now() + wait;
    while client.list()?.count() < n && Instant::now() < deadline {
        let _ = client.next_event(Instant::now() + Duration::from_millis(200))?;
    }
    Ok(())
}

/// The same list as a remote user sees it, over authenticated UDP.
pub(super) fn remote_list(g: &Guest) -> Result<(), UserError> {
    let Some(addr) = g.addr else {
        return Ok(());
    };
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(10),
        handle_signals: false,
        watch_list: false,
    };
    let remote = RemoteOptions {
        broker: addr,
        name: "guest".into(),
        key: g.key.clone(),
        broker_key: None,
        faults: None,
    };
    let mut c = UserClient::connect_remote(remote, &opts)?;
    let list = c.list()?;
    out!(
        "== remote users: UDP {} (this run's guest key: muster user --remote {} --key {}) ==",
        addr,
        addr,
        g.dir.join("guest.key").display()
    );
    out!(
        "the same list over UDP: {} services, generation {}",
        list.count(),
        list.generation
    );
    c.close();
    Ok(())
}

fn demo(
    client: &mut UserClient,
    end: Option<Instant>,
    (tracker, delivery): (ServiceId, ServiceId),
) -> Result<(), UserError> {
    let list = client.list()?;
    out!("== service list (generation {}) ==", list.generation);
    out!("{}", muster_users::menu::table(&list.views()));

    out!("\n== request {tracker} for 2 s ==");
    let req = client.request(&tracker)?;
    let mut session = None;
    let until = Instant::now() + Duration::from_secs(2);
    while let Some(e) = client.next_event(until)? {
        match e {
            UserEvent::Granted {
                req: r, session: s, ..
            } if r == req => {
                out!("granted: session {s}");
                session = Some(s);
            }
            UserEvent::Refused { req: r, reason, .. } if r == req => out!("refused: {reason}"),
            UserEvent::Update { seq, payload, .. } => out!("  #{seq} {payload}"),
            _ => {}
        }
    }
    if let Some(s) = session {
        client.end(s);
        out!("session ended by the user");
    }

    out!("\n== link {tracker} -> {delivery} ==");
    let link = client.link(&tracker, &delivery)?;
    let mut shown = 0u32;
    let mut kinds_shown = Vec::new();
    loop {
        let deadline = end.unwrap_or(Instant::now() + Duration::from_secs(3600));
        let Some(e) = client.next_event(deadline)? else {
            break;
        };
        match e {
            UserEvent::LinkUp { link: l } if l == link => {
                out!("link up: tracker positions become delivery goals (Ctrl-C to stop)")
            }
            UserEvent::LinkForwarded { input, .. } if shown.is_multiple_of(10) => {
                out!("  forwarded {input}");
                shown += 1;
            }
            UserEvent::LinkForwarded { .. } => shown += 1,
            // The first status of each kind (idle, the goal accepted, done) always
            // shows; the rest at the forwarding's pace (a robot that keeps up with a
            // moving goal would otherwise print every acceptance and arrival).
            UserEvent::Status { status, .. } => {
                let kind = std::mem::discriminant(&status);
                let first = !kinds_shown.contains(&kind);
                if first || shown % 10 == 1 {
                    out!("  delivery: {status}");
                }
                if first {
                    kinds_shown.push(kind);
                }
            }
            UserEvent::LinkEnded { link: l, reason } if l == link => {
                out!("link ended: {reason}");
                break;
            }
            UserEvent::BrokerLost => out!("(broker lost; the link goes on)"),
            _ => {}
        }
    }
    Ok(())
}

/// `muster up --hosts`: three hosts federated over Zenoh, on this machine (three
/// instances on loopback TCP): the operator's host `a` (a broker and this user), the
/// tracker's host `b` (`t1`, three data services) and the delivery robot's host `c`
/// (`d1`, a command service with a task queue). The user on `a` lists every host's
/// services, requests `t1@b/s0`, then links it into `d1@c/s0`: data from b drives the
/// robot on c, with the user on a third host.
fn run_hosts(inst: &Instance, a: UpArgs) -> anyhow::Result<ExitCode> {
    let hosts = super::children::LoopbackHosts::new(inst, &["a", "b", "c"], "up")?;
    let (insts, ports) = (&hosts.insts, &hosts.ports);
    // Declared before the children, so it goes after them.
    let net = match a.netns {
        true => {
            let names: Vec<String> = hosts.names.iter().map(|h| h.to_string()).collect();
            Some(super::netns::Topology::create(inst, &names, &a.link)?)
        }
        false => None,
    };
    let mut children = Children::default();
    match &net {
        None => hosts.spawn_brokers(&mut children, &[], Stdio::inherit)?,
        Some(t) => {
            for (i, host) in hosts.names.iter().enumerate() {
                let mut args = hosts.federated(i);
                args.extend(t.broker_flags(i));
                let args: Vec<&str> = args.iter().map(String::as_str).collect();
                children.spawn(
                    &insts[i],
                    &format!("broker-{host}"),
                    &args,
                    Stdio::inherit(),
                )?;
            }
        }
    }
    children.spawn(
        &insts[1],
        "tracker system t1 (host b)",
        &TRACKER,
        Stdio::inherit(),
    )?;
    children.spawn(
        &insts[2],
        "delivery system d1 (host c)",
        &DELIVERY,
        Stdio::inherit(),
    )?;
    match &net {
        None => out!(
            "== three hosts on this machine: a (instance {}), b ({}), c ({}); Zenoh on 127.0.0.1 ports {}, {}, {} ==",
            insts[0], insts[1], insts[2], ports[0], ports[1], ports[2]
        ),
        Some(t) => out!(
            "== three hosts on this machine, each in its network namespace: {}; every pair linked through a proxy adding {} each way and {} % loss ==",
            t.hosts
                .iter()
                .zip(insts)
                .map(|(h, i)| format!("{} at {} (namespace {}, instance {i})", h.host, h.ip, h.netns))
                .collect::<Vec<_>>()
                .join(", "),
            humantime::format_duration(a.link.delay),
            a.link.loss
        ),
    }
    let opts = ConnectOptions {
        wait_for_broker: Duration::from_secs(10),
        handle_signals: true,
        watch_list: false,
    };
    let mut client = UserClient::connect(&insts[0], &opts)?;
    let end = a.duration.map(|d| Instant::now() + d);
    let ids = (
        ServiceId::on_host("t1", "b", "s0"),
        ServiceId::on_host("d1", "c", "s0"),
    );
    match wait_for_services(&mut client, 4, Duration::from_secs(20))
        .and_then(|()| demo(&mut client, end, ids))
    {
        Ok(()) | Err(UserError::Interrupted) => {}
        Err(e) => return Err(e.into()),
    }
    client.close();
    children.stop();
    out!("muster up: stopped");
    Ok(ExitCode::SUCCESS)
}
