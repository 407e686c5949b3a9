//! Exact ray casts in batches, against the map's walls as segments.
//!
//! Every boundary between a free and an occupied cell (beyond the map's edge counts as
//! occupied) lies on a cell line. Neighbouring boundaries on one line that face the same
//! way are merged into a segment, and each segment is filed in the square buckets it
//! crosses, cut at their borders. A ray leaving free space first crosses a boundary from
//! its free side, so a cast looks only at the segments in range whose free side faces the
//! origin, and tests each against only the rays whose direction lies within the angle it
//! subtends. To find those rays cheaply, a cast first sorts its rays into bins of
//! pseudo-angle (a cheap function of direction that grows with the angle): the rays a
//! segment can hit are then one or two contiguous runs, and each test is a few
//! multiplications with no data-dependent branch.
//!
//! Cost: per segment in range and facing the origin, two divisions; per ray, the segments
//! in its direction within range (about the number of walls it would pass through). A
//! cell-by-cell walk costs a step per cell near a wall, and a ray grazing a wall is near
//! it all the way; here that ray costs one test.

use crate::map::OccupancyMap;
use std::cell::RefCell;

/// Side of a bucket, cells.
const BUCKET: usize = 32;
/// Pseudo-angle bins a cast sorts its rays into (a bin number fits a byte).
const BINS: usize = 256;
/// An origin this close to a segment's end (cells) sees it at every angle.
const EPS: f64 = 1e-9;

/// One segment on a cell line: the line's coordinate `c` (y for a horizontal segment, x
/// for a vertical one) and its span `[a, b)` along the line, in cells.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Seg {
    c: f64,
    a: f64,
    b: f64,
}

/// The four ways a boundary faces, by where its free side is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Facing {
    /// Horizontal, free below: hit by rays going up.
    Down,
    /// Horizontal, free above: hit by rays going down.
    Up,
    /// Vertical, free on the left: hit by rays going right.
    Left,
    /// Vertical, free on the right: hit by rays going left.
    Right,
}

const FACINGS: [Facing; 4] = [Facing::Down, Facing::Up, Facing::Left, Facing::Right];

/// The segments of one facing, by bucket: bucket `k`'s are `segs[start[k]..start[k + 1]]`.
#[derive(Clone, Debug, Default)]
struct Filed {
    start: Vec<u32>,
    segs: Vec<Seg>,
}

/// The map's walls as segments, for batched ray casts.
#[derive(Clone, Debug)]
pub(crate) struct Walls {
    buckets_x: usize,
    buckets_y: usize,
    /// Indexed like [`FACINGS`].
    filed: [Filed; 4],
}

/// Whether the cell a ray enters after the grid corner (`vx`, `vy`), going along (`dx`,
/// `dy`), is occupied (outside the map counts). Cells are half-open: a ray running along
/// the line x = i is in column i.
#[cold]
fn occupied_beyond(map: &OccupancyMap, vx: f64, vy: f64, dx: f64, dy: f64) -> bool {
    map.occupied(
        vx as i64 - i64::from(dx < 0.0),
        vy as i64 - i64::from(dy < 0.0),
    )
}

/// One ray of a cast, as the tests read it.
#[derive(Clone, Copy, Default)]
struct RayDir {
    dx: f64,
    dy: f64,
    inv_dx: f64,
    inv_dy: f64,
}

