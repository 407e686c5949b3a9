//! Round bodies (robots and people) in a uniform grid, for collision and occlusion.

use crate::scenario::Colour;

/// A round body at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Body {
    /// Centre x, m.
    pub x: f64,
    /// Centre y, m.
    pub y: f64,
    /// Radius, m.
    pub r: f64,
    /// The beacon it carries, if any, worn [`BEACON_AT`] of the way up.
    pub beacon: Option<Colour>,
    /// Height, m: what a camera sees over ([`PERSON_HEIGHT`], [`ROBOT_HEIGHT`]).
    pub height: f64,
}

/// A person's height, m. People hide what is behind them from a robot's camera.
pub const PERSON_HEIGHT: f64 = 1.7;

/// A robot's height to the top of its base, m (a Pioneer-class base with its laser and
/// sonar): below the camera mounted on it, which sees over other robots at a person's
/// beacon, as the paper's convoy (a tracker behind the delivery robot behind the
/// person) needs.
pub const ROBOT_HEIGHT: f64 = 0.4;

/// Where on a body its beacon is, as a share of its height (a person's chest).
pub const BEACON_AT: f64 = 0.75;

impl Body {
    /// The height of its beacon, m.
    pub fn beacon_height(&self) -> f64 {
        self.height * BEACON_AT
    }
}

/// Bodies bucketed in square cells, built once per step and read by every robot.
pub struct BodyGrid {
    bodies: Vec<Body>,
    cell: f64,
    origin: (f64, f64),
    nx: usize,
    ny: usize,
    start: Vec<u32>,
    index: Vec<u32>,
    /// Each body's cell.
    keys: Vec<u32>,
}

impl BodyGrid {
    /// Buckets `bodies` in cells of `cell` metres over the rectangle `origin` + `size`.
    pub fn new(bodies: Vec<Body>, origin: (f64, f64), size: (f64, f64), cell: f64) -> Self {
        let nx = ((size.0 / cell).ceil() as usize).max(1);
        let ny = ((size.1 / cell).ceil() as usize).max(1);
        let mut grid = BodyGrid {
            bodies: Vec::new(),
            cell,
            origin,
            nx,
            ny,
            start: Vec::new(),
            index: Vec::new(),
            keys: Vec::new(),
        };
        grid.rebuild(bodies);
        grid
    }

    /// Buckets a new set of bodies over the same rectangle, reusing this grid's memory.
    /// When no body has changed cell (most steps: bodies move millimetres), only their
    /// positions are written.
    pub fn rebuild(&mut self, bodies: impl IntoIterator<Item = Body>) {
        let mut list = std::mem::take(&mut self.bodies);
        let mut keys = std::mem::take(&mut self.keys);
        let old = list.len();
        // A grid never bucketed (just made) buckets whatever it is given.
        let mut moved = self.start.is_empty();
        let mut n = 0;
        for b in bodies {
            let k = self.key(&b) as u32;
            if n < old {
                moved |= k != keys[n];
                (list[n], keys[n]) = (b, k);
            } else {
                list.push(b);
                keys.push(k);
                moved = true;
            }
            n += 1;
        }
        if n != old {
            list.truncate(n);
            keys.truncate(n);
            moved = true;
        }
        self.bodies = list;
        self.keys = keys;
        if moved {
            self.bucket();
        }
    }

    /// The cell holding a body's centre (clamped to the grid; `as` saturates a negative
    /// or NaN coordinate to 0 and truncates the rest, which is floor for them).
    #[inline]
    fn key(&self, b: &Body) -> usize {
        let i = (((b.x - self.origin.0) / self.cell) as usize).min(self.nx - 1);
        let j = (((b.y - self.origin.1) / self.cell) as usize).min(self.ny - 1);
        j * self.nx + i
    }

