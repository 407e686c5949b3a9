//! Occupancy maps in the ROS map_server format, the built-in office floor, and exact
//! geometry on them: ray casts and clearance.
//!
//! Occupied cells are exact squares. A Euclidean distance transform of the occupied
//! cells gives, anywhere, a lower bound on the distance to the nearest wall; ray casts
//! jump by that bound (sphere tracing) while far from walls and walk cell by cell
//! (Amanatides–Woo) near them, so every hit is the exact entry point into an occupied
//! square. Clearance near walls is the exact point-to-square distance.

use crate::walls::Walls;
use serde::Deserialize;
use std::path::Path;

/// Why a map could not be loaded. Nothing is loaded on error.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    /// The YAML file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// The YAML does not describe a map (a field is missing or has the wrong type).
    #[error("{path}: not a map_server YAML: {detail}")]
    Yaml {
        /// The file.
        path: String,
        /// What is wrong.
        detail: String,
    },
    /// A value is out of range (resolution ≤ 0, thresholds outside 0..1, ...).
    #[error("{path}: {detail}")]
    Invalid {
        /// The file.
        path: String,
        /// What is wrong.
        detail: String,
    },
    /// The image named by the YAML could not be decoded (PGM or PNG expected).
    #[error("{path}: cannot decode the map image: {detail}")]
    Image {
        /// The image file.
        path: String,
        /// What the decoder said.
        detail: String,
    },
}

#[derive(Deserialize)]
struct MapYaml {
    image: String,
    resolution: f64,
    origin: Vec<f64>,
    #[serde(default)]
    negate: u8,
    #[serde(default = "default_occupied")]
    occupied_thresh: f64,
    #[serde(default = "default_free")]
    free_thresh: f64,
}

fn default_occupied() -> f64 {
    0.65
}
fn default_free() -> f64 {
    0.196
}

/// A 2-D occupancy grid: cell (i, j) covers x in origin.x + [i, i+1)·res, y likewise
/// (j = 0 is the bottom row). Unknown cells count as occupied.
#[derive(Clone, Debug)]
pub struct OccupancyMap {
    width: usize,
    height: usize,
    resolution: f64,
    origin: (f64, f64),
    occupied: Vec<bool>,
    /// Distance, in whole cells (rounded down, at most 255), from each cell's centre to
    /// the nearest occupied cell's centre (0 exactly on occupied cells), one byte a cell
    /// to keep ray casts in cache, in 8 × 8-cell tiles of 64 bytes (one cache line
    /// each): a ray walking cell by cell stays within a line for several steps.
    edt_tiles: Vec<u8>,
    /// Tiles per row.
    tiles_x: usize,
    /// The minimum of the field over 4 × 4-cell blocks: 16 times smaller, so the long
    /// jumps of a ray (far from walls) read a table that stays in cache.
    coarse: Vec<u8>,
    /// Blocks per row of `coarse`.
    coarse_x: usize,
    /// The walls as segments, for batched ray casts.
    walls: Walls,
}

const COARSE: usize = 4;

const TILE: usize = 8;

/// Most cells a map may have (≈ 1 km² at 5 cm).
pub const MAX_CELLS: usize = 400_000_000;

impl OccupancyMap {
    /// A map from a grid of occupied flags, row 0 at the bottom.
    pub fn from_grid(
        width: usize,
        height: usize,
        resolution: f64,
        origin: (f64, f64),
        occupied: Vec<bool>,
    ) -> Self {
        assert_eq!(occupied.len(), width * height, "grid size");
        assert!(resolution > 0.0, "resolution");
        let edt = distance_transform(width, height, &occupied);
        let tiles_x = width.div_ceil(TILE);
        let tiles_y = height.div_ceil(TILE);
        let mut edt_tiles = vec![0u8; tiles_x * tiles_y * TILE * TILE];
        for j in 0..height {
            for i in 0..width {
                edt_tiles[tile_index(tiles_x, i, j)] = edt[j * width + i];
            }
        }
        let coarse_x = width.div_ceil(COARSE);
        let coarse_y = height.div_ceil(COARSE);
        let mut coarse = vec![u8::MAX; coarse_x * coarse_y];
        for j in 0..height {
            for i in 0..width {
                let c = &mut coarse[(j / COARSE) * coarse_x + i / COARSE];
                *c = (*c).min(edt[j * width + i]);
            }
        }
        OccupancyMap {
            width,
            height,
            resolution,
            origin,
            edt_tiles,
            tiles_x,
            coarse,
            coarse_x,
            walls: Walls::new(width, height, &occupied),
            occupied,
        }
    }