/// Per-cast working memory, kept per thread so that a cast allocates nothing.
#[derive(Default)]
struct Scratch {
    /// The rays sorted by bin; bin k's are `rays[start[k]..start[k + 1]]`.
    rays: Vec<RayDir>,
    /// The nearest hit so far of each sorted ray, cells.
    best: Vec<f64>,
    /// Each sorted ray's index in the caller's list.
    index: Vec<u32>,
    bin_of: Vec<u8>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// A pseudo-angle of (x, y) in [0, 4): 0 along +x, 1 along +y, 2 along -x, 3 along -y,
/// growing with the angle in between (but not in proportion to it).
#[inline(always)]
fn pseudo_angle(x: f64, y: f64) -> f64 {
    let q = y / (x.abs() + y.abs());
    if x < 0.0 {
        2.0 - q
    } else if q < 0.0 {
        4.0 + q
    } else {
        q
    }
}

#[inline(always)]
fn bin(p: f64) -> usize {
    // p < 4, so this is below 256; the cast saturates anyway.
    usize::from((p * (BINS as f64 / 4.0)) as u8)
}

impl Walls {
    /// The segments of a `width` × `height` grid of occupied flags (row 0 at the bottom).
    pub(crate) fn new(width: usize, height: usize, occupied: &[bool]) -> Self {
        let occ = |i: usize, j: usize| occupied[j * width + i];
        let buckets_x = width.div_ceil(BUCKET).max(1);
        let buckets_y = height.div_ceil(BUCKET).max(1);
        let mut found: [Vec<(u32, Seg)>; 4] = Default::default();
        // Runs along one line: `facing(k)` says how position k on the line faces (if it
        // is a boundary); runs are cut where the facing changes and at bucket borders.
        let mut runs = |len: usize,
                        c: usize,
                        facing: &dyn Fn(usize) -> Option<Facing>,
                        bucket: &dyn Fn(usize) -> usize| {
            let mut k = 0;
            while k < len {
                let Some(f) = facing(k) else {
                    k += 1;
                    continue;
                };
                let from = k;
                k += 1;
                while k < len && k % BUCKET != 0 && facing(k) == Some(f) {
                    k += 1;
                }
                let seg = Seg {
                    c: c as f64,
                    a: from as f64,
                    b: k as f64,
                };
                let slot = FACINGS.iter().position(|&g| g == f).unwrap_or(0);
                found[slot].push((bucket(from) as u32, seg));
            }
        };
        for j in 0..=height {
            let row = (j / BUCKET).min(buckets_y - 1);
            let facing = |i: usize| {
                let below = j == 0 || occ(i, j - 1);
                let above = j == height || occ(i, j);
                match (below, above) {
                    (false, true) => Some(Facing::Down),
                    (true, false) => Some(Facing::Up),
                    _ => None,
                }
            };
            runs(width, j, &facing, &|i| row * buckets_x + i / BUCKET);
        }
        for i in 0..=width {
            let col = (i / BUCKET).min(buckets_x - 1);
            let facing = |j: usize| {
                let left = i == 0 || occ(i - 1, j);
                let right = i == width || occ(i, j);
                match (left, right) {
                    (false, true) => Some(Facing::Left),
                    (true, false) => Some(Facing::Right),
                    _ => None,
                }
            };
            runs(height, i, &facing, &|j| (j / BUCKET) * buckets_x + col);
        }
        let filed = found.map(|mut list| {
            list.sort_by_key(|&(b, _)| b);
            let mut start = vec![0u32; buckets_x * buckets_y + 1];
            for &(b, _) in &list {
                start[b as usize + 1] += 1;
            }
            for k in 1..start.len() {
                start[k] += start[k - 1];
            }
            Filed {
                start,
                segs: list.into_iter().map(|(_, s)| s).collect(),
            }
        });
        Walls {
            buckets_x,
            buckets_y,
            filed,
        }
    }

    /// How many segments there are (for figures).
    pub(crate) fn segments(&self) -> usize {
        self.filed.iter().map(|f| f.segs.len()).sum()
    }

    /// The distance in cells from (`px`, `py`) (cells, in a free cell) to the nearest
    /// segment within `limit` cells, or `limit`. From a free point, the nearest occupied
    /// point lies on the boundary, so this is the distance to the nearest occupied cell.
    pub(crate) fn clearance(&self, px: f64, py: f64, limit: f64) -> f64 {
        let mut best_sq = limit * limit;
        for slot in 0..FACINGS.len() {
            let vertical = slot >= 2;
            let (u, v) = if vertical { (py, px) } else { (px, py) };
            let area = (px - limit, px + limit, py - limit, py + limit);
            self.each_filed_in(slot, area, |seg| {
                let along = (seg.a - u).max(u - seg.b).max(0.0);
                let across = seg.c - v;
                best_sq = best_sq.min(along * along + across * across);
            });
        }
        best_sq.sqrt()
    }

