//! Navigation fields: for every place, the walking distance to it from every free cell
//! of a coarse grid, so that people (and robots sent somewhere) follow the gradient
//! around walls through doors.

use crate::map::OccupancyMap;
use std::collections::VecDeque;

/// Cell size of the navigation grid, m.
pub const NAV_CELL: f64 = 0.2;
/// Clearance a walker needs, m.
pub const NAV_CLEARANCE: f64 = 0.35;
const UNREACHABLE: u32 = u32::MAX;

/// Distance-to-place fields on a coarse grid.
pub struct Navigation {
    nx: usize,
    ny: usize,
    origin: (f64, f64),
    walkable: Vec<bool>,
    fields: Vec<Vec<u32>>,
    places: Vec<(f64, f64)>,
}

impl Navigation {
    /// Builds one field per place (breadth-first over walkable cells; diagonal steps
    /// count 1.41 via a two-level cost).
    pub fn new(map: &OccupancyMap, places: &[(f64, f64)]) -> Self {
        let (w, h) = map.size();
        let origin = map.origin();
        let nx = (w / NAV_CELL).floor() as usize;
        let ny = (h / NAV_CELL).floor() as usize;
        let mut walkable = vec![false; nx * ny];
        for j in 0..ny {
            for i in 0..nx {
                let (x, y) = (
                    origin.0 + (i as f64 + 0.5) * NAV_CELL,
                    origin.1 + (j as f64 + 0.5) * NAV_CELL,
                );
                walkable[j * nx + i] = map.clearance(x, y, NAV_CLEARANCE) >= NAV_CLEARANCE;
            }
        }
        let mut nav = Navigation {
            nx,
            ny,
            origin,
            walkable,
            fields: Vec::new(),
            places: places.to_vec(),
        };
        nav.fields = places.iter().map(|&(x, y)| nav.field(x, y)).collect();
        nav
    }

    fn cell(&self, x: f64, y: f64) -> Option<usize> {
        crate::map::grid_cell(
            (x - self.origin.0) / NAV_CELL,
            (y - self.origin.1) / NAV_CELL,
            self.nx,
            self.ny,
        )
        .map(|(i, j)| j * self.nx + i)
    }

    fn centre(&self, k: usize) -> (f64, f64) {
        let (i, j) = (k % self.nx, k / self.nx);
        (
            self.origin.0 + (i as f64 + 0.5) * NAV_CELL,
            self.origin.1 + (j as f64 + 0.5) * NAV_CELL,
        )
    }

    /// Dijkstra with costs 10 (straight) and 14 (diagonal) from the place's cell.
    fn field(&self, x: f64, y: f64) -> Vec<u32> {
        let mut dist = vec![UNREACHABLE; self.nx * self.ny];
        let Some(start) = self
            .cell(x, y)
            .filter(|&k| self.walkable[k])
            .or_else(|| self.nearest_walkable(x, y))
        else {
            return dist;
        };
        dist[start] = 0;
        // Two FIFO queues approximate Dijkstra well for two small integer costs; a
        // cell is re-relaxed if a shorter path arrives later.
        let mut queue = VecDeque::from([start]);
        while let Some(k) = queue.pop_front() {
            let (i, j) = ((k % self.nx) as i64, (k / self.nx) as i64);
            for (di, dj, c) in [
                (1, 0, 10),
                (-1, 0, 10),
                (0, 1, 10),
                (0, -1, 10),
                (1, 1, 14),
                (1, -1, 14),
                (-1, 1, 14),
                (-1, -1, 14),
            ] {
                let (ni, nj) = (i + di, j + dj);
                if ni < 0 || nj < 0 || ni as usize >= self.nx || nj as usize >= self.ny {
                    continue;
                }
                let n = nj as usize * self.nx + ni as usize;
                // No cutting corners: diagonal moves need both side cells walkable.
                let corner_ok = di == 0
                    || dj == 0
                    || (self.walkable[(j as usize) * self.nx + ni as usize]
                        && self.walkable[nj as usize * self.nx + i as usize]);
                if self.walkable[n] && corner_ok && dist[k] + c < dist[n] {
                    dist[n] = dist[k] + c;
                    queue.push_back(n);
                }
            }
        }
        dist
    }

