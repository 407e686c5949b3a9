//! `muster bench list`: the service list at a size, in shared memory on this host.
//!
//! A list of N services is written into a real blackboard (the broker's writer) and
//! read back by a real reader (a user's), both in this process: what crosses between
//! processes is the same shared memory. It times a page of the list read in place,
//! pages through filters, the whole list read (unchanged, and after a change), and the
//! broker's side of one change: every row made into an entry and written, and the
//! broker's own path (a core of N services taking only the rows whose counts changed).

use crate::cli::ListBenchArgs;
use hdrhistogram::Histogram;
use muster_broker::core::{Broker, BrokerConfig};
use muster_shared::fence::Fence;
use muster_shared::ipc::{create_node, ListReader, ListWriter};
use muster_shared::protocol::ToBroker;
use muster_shared::snapshot::DEFAULT_MAX_SERVICES;
use muster_shared::snapshot::{ListFilter, ServiceListSnapshot, ServiceView};
use muster_shared::types::{ServiceId, ServiceKind, ServiceSpec, UserId};
use muster_shared::Instance;
use rand::{RngExt, SeedableRng};
use serde_json::{json, Value};
use std::process::ExitCode;
use std::time::Instant;

/// Services per synthetic system (a system may offer at most 128).
const PER_SYSTEM: usize = 100;

pub fn run(inst: &Instance, a: ListBenchArgs) -> anyhow::Result<ExitCode> {
    if a.services == 0 || a.page == 0 || a.reads == 0 {
        anyhow::bail!("--services, --page and --reads must be at least 1");
    }
    let inst = Instance::new(&format!("{}-list-{}", inst.as_str(), std::process::id()))?;
    let node = create_node("bench-list", false)?;
    let fence = Fence::open(&inst)?;
    let result = bench(&inst, &node, &fence, &a);
    fence.remove();
    let report = result?;
    if a.json {
        println!("{report}");
    }
    Ok(ExitCode::SUCCESS)
}

/// A broker core with `n` services (systems `sys00000`.. of [`PER_SYSTEM`] each, every
/// fourth a command service, quota 1000) and 1,000 users said hello; its views are the
/// list the other rows read.
fn loaded_core(n: usize) -> anyhow::Result<(Broker, Vec<UserId>)> {
    let cfg = BrokerConfig {
        max_services: n.max(DEFAULT_MAX_SERVICES),
        ..BrokerConfig::default()
    };
    let mut core = Broker::new(cfg, 1, 1);
    let now = std::time::Duration::from_secs(1);
    for s in 0..n.div_ceil(PER_SYSTEM) {
        let services = (s * PER_SYSTEM..((s + 1) * PER_SYSTEM).min(n))
            .map(|i| ServiceSpec {
                name: format!("s{}", i % PER_SYSTEM),
                description: "a synthetic service of bench list".into(),
                kind: if i % 4 == 3 {
                    ServiceKind::Command
                } else {
                    ServiceKind::Data
                },
                queue: false,
                quota: 1000,
                payload: if i % 4 == 3 { "goal2d" } else { "pose2d" }.into(),
                schema: None,
            })
            .collect();
        core.handle(
            now,
            ToBroker::Register {
                system: format!("sys{s:05}"),
                pid: 100_000 + s as u32,
                services,
                sessions: vec![],
                udp: None,
            },
        );
    }
    let users: Vec<UserId> = (0..1000).map(|u| UserId(format!("u{u}"))).collect();
    for (k, u) in users.iter().enumerate() {
        core.handle(
            now,
            ToBroker::Hello {
                user: u.clone(),
                pid: 200_000 + k as u32,
                links: vec![],
                watch_list: false,
            },
        );
    }
    while core.poll_output().is_some() {}
    if core.views().len() != n {
        anyhow::bail!("the core lists {} services, not {n}", core.views().len());
    }
    Ok((core, users))
}

/// The broker's steps on a list change: the rows made into the snapshot's entries.
fn fill(snapshot: &mut ServiceListSnapshot, rows: &[ServiceView]) {
    for (slot, v) in snapshot.resize(rows.len()).iter_mut().zip(rows) {
        *slot = v.to_entry();
    }
}

fn histogram() -> anyhow::Result<Histogram<u64>> {
    Ok(Histogram::new_with_bounds(1, 60_000_000_000, 3)?)
}

