//! Quick look at the real-time factor: `cargo run --release -p muster-sim-world --example
//! rtf N [SIM_SECONDS]`. Under `valgrind --tool=callgrind`, two runs with different
//! SIM_SECONDS give instructions per simulated second (the difference).
fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(100);
    let sim_s: f64 = std::env::args()
        .nth(2)
        .and_then(|a| a.parse().ok())
        .unwrap_or(2.0);
    let t = std::time::Instant::now();
    let mut w = muster_sim_world::bench::world(n, 1);
    eprintln!("built {} robots in {:?}", w.robots().len(), t.elapsed());
    let f = muster_sim_world::bench::realtime_factor(&mut w, sim_s);
    println!("{f:?}");
    println!(
        "ns per beam: {:.1}",
        muster_sim_world::bench::ns_per_beam(&w, 3)
    );
}