    fn nearest_walkable(&self, x: f64, y: f64) -> Option<usize> {
        (0..self.walkable.len())
            .filter(|&k| self.walkable[k])
            .min_by(|&a, &b| {
                let (ax, ay) = self.centre(a);
                let (bx, by) = self.centre(b);
                (ax - x).hypot(ay - y).total_cmp(&(bx - x).hypot(by - y))
            })
    }

    /// Number of places.
    pub fn places(&self) -> usize {
        self.places.len()
    }

    /// Position of a place.
    pub fn place(&self, k: usize) -> (f64, f64) {
        self.places[k]
    }

    /// Whether `place` can be walked to from (x, y).
    pub fn reachable(&self, place: usize, x: f64, y: f64) -> bool {
        self.cell(x, y)
            .is_some_and(|k| self.fields[place][k] != UNREACHABLE)
    }

    /// Remaining walking distance to `place`, m (None if unreachable).
    pub fn distance(&self, place: usize, x: f64, y: f64) -> Option<f64> {
        let k = self.cell(x, y)?;
        let (i, j) = ((k % self.nx) as i64, (k / self.nx) as i64);
        let field = &self.fields[place];
        // An unwalkable cell next to reachable ones is one step further than the best.
        let mut d = field[k];
        if d == UNREACHABLE {
            for (di, dj) in [
                (1, 0),
                (-1, 0),
                (0, 1),
                (0, -1),
                (1, 1),
                (1, -1),
                (-1, 1),
                (-1, -1),
            ] {
                let (ni, nj) = (i + di, j + dj);
                if ni >= 0 && nj >= 0 && (ni as usize) < self.nx && (nj as usize) < self.ny {
                    let n = field[nj as usize * self.nx + ni as usize];
                    if n != UNREACHABLE {
                        d = d.min(n + 14);
                    }
                }
            }
        }
        (d != UNREACHABLE).then(|| f64::from(d) / 10.0 * NAV_CELL)
    }

    /// The direction (rad) to walk from (x, y) towards `place`: to the centre of the
    /// neighbouring cell nearest to it, or straight at the place once in its cell.
    pub fn heading(&self, place: usize, x: f64, y: f64) -> Option<f64> {
        let k = self.cell(x, y)?;
        let field = &self.fields[place];
        if field[k] == 0 {
            let (px, py) = self.places[place];
            return Some((py - y).atan2(px - x));
        }
        // From an unwalkable cell (a walker pushed close to a wall), steer back to the
        // best reachable neighbour.
        let (i, j) = ((k % self.nx) as i64, (k / self.nx) as i64);
        let mut best = (field[k], k);
        for dj in -1..=1 {
            for di in -1..=1 {
                let (ni, nj) = (i + di, j + dj);
                if ni < 0 || nj < 0 || ni as usize >= self.nx || nj as usize >= self.ny {
                    continue;
                }
                let n = nj as usize * self.nx + ni as usize;
                if field[n] < best.0 {
                    best = (field[n], n);
                }
            }
        }
        if best.0 == UNREACHABLE {
            return None;
        }
        let (cx, cy) = self.centre(best.1);
        Some((cy - y).atan2(cx - x))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn walking_distances_go_around_walls_through_doors() {
        let map = OccupancyMap::office();
        // From the south corridor into office-south-0 (door on its south wall at x 5.5..6.5).
        let nav = Navigation::new(&map, &[(6.0, 6.5)]);
        let d = nav.distance(0, 6.0, 3.0).unwrap();
        assert!((3.0..4.5).contains(&d), "through the door: {d}");
        // From office-south-1 (door on its north wall) the walk goes round: much longer than 4 m.
        let far = nav.distance(0, 10.0, 6.5).unwrap();
        assert!(far > 12.0, "{far}");
        // Following the heading gets there.
        let (mut x, mut y) = (10.0, 6.5);
        for _ in 0..2000 {
            if nav.distance(0, x, y).unwrap() < 0.3 {
                break;
            }
            let a = nav.heading(0, x, y).unwrap();
            x += 0.05 * a.cos();
            y += 0.05 * a.sin();
            assert!(
                map.clearance(x, y, 0.2) > 0.1,
                "walked into a wall at ({x}, {y})"
            );
        }
        assert!((x - 6.0).hypot(y - 6.5) < 0.5, "arrived at ({x}, {y})");
    }
}
