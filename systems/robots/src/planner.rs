//! Paths on the occupancy grid: A* (the `pathfinding` crate) over a planning grid where a
//! cell is free when the robot's body fits there with a margin (the map inflated by the
//! robot's radius), with a cost that keeps paths away from walls where there is room.
//! Paths are then shortened by line of sight over the same free cells.
//!
//! Walls stay grid cells here, as in the simulator: the map's exact distance transform
//! answers "does the body fit here" in one lookup, which no shape query over a few
//! hundred thousand wall squares can beat. Bodies the laser sees (people, robots) are
//! added as temporary obstacles when the robot replans round them.

use muster_world_model::map::OccupancyMap;
use pathfinding::prelude::astar;

/// How the planner is tuned.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannerParams {
    /// Planning grid cell, m.
    pub cell: f64,
    /// The robot's radius, m.
    pub radius: f64,
    /// Clearance beyond the radius a path must keep from walls, m.
    pub margin: f64,
    /// Clearance beyond which a cell costs nothing extra, m (paths prefer the middle of
    /// corridors and doors up to this).
    pub comfort: f64,
    /// How far a goal inside a wall or too close to one may be moved to the nearest
    /// free cell, m.
    pub snap: f64,
}

impl Default for PlannerParams {
    fn default() -> Self {
        PlannerParams {
            cell: 0.1,
            radius: 0.25,
            margin: 0.08,
            comfort: 0.8,
            snap: 1.0,
        }
    }
}

/// Why there is no path.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlanError {
    /// The goal is outside the map.
    #[error("goal ({0:.2}, {1:.2}) is outside the map")]
    OutsideMap(f64, f64),
    /// The goal is in or too near a wall, with no free place within the snap distance.
    #[error("goal ({0:.2}, {1:.2}) is inside a wall or too close to one for the robot")]
    GoalBlocked(f64, f64),
    /// The robot's own position is not free (it is against a wall or an obstacle).
    #[error("the robot's own position is blocked")]
    StartBlocked,
    /// Start and goal are in parts of the map no path joins.
    #[error("no path to ({0:.2}, {1:.2})")]
    NoPath(f64, f64),
}

/// The planning grid of one map for one robot size.
pub struct Planner {
    params: PlannerParams,
    w: usize,
    h: usize,
    origin: (f64, f64),
    /// Extra cost per cell (0..=COST_SCALE), `None` where the body does not fit.
    cost: Vec<Option<u32>>,
    /// Distance from each cell's centre to the nearest wall (capped), m.
    wall: Vec<f32>,
    /// The map itself, for lines of sight.
    map: OccupancyMap,
}

/// Cost of one straight step.
const STEP: u32 = 100;
/// Largest extra cost of a cell next to a wall.
const COST_SCALE: u32 = 300;

type Cell = (i32, i32);

impl Planner {
    /// The planning grid for `map` and a robot of `params.radius`.
    pub fn new(map: &OccupancyMap, params: PlannerParams) -> Self {
        let (mw, mh) = map.size();
        let w = (mw / params.cell).ceil() as usize;
        let h = (mh / params.cell).ceil() as usize;
        let origin = map.origin();
        let need = params.radius + params.margin;
        let mut cost = Vec::with_capacity(w * h);
        let mut wall = Vec::with_capacity(w * h);
        for j in 0..h {
            for i in 0..w {
                let x = origin.0 + (i as f64 + 0.5) * params.cell;
                let y = origin.1 + (j as f64 + 0.5) * params.cell;
                let c = map.clearance(x, y, params.comfort + need);
                wall.push(c as f32);
                cost.push(if c < need {
                    None
                } else {
                    let short = ((params.comfort + need - c) / params.comfort).clamp(0.0, 1.0);
                    Some((short * short * f64::from(COST_SCALE)) as u32)
                });
            }
        }
        Planner {
            params,
            w,
            h,
            origin,
            cost,
            wall,
            map: map.clone(),
        }
    }

    /// The parameters in use.
    pub fn params(&self) -> &PlannerParams {
        &self.params
    }