    /// Loads a ROS map_server YAML and the PGM/PNG image it names (relative to the YAML).
    pub fn load(yaml_path: &Path) -> Result<Self, MapError> {
        let path = yaml_path.display().to_string();
        let text = std::fs::read_to_string(yaml_path).map_err(|source| MapError::Io {
            path: path.clone(),
            source,
        })?;
        let y: MapYaml = serde_norway::from_str(&text).map_err(|e| MapError::Yaml {
            path: path.clone(),
            detail: e.to_string(),
        })?;
        let invalid = |detail: String| MapError::Invalid {
            path: path.clone(),
            detail,
        };
        if !(y.resolution.is_finite() && y.resolution > 0.0) {
            return Err(invalid(format!(
                "resolution must be > 0, got {}",
                y.resolution
            )));
        }
        if y.origin.len() != 3 || y.origin.iter().any(|v| !v.is_finite()) {
            return Err(invalid("origin must be [x, y, yaw]".into()));
        }
        if y.origin[2] != 0.0 {
            return Err(invalid(
                "rotated maps (origin yaw ≠ 0) are not supported".into(),
            ));
        }
        let ok = |t: f64| (0.0..=1.0).contains(&t);
        if !ok(y.occupied_thresh) || !ok(y.free_thresh) || y.free_thresh > y.occupied_thresh {
            return Err(invalid(
                "thresholds must satisfy 0 ≤ free_thresh ≤ occupied_thresh ≤ 1".into(),
            ));
        }
        let image_path = yaml_path.parent().unwrap_or(Path::new(".")).join(&y.image);
        let img = image::open(&image_path)
            .map_err(|e| MapError::Image {
                path: image_path.display().to_string(),
                detail: e.to_string(),
            })?
            .to_luma8();
        let (w, h) = (img.width() as usize, img.height() as usize);
        if w == 0 || h == 0 || w.saturating_mul(h) > MAX_CELLS {
            return Err(invalid(format!(
                "image of {w}x{h} cells: must be 1..={MAX_CELLS} cells"
            )));
        }
        let mut occupied = vec![false; w * h];
        for (x, yy, p) in img.enumerate_pixels() {
            let v = f64::from(p.0[0]) / 255.0;
            let occ = if y.negate == 0 { 1.0 - v } else { v };
            // Unknown (between the thresholds) counts as occupied: robots stay out.
            let blocked = occ > y.free_thresh;
            let row = h - 1 - yy as usize; // image row 0 is the top
            occupied[row * w + x as usize] = blocked;
        }
        Ok(Self::from_grid(
            w,
            h,
            y.resolution,
            (y.origin[0], y.origin[1]),
            occupied,
        ))
    }

    /// Writes the map as map_server YAML plus a PGM image named `stem.pgm` beside it.
    pub fn save(&self, yaml_path: &Path) -> std::io::Result<()> {
        let stem = yaml_path
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("map");
        let pgm = format!("{stem}.pgm");
        let mut img = image::GrayImage::new(self.width as u32, self.height as u32);
        for j in 0..self.height {
            for i in 0..self.width {
                let v = if self.occupied[j * self.width + i] {
                    0
                } else {
                    254
                };
                img.put_pixel(i as u32, (self.height - 1 - j) as u32, image::Luma([v]));
            }
        }
        let dir = yaml_path.parent().unwrap_or(Path::new("."));
        img.save(dir.join(&pgm)).map_err(std::io::Error::other)?;
        std::fs::write(
            yaml_path,
            format!(
                "image: {pgm}\nresolution: {}\norigin: [{}, {}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
                self.resolution, self.origin.0, self.origin.1
            ),
        )
    }

    /// The paper's Figure 3, roughly: an office floor of 40 m × 20 m with a corridor
    /// loop around two rows of offices, doors into every office, a lab and a lobby.
    pub fn office() -> Self {
        let res = 0.05;
        let (w, h) = (800usize, 400usize);
        let mut g = Grid {
            w,
            h,
            res,
            cells: vec![false; w * h],
        };
        // Outer walls, 0.2 m thick.
        g.rect(0.0, 0.0, 40.0, 0.2);
        g.rect(0.0, 19.8, 40.0, 20.0);
        g.rect(0.0, 0.0, 0.2, 20.0);
        g.rect(39.8, 0.0, 40.0, 20.0);
        // Corridors: a loop at y 2..4 and 16..18, x 2..4 and 36..38, and a middle one at y 9..11.
        // Office blocks are the areas between corridors; their walls have doors.
        let blocks = [(4.0, 4.0, 36.0, 9.0), (4.0, 11.0, 36.0, 16.0)];
        for &(x0, y0, x1, y1) in &blocks {
            g.rect(x0, y0, x1, y0 + 0.1);
            g.rect(x0, y1 - 0.1, x1, y1);
            g.rect(x0, y0, x0 + 0.1, y1);
            g.rect(x1 - 0.1, y0, x1, y1);
            // Offices 4 m wide, separated by walls, each with a 1 m door on a corridor side.
            let mut x = x0 + 4.0;
            while x < x1 - 0.5 {
                g.rect(x - 0.05, y0, x + 0.05, y1);
                x += 4.0;
            }
            let mut x = x0;
            let mut k = 0;
            while x < x1 - 0.5 {
                let door_y = if k % 2 == 0 { y0 } else { y1 - 0.1 };
                g.clear(x + 1.5, door_y - 0.05, x + 2.5, door_y + 0.15);
                x += 4.0;
                k += 1;
            }
        }
        // The outer band between corridor and outer wall: a lab (west) and lobby (east),
        // separated from the rest by walls with wide openings.
        g.rect(0.2, 4.0, 2.0, 4.1);
        g.rect(38.0, 15.9, 39.8, 16.0);
        Self::from_grid(w, h, res, (0.0, 0.0), g.cells)
    }

