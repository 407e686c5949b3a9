//! Runs the paper's Experiment 2 in process over seeds and prints each run's figures:
//! `cargo run --release -p muster-robots --example link_sim -- [SEEDS] [MINUTES] [LATENCY_S] [CROWD]`
//! (SEEDS as `1-20` or `1,5,9`). Contacts are logged on stderr; `TRACE=1` adds a line a
//! second of where everyone is.
use muster_robots::link_sim::{run, LinkSimParams};
use muster_robots::percentile as pct;

fn main() {
    // The simulator logs each contact (robot, pose, velocity, the nearest body) at info.
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let seeds: Vec<u64> = match args.first().map(String::as_str) {
        Some(s) if s.contains('-') => {
            let (a, b) = s.split_once('-').unwrap_or(("1", "1"));
            (a.parse().unwrap_or(1)..=b.parse().unwrap_or(1)).collect()
        }
        Some(s) => s.split(',').filter_map(|x| x.parse().ok()).collect(),
        None => vec![1],
    };
    let minutes: f64 = args.get(1).and_then(|x| x.parse().ok()).unwrap_or(10.0);
    let latency: f64 = args.get(2).and_then(|x| x.parse().ok()).unwrap_or(0.0);
    let crowd: usize = args.get(3).and_then(|x| x.parse().ok()).unwrap_or(0);
    let mut all_tracked = Vec::new();
    let mut contacts = 0;
    println!("seed  d1-person tracked p50/p90  all p50/p90  tracked%  t3-person p50  d1-t3 p50  arrivals(≤1m)  contacts  T3 loc p95/max  D1 loc p95/max  [wall]  red held up");
    for seed in seeds {
        let started = std::time::Instant::now();
        let f = match run(&LinkSimParams {
            seed,
            duration: minutes * 60.0,
            latency,
            crowd,
            trace: std::env::var_os("TRACE").is_some(),
            ..LinkSimParams::default()
        }) {
            Ok(f) => f,
            Err(e) => {
                eprintln!("seed {seed}: {e}");
                std::process::exit(1);
            }
        };
        let q = |v: &[f64], x| pct(v, x).unwrap_or(f64::NAN);
        let near = f.arrivals.iter().filter(|d| **d <= 1.0).count();
        println!(
            "{seed:4}  {:5.2} / {:5.2}  {:5.2} / {:5.2}  {:5.1}  {:5.2}  {:5.2}  {}({near})  {:?}  {:.2}/{:.2}  {:.2}/{:.2}  [{:.1} s]  {:.1} %",
            q(&f.d1_person_tracked, 0.5),
            q(&f.d1_person_tracked, 0.9),
            q(&f.d1_person_all, 0.5),
            q(&f.d1_person_all, 0.9),
            100.0 * f.tracked_fraction(),
            q(&f.t3_person, 0.5),
            q(&f.d1_t3, 0.5),
            f.arrivals.len(),
            f.contacts,
            q(&f.t3_localization, 0.95),
            q(&f.t3_localization, 1.0),
            q(&f.d1_localization, 0.95),
            q(&f.d1_localization, 1.0),
            started.elapsed().as_secs_f64(),
            100.0 * f.held_up_fraction()
        );
        contacts += f.total_contacts();
        all_tracked.extend(f.d1_person_tracked);
    }
    println!(
        "all: d1-person tracked p50 {:.2} p90 {:.2}; contacts {contacts}",
        pct(&all_tracked, 0.5).unwrap_or(f64::NAN),
        pct(&all_tracked, 0.9).unwrap_or(f64::NAN)
    );
}