    fn cell_of(&self, x: f64, y: f64) -> Option<Cell> {
        let i = ((x - self.origin.0) / self.params.cell).floor();
        let j = ((y - self.origin.1) / self.params.cell).floor();
        (i >= 0.0 && j >= 0.0 && (i as usize) < self.w && (j as usize) < self.h)
            .then_some((i as i32, j as i32))
    }

    fn centre(&self, c: Cell) -> (f64, f64) {
        (
            self.origin.0 + (f64::from(c.0) + 0.5) * self.params.cell,
            self.origin.1 + (f64::from(c.1) + 0.5) * self.params.cell,
        )
    }

    fn cost_at(&self, c: Cell, blocked: &[bool]) -> Option<u32> {
        if c.0 < 0 || c.1 < 0 || c.0 as usize >= self.w || c.1 as usize >= self.h {
            return None;
        }
        let k = c.1 as usize * self.w + c.0 as usize;
        if blocked.get(k).copied().unwrap_or(false) {
            return None;
        }
        self.cost[k]
    }

    /// Distance from (x, y) to the nearest wall, to the planning grid's resolution
    /// (0 outside the map): tells a wall the laser sees from a body the map does not
    /// know.
    pub fn wall_distance(&self, x: f64, y: f64) -> f64 {
        self.cell_of(x, y).map_or(0.0, |c| {
            f64::from(self.wall[c.1 as usize * self.w + c.0 as usize])
        })
    }

    /// Whether nothing on the map lies on the straight line from `a` to `b`
    /// ([`OccupancyMap::in_sight`]).
    pub fn in_sight(&self, a: (f64, f64), b: (f64, f64)) -> bool {
        self.map.in_sight(a, b)
    }

    /// Whether the robot's body fits at (x, y) with its margin (walls only).
    pub fn free(&self, x: f64, y: f64) -> bool {
        self.cell_of(x, y)
            .is_some_and(|c| self.cost_at(c, &[]).is_some())
    }

    /// The free cell nearest to `c` within the snap distance.
    fn snap(&self, c: Cell, blocked: &[bool]) -> Option<Cell> {
        if self.cost_at(c, blocked).is_some() {
            return Some(c);
        }
        let reach = (self.params.snap / self.params.cell).ceil() as i32;
        let mut best: Option<(i32, Cell)> = None;
        for dj in -reach..=reach {
            for di in -reach..=reach {
                let d2 = di * di + dj * dj;
                if d2 > reach * reach || best.is_some_and(|(b, _)| b <= d2) {
                    continue;
                }
                let n = (c.0 + di, c.1 + dj);
                if self.cost_at(n, blocked).is_some() {
                    best = Some((d2, n));
                }
            }
        }
        best.map(|(_, n)| n)
    }

    /// A path from `from` to `to` (waypoints in metres, the first near `from`, the last
    /// `to` itself or the nearest free place to it), avoiding walls and the circles in
    /// `obstacles` (x, y, radius: bodies the robot saw in its way).
    pub fn plan(
        &self,
        from: (f64, f64),
        to: (f64, f64),
        obstacles: &[(f64, f64, f64)],
    ) -> Result<Vec<(f64, f64)>, PlanError> {
        let goal_cell = self
            .cell_of(to.0, to.1)
            .ok_or(PlanError::OutsideMap(to.0, to.1))?;
        let start_cell = self
            .cell_of(from.0, from.1)
            .ok_or(PlanError::StartBlocked)?;
        let blocked = self.blocked_by(obstacles, from);
        let goal = self
            .snap(goal_cell, &blocked)
            .ok_or(PlanError::GoalBlocked(to.0, to.1))?;
        // A robot pressed against a wall still plans from the nearest free cell.
        let start = self
            .snap(start_cell, &blocked)
            .ok_or(PlanError::StartBlocked)?;
        let octile = |a: &Cell| {
            let (dx, dy) = ((a.0 - goal.0).unsigned_abs(), (a.1 - goal.1).unsigned_abs());
            let (lo, hi) = (dx.min(dy), dx.max(dy));
            STEP * (hi - lo) + 141 * lo
        };
        let (cells, _) = astar(
            &start,
            |&c| {
                let mut next = Vec::with_capacity(8);
                for (di, dj, step) in [
                    (1, 0, STEP),
                    (-1, 0, STEP),
                    (0, 1, STEP),
                    (0, -1, STEP),
                    (1, 1, 141),
                    (1, -1, 141),
                    (-1, 1, 141),
                    (-1, -1, 141),
                ] {
                    let n = (c.0 + di, c.1 + dj);
                    let Some(extra) = self.cost_at(n, &blocked) else {
                        continue;
                    };
                    // No corner cutting: both side cells of a diagonal must be free.
                    if di != 0
                        && dj != 0
                        && (self.cost_at((c.0 + di, c.1), &blocked).is_none()
                            || self.cost_at((c.0, c.1 + dj), &blocked).is_none())
                    {
                        continue;
                    }
                    next.push((n, step + extra * step / STEP));
                }
                next
            },
            octile,
            |&c| c == goal,
        )
        .ok_or(PlanError::NoPath(to.0, to.1))?;
        let mut path = self.shorten(&cells, &blocked);
        if goal == goal_cell {
            if let Some(last) = path.last_mut() {
                *last = to;
            }
        }
        Ok(path)
    }

