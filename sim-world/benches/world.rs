//! `cargo bench -p muster-sim-world`: one world step and one laser scan, at several sizes.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use muster_sim_world::bench;

fn step(c: &mut Criterion) {
    let mut g = c.benchmark_group("world_step_10ms");
    g.sample_size(10);
    for n in [1usize, 10, 100, 1000] {
        let mut w = bench::world(n, 1);
        w.step(0.5);
        g.bench_with_input(BenchmarkId::from_parameter(n), &n, |b, _| {
            b.iter(|| w.step(0.01))
        });
    }
    g.finish();
}

fn laser(c: &mut Criterion) {
    let w = bench::world(100, 1);
    c.bench_function("laser_scans_100_robots", |b| {
        b.iter(|| bench::ns_per_beam(&w, 1))
    });
}

criterion_group!(benches, step, laser);
criterion_main!(benches);