    /// Calls `f` for the segments of facing `slot` filed in the buckets that overlap the
    /// box `(x0, x1, y0, y1)` (cells; clamped to the map), a contiguous run per row.
    #[inline(always)]
    fn each_filed_in(
        &self,
        slot: usize,
        (x0, x1, y0, y1): (f64, f64, f64, f64),
        mut f: impl FnMut(&Seg),
    ) {
        let b = BUCKET as f64;
        // `as` saturates a negative coordinate to 0 and truncates the rest (floor).
        let bucket_x = |v: f64| ((v / b) as usize).min(self.buckets_x - 1);
        let bucket_y = |v: f64| ((v / b) as usize).min(self.buckets_y - 1);
        let (from_x, to_x) = (bucket_x(x0), bucket_x(x1));
        let filed = &self.filed[slot];
        for by in bucket_y(y0)..=bucket_y(y1) {
            let row = by * self.buckets_x;
            let from = filed.start[row + from_x] as usize;
            let to = filed.start[row + to_x + 1] as usize;
            filed.segs[from..to].iter().for_each(&mut f);
        }
    }

    /// Casts one ray per unit direction in `dirs` from (`px`, `py`) (cells, from the map's
    /// corner; the origin must be in a free cell); `out[k]` becomes the distance to where
    /// ray k enters an occupied cell, in cells times `scale`, or `miss` if that is not
    /// within `max_t` cells.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn cast(
        &self,
        map: &OccupancyMap,
        px: f64,
        py: f64,
        dirs: &[(f64, f64)],
        max_t: f64,
        (scale, miss): (f64, f64),
        out: &mut [f64],
    ) {
        SCRATCH.with(|s| {
            let s = &mut s.borrow_mut();
            self.cast_with(s, map, px, py, dirs, max_t);
            for (&best, &k) in s.best.iter().zip(&s.index) {
                if let Some(o) = out.get_mut(k as usize) {
                    *o = if best <= max_t { best * scale } else { miss };
                }
            }
        });
    }

    /// The cast itself: leaves each sorted ray's nearest hit in `s.best`.
    #[allow(clippy::too_many_arguments)]
    fn cast_with(
        &self,
        s: &mut Scratch,
        map: &OccupancyMap,
        px: f64,
        py: f64,
        dirs: &[(f64, f64)],
        max_t: f64,
    ) {
        let n = dirs.len();
        // Sort the rays by pseudo-angle bin (a counting sort).
        let mut start = [0u32; BINS + 1];
        s.bin_of.clear();
        s.bin_of
            .extend(dirs.iter().map(|&(dx, dy)| bin(pseudo_angle(dx, dy)) as u8));
        for &b in &s.bin_of {
            start[b as usize + 1] += 1;
        }
        for k in 1..=BINS {
            start[k] += start[k - 1];
        }
        s.rays.clear();
        s.rays.resize(n, RayDir::default());
        s.index.clear();
        s.index.resize(n, 0);
        s.best.clear();
        s.best.resize(n, f64::INFINITY);
        let mut next = start;
        // Components this small (cos(π/2) ≈ 6e-17) would send a ray's line to infinity.
        let tidy = |c: f64| if c.abs() < 1e-12 { 0.0 } else { c };
        for (k, (&(dx, dy), &b)) in dirs.iter().zip(&s.bin_of).enumerate() {
            let r = next[b as usize] as usize;
            next[b as usize] += 1;
            let (dx, dy) = (tidy(dx), tidy(dy));
            if let (Some(ray), Some(i)) = (s.rays.get_mut(r), s.index.get_mut(r)) {
                *ray = RayDir {
                    dx,
                    dy,
                    inv_dx: 1.0 / dx,
                    inv_dy: 1.0 / dy,
                };
                *i = k as u32;
            }
        }
        for (slot, facing) in FACINGS.iter().enumerate() {
            // The buckets that can hold a segment of this facing in range.
            let area = match facing {
                Facing::Down => (px - max_t, px + max_t, py, py + max_t),
                Facing::Up => (px - max_t, px + max_t, py - max_t, py),
                Facing::Left => (px, px + max_t, py - max_t, py + max_t),
                Facing::Right => (px - max_t, px, py - max_t, py + max_t),
            };
            self.each_filed_in(slot, area, |seg| match facing {
                Facing::Down => {
                    hits::<false, false>(s, &start, map, px, py, seg, seg.c - py, max_t)
                }
                Facing::Up => hits::<false, true>(s, &start, map, px, py, seg, py - seg.c, max_t),
                Facing::Left => hits::<true, false>(s, &start, map, px, py, seg, seg.c - px, max_t),
                Facing::Right => hits::<true, true>(s, &start, map, px, py, seg, px - seg.c, max_t),
            });
        }
    }
}

