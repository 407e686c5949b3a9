//! The live floor for the map page: the simulator's robots and people (its world
//! sample in shared memory) and the local systems' own views (their tracks and plans),
//! read by one thread at [`RATE_HZ`] while some tab watches, and the map's walls once.

use muster_shared::ipc::{create_node, ListReader, VizReader};
use muster_shared::Instance;
use muster_sim_world::shm::WorldView;
use muster_world_model::{Colour, OccupancyMap};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::broadcast;

/// Frames a second sent to a watching tab.
pub const RATE_HZ: f64 = 15.0;

/// One instant of the floor: the world for everyone, and each system's view for the
/// users allowed one of its services.
#[derive(Clone, Debug)]
pub struct WorldFrame {
    /// Sim time, s.
    pub t: f64,
    /// Robots: name, x, y, theta, contacts.
    pub robots: Value,
    /// People: name, colour, x, y.
    pub people: Value,
    /// Per system: its tracks and plans.
    pub views: BTreeMap<String, (Value, Value)>,
}

impl WorldFrame {
    /// The frame as a user allowed the systems `allowed` sees it.
    pub fn json_for(&self, allowed: impl Fn(&str) -> bool) -> String {
        let mut tracks = Vec::new();
        let mut plans = Vec::new();
        for (system, (t, p)) in &self.views {
            if allowed(system) {
                tracks.extend(t.as_array().into_iter().flatten().cloned());
                plans.extend(p.as_array().into_iter().flatten().cloned());
            }
        }
        json!({"t": "world", "time": self.t, "robots": self.robots, "people": self.people,
               "tracks": tracks, "plans": plans})
        .to_string()
    }
}

/// The walls, as a `map` frame: the grid's size, resolution and origin, and each row's
/// runs of occupied cells as `[row, first, length, ...]`.
pub fn map_frame(map: &OccupancyMap) -> String {
    let mut runs = Vec::new();
    for j in 0..map.height() {
        let mut i = 0;
        while i < map.width() {
            if map.occupied(i as i64, j as i64) {
                let start = i;
                while i < map.width() && map.occupied(i as i64, j as i64) {
                    i += 1;
                }
                runs.extend([j, start, i - start]);
            } else {
                i += 1;
            }
        }
    }
    let (ox, oy) = map.origin();
    json!({"t": "map", "width": map.width(), "height": map.height(),
           "resolution": map.resolution(), "origin": [ox, oy], "runs": runs})
    .to_string()
}

/// Starts the reader thread; it reads only while `frames` has receivers, and stops
/// when `stop` is set.
pub fn start(
    inst: Instance,
    frames: broadcast::Sender<Arc<WorldFrame>>,
    stop: Arc<AtomicBool>,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    std::thread::Builder::new()
        .name("web-world".into())
        .spawn(move || {
            if let Err(e) = run(&inst, &frames, &stop) {
                tracing::warn!("the map's reader stopped: {e}");
            }
        })
}