fn bench(
    inst: &Instance,
    node: &iceoryx2::node::Node<muster_shared::ipc::Ipc>,
    fence: &Fence,
    a: &ListBenchArgs,
) -> anyhow::Result<Value> {
    let n = a.services;
    let (mut core, users) = loaded_core(n)?;
    let mut rows = core.views();
    let mut writer = ListWriter::open(node, inst, 1)?;
    let mut snapshot = ServiceListSnapshot::empty();
    snapshot.epoch = 1;
    snapshot.generation = 1;
    let t = Instant::now();
    fill(&mut snapshot, &rows);
    writer.publish(node, &snapshot, fence)?;
    let first_write_us = t.elapsed().as_secs_f64() * 1e6;
    let mut reader = ListReader::open(node, inst)?;
    let mut rng = rand_pcg::Pcg64::seed_from_u64(a.seed);
    let page = a.page;
    let everything = ListFilter::default();
    let mut report = serde_json::Map::new();
    let mut table = Vec::new();
    let mut add = |name: &str, h: &Histogram<u64>, got: usize| {
        let us = |q: f64| h.value_at_quantile(q) as f64 / 1000.0;
        table.push(format!(
            "{name:<36} {:>7} {:>9.2} {:>9.2} {:>9.2} {:>9.1} {:>7}",
            h.len(),
            us(0.5),
            us(0.9),
            us(0.99),
            h.max() as f64 / 1000.0,
            got
        ));
        report.insert(
            name.to_string(),
            json!({"count": h.len(), "p50_us": us(0.5), "p90_us": us(0.9), "p99_us": us(0.99),
                   "max_us": h.max() as f64 / 1000.0, "entries": got}),
        );
    };
    // Each read timed alone; returns the histogram and the entries the last read got.
    let reads = a.reads;
    let time = |what: &mut dyn FnMut(usize) -> anyhow::Result<usize>| {
        let mut h = histogram()?;
        let mut got = 0;
        for i in 0..reads {
            let t = Instant::now();
            got = what(i)?;
            h.record(t.elapsed().as_nanos().max(1) as u64)?;
        }
        anyhow::Ok((h, got))
    };
    let offsets: Vec<usize> = (0..a.reads)
        .map(|_| rng.random_range(0..n.saturating_sub(page).max(1)))
        .collect();
    let (h, got) = time(&mut |i| {
        Ok(reader
            .page_from(node, &everything, offsets[i], page)?
            .entries
            .len())
    })?;
    add(&format!("page of {page}, in place"), &h, got);
    let one_system = ListFilter {
        system: Some(format!("sys{:05}", (n - 1) / PER_SYSTEM / 2)),
        ..ListFilter::default()
    };
    let (h, got) = time(&mut |_| Ok(reader.page_from(node, &one_system, 0, page)?.entries.len()))?;
    add(&format!("page of {page}, one system"), &h, got);
    let commands = ListFilter {
        kind: Some(ServiceKind::Command),
        ..ListFilter::default()
    };
    let (h, got) = time(&mut |i| {
        Ok(reader
            .page_from(node, &commands, offsets[i] / 4, page)?
            .entries
            .len())
    })?;
    add(&format!("page of {page}, command services"), &h, got);
    let glob = ListFilter {
        name: Some("s1?".into()),
        ..ListFilter::default()
    };
    let (h, got) = time(&mut |_| Ok(reader.page_from(node, &glob, 0, page)?.entries.len()))?;
    add(&format!("page of {page}, name glob s1?"), &h, got);
    let (h, got) = time(&mut |_| Ok(reader.read_from(node)?.entries().len()))?;
    add("whole list, unchanged", &h, got);
    // A change (one service's sessions in use) before each read: the broker's fill and
    // write, and then the reader's copy of the whole list, or a page, timed apart.
    let (mut write, mut whole, mut paged) = (histogram()?, histogram()?, histogram()?);
    let (mut got_whole, mut got_page) = (0, 0);
    for (i, &k) in offsets.iter().enumerate() {
        rows[k].in_use = (rows[k].in_use + 1) % 10;
        snapshot.generation += 1;
        let t = Instant::now();
        fill(&mut snapshot, &rows);
        writer.publish(node, &snapshot, fence)?;
        write.record(t.elapsed().as_nanos().max(1) as u64)?;
        let t = Instant::now();
        if i % 2 == 0 {
            got_whole = reader.read_from(node)?.entries().len();
            whole.record(t.elapsed().as_nanos().max(1) as u64)?;
        } else {
            got_page = reader.page_from(node, &everything, k, page)?.entries.len();
            paged.record(t.elapsed().as_nanos().max(1) as u64)?;
        }
    }
    add("whole list, after a change", &whole, got_whole);
    add(
        &format!("page of {page}, in place, after a change"),
        &paged,
        got_page,
    );
    add("fill every row + write", &write, n);
    // The broker's own path: a core of N services; each request puts an offer out
    // (one service's sessions in use change), and the list is taken (only the rows
    // whose counts changed), filled and written.
    let ids: Vec<ServiceId> = rows.iter().map(|v| ServiceId(v.id.clone())).collect();
    let (mut views, mut shape) = (Vec::new(), u64::MAX);
    let mut snap = ServiceListSnapshot::empty();
    snap.epoch = 1;
    if let Some((g, _)) = core.take_list_change_rows(&mut views, &mut shape) {
        snap.generation = g;
        fill(&mut snap, &views);
    }
    writer.publish(node, &snap, fence)?;
    let mut broker = histogram()?;
    let t0 = std::time::Duration::from_secs(2);
    for (i, &k) in offsets.iter().enumerate() {
        core.handle(
            t0,
            ToBroker::Request {
                user: users[i % users.len()].clone(),
                req: i as u64 + 1,
                service: ids[k].clone(),
            },
        );
        while core.poll_output().is_some() {}
        let t = Instant::now();
        if let Some((g, changed)) = core.take_list_change_rows(&mut views, &mut shape) {
            snap.generation = g;
            match &changed {
                Some(changed) => {
                    let slots = snap.resize(views.len());
                    for &r in changed {
                        slots[r] = views[r].to_entry();
                    }
                }
                None => fill(&mut snap, &views),
            }
            writer.publish_rows(node, &snap, fence, changed.as_deref())?;
        }
        broker.record(t.elapsed().as_nanos().max(1) as u64)?;
    }
    add("broker: a request's list change", &broker, n);
    if !a.json {
        println!(
            "service list of {n} in shared memory (blackboard room for {}; first write {first_write_us:.0} µs)",
            writer.capacity()
        );
        println!(
            "{:<36} {:>7} {:>9} {:>9} {:>9} {:>9} {:>7}",
            "read", "count", "p50 µs", "p90 µs", "p99 µs", "max µs", "entries"
        );
        for l in &table {
            println!("{l}");
        }
    }
    report.insert("services".into(), json!(n));
    report.insert("page".into(), json!(page));
    report.insert("room".into(), json!(writer.capacity()));
    report.insert("first_write_us".into(), json!(first_write_us));
    Ok(Value::Object(report))
}
