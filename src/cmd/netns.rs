//! Hosts in network namespaces on one machine, and the proxy that links them.
//!
//! `muster netns` (and `muster up --hosts --netns`) give each host a network namespace
//! of its own (`ip netns`, root only), wired by a veth pair to a hub namespace that
//! routes nothing: host k is `10.77.k.2`, its side of the hub `10.77.k.1`. The only
//! way between two hosts is the TCP proxy for that pair, running in the hub: the
//! lower-numbered host connects to it, and it connects on to the other host's Zenoh
//! port. The kernel here has no netem, so the proxy is where the link's delay and loss
//! are made; stopping it (SIGSTOP) cuts the link between the two hosts alone, a
//! partition, while each still reaches the third.

use super::children::Children;
use crate::cli::{LinkArgs, NetProxyArgs, NetnsArgs};
use anyhow::{bail, Context};
use muster_shared::reactor::SignalPipe;
use muster_shared::Instance;
use rand::{RngExt, SeedableRng};
use std::io::{Read, Write};
use std::net::{Ipv4Addr, Shutdown, SocketAddr, TcpListener, TcpStream};
use std::os::fd::AsRawFd;
use std::process::{Command, ExitCode, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// The port each host's broker listens on for Zenoh (inside its namespace).
pub const ZENOH_PORT: u16 = 7447;
/// The extra wait of a read the proxy counts as lost: Linux's least TCP
/// retransmission timeout.
const LOSS_STALL: Duration = Duration::from_millis(200);
/// Most hosts (one /24 each under 10.77.0.0/16).
const MAX_HOSTS: usize = 200;

/// Moves this process into network namespace `name` (`/run/netns/NAME`, as `ip netns`
/// makes them). Call before any thread starts: threads started later inherit it.
pub fn enter(name: &str) -> anyhow::Result<()> {
    let path = format!("/run/netns/{name}");
    let f = std::fs::File::open(&path).with_context(|| format!("opening {path}"))?;
    // SAFETY: setns on a file descriptor we hold open; it changes only this thread's
    // (still the only thread's) network namespace.
    let r = unsafe { libc::setns(f.as_raw_fd(), libc::CLONE_NEWNET) };
    if r != 0 {
        bail!(
            "entering network namespace {name}: {}",
            std::io::Error::last_os_error()
        );
    }
    Ok(())
}

/// One host of a [`Topology`].
#[derive(Clone, Debug, serde::Serialize)]
pub struct NetHost {
    /// Its name (`muster broker --host`).
    pub host: String,
    /// Its network namespace.
    pub netns: String,
    /// Its address.
    pub ip: Ipv4Addr,
    /// What its broker listens on.
    pub listen: String,
    /// What its broker connects to (the proxies to the hosts after it).
    pub connect: Vec<String>,
}

/// The proxy between two hosts.
#[derive(Clone, Debug, serde::Serialize)]
pub struct NetProxy {
    /// The two hosts.
    pub hosts: [String; 2],
    /// Its process id (SIGSTOP cuts the link, SIGCONT mends it).
    pub pid: u32,
    /// Where it listens (in the hub).
    pub listen: SocketAddr,
    /// Where it connects to.
    pub to: SocketAddr,
}

/// Namespaces, veth pairs and proxies; all removed on drop.
pub struct Topology {
    /// The hosts.
    pub hosts: Vec<NetHost>,
    /// The proxies, one per pair of hosts.
    pub proxies: Vec<NetProxy>,
    /// The hub's namespace.
    pub hub: String,
    kids: Children,
    made: Vec<String>,
}

fn ip(args: &[&str]) -> anyhow::Result<()> {
    let out = Command::new("ip")
        .args(args)
        .stdin(Stdio::null())
        .output()
        .context("running `ip` (iproute2)")?;
    if !out.status.success() {
        bail!(
            "`ip {}`: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(())
}

fn link_flags(link: &LinkArgs) -> Vec<String> {
    vec![
        "--delay".into(),
        humantime::format_duration(link.delay).to_string(),
        "--loss".into(),
        link.loss.to_string(),
        "--seed".into(),
        link.seed.to_string(),
    ]
}

impl Topology {
    /// Makes a namespace per host and the hub, and starts a proxy per pair (`inst`
    /// only names the proxies' instance; they use no shared memory).
    pub fn create(inst: &Instance, names: &[String], link: &LinkArgs) -> anyhow::Result<Self> {
        // SAFETY: geteuid has no preconditions.
        if unsafe { libc::geteuid() } != 0 {
            bail!("network namespaces need root (without: `muster up --hosts`, on loopback)");
        }
        if names.len() < 2 || names.len() > MAX_HOSTS {
            bail!("2 to {MAX_HOSTS} hosts");
        }
        if !(0.0..=100.0).contains(&link.loss) {
            bail!("--loss is a percentage, 0 to 100");
        }
        let tag = format!("mu{}", std::process::id());
        let hub = format!("muster-{}-net", std::process::id());
        let mut t = Topology {
            hosts: Vec::new(),
            proxies: Vec::new(),
            hub: hub.clone(),
            kids: Children::default(),
            made: Vec::new(),
        };
        ip(&["netns", "add", &hub])?;
        t.made.push(hub.clone());
        ip(&["-n", &hub, "link", "set", "lo", "up"])?;
        for (k, name) in names.iter().enumerate() {
            let ns = format!("muster-{}-{name}", std::process::id());
            ip(&["netns", "add", &ns])?;
            t.made.push(ns.clone());
            let (outer, inner) = (format!("{tag}h{k}"), format!("{tag}v{k}"));
            ip(&[
                "link", "add", "name", &outer, "netns", &hub, "type", "veth", "peer", "name",
                &inner, "netns", &ns,
            ])?;
            let net = k + 1;
            let (hub_ip, host_ip) = (
                Ipv4Addr::new(10, 77, net as u8, 1),
                Ipv4Addr::new(10, 77, net as u8, 2),
            );
            ip(&[
                "-n",
                &hub,
                "addr",
                "add",
                &format!("{hub_ip}/24"),
                "dev",
                &outer,
            ])?;
            ip(&["-n", &hub, "link", "set", &outer, "up"])?;
            ip(&[
                "-n",
                &ns,
                "addr",
                "add",
                &format!("{host_ip}/24"),
                "dev",
                &inner,
            ])?;
            ip(&["-n", &ns, "link", "set", &inner, "up"])?;
            ip(&["-n", &ns, "link", "set", "lo", "up"])?;
            t.hosts.push(NetHost {
                host: name.clone(),
                netns: ns,
                ip: host_ip,
                listen: format!("tcp/{host_ip}:{ZENOH_PORT}"),
                connect: Vec::new(),
            });
        }
        let flags = link_flags(link);
        for i in 0..names.len() {
            for j in i + 1..names.len() {
                let listen = SocketAddr::new(
                    Ipv4Addr::new(10, 77, (i + 1) as u8, 1).into(),
                    7500 + j as u16,
                );
                let to = SocketAddr::new(t.hosts[j].ip.into(), ZENOH_PORT);
                let (l, d) = (listen.to_string(), to.to_string());
                let mut args = vec!["--in-netns", &hub, "net-proxy", "--listen", &l, "--to", &d];
                args.extend(flags.iter().map(String::as_str));
                let label = format!("proxy {}-{}", names[i], names[j]);
                let pid = t.kids.spawn(inst, &label, &args, Stdio::null())?.id();
                t.hosts[i].connect.push(format!("tcp/{listen}"));
                t.proxies.push(NetProxy {
                    hosts: [names[i].clone(), names[j].clone()],
                    pid,
                    listen,
                    to,
                });
            }
        }
        Ok(t)
    }

    /// `muster broker` flags for host `i`: in its namespace, listening on its address,
    /// connecting through the proxies.
    pub fn broker_flags(&self, i: usize) -> Vec<String> {
        let h = &self.hosts[i];
        let mut a = vec![
            "--in-netns".into(),
            h.netns.clone(),
            "--listen".into(),
            h.listen.clone(),
        ];
        for c in &h.connect {
            a.push("--connect".into());
            a.push(c.clone());
        }
        a
    }
}

impl Drop for Topology {
    fn drop(&mut self) {
        // A proxy stopped to cut its link must run again to hear the SIGTERM.
        for p in &self.proxies {
            if let Ok(pid) = libc::pid_t::try_from(p.pid) {
                // SAFETY: signalling a child we spawned and have not reaped.
                unsafe { libc::kill(pid, libc::SIGCONT) };
            }
        }
        self.kids.stop();
        // Deleting a namespace deletes its end of each veth pair, and so the pair.
        for ns in self.made.iter().rev() {
            if let Err(e) = ip(&["netns", "del", ns]) {
                eprintln!("muster: {e}");
            }
        }
    }
}

/// `muster netns`: makes the hosts' network, prints it, keeps it until stopped.
pub fn run(inst: &Instance, a: NetnsArgs) -> anyhow::Result<ExitCode> {
    let mut signals = SignalPipe::install().context("signal handlers")?;
    let t = Topology::create(inst, &a.hosts, &a.link)?;
    if a.json {
        let v = serde_json::json!({"hub": t.hub, "hosts": t.hosts, "proxies": t.proxies});
        println!("{v}");
    } else {
        println!(
            "hosts in network namespaces; each pair joined by a proxy adding {} each way and {} % loss:",
            humantime::format_duration(a.link.delay),
            a.link.loss
        );
        for (i, h) in t.hosts.iter().enumerate() {
            let flags: Vec<String> = t.broker_flags(i).into_iter().skip(2).collect();
            println!(
                "  {}: {} (ip netns exec {} muster --instance {} broker --federate --insecure-no-tls --host {} {})",
                h.host,
                h.ip,
                h.netns,
                h.host,
                h.host,
                flags.join(" ")
            );
        }
        for p in &t.proxies {
            println!(
                "  link {}-{}: proxy pid {} (kill -STOP to cut, -CONT to mend)",
                p.hosts[0], p.hosts[1], p.pid
            );
        }
    }
    let _ = std::io::stdout().flush();
    let end = a.duration.map(|d| Instant::now() + d);
    while !signals.drain() && end.is_none_or(|e| Instant::now() < e) {
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(t);
    Ok(ExitCode::SUCCESS)
}

/// `muster net-proxy`: relays each connection to `--to`, both ways, through [`pipe`].
pub fn proxy(a: NetProxyArgs) -> anyhow::Result<ExitCode> {
    let listener = TcpListener::bind(a.listen).with_context(|| format!("binding {}", a.listen))?;
    let mut seed = a.link.seed;
    for conn in listener.incoming() {
        let Ok(inbound) = conn else { continue };
        seed = seed.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let (to, link) = (a.to, a.link);
        std::thread::spawn(move || {
            let outbound = match TcpStream::connect_timeout(&to, Duration::from_secs(5)) {
                Ok(s) => s,
                Err(e) => {
                    tracing::debug!("net-proxy: cannot reach {to}: {e}");
                    return;
                }
            };
            let _ = inbound.set_nodelay(true);
            let _ = outbound.set_nodelay(true);
            let halves = (inbound.try_clone(), outbound.try_clone());
            let (Ok(in2), Ok(out2)) = halves else { return };
            let up = std::thread::spawn(move || pipe(inbound, outbound, link, seed));
            pipe(out2, in2, link, seed ^ 1);
            let _ = up.join();
        });
    }
    Ok(ExitCode::SUCCESS)
}

/// Copies `from` to `to`, each read held back by the link's delay, and a lost one (with
/// what follows, in order) by [`LOSS_STALL`] more. Ends both when either side ends.
fn pipe(mut from: TcpStream, to: TcpStream, link: LinkArgs, seed: u64) {
    let (tx, rx) = mpsc::channel::<(Instant, Vec<u8>)>();
    let mut writer_end = match to.try_clone() {
        Ok(s) => s,
        Err(_) => return,
    };
    let writer = std::thread::spawn(move || {
        for (at, bytes) in rx {
            let now = Instant::now();
            if at > now {
                std::thread::sleep(at - now);
            }
            if writer_end.write_all(&bytes).is_err() {
                break;
            }
        }
        let _ = writer_end.shutdown(Shutdown::Write);
    });
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut last = Instant::now();
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = match from.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        let mut at = Instant::now() + link.delay;
        if link.loss > 0.0 && rng.random::<f64>() * 100.0 < link.loss {
            at += LOSS_STALL;
        }
        // In order, as a TCP stream delivers.
        at = at.max(last);
        last = at;
        if tx.send((at, buf[..n].to_vec())).is_err() {
            break;
        }
    }
    drop(tx);
    let _ = writer.join();
    let _ = from.shutdown(Shutdown::Both);
    let _ = to.shutdown(Shutdown::Both);
}