    /// Cells covered by obstacle circles grown by the robot's radius and margin; the
    /// robot's own cell and its neighbours are never blocked (it is there already).
    fn blocked_by(&self, obstacles: &[(f64, f64, f64)], from: (f64, f64)) -> Vec<bool> {
        if obstacles.is_empty() {
            return Vec::new();
        }
        let mut b = vec![false; self.w * self.h];
        let need = self.params.radius + self.params.margin;
        for &(ox, oy, r) in obstacles {
            let grow = r + need;
            let reach = (grow / self.params.cell).ceil() as i32 + 1;
            let Some(c) = self.cell_of(ox, oy) else {
                continue;
            };
            for dj in -reach..=reach {
                for di in -reach..=reach {
                    let n = (c.0 + di, c.1 + dj);
                    if n.0 < 0 || n.1 < 0 || n.0 as usize >= self.w || n.1 as usize >= self.h {
                        continue;
                    }
                    let (x, y) = self.centre(n);
                    if (x - ox).hypot(y - oy) < grow && (x - from.0).hypot(y - from.1) > need {
                        b[n.1 as usize * self.w + n.0 as usize] = true;
                    }
                }
            }
        }
        b
    }

    /// Whether the straight segment a → b stays on free cells.
    fn line_free(&self, a: (f64, f64), b: (f64, f64), blocked: &[bool]) -> bool {
        let len = (b.0 - a.0).hypot(b.1 - a.1);
        let n = (len / (self.params.cell * 0.5)).ceil().max(1.0) as usize;
        (0..=n).all(|k| {
            let t = k as f64 / n as f64;
            let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
            self.cell_of(x, y).is_some_and(|c| {
                self.cost_at(c, blocked)
                    .is_some_and(|extra| extra < COST_SCALE * 3 / 4)
            })
        })
    }

    /// Keeps only the waypoints needed for straight segments over comfortable cells.
    fn shorten(&self, cells: &[Cell], blocked: &[bool]) -> Vec<(f64, f64)> {
        let pts: Vec<(f64, f64)> = cells.iter().map(|&c| self.centre(c)).collect();
        let Some(&first) = pts.first() else {
            return pts;
        };
        let mut out = vec![first];
        let mut anchor = 0;
        let mut k = 1;
        while k < pts.len() {
            // Extend from the anchor as far as the line stays free.
            let mut far = k;
            while far + 1 < pts.len() && self.line_free(pts[anchor], pts[far + 1], blocked) {
                far += 1;
            }
            out.push(pts[far]);
            anchor = far;
            k = far + 1;
        }
        out
    }
}