    /// This map with discs `(x, y, radius)` (m) marked occupied: fixtures that are
    /// not walls, such as robots that never move.
    pub fn with_discs(&self, discs: &[(f64, f64, f64)]) -> Self {
        let mut cells = self.occupied.clone();
        let res = self.resolution;
        for &(x, y, r) in discs {
            if !(x.is_finite() && y.is_finite() && r.is_finite() && r > 0.0) {
                continue;
            }
            let cells_r = (r / res).ceil() as i64 + 1;
            let ci = ((x - self.origin.0) / res).floor() as i64;
            let cj = ((y - self.origin.1) / res).floor() as i64;
            for j in (cj - cells_r)..=(cj + cells_r) {
                for i in (ci - cells_r)..=(ci + cells_r) {
                    if i < 0 || j < 0 || i as usize >= self.width || j as usize >= self.height {
                        continue;
                    }
                    let (cx, cy) = (
                        self.origin.0 + (i as f64 + 0.5) * res,
                        self.origin.1 + (j as f64 + 0.5) * res,
                    );
                    if (cx - x).hypot(cy - y) <= r {
                        cells[j as usize * self.width + i as usize] = true;
                    }
                }
            }
        }
        Self::from_grid(self.width, self.height, res, self.origin, cells)
    }

    /// Tiles this map `nx` × `ny` times (for large benchmark worlds at the same density).
    pub fn tiled(&self, nx: usize, ny: usize) -> Self {
        let (w, h) = (self.width * nx, self.height * ny);
        let mut cells = vec![false; w * h];
        for j in 0..h {
            for i in 0..w {
                cells[j * w + i] = self.occupied[(j % self.height) * self.width + (i % self.width)];
            }
        }
        Self::from_grid(w, h, self.resolution, self.origin, cells)
    }

    /// Width in cells.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in cells.
    pub fn height(&self) -> usize {
        self.height
    }
    /// Cell size, metres.
    pub fn resolution(&self) -> f64 {
        self.resolution
    }
    /// World coordinates of the lower-left corner.
    pub fn origin(&self) -> (f64, f64) {
        self.origin
    }
    /// Size in metres.
    pub fn size(&self) -> (f64, f64) {
        (
            self.width as f64 * self.resolution,
            self.height as f64 * self.resolution,
        )
    }

    /// The cell holding a point, if inside the map.
    pub fn cell(&self, x: f64, y: f64) -> Option<(usize, usize)> {
        grid_cell(
            (x - self.origin.0) / self.resolution,
            (y - self.origin.1) / self.resolution,
            self.width,
            self.height,
        )
    }

    /// Whether a cell is occupied (outside the map counts as occupied).
    pub fn occupied(&self, i: i64, j: i64) -> bool {
        if i < 0 || j < 0 || i as usize >= self.width || j as usize >= self.height {
            return true;
        }
        self.occupied[j as usize * self.width + i as usize]
    }

    /// Whether the point lies in an occupied cell or outside the map.
    pub fn blocked(&self, x: f64, y: f64) -> bool {
        match self.cell(x, y) {
            Some((i, j)) => self.occupied[j * self.width + i],
            None => true,
        }
    }

    /// A lower bound on the distance from (x, y) to any occupied square, metres (beyond
    /// the map's edge counts as occupied).
    /// It reads the field's 4 × 4-cell block minimum, a table 16 times smaller than the
    /// field that stays in cache on maps of hundreds of floors.
    pub fn distance_bound(&self, x: f64, y: f64) -> f64 {
        match self.cell(x, y) {
            Some((i, j)) => {
                let block = self.coarse[(j / COARSE) * self.coarse_x + i / COARSE];
                let d = f64::from(block) * self.resolution;
                let (ox, oy) = self.origin;
                let (w, h) = self.size();
                let edge = (x - ox).min(ox + w - x).min(y - oy).min(oy + h - y);
                (d - self.resolution * std::f64::consts::SQRT_2)
                    .min(edge)
                    .max(0.0)
            }
            None => 0.0,
        }
    }

    /// The exact distance from (x, y) to the nearest occupied square, or `limit` if none
    /// is within `limit` metres (from the walls as segments, see [`crate::walls`]).
    pub fn clearance(&self, x: f64, y: f64, limit: f64) -> f64 {
        let bound = self.distance_bound(x, y);
        if bound >= limit {
            return limit;
        }
        if self.blocked(x, y) {
            return 0.0;
        }
        let inv_res = 1.0 / self.resolution;
        let (px, py) = ((x - self.origin.0) * inv_res, (y - self.origin.1) * inv_res);
        (self.walls.clearance(px, py, limit * inv_res) * self.resolution).min(limit)
    }

    /// Whether nothing on the map stands on the straight line from `from` to `to`: what
    /// a laser or camera at `from` could see at `to`, or a walk from one to the other
    /// the walls leave open.
    pub fn in_sight(&self, from: (f64, f64), to: (f64, f64)) -> bool {
        let (dx, dy) = (to.0 - from.0, to.1 - from.1);
        self.raycast(from.0, from.1, dy.atan2(dx), dx.hypot(dy))
            .is_none()
    }

    /// Casts a ray from (x, y) along `angle`; the distance to the first occupied square,
    /// or `None` if there is none within `max` metres.
    pub fn raycast(&self, x: f64, y: f64, angle: f64, max: f64) -> Option<f64> {
        self.raycast_dir(x, y, angle.cos(), angle.sin(), max)
    }

