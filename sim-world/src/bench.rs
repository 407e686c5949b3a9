//! Benchmark worlds: N robots wandering with every sensor on, on the office floor tiled
//! so that the density stays at most [`ROBOTS_PER_TILE`] robots per 40 m × 20 m floor.

use crate::map::OccupancyMap;
use crate::scenario::{CameraParams, Colour, LaserParams, RobotSpec, Scenario, SonarParams};
use crate::sensors::laser_scan;
use crate::world::World;
use rand::{RngExt, SeedableRng};
use serde::Serialize;
use std::time::Instant;

/// Robots per office floor in benchmark worlds.
pub const ROBOTS_PER_TILE: usize = 50;

/// A world of `n` wandering robots with laser, sonar and camera, each carrying a beacon.
pub fn world(n: usize, seed: u64) -> World {
    let tiles = n.div_ceil(ROBOTS_PER_TILE).max(1);
    let tx = (tiles as f64 / 2.0).sqrt().ceil().max(1.0) as usize * 2;
    let ty = tiles.div_ceil(tx).max(1);
    let (tx, ty) = if tiles == 1 { (1, 1) } else { (tx, ty) };
    let office = OccupancyMap::office();
    let map = office.tiled(tx, ty);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let (w, h) = map.size();
    let mut placed: Vec<(f64, f64)> = Vec::with_capacity(n);
    let cell = 1.0;
    let gx = (w / cell).ceil() as usize;
    let mut grid: std::collections::HashMap<usize, Vec<usize>> = std::collections::HashMap::new();
    let mut robots = Vec::with_capacity(n);
    let mut poses: Vec<[f64; 3]> = Vec::with_capacity(n);
    let mut tries = 0u64;
    while poses.len() < n && tries < 1000 * n as u64 + 10_000 {
        tries += 1;
        let (x, y) = (rng.random::<f64>() * w, rng.random::<f64>() * h);
        if map.clearance(x, y, 0.4) < 0.4 {
            continue;
        }
        let (ci, cj) = ((x / cell) as usize, (y / cell) as usize);
        let crowded = (ci.saturating_sub(1)..=ci + 1).any(|i| {
            (cj.saturating_sub(1)..=cj + 1).any(|j| {
                grid.get(&(j * gx + i)).is_some_and(|v| {
                    v.iter()
                        .any(|&k| (placed[k].0 - x).hypot(placed[k].1 - y) < 0.7)
                })
            })
        });
        if crowded {
            continue;
        }
        grid.entry(cj * gx + ci).or_default().push(placed.len());
        placed.push((x, y));
        poses.push([x, y, rng.random::<f64>() * 360.0]);
    }
    // Numbered floor by floor, as a fleet would be: robots next in number are next to
    // each other, and so are the parts of the map their steps read.
    let (fw, fh) = office.size();
    let floor = |p: &[f64; 3]| ((p[1] / fh) as usize, (p[0] / fw) as usize);
    poses.sort_by_key(floor);
    for (k, pose) in poses.into_iter().enumerate() {
        robots.push(RobotSpec {
            name: format!("r{k}"),
            pose,
            drive: Default::default(),
            laser: Some(LaserParams::default()),
            sonar: Some(SonarParams::default()),
            camera: Some(CameraParams::default()),
            beacon: Some(Colour::ALL[k % Colour::ALL.len()]),
            wander: true,
            home: None,
            fixed: false,
        });
    }
    let scenario = Scenario {
        map: None,
        seed,
        dt: 0.01,
        robots,
        people: vec![],
        places: vec![],
    };
    World::new(&scenario, Some(map)).expect("benchmark robots are placed on free cells")
}

/// One benchmark result.
#[derive(Clone, Debug, Serialize)]
pub struct Figure {
    /// Robots.
    pub robots: usize,
    /// Simulated seconds per wall-clock second.
    pub realtime_factor: f64,
    /// Simulated seconds run.
    pub sim_seconds: f64,
    /// Wall-clock seconds taken.
    pub wall_seconds: f64,
    /// Threads used.
    pub threads: usize,
}

/// Runs `world` for `sim_seconds` after a 0.5 s warm-up; returns the real-time factor.
pub fn realtime_factor(world: &mut World, sim_seconds: f64) -> Figure {
    world.step(0.5);
    let start = Instant::now();
    let steps = (sim_seconds / 0.01).round() as usize;
    for _ in 0..steps {
        world.step(0.01);
    }
    let wall = start.elapsed().as_secs_f64();
    Figure {
        robots: world.robots().len(),
        realtime_factor: sim_seconds / wall,
        sim_seconds,
        wall_seconds: wall,
        threads: rayon::current_num_threads(),
    }
}

/// Nanoseconds per laser beam (walls and bodies), on one thread, over the robots of `world`.
pub fn ns_per_beam(world: &World, rounds: usize) -> f64 {
    let bodies = world.body_grid_snapshot();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
    let mut out = Vec::new();
    let mut beams = 0usize;
    let start = Instant::now();
    for _ in 0..rounds {
        for (i, r) in world.robots().iter().enumerate() {
            if let Some(l) = &r.spec.laser {
                laser_scan(world.map(), &bodies, i, r.pose, l, &mut rng, &mut out);
                beams += out.len();
            }
        }
    }
    start.elapsed().as_nanos() as f64 / beams.max(1) as f64
}