/// Tests the rays that can reach `seg` against it. `VERTICAL`: the segment lies on x =
/// c (else y = c). `DOWNWARDS`: it is hit by rays going to -x or -y (its free side faces
/// +x or +y). `gap` is the origin's distance to the segment's line on its free side
/// (negative: the origin is on the occupied side, so no ray can reach it first).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn hits<const VERTICAL: bool, const DOWNWARDS: bool>(
    s: &mut Scratch,
    start: &[u32; BINS + 1],
    map: &OccupancyMap,
    px: f64,
    py: f64,
    seg: &Seg,
    gap: f64,
    max_t: f64,
) {
    if !(gap >= 0.0 && gap <= max_t) {
        return;
    }
    // The segment's ends, from the origin; too far along the line to be in range: skip.
    let (u, v) = if VERTICAL { (py, px) } else { (px, py) };
    if seg.a - u > max_t || u - seg.b > max_t {
        return;
    }
    let end = |along: f64| {
        if VERTICAL {
            (seg.c - v, along - u)
        } else {
            (along - u, seg.c - v)
        }
    };
    let (ea, eb) = (end(seg.a), end(seg.b));
    // Going anticlockwise, which end's ray comes first: a horizontal segment above the
    // origin is swept from its b end (+x) to its a end; one below, from a to b; a
    // vertical one to the right, from a (-y) to b; one to the left, from b to a.
    let (first, last) = if VERTICAL != DOWNWARDS {
        (ea, eb)
    } else {
        (eb, ea)
    };
    // The runs of rays whose bins overlap the angle from `first` to `last`, with a bin
    // of slack each side for rounding.
    let (lo, hi) = if first.0.abs() + first.1.abs() < EPS || last.0.abs() + last.1.abs() < EPS {
        // The origin sits on an end: every ray is a candidate.
        (0, BINS as isize - 1)
    } else {
        let (pf, pl) = (pseudo_angle(first.0, first.1), pseudo_angle(last.0, last.1));
        let lo = bin(pf) as isize - 1;
        let hi = bin(pl) as isize + 1 + if pf > pl { BINS as isize } else { 0 };
        (lo, hi.min(lo + BINS as isize - 1))
    };
    let mut v_bin = lo;
    while v_bin <= hi {
        let real = v_bin.rem_euclid(BINS as isize) as usize;
        let take = ((hi - v_bin + 1) as usize).min(BINS - real);
        let (from, to) = (start[real] as usize, start[real + take] as usize);
        let (c, a, b) = (seg.c, seg.a, seg.b);
        let (Some(rays), Some(bests)) = (s.rays.get(from..to), s.best.get_mut(from..to)) else {
            return;
        };
        for (ray, best) in rays.iter().zip(bests) {
            let (t, along, d, inv) = if VERTICAL {
                let t = (c - px) * ray.inv_dx;
                (t, py + t * ray.dy, ray.dy, ray.inv_dx)
            } else {
                let t = (c - py) * ray.inv_dy;
                (t, px + t * ray.dx, ray.dx, ray.inv_dy)
            };
            // Heading into the segment's free side (a ray leaving a line it starts on
            // does not hit it), reaching it ahead and nearer, and within its span.
            let towards = if DOWNWARDS { inv < 0.0 } else { inv > 0.0 };
            let ahead = towards && t >= 0.0 && t < *best;
            let mut hit = ahead && along > a && along < b;
            if ahead && (along == a || along == b) {
                // Exactly at a grid corner (rare): the ray goes on into the cell beyond
                // it in its direction, which may be this segment's, or one diagonal to
                // it that no segment through the corner belongs to.
                let (vx, vy, dx, dy) = if VERTICAL {
                    (c, along, ray.dx, d)
                } else {
                    (along, c, d, ray.dy)
                };
                hit = occupied_beyond(map, vx, vy, dx, dy);
            }
            *best = if hit { t } else { *best };
        }
        v_bin += take as isize;
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_room_has_its_four_inner_faces_and_a_pillar_has_four() {
        // 6 × 5 cells, a one-cell border wall, and one occupied cell at (3, 2).
        let walls = Walls::new(6, 5, &crate::map::walled_cells(6, 5, &[(3, 2)]));
        let all = |f: usize| walls.filed[f].segs.clone();
        // Inner faces: floor top at y = 1 (free above), ceiling at y = 4 (free below),
        // left at x = 1 (free right), right at x = 5 (free left); the pillar's four.
        assert_eq!(
            all(0),
            vec![
                Seg {
                    c: 2.0,
                    a: 3.0,
                    b: 4.0
                },
                Seg {
                    c: 4.0,
                    a: 1.0,
                    b: 5.0
                }
            ]
        );
        assert_eq!(
            all(1),
            vec![
                Seg {
                    c: 1.0,
                    a: 1.0,
                    b: 5.0
                },
                Seg {
                    c: 3.0,
                    a: 3.0,
                    b: 4.0
                }
            ]
        );
        assert_eq!(
            all(2),
            vec![
                Seg {
                    c: 3.0,
                    a: 2.0,
                    b: 3.0
                },
                Seg {
                    c: 5.0,
                    a: 1.0,
                    b: 4.0
                }
            ]
        );
        assert_eq!(
            all(3),
            vec![
                Seg {
                    c: 1.0,
                    a: 1.0,
                    b: 4.0
                },
                Seg {
                    c: 4.0,
                    a: 2.0,
                    b: 3.0
                }
            ]
        );
        // The outer faces of the border are boundaries with the outside, which counts as
        // occupied: none.
        assert_eq!(walls.segments(), 8);
    }

    #[test]
    fn segments_are_cut_at_bucket_borders() {
        let (w, h) = (3 * BUCKET + 5, 3);
        let mut occ = vec![false; w * h];
        occ[..w].fill(true); // the floor row
        let walls = Walls::new(w, h, &occ);
        let ups = &walls.filed[1].segs;
        // The floor's top face, y = 1, runs 0..w in four pieces; the map's top edge, y =
        // 3, likewise (free below it).
        assert_eq!(ups.len(), 4);
        assert_eq!(ups.iter().map(|s| s.b - s.a).sum::<f64>(), w as f64);
        assert!(ups
            .iter()
            .all(|s| (s.a as usize) / BUCKET == (s.b as usize - 1) / BUCKET));
        assert_eq!(walls.filed[0].segs.len(), 4);
    }

    #[test]
    fn pseudo_angles_grow_with_the_angle() {
        let mut last = -1.0;
        for k in 0..3600 {
            let a = k as f64 * std::f64::consts::TAU / 3600.0;
            let p = pseudo_angle(a.cos(), a.sin());
            assert!((0.0..4.0).contains(&p), "{p}");
            assert!(p > last, "at {k}: {p} after {last}");
            last = p;
        }
    }
}