    /// Buckets the bodies by their `keys`.
    fn bucket(&mut self) {
        let count = &mut self.start;
        count.clear();
        count.resize(self.nx * self.ny + 1, 0);
        for &k in &self.keys {
            count[k as usize + 1] += 1;
        }
        for k in 1..count.len() {
            count[k] += count[k - 1];
        }
        self.index.clear();
        self.index.resize(self.keys.len(), 0);
        // Fill each cell from its end backwards, so that `start` ends up as it began.
        for (n, &k) in self.keys.iter().enumerate().rev() {
            let k = k as usize + 1;
            count[k] -= 1;
            self.index[count[k] as usize] = n as u32;
        }
        // Each cell's entry now holds where the cell starts; shift back by one.
        for k in 1..count.len() {
            count[k - 1] = count[k];
        }
        if let Some(last) = count.last_mut() {
            *last = self.keys.len() as u32;
        }
    }

    /// All bodies.
    pub fn bodies(&self) -> &[Body] {
        &self.bodies
    }

    /// Calls `f(index, body)` for every body whose centre may lie within `radius` of (x, y).
    pub fn near(&self, x: f64, y: f64, radius: f64, mut f: impl FnMut(usize, &Body)) {
        let lo_i = (((x - radius - self.origin.0) / self.cell) as usize).min(self.nx - 1);
        let hi_i = (((x + radius - self.origin.0) / self.cell) as usize).min(self.nx - 1);
        let lo_j = (((y - radius - self.origin.1) / self.cell) as usize).min(self.ny - 1);
        let hi_j = (((y + radius - self.origin.1) / self.cell) as usize).min(self.ny - 1);
        for j in lo_j..=hi_j {
            for i in lo_i..=hi_i {
                let k = j * self.nx + i;
                for &n in &self.index[self.start[k] as usize..self.start[k + 1] as usize] {
                    f(n as usize, &self.bodies[n as usize]);
                }
            }
        }
    }

    /// Half the smallest gap between a body of radius `r` at (x, y) and any other body
    /// (both may move, so each may close at most half of it), capped at `limit`.
    pub fn half_gap(&self, skip: usize, x: f64, y: f64, r: f64, limit: f64) -> f64 {
        let mut best = limit;
        self.near(x, y, limit * 2.0 + r + 0.5, |n, b| {
            if n != skip {
                let gap = ((b.x - x).hypot(b.y - y) - r - b.r) / 2.0;
                best = best.min(gap);
            }
        });
        best
    }
}

/// Where the sensors find bodies: the grid, or the bodies near one robot gathered from
/// it once for all of that robot's sensors.
pub trait Bodies {
    /// Calls `f(index, body)` for every body whose centre may lie within `radius` of
    /// (x, y) (a superset: callers test the distance), in the grid's order.
    fn near(&self, x: f64, y: f64, radius: f64, f: impl FnMut(usize, &Body));
}

impl Bodies for BodyGrid {
    fn near(&self, x: f64, y: f64, radius: f64, f: impl FnMut(usize, &Body)) {
        BodyGrid::near(self, x, y, radius, f);
    }
}

/// The bodies whose centres may lie within some radius of a point, in the grid's order:
/// one grid query serves every sensor of a robot.
#[derive(Default)]
pub struct Nearby {
    list: Vec<(usize, Body)>,
}

impl Nearby {
    /// Gathers from `grid` the bodies that [`BodyGrid::near`] finds within `radius`.
    pub fn gather(&mut self, grid: &BodyGrid, x: f64, y: f64, radius: f64) {
        self.list.clear();
        grid.near(x, y, radius, |n, b| self.list.push((n, *b)));
    }
}

impl Bodies for Nearby {
    fn near(&self, x: f64, y: f64, radius: f64, mut f: impl FnMut(usize, &Body)) {
        for (n, b) in &self.list {
            if (b.x - x).abs() <= radius && (b.y - y).abs() <= radius {
                f(*n, b);
            }
        }
    }
}