    /// [`OccupancyMap::raycast`] along a unit direction (dx, dy).
    pub fn raycast_dir(&self, x: f64, y: f64, dx: f64, dy: f64, max: f64) -> Option<f64> {
        let mut ray = Ray::new(self, x, y, dx, dy, max);
        loop {
            if let Some(hit) = ray.turn(self) {
                return hit;
            }
        }
    }

    /// Casts one ray per unit direction in `dirs` from (x, y); `out[k]` is the distance
    /// to the first occupied square along `dirs[k]`, or `max`. The same distances as
    /// [`OccupancyMap::raycast_dir`] (to rounding), found against the walls as segments
    /// (see [`crate::walls`]): a laser scan costs a few tests per beam wherever it is.
    pub fn raycast_batch(&self, x: f64, y: f64, dirs: &[(f64, f64)], max: f64, out: &mut Vec<f64>) {
        out.clear();
        out.resize(dirs.len(), max);
        let inv_res = 1.0 / self.resolution;
        let (px, py) = ((x - self.origin.0) * inv_res, (y - self.origin.1) * inv_res);
        let free = grid_cell(px, py, self.width, self.height)
            .is_some_and(|(i, j)| !self.occupied[j * self.width + i]);
        if !free {
            // Outside the map or inside a wall: every ray ends where it starts.
            out.fill(0.0);
            return;
        }
        self.walls.cast(
            self,
            px,
            py,
            dirs,
            max * inv_res,
            (self.resolution, max),
            out,
        );
    }

    /// Wall segments the batched ray casts test against (for figures).
    pub fn wall_segments(&self) -> usize {
        self.walls.segments()
    }
}

/// One ray being cast, in cell units (single rays: [`OccupancyMap::raycast_dir`]). Far
/// from walls it jumps by the distance bound; near them it walks one cell at a time
/// (Amanatides–Woo), so a hit is the exact entry into an occupied square.
struct Ray {
    gx: f64,
    gy: f64,
    dx: f64,
    dy: f64,
    inv_dx: f64,
    inv_dy: f64,
    /// 1 when the ray heads to +x (or runs parallel to x), 0 when to -x: the cell edge
    /// it leaves through is at `i + off_x`. Likewise for y.
    off_x: f64,
    off_y: f64,
    t: f64,
    max_t: f64,
    /// Where the ray leaves the map (0 if it starts outside): the map's edge counts as a
    /// wall, and the distance field, which knows only occupied cells, may jump past it.
    exit_t: f64,
    turns: u64,
}

/// Below this many cells from a wall a ray walks cell by cell.
const NEAR: f64 = 2.0 + std::f64::consts::SQRT_2;

impl Ray {
    fn new(map: &OccupancyMap, x: f64, y: f64, dx: f64, dy: f64, max: f64) -> Self {
        // Components this small (cos(π/2) ≈ 6e-17) would make a step along them vanish.
        let tidy = |c: f64| if c.abs() < 1e-12 { 0.0 } else { c };
        let (dx, dy) = (tidy(dx), tidy(dy));
        let inv_res = 1.0 / map.resolution;
        let max_t = max * inv_res;
        let (gx, gy) = ((x - map.origin.0) * inv_res, (y - map.origin.1) * inv_res);
        let (w, h) = (map.width as f64, map.height as f64);
        let exit = |g: f64, d: f64, size: f64| {
            if d > 0.0 {
                (size - g) / d
            } else if d < 0.0 {
                -g / d
            } else {
                f64::INFINITY
            }
        };
        let exit_t = if gx >= 0.0 && gy >= 0.0 && gx < w && gy < h {
            exit(gx, dx, w).min(exit(gy, dy, h))
        } else {
            0.0
        };
        Ray {
            gx,
            gy,
            dx,
            dy,
            inv_dx: if dx != 0.0 { 1.0 / dx } else { f64::INFINITY },
            inv_dy: if dy != 0.0 { 1.0 / dy } else { f64::INFINITY },
            off_x: if dx < 0.0 { 0.0 } else { 1.0 },
            off_y: if dy < 0.0 { 0.0 } else { 1.0 },
            t: 0.0,
            max_t,
            exit_t,
            // A few turns per cell crossed at most.
            turns: (4.0 * max_t) as u64 + 64,
        }
    }