/// Length of a polyline, m.
pub fn path_length(from: (f64, f64), path: &[(f64, f64)]) -> f64 {
    let mut prev = from;
    let mut len = 0.0;
    for &p in path {
        len += (p.0 - prev.0).hypot(p.1 - prev.1);
        prev = p;
    }
    len
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn office() -> (OccupancyMap, Planner) {
        let map = OccupancyMap::office();
        let p = Planner::new(&map, PlannerParams::default());
        (map, p)
    }

    #[test]
    fn paths_keep_clearance_from_walls_across_the_office() {
        let (map, p) = office();
        let need = p.params().radius + p.params().margin;
        // From the south-west corridor into an office across the floor and out to the lobby.
        for (from, to) in [
            ((3.0, 3.0), (30.0, 6.5)),
            ((30.0, 3.0), (6.0, 13.5)),
            ((20.0, 10.0), (38.9, 18.0)),
            ((3.0, 17.0), (37.0, 3.0)),
        ] {
            let path = p.plan(from, to, &[]).unwrap();
            assert_eq!(*path.last().unwrap(), to);
            let mut prev = from;
            for &q in &path {
                let len = (q.0 - prev.0).hypot(q.1 - prev.1);
                let n = (len / 0.02).ceil().max(1.0) as usize;
                for k in 0..=n {
                    let t = k as f64 / n as f64;
                    let (x, y) = (prev.0 + (q.0 - prev.0) * t, prev.1 + (q.1 - prev.1) * t);
                    // The last segment may end at the exact goal, a little closer to a wall.
                    let c = map.clearance(x, y, 2.0);
                    assert!(
                        c >= need - 0.08,
                        "{from:?} -> {to:?}: clearance {c:.3} at ({x:.2}, {y:.2})"
                    );
                }
                prev = q;
            }
            let straight = (to.0 - from.0).hypot(to.1 - from.1);
            let len = path_length(from, &path);
            assert!(
                len >= straight - 1e-9 && len < straight * 2.5,
                "length {len} vs {straight}"
            );
        }
    }

    #[test]
    fn goals_in_walls_or_outside_are_reported() {
        let (_, p) = office();
        assert_eq!(
            p.plan((3.0, 3.0), (50.0, 3.0), &[]),
            Err(PlanError::OutsideMap(50.0, 3.0))
        );
        // Deep inside the block of wall between two offices is snapped if near enough...
        assert!(p.plan((3.0, 3.0), (8.0, 6.5), &[]).is_ok());
        // ...and a goal in a closed-off place is refused.
        let mut cells = vec![false; 100 * 100];
        for j in 0..100 {
            for i in 0..100 {
                let border = i < 2 || j < 2 || i > 97 || j > 97;
                let ring = (i == 60 || j == 60) && i >= 60 && j >= 60;
                cells[j * 100 + i] = border || ring;
            }
        }
        let map = OccupancyMap::from_grid(100, 100, 0.1, (0.0, 0.0), cells);
        let p = Planner::new(
            &map,
            PlannerParams {
                snap: 0.2,
                ..PlannerParams::default()
            },
        );
        assert_eq!(
            p.plan((2.0, 2.0), (8.0, 8.0), &[]),
            Err(PlanError::NoPath(8.0, 8.0))
        );
    }

    #[test]
    fn a_body_blocking_a_door_makes_the_path_go_another_way_or_fail() {
        let (_, p) = office();
        // Office south-1 (x 8..12, y 4..9) has its door on the middle corridor (k odd:
        // the door is at the top wall, y 9). Block the door with a person.
        let inside = (10.0, 6.5);
        let free = p.plan((10.0, 10.0), inside, &[]).unwrap();
        assert!(free.len() >= 2);
        let blocked = p.plan((10.0, 10.0), inside, &[(10.0, 9.0, 0.3)]);
        assert_eq!(blocked, Err(PlanError::NoPath(10.0, 6.5)));
        // In a wide corridor a body in the way is passed round.
        let round = p
            .plan((5.0, 3.0), (15.0, 3.0), &[(10.0, 3.0, 0.3)])
            .unwrap();
        let closest = round
            .windows(2)
            .flat_map(|w| {
                (0..=50).map(move |k| {
                    let t = f64::from(k) / 50.0;
                    (
                        w[0].0 + (w[1].0 - w[0].0) * t,
                        w[0].1 + (w[1].1 - w[0].1) * t,
                    )
                })
            })
            .map(|(x, y)| (x - 10.0).hypot(y - 3.0))
            .fold(f64::INFINITY, f64::min);
        assert!(closest > 0.3 + 0.25, "passes {closest:.2} m from the body");
    }
}