fn run(
    inst: &Instance,
    frames: &broadcast::Sender<Arc<WorldFrame>>,
    stop: &AtomicBool,
) -> Result<(), String> {
    let node = create_node(&format!("muster-web-world-{}", std::process::id()), false)
        .map_err(|e| e.to_string())?;
    let period = Duration::from_secs_f64(1.0 / RATE_HZ);
    let mut world: Option<WorldView> = None;
    let mut list: Option<ListReader> = None;
    let mut views: BTreeMap<String, VizReader> = BTreeMap::new();
    let mut last_views: BTreeMap<String, (Value, Value)> = BTreeMap::new();
    let mut next_attach = Instant::now();
    let mut last: Option<WorldFrame> = None;
    while !stop.load(Ordering::Acquire) {
        let tick = Instant::now();
        if frames.receiver_count() == 0 {
            std::thread::sleep(period);
            continue;
        }
        if tick >= next_attach {
            next_attach = tick + Duration::from_secs(1);
            if world.is_none() {
                world = WorldView::open(&node, inst.as_str()).ok();
            }
            if list.is_none() {
                list = ListReader::open(&node, inst).ok();
            }
            if let Some(snap) = list.as_mut().and_then(|l| l.read_from(&node).ok()) {
                for v in snap.views().into_iter().filter(|v| !v.remote) {
                    if !views.contains_key(&v.system) {
                        if let Ok(r) = VizReader::open(&node, inst, &v.system) {
                            views.insert(v.system.clone(), r);
                        }
                    }
                }
            }
        }
        for (system, r) in views.iter_mut() {
            if let Some(v) = r.latest() {
                let tracks: Vec<Value> = v
                    .tracks
                    .iter()
                    .map(|t| json!({"system": system, "colour": t.colour, "x": t.x, "y": t.y, "sigma": t.sigma, "lost": t.lost}))
                    .collect();
                let plans: Vec<Value> = v
                    .plans
                    .iter()
                    .map(|p| json!({"system": system, "robot": p.robot, "goal": [p.goal.0, p.goal.1], "path": p.path.iter().map(|(x, y)| [x, y]).collect::<Vec<_>>()}))
                    .collect();
                last_views.insert(system.clone(), (json!(tracks), json!(plans)));
            }
        }
        let after = last.as_ref().map_or(f64::NEG_INFINITY, |f| f.t);
        let sample = world.as_ref().and_then(|w| {
            w.next(after, Duration::ZERO, |s| {
                let robots: Vec<Value> = s.robots[..(s.n_robots as usize).min(s.robots.len())]
                    .iter()
                    .map(|r| json!({"name": r.name.as_str(), "x": r.pose.x, "y": r.pose.y, "theta": r.pose.theta, "contacts": r.contacts}))
                    .collect();
                let people: Vec<Value> = s.people[..(s.n_people as usize).min(s.people.len())]
                    .iter()
                    .map(|p| json!({"name": p.name.as_str(), "colour": Colour::from_code(p.beacon).map(Colour::name), "x": p.pose.x, "y": p.pose.y}))
                    .collect();
                (s.time, json!(robots), json!(people))
            })
            .ok()
            .flatten()
        });
        if let Some((t, robots, people)) = sample {
            last = Some(WorldFrame {
                t,
                robots,
                people,
                views: last_views.clone(),
            });
        } else if let Some(l) = last.as_mut() {
            // The world stands still (a paused or absent simulator): the views still move.
            l.views = last_views.clone();
        }
        if let Some(f) = &last {
            let _ = frames.send(Arc::new(f.clone()));
        }
        let spent = tick.elapsed();
        if spent < period {
            std::thread::sleep(period - spent);
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_map_frame_holds_each_rows_runs_of_walls() {
        // 5 × 3 cells, row 0 at the bottom: a full bottom row, two runs in the middle,
        // an empty top.
        #[rustfmt::skip]
        let cells = [
            1, 1, 1, 1, 1,
            1, 0, 0, 1, 1,
            0, 0, 0, 0, 0,
        ];
        let map = OccupancyMap::from_grid(
            5,
            3,
            0.5,
            (-1.0, 2.0),
            cells.iter().map(|&c| c == 1).collect(),
        );
        let f: Value = serde_json::from_str(&map_frame(&map)).unwrap();
        assert_eq!(f["t"], json!("map"));
        assert_eq!(
            (f["width"].clone(), f["height"].clone()),
            (json!(5), json!(3))
        );
        assert_eq!(f["resolution"], json!(0.5));
        assert_eq!(f["origin"], json!([-1.0, 2.0]));
        assert_eq!(f["runs"], json!([0, 0, 5, 1, 0, 1, 1, 3, 2]));
    }

    #[test]
    fn a_user_sees_the_world_and_only_the_views_of_systems_it_may_use() {
        let mut views = BTreeMap::new();
        views.insert(
            "tracking".to_string(),
            (json!([{"colour": "red", "x": 1.0}]), json!([])),
        );
        views.insert(
            "delivery".to_string(),
            (
                json!([]),
                json!([{"robot": "D1", "goal": [2.0, 3.0], "path": []}]),
            ),
        );
        let frame = WorldFrame {
            t: 12.5,
            robots: json!([{"name": "D1"}]),
            people: json!([{"name": "p0", "colour": "red"}]),
            views,
        };
        let all: Value = serde_json::from_str(&frame.json_for(|_| true)).unwrap();
        assert_eq!(all["time"], json!(12.5));
        assert_eq!(all["tracks"].as_array().unwrap().len(), 1);
        assert_eq!(all["plans"].as_array().unwrap().len(), 1);
        let tracking_only: Value =
            serde_json::from_str(&frame.json_for(|s| s == "tracking")).unwrap();
        assert_eq!(tracking_only["tracks"][0]["colour"], json!("red"));
        assert_eq!(
            tracking_only["plans"],
            json!([]),
            "no plan of a system it may not use"
        );
        assert_eq!(
            tracking_only["robots"], all["robots"],
            "the floor itself is everyone's"
        );
        assert_eq!(tracking_only["people"], all["people"]);
    }
}