    /// One jump or one cell; `Some(result)` once the ray is done.
    #[inline(always)]
    fn turn(&mut self, map: &OccupancyMap) -> Option<Option<f64>> {
        if self.t >= self.exit_t {
            return Some((self.exit_t <= self.max_t).then_some(self.exit_t * map.resolution));
        }
        if self.t > self.max_t || self.turns == 0 {
            return Some(None);
        }
        self.turns -= 1;
        let t = self.t;
        let (px, py) = (self.gx + self.dx * t, self.gy + self.dy * t);
        let Some((i, j)) = grid_cell(px, py, map.width, map.height) else {
            return Some(Some(t * map.resolution)); // the map's edge counts as a wall
        };
        // Every cell of the coarse block is at least this far from a wall.
        let c = f64::from(map.coarse[(j / COARSE) * map.coarse_x + i / COARSE]);
        if c > NEAR {
            self.t += c - std::f64::consts::SQRT_2;
            return None;
        }
        let e = f64::from(map.edt_tiles[tile_index(map.tiles_x, i, j)]);
        if e > NEAR {
            self.t += e - std::f64::consts::SQRT_2;
            return None;
        }
        if e == 0.0 {
            return Some(Some(t * map.resolution)); // occupied
        }
        // Branch-free: for a zero component, off = 1 makes the distance to the edge
        // positive, so it times an infinite inverse to infinity (never NaN).
        let tx = (i as f64 + self.off_x - px) * self.inv_dx;
        let ty = (j as f64 + self.off_y - py) * self.inv_dy;
        // A hair past the boundary so the next cell is the neighbour.
        self.t += tx.min(ty).max(0.0) + 1e-9 * (1.0 + t);
        None
    }
}

/// The cell (column, row) at grid coordinates `(u, v)` (in cells from the origin) on
/// a `w` × `h` grid, if on it; NaN is off it. The same as flooring both and checking
/// the bounds, without `floor`, a library call on x86-64's baseline: for a coordinate
/// not below zero truncation is the floor, and one too large to fit saturates.
#[inline]
pub fn grid_cell(u: f64, v: f64, w: usize, h: usize) -> Option<(usize, usize)> {
    if !(u >= 0.0 && v >= 0.0) {
        return None;
    }
    let (i, j) = (u as usize, v as usize);
    (i < w && j < h).then_some((i, j))
}

#[inline]
fn tile_index(tiles_x: usize, i: usize, j: usize) -> usize {
    ((j / TILE) * tiles_x + i / TILE) * (TILE * TILE) + (j % TILE) * TILE + i % TILE
}

struct Grid {
    w: usize,
    h: usize,
    res: f64,
    cells: Vec<bool>,
}

impl Grid {
    fn span(&self, x0: f64, y0: f64, x1: f64, y1: f64) -> (usize, usize, usize, usize) {
        let c = |v: f64, n: usize| ((v / self.res).round().max(0.0) as usize).min(n);
        (c(x0, self.w), c(y0, self.h), c(x1, self.w), c(y1, self.h))
    }
    fn set(&mut self, x0: f64, y0: f64, x1: f64, y1: f64, v: bool) {
        let (i0, j0, i1, j1) = self.span(x0, y0, x1, y1);
        for j in j0..j1.max(j0 + 1).min(self.h) {
            for i in i0..i1.max(i0 + 1).min(self.w) {
                self.cells[j * self.w + i] = v;
            }
        }
    }
    fn rect(&mut self, x0: f64, y0: f64, x1: f64, y1: f64) {
        self.set(x0, y0, x1, y1, true);
    }
    fn clear(&mut self, x0: f64, y0: f64, x1: f64, y1: f64) {
        self.set(x0, y0, x1, y1, false);
    }
}

/// Exact Euclidean distance transform (Felzenszwalb & Huttenlocher), in cells, from
/// every cell centre to the nearest occupied cell centre.
fn distance_transform(w: usize, h: usize, occupied: &[bool]) -> Vec<u8> {
    const INF: f64 = 1e20;
    let mut f: Vec<f64> = occupied
        .iter()
        .map(|&o| if o { 0.0 } else { INF })
        .collect();
    let n = w.max(h);
    let (mut d, mut v, mut z, mut col) = (
        vec![0.0; n],
        vec![0usize; n],
        vec![0.0; n + 1],
        vec![0.0; n],
    );
    let mut edt_1d = |src: &[f64], len: usize, out: &mut [f64]| {
        let mut k = 0usize;
        v[0] = 0;
        z[0] = f64::NEG_INFINITY;
        z[1] = f64::INFINITY;
        for q in 1..len {
            loop {
                let p = v[k];
                let s = ((src[q] + (q * q) as f64) - (src[p] + (p * p) as f64))
                    / (2.0 * q as f64 - 2.0 * p as f64);
                if s <= z[k] && k > 0 {
                    k -= 1;
                } else if s <= z[k] {
                    // k == 0: replace the first parabola.
                    v[0] = q;
                    z[0] = f64::NEG_INFINITY;
                    z[1] = f64::INFINITY;
                    break;
                } else {
                    k += 1;
                    v[k] = q;
                    z[k] = s;
                    z[k + 1] = f64::INFINITY;
                    break;
                }
            }
        }
        k = 0;
        for (q, o) in out.iter_mut().enumerate().take(len) {
            while z[k + 1] < q as f64 {
                k += 1;
            }
            let p = v[k];
            *o = (q as f64 - p as f64).powi(2) + src[p];
        }
    };
    // Columns, then rows.
    for i in 0..w {
        for j in 0..h {
            col[j] = f[j * w + i];
        }
        edt_1d(&col[..h], h, &mut d[..h]);
        for j in 0..h {
            f[j * w + i] = d[j];
        }
    }
    for j in 0..h {
        let row: Vec<f64> = f[j * w..(j + 1) * w].to_vec();
        edt_1d(&row, w, &mut d[..w]);
        f[j * w..(j + 1) * w].copy_from_slice(&d[..w]);
    }
    f.into_iter()
        .map(|v| v.min(1e12).sqrt().floor().min(255.0) as u8)
        .collect()
}