/// Distance along a unit ray from (x, y) in direction (dx, dy) to a circle, if it is hit
/// at a positive distance.
pub fn ray_circle(x: f64, y: f64, dx: f64, dy: f64, b: &Body) -> Option<f64> {
    let (ox, oy) = (x - b.x, y - b.y);
    let bq = ox * dx + oy * dy;
    let c = ox * ox + oy * oy - b.r * b.r;
    let disc = bq * bq - c;
    if disc < 0.0 {
        return None;
    }
    let t = -bq - disc.sqrt();
    (t > 0.0).then_some(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(x: f64, y: f64) -> Body {
        Body {
            x,
            y,
            r: 0.25,
            beacon: None,
            height: PERSON_HEIGHT,
        }
    }

    #[test]
    fn the_grid_finds_neighbours_and_gaps() {
        let g = BodyGrid::new(
            vec![body(1.0, 1.0), body(2.0, 1.0), body(9.0, 9.0)],
            (0.0, 0.0),
            (10.0, 10.0),
            2.0,
        );
        let mut seen = Vec::new();
        g.near(1.0, 1.0, 1.5, |n, _| seen.push(n));
        seen.sort();
        assert_eq!(seen, vec![0, 1]);
        // Centres 1 m apart, radii 0.25: gap 0.5, half 0.25.
        assert!((g.half_gap(0, 1.0, 1.0, 0.25, 5.0) - 0.25).abs() < 1e-12);
        assert_eq!(
            g.half_gap(2, 9.0, 9.0, 0.25, 1.0),
            1.0,
            "nobody near: the cap"
        );
    }

    #[test]
    fn a_rebuilt_grid_finds_bodies_where_they_are_now() {
        let mut g = BodyGrid::new(
            vec![body(1.0, 1.0), body(2.0, 1.0), body(9.0, 9.0)],
            (0.0, 0.0),
            (10.0, 10.0),
            2.0,
        );
        let found = |g: &BodyGrid, x: f64, y: f64| {
            let mut seen = Vec::new();
            g.near(x, y, 0.5, |n, b| seen.push((n, b.x, b.y)));
            seen.sort_by_key(|s| s.0);
            seen
        };
        // Moves within their cells: positions change, cells do not.
        g.rebuild(vec![body(1.1, 1.0), body(2.1, 1.0), body(9.0, 8.9)]);
        assert_eq!(found(&g, 1.0, 1.0), vec![(0, 1.1, 1.0)]);
        assert_eq!(found(&g, 9.0, 9.0), vec![(2, 9.0, 8.9)]);
        // One changes cell; then one body fewer; then one more.
        g.rebuild(vec![body(1.1, 1.0), body(5.0, 5.0), body(9.0, 8.9)]);
        assert_eq!(found(&g, 5.0, 5.0), vec![(1, 5.0, 5.0)]);
        assert_eq!(found(&g, 2.5, 1.0), vec![]);
        g.rebuild(vec![body(1.1, 1.0), body(5.0, 5.0)]);
        assert_eq!(found(&g, 9.0, 9.0), vec![]);
        assert_eq!(g.bodies().len(), 2);
        g.rebuild(vec![body(1.1, 1.0), body(5.0, 5.0), body(7.0, 3.0)]);
        assert_eq!(found(&g, 7.0, 3.0), vec![(2, 7.0, 3.0)]);
        let mut all = Vec::new();
        g.near(5.0, 5.0, 20.0, |n, _| all.push(n));
        all.sort();
        assert_eq!(all, vec![0, 1, 2]);
    }

    #[test]
    fn rays_hit_circles_at_the_near_side() {
        let b = body(5.0, 0.0);
        assert!((ray_circle(0.0, 0.0, 1.0, 0.0, &b).unwrap() - 4.75).abs() < 1e-12);
        assert_eq!(ray_circle(0.0, 0.0, -1.0, 0.0, &b), None);
        assert_eq!(ray_circle(0.0, 1.0, 1.0, 0.0, &b), None);
    }
}