/// A `w` × `h` cell room with one-cell walls on its border and extra occupied cells
/// `inside` (tests build small worlds with it).
pub fn walled_room(w: usize, h: usize, res: f64, inside: &[(usize, usize)]) -> OccupancyMap {
    OccupancyMap::from_grid(w, h, res, (0.0, 0.0), walled_cells(w, h, inside))
}

/// The occupied flags of [`walled_room`].
pub fn walled_cells(w: usize, h: usize, inside: &[(usize, usize)]) -> Vec<bool> {
    let mut occ = vec![false; w * h];
    for i in 0..w {
        occ[i] = true;
        occ[(h - 1) * w + i] = true;
    }
    for j in 0..h {
        occ[j * w] = true;
        occ[j * w + w - 1] = true;
    }
    for &(i, j) in inside {
        occ[j * w + i] = true;
    }
    occ
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A 10 m × 10 m room at 0.1 m with 0.1 m walls and a 1-cell pillar at (5.05, 5.05).
    fn room() -> OccupancyMap {
        walled_room(100, 100, 0.1, &[(50, 50)])
    }

    #[test]
    fn distance_transform_matches_brute_force() {
        let m = room();
        let edt = distance_transform(100, 100, &m.occupied);
        for &(i, j) in &[(10usize, 10usize), (50, 40), (47, 53), (2, 90), (70, 70)] {
            let mut best = f64::INFINITY;
            for jj in 0..100 {
                for ii in 0..100 {
                    if m.occupied[jj * 100 + ii] {
                        best = best.min(
                            ((ii as f64 - i as f64).powi(2) + (jj as f64 - j as f64).powi(2))
                                .sqrt(),
                        );
                    }
                }
            }
            assert_eq!(f64::from(edt[j * 100 + i]), best.floor(), "({i},{j})");
        }
    }

    #[test]
    fn rays_hit_walls_exactly() {
        let m = room();
        // From (2.05, 3.05) east: the wall's inner face is at x = 9.9.
        let d = m.raycast(2.05, 3.05, 0.0, 20.0).unwrap();
        assert!((d - (9.9 - 2.05)).abs() < 1e-6, "{d}");
        // West: inner face at x = 0.1.
        let d = m.raycast(2.05, 3.05, std::f64::consts::PI, 20.0).unwrap();
        assert!((d - 1.95).abs() < 1e-6, "{d}");
        // Diagonal up-right towards the pillar square [5.0, 5.1]²: from (4.0, 4.0) at 45°
        // the ray enters at (5.0, 5.0), √2 m away.
        let d = m
            .raycast(4.0, 4.0, std::f64::consts::FRAC_PI_4, 20.0)
            .unwrap();
        assert!((d - std::f64::consts::SQRT_2).abs() < 1e-6, "{d}");
        // Out of range.
        assert_eq!(m.raycast(2.05, 3.05, 0.0, 5.0), None);
        // Axis-aligned rays from exactly on a cell boundary (cos(π/2) is 6e-17, not 0).
        let d = m
            .raycast(2.0, 3.0, std::f64::consts::FRAC_PI_2, 20.0)
            .unwrap();
        assert!((d - 6.9).abs() < 1e-6, "{d}");
        let d = m
            .raycast(2.0, 3.0, -std::f64::consts::FRAC_PI_2, 20.0)
            .unwrap();
        assert!((d - 2.9).abs() < 1e-6, "{d}");
        // A shallow ray that grazes along the floor wall still ends at the east wall.
        let d = m.raycast(1.0, 0.15, 0.001, 20.0).unwrap();
        let expect = (9.9 - 1.0) / 0.001f64.cos();
        assert!((d - expect).abs() < 1e-3, "{d} vs {expect}");
    }

    #[test]
    fn batched_rays_equal_single_rays() {
        let m = room();
        let dirs: Vec<(f64, f64)> = (0..37)
            .map(|k| {
                let a = k as f64 * 0.17;
                (a.cos(), a.sin())
            })
            .collect();
        let mut out = Vec::new();
        m.raycast_batch(4.2, 3.3, &dirs, 6.0, &mut out);
        for (k, &(dx, dy)) in dirs.iter().enumerate() {
            let single = m.raycast_dir(4.2, 3.3, dx, dy, 6.0).unwrap_or(6.0);
            // The cell walk steps a hair past each boundary it crosses.
            assert!(
                (out[k] - single).abs() < 1e-6,
                "ray {k}: {} vs {single}",
                out[k]
            );
        }
        // Inside a wall, and outside the map: every ray ends where it starts.
        m.raycast_batch(0.05, 5.0, &dirs, 6.0, &mut out);
        assert!(out.iter().all(|&d| d == 0.0));
        m.raycast_batch(-1.0, 5.0, &dirs, 6.0, &mut out);
        assert!(out.iter().all(|&d| d == 0.0));
    }

    use proptest::prop_oneof;

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(1000))]
        /// The two ray casts, cell walk and segments, agree on random maps from random
        /// free points, in every direction, at any range.
        #[test]
        fn batched_rays_agree_with_the_cell_walk_on_random_maps(
            // Up to 10 buckets a side (320 cells), so that far buckets are culled.
            (w, h) in prop_oneof![(3usize..70, 3usize..70), (100usize..320, 100usize..320)],
            density in prop_oneof![0.0f64..0.5, 0.0f64..0.1],
            res in 0.03f64..0.3,
            origin in (-5.0f64..5.0, -5.0f64..5.0),
            seed in 0u64..u64::MAX,
            at in (0.0f64..1.0, 0.0f64..1.0),
            angles in proptest::collection::vec(-4.0f64..4.0, 1..200),
            max in prop_oneof![0.0f64..30.0, 0.0f64..300.0],
            on_lines in 0u8..4,
        ) {
            use rand::{RngExt, SeedableRng};
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            let occ: Vec<bool> = (0..w * h).map(|_| rng.random::<f64>() < density).collect();
            // Some origins on cell lines or corners, and some rays along the axes. On a
            // line, world and cell coordinates are kept exact (a power-of-two cell size,
            // an origin on the grid): 1e-16 off a corner, either answer is right.
            let (res, origin) = if on_lines == 0 {
                (res, origin)
            } else {
                let res = 2f64.powi(-((seed % 5) as i32 + 1));
                (res, ((origin.0 / res).round() * res, (origin.1 / res).round() * res))
            };
            let m = OccupancyMap::from_grid(w, h, res, origin, occ);
            let snap = |f: f64, n: usize, on: bool| if on { (f * n as f64).round() } else { f * n as f64 };
            let (gx, gy) = (snap(at.0, w, on_lines & 1 == 1), snap(at.1, h, on_lines & 2 == 2));
            let (x, y) = (origin.0 + gx * res, origin.1 + gy * res);
            let angles: Vec<f64> = angles
                .iter()
                .enumerate()
                .map(|(k, &a)| if k % 4 == 0 { (a * 2.0).round() * std::f64::consts::FRAC_PI_2 } else { a })
                .collect();
            let dirs: Vec<(f64, f64)> = angles.iter().map(|a| (a.cos(), a.sin())).collect();
            let mut out = Vec::new();
            m.raycast_batch(x, y, &dirs, max, &mut out);
            proptest::prop_assert_eq!(out.len(), dirs.len());
            for (k, &(dx, dy)) in dirs.iter().enumerate() {
                let single = m.raycast_dir(x, y, dx, dy, max).unwrap_or(max);
                proptest::prop_assert!(
                    (out[k] - single).abs() < 1e-6,
                    "ray {} at {:.4} rad: batch {} vs walk {}", k, angles[k], out[k], single
                );
            }
        }
    }

    /// Offices (corridors, rooms, doors) are where walls hide walls: the far buckets a
    /// cast skips must never hold a nearer hit.
    #[test]
    fn batched_rays_agree_with_the_cell_walk_in_a_tiled_office() {
        use rand::{RngExt, SeedableRng};
        let m = OccupancyMap::office().tiled(2, 2);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let (w, h) = m.size();
        let mut out = Vec::new();
        let mut origins = 0;
        while origins < 300 {
            let (x, y) = (rng.random::<f64>() * w, rng.random::<f64>() * h);
            if m.blocked(x, y) {
                continue;
            }
            origins += 1;
            let first = rng.random::<f64>() * std::f64::consts::TAU;
            let dirs: Vec<(f64, f64)> = (0..181)
                .map(|k| {
                    let a = first + k as f64 * std::f64::consts::PI / 180.0;
                    (a.cos(), a.sin())
                })
                .collect();
            let max = if origins % 2 == 0 { 8.0 } else { 30.0 };
            m.raycast_batch(x, y, &dirs, max, &mut out);
            for (k, &(dx, dy)) in dirs.iter().enumerate() {
                let single = m.raycast_dir(x, y, dx, dy, max).unwrap_or(max);
                assert!(
                    (out[k] - single).abs() < 1e-6,
                    "from ({x:.3}, {y:.3}) ray {k}: batch {} vs walk {single}",
                    out[k]
                );
            }
        }
    }

    #[test]
    fn grid_cells_are_the_floored_coordinates_within_bounds() {
        let floored = |u: f64, v: f64, w: usize, h: usize| {
            let (i, j) = (u.floor(), v.floor());
            (i >= 0.0 && j >= 0.0 && (i as usize) < w && (j as usize) < h)
                .then_some((i as usize, j as usize))
        };
        let special = [
            0.0,
            -0.0,
            -1e-300,
            1e-300,
            0.999_999_999_999,
            1.0,
            -1.0,
            -0.5,
            9.999_999,
            10.0,
            10.5,
            1e30,
            -1e30,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            f64::MAX,
            f64::MIN_POSITIVE,
        ];
        for &u in &special {
            for &v in &special {
                assert_eq!(grid_cell(u, v, 10, 7), floored(u, v, 10, 7), "({u}, {v})");
            }
        }
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        for _ in 0..100_000 {
            let (u, v) = (rng.random_range(-20.0..40.0), rng.random_range(-20.0..40.0));
            assert_eq!(grid_cell(u, v, 17, 23), floored(u, v, 17, 23), "({u}, {v})");
        }
    }

    /// Clearance the slow way: every square within reach.
    fn clearance_by_squares(m: &OccupancyMap, x: f64, y: f64, limit: f64) -> f64 {
        if m.blocked(x, y) {
            return 0.0;
        }
        let r = m.resolution;
        let (ox, oy) = m.origin;
        let reach = (limit / r).ceil() as i64 + 1;
        let ci = ((x - ox) / r).floor() as i64;
        let cj = ((y - oy) / r).floor() as i64;
        let mut best = limit;
        for j in cj - reach..=cj + reach {
            for i in ci - reach..=ci + reach {
                if m.occupied(i, j) {
                    let (x0, y0) = (ox + i as f64 * r, oy + j as f64 * r);
                    let dx = (x0 - x).max(0.0).max(x - (x0 + r));
                    let dy = (y0 - y).max(0.0).max(y - (y0 + r));
                    best = best.min(dx.hypot(dy));
                }
            }
        }
        best
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(500))]
        /// Clearance from the segments equals the distance to the nearest square.
        #[test]
        fn clearance_equals_the_nearest_square_on_random_maps(
            (w, h) in (3usize..70, 3usize..70),
            density in 0.0f64..0.3,
            res in 0.03f64..0.3,
            seed in 0u64..u64::MAX,
            points in proptest::collection::vec((0.0f64..1.0, 0.0f64..1.0), 1..40),
            limit in 0.0f64..3.0,
        ) {
            use rand::{RngExt, SeedableRng};
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            let occ: Vec<bool> = (0..w * h).map(|_| rng.random::<f64>() < density).collect();
            let m = OccupancyMap::from_grid(w, h, res, (-1.0, 2.0), occ);
            for (fx, fy) in points {
                let (x, y) = (-1.0 + fx * w as f64 * res, 2.0 + fy * h as f64 * res);
                let fast = m.clearance(x, y, limit);
                let slow = clearance_by_squares(&m, x, y, limit);
                proptest::prop_assert!((fast - slow).abs() < 1e-9, "at ({}, {}): {} vs {}", x, y, fast, slow);
            }
        }
    }

    #[test]
    fn clearance_is_exact_near_walls() {
        let m = room();
        assert!((m.clearance(0.35, 5.55, 1.0) - 0.25).abs() < 1e-9);
        // Corner of the pillar: nearest point (5.0, 5.0) from (4.7, 4.6) is 0.5 away.
        assert!((m.clearance(4.7, 4.6, 1.0) - 0.5).abs() < 1e-9);
        assert_eq!(m.clearance(3.0, 3.0, 0.5), 0.5, "capped at the limit");
        assert_eq!(m.clearance(0.05, 0.05, 1.0), 0.0, "inside a wall");
    }

    #[test]
    fn save_and_load_round_trip_and_bad_files_fail_clearly() {
        let dir = std::env::temp_dir().join(format!("muster-map-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let m = room();
        let yaml = dir.join("room.yaml");
        m.save(&yaml).unwrap();
        let back = OccupancyMap::load(&yaml).unwrap();
        assert_eq!(
            (back.width(), back.height(), back.resolution()),
            (100, 100, 0.1)
        );
        assert_eq!(back.occupied, m.occupied);

        std::fs::write(
            dir.join("bad1.yaml"),
            "image: room.pgm\nresolution: 0\norigin: [0, 0, 0]\n",
        )
        .unwrap();
        assert!(matches!(
            OccupancyMap::load(&dir.join("bad1.yaml")),
            Err(MapError::Invalid { .. })
        ));
        std::fs::write(
            dir.join("bad2.yaml"),
            "image: nosuch.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n",
        )
        .unwrap();
        assert!(matches!(
            OccupancyMap::load(&dir.join("bad2.yaml")),
            Err(MapError::Image { .. })
        ));
        std::fs::write(dir.join("bad3.yaml"), "resolution: [oops\n").unwrap();
        assert!(matches!(
            OccupancyMap::load(&dir.join("bad3.yaml")),
            Err(MapError::Yaml { .. })
        ));
        std::fs::write(
            dir.join("bad4.yaml"),
            "image: room.pgm\nresolution: 0.1\norigin: [0, 0]\n",
        )
        .unwrap();
        let e = OccupancyMap::load(&dir.join("bad4.yaml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("origin must be [x, y, yaw]"), "{e}");
        std::fs::write(dir.join("notimage.pgm"), "P5 garbage").unwrap();
        std::fs::write(
            dir.join("bad5.yaml"),
            "image: notimage.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n",
        )
        .unwrap();
        assert!(matches!(
            OccupancyMap::load(&dir.join("bad5.yaml")),
            Err(MapError::Image { .. })
        ));
        assert!(matches!(
            OccupancyMap::load(&dir.join("missing.yaml")),
            Err(MapError::Io { .. })
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_office_is_40_by_20_with_corridors() {
        let m = OccupancyMap::office();
        assert_eq!(m.size(), (40.0, 20.0));
        // Corridors are free; office block walls are not.
        assert!(!m.blocked(3.0, 3.0));
        assert!(!m.blocked(20.0, 10.0));
        assert!(!m.blocked(20.0, 17.0));
        assert!(m.blocked(20.0, 0.1));
        // A corridor is long: a ray along the middle corridor runs ~30 m before a wall.
        assert!(m.raycast(3.0, 10.0, 0.0, 50.0).unwrap() > 30.0);
    }
}
