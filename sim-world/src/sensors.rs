//! Sensor models: a laser scanner, a sonar ring and a PTZ camera with a beacon tracker.
//! Each sees walls (exact ray casts on the map) and every other body.

use crate::bodies::{ray_circle, Bodies};
use crate::kinematics::{wrap, Pose};
use crate::map::OccupancyMap;
use crate::scenario::{CameraParams, Colour, LaserParams, SonarParams};
use rand::RngExt;
use rand_distr::{Distribution, Normal};

fn gaussian(rng: &mut impl rand::Rng, sd: f64) -> f64 {
    if sd > 0.0 {
        Normal::new(0.0, sd).map(|n| n.sample(rng)).unwrap_or(0.0)
    } else {
        0.0
    }
}

/// One laser scan: `beams` ranges from right to left across the field of view. A beam
/// that hits nothing reads the maximum range.
pub fn laser_scan(
    map: &OccupancyMap,
    bodies: &impl Bodies,
    skip: usize,
    p: Pose,
    params: &LaserParams,
    rng: &mut impl rand::Rng,
    out: &mut Vec<f32>,
) {
    let n = params.beams;
    let fov = params.fov_deg.to_radians();
    let step = if n > 1 { fov / (n - 1) as f64 } else { 0.0 };
    let first = p.theta - if n > 1 { fov / 2.0 } else { 0.0 };
    out.clear();
    // Beam directions by rotating the first one step by step (no sin/cos per beam).
    let mut dirs = Vec::with_capacity(n);
    let (mut dx, mut dy) = (first.cos(), first.sin());
    let (cs, sn) = (step.cos(), step.sin());
    for k in 0..n {
        if k % 32 == 0 {
            // Re-anchor now and then so rounding cannot drift.
            let a = first + step * k as f64;
            (dx, dy) = (a.cos(), a.sin());
        }
        dirs.push((dx, dy));
        (dx, dy) = (dx * cs - dy * sn, dx * sn + dy * cs);
    }
    let mut ranges = Vec::with_capacity(n);
    map.raycast_batch(p.x, p.y, &dirs, params.range, &mut ranges);
    out.extend(ranges.iter().map(|&r| r as f32));
    // Bodies: each occludes the beams within its angular extent. A field of view of at
    // most 180° lies ahead of the line across the robot: a body wholly behind it is
    // skipped before any trigonometry.
    let (hx, hy) = (p.theta.cos(), p.theta.sin());
    let ahead_only = fov <= std::f64::consts::PI;
    bodies.near(p.x, p.y, params.range + 0.5, |idx, b| {
        if idx == skip {
            return;
        }
        let (bx, by) = (b.x - p.x, b.y - p.y);
        if ahead_only && bx * hx + by * hy < -b.r {
            return;
        }
        let d = (bx * bx + by * by).sqrt();
        if d <= b.r || d - b.r > params.range {
            return;
        }
        let half = (b.r / d).asin();
        let centre = by.atan2(bx);
        let rel = wrap(centre - first);
        // Beam indices whose angle lies in [rel - half, rel + half] (mod 2π).
        for (lo, hi) in [
            (rel - half, rel + half),
            (
                rel - half + 2.0 * std::f64::consts::PI,
                rel + half + 2.0 * std::f64::consts::PI,
            ),
        ] {
            if step == 0.0 {
                if lo <= 0.0 && hi >= 0.0 {
                    hit_beam(out, 0, dirs[0], p, b);
                }
                continue;
            }
            let k0 = (lo / step).ceil().max(0.0) as usize;
            let k1 = (hi / step).floor();
            if k1 < 0.0 {
                continue;
            }
            let k1 = (k1 as usize).min(n - 1);
            for (k, &dir) in dirs.iter().enumerate().take(k1 + 1).skip(k0) {
                hit_beam(out, k, dir, p, b);
            }
        }
    });
    if params.noise > 0.0 {
        for r in out.iter_mut() {
            if f64::from(*r) < params.range {
                *r = (f64::from(*r) + gaussian(rng, params.noise)).clamp(0.0, params.range) as f32;
            }
        }
    }
}

fn hit_beam(out: &mut [f32], k: usize, dir: (f64, f64), p: Pose, b: &crate::bodies::Body) {
    if let Some(t) = ray_circle(p.x, p.y, dir.0, dir.1, b) {
        if (t as f32) < out[k] {
            out[k] = t as f32;
        }
    }
}

/// One sonar ring reading: per transducer, the nearest echo within its cone.
pub fn sonar_ring(
    map: &OccupancyMap,
    bodies: &impl Bodies,
    skip: usize,
    p: Pose,
    params: &SonarParams,
    rng: &mut impl rand::Rng,
    out: &mut Vec<f32>,
) {
    out.clear();
    let cone = params.cone_deg.to_radians();
    let rays = params.rays_per_cone.max(1);
    let mut dirs = Vec::with_capacity(params.bearings_deg.len() * rays);
    // Each cone's rays by rotating its first one step by step (one sin/cos per cone).
    let (first, step) = if rays == 1 {
        (0.0, 0.0)
    } else {
        (-cone / 2.0, cone / (rays - 1) as f64)
    };
    let (cs, sn) = (step.cos(), step.sin());
    // A cone's axis: its first ray turned back by `first`.
    let (ca, sa) = (first.cos(), -first.sin());
    let mut centres = Vec::with_capacity(params.bearings_deg.len());
    for bearing in &params.bearings_deg {
        let a = p.theta + bearing.to_radians() + first;
        let (mut dx, mut dy) = (a.cos(), a.sin());
        centres.push((dx * ca - dy * sa, dx * sa + dy * ca));
        for _ in 0..rays {
            dirs.push((dx, dy));
            (dx, dy) = (dx * cs - dy * sn, dx * sn + dy * cs);
        }
    }
    let mut walls = Vec::with_capacity(dirs.len());
    map.raycast_batch(p.x, p.y, &dirs, params.range, &mut walls);
    // Bodies within range, gathered once for the whole ring, each with the cosine of
    // the widest angle from a cone's axis at which the cone can still touch it (its
    // half-width plus the body's angular radius): a cone whose axis is farther off
    // skips the body without testing its rays.
    let (ch, sh) = ((cone / 2.0).cos(), (cone / 2.0).sin());
    let mut near: Vec<(crate::bodies::Body, f64, f64, f64)> = Vec::new();
    bodies.near(p.x, p.y, params.range + 0.5, |n, b| {
        if n != skip {
            let (bx, by) = (b.x - p.x, b.y - p.y);
            let d = (bx * bx + by * by).sqrt();
            let reach = if d > b.r && cone < std::f64::consts::PI {
                let s = b.r / d;
                ch * (1.0 - s * s).sqrt() - sh * s - 1e-9
            } else {
                -2.0 // around the robot, or a cone as wide as a half turn: always test
            };
            near.push((*b, bx, by, reach * d));
        }
    });
    for ((cone_rays, walls), &(cx, cy)) in dirs.chunks(rays).zip(walls.chunks(rays)).zip(&centres) {
        let mut best = params.range;
        for &wall in walls {
            best = best.min(wall);
        }
        for (b, bx, by, reach) in &near {
            if bx * cx + by * cy < *reach {
                continue;
            }
            for &(dx, dy) in cone_rays {
                if let Some(t) = ray_circle(p.x, p.y, dx, dy, b) {
                    best = best.min(t);
                }
            }
        }
        if best < params.range {
            best = (best + gaussian(rng, params.noise)).clamp(0.0, params.range);
        }
        out.push(best as f32);
    }
}

/// Where the camera points and how far it zooms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ptz {
    /// Pan, rad, relative to the robot's heading.
    pub pan: f64,
    /// Tilt, rad (kept for the interface; the world is 2-D).
    pub tilt: f64,
    /// Zoom factor, ≥ 1.
    pub zoom: f64,
}

impl Default for Ptz {
    fn default() -> Self {
        Ptz {
            pan: 0.0,
            tilt: 0.0,
            zoom: 1.0,
        }
    }
}

/// One detected beacon, as the blob tracker reports it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Detection {
    /// The beacon's colour.
    pub colour: Colour,
    /// Bearing, rad, relative to the robot's heading (positive: left).
    pub bearing: f64,
    /// Range, m.
    pub range: f64,
}

/// The camera's field of view and range at a zoom.
pub fn camera_cone(params: &CameraParams, zoom: f64) -> (f64, f64) {
    let z = zoom.clamp(1.0, params.max_zoom);
    (params.fov_deg.to_radians() / z, params.range * z.sqrt())
}

/// Height of a robot's camera, m: on top of its base, above
/// [`ROBOT_HEIGHT`](crate::bodies::ROBOT_HEIGHT).
pub const CAMERA_HEIGHT: f64 = 0.5;

/// One camera frame: every beacon inside the field of view and range, not hidden by a
/// wall or by a body taller than the line of sight (a person; not a robot's base,
/// unless the beacon is low too), with noisy bearing and range.
#[allow(clippy::too_many_arguments)] // the sensor's full context, as the others take it
pub fn camera_frame(
    map: &OccupancyMap,
    bodies: &impl Bodies,
    skip: usize,
    p: Pose,
    ptz: Ptz,
    params: &CameraParams,
    rng: &mut impl rand::Rng,
    out: &mut Vec<Detection>,
) {
    out.clear();
    let (fov, range) = camera_cone(params, ptz.zoom);
    let axis = p.theta + ptz.pan;
    let mut seen: Vec<(usize, Colour, f64, f64, f64, f64)> = Vec::new();
    // Cheap tests first (range, and the cone by a dot product, with a margin), the
    // exact ones after.
    let (ax, ay) = (axis.cos(), axis.sin());
    let cos_half = if fov < std::f64::consts::PI {
        (fov / 2.0).cos() - 1e-6
    } else {
        -2.0
    };
    bodies.near(p.x, p.y, range + 0.5, |n, b| {
        let Some(colour) = b.beacon else { return };
        if n == skip {
            return;
        }
        let (bx, by) = (b.x - p.x, b.y - p.y);
        let d2 = bx * bx + by * by;
        if d2 > range * range * (1.0 + 1e-9) || bx * ax + by * ay < cos_half * d2.sqrt() {
            return;
        }
        let d = (b.x - p.x).hypot(b.y - p.y);
        let angle = (b.y - p.y).atan2(b.x - p.x);
        if d > range || wrap(angle - axis).abs() > fov / 2.0 {
            return;
        }
        seen.push((n, colour, angle, d, b.r, b.beacon_height()));
    });
    for (n, colour, angle, d, radius, beacon_z) in seen {
        let visible_to = d - radius;
        if map.raycast(p.x, p.y, angle, visible_to).is_some() {
            continue; // a wall in between
        }
        let (dx, dy) = (angle.cos(), angle.sin());
        let mut hidden = false;
        bodies.near(p.x, p.y, d, |m, b| {
            if m != skip && m != n && !hidden {
                if let Some(t) = ray_circle(p.x, p.y, dx, dy, b) {
                    // In front of the beacon and taller than the line of sight where
                    // it stands: a person hides it, a robot's base is below the view.
                    let sight = CAMERA_HEIGHT + (beacon_z - CAMERA_HEIGHT) * t / d;
                    hidden = t < visible_to && b.height > sight;
                }
            }
        });
        if hidden {
            continue;
        }
        let bearing = wrap(angle - p.theta + gaussian(rng, params.bearing_noise_deg.to_radians()));
        let range = (d * (1.0 + gaussian(rng, params.range_noise))).max(0.0);
        out.push(Detection {
            colour,
            bearing,
            range,
        });
    }
    out.sort_by(|a, b| a.range.total_cmp(&b.range));
    let _ = rng.random::<u8>(); // keep the stream advancing per frame, seen or not
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::bodies::{Body, BodyGrid, PERSON_HEIGHT, ROBOT_HEIGHT};
    use rand::SeedableRng;

    /// 10 m × 10 m room, 0.1 m cells, walls on the border; a wall segment from
    /// (6.0, 2.0) to (6.1, 8.0).
    fn room() -> OccupancyMap {
        let wall: Vec<(usize, usize)> = (20..80).map(|j| (60, j)).collect();
        crate::map::walled_room(100, 100, 0.1, &wall)
    }

    fn quiet_laser() -> LaserParams {
        LaserParams {
            noise: 0.0,
            ..LaserParams::default()
        }
    }

    fn rng() -> rand_pcg::Pcg64 {
        rand_pcg::Pcg64::seed_from_u64(1)
    }

    /// The body grid of the 10 m test room.
    fn grid(bodies: Vec<Body>) -> BodyGrid {
        BodyGrid::new(bodies, (0.0, 0.0), (10.0, 10.0), 2.0)
    }

    /// What a noiseless camera at (x, 5) facing +x (body 0 is its own), panned `pan`, sees of the
    /// beacons among `bodies` in the test room.
    fn look(bodies: Vec<Body>, x: f64, pan: f64) -> Vec<Detection> {
        let params = CameraParams {
            bearing_noise_deg: 0.0,
            range_noise: 0.0,
            ..CameraParams::default()
        };
        let mut det = Vec::new();
        let p = Pose {
            x,
            y: 5.0,
            theta: 0.0,
        };
        let ptz = Ptz {
            pan,
            ..Ptz::default()
        };
        camera_frame(
            &room(),
            &grid(bodies),
            0,
            p,
            ptz,
            &params,
            &mut rng(),
            &mut det,
        );
        det
    }

    /// The sensing robot's own body, at (3, 3).
    fn robot_at_3_3() -> Body {
        Body {
            x: 3.0,
            y: 3.0,
            r: 0.25,
            beacon: None,
            height: PERSON_HEIGHT,
        }
    }

    #[test]
    fn laser_ranges_match_hand_geometry() {
        let map = room();
        let bodies = grid(vec![robot_at_3_3()]);
        let p = Pose {
            x: 3.0,
            y: 3.0,
            theta: 0.0,
        };
        let mut scan = Vec::new();
        laser_scan(&map, &bodies, 0, p, &quiet_laser(), &mut rng(), &mut scan);
        assert_eq!(scan.len(), 181);
        // Beam 90 points ahead (+x): the wall segment's face at x = 6.0 is 3 m away.
        assert!((scan[90] - 3.0).abs() < 1e-5, "{}", scan[90]);
        // Beam 0 points right (-y): the floor wall's face at y = 0.1 is 2.9 m away.
        assert!((scan[0] - 2.9).abs() < 1e-5, "{}", scan[0]);
        // Beam 180 points left (+y): the top wall at y = 9.9, 6.9 m away.
        assert!((scan[180] - 6.9).abs() < 1e-5, "{}", scan[180]);
        // Beam 45 is at -45°: it reaches the floor at y = 0.1 after 2.9·√2 m.
        assert!(
            (f64::from(scan[45]) - 2.9 * std::f64::consts::SQRT_2).abs() < 1e-4,
            "{}",
            scan[45]
        );
    }

    #[test]
    fn bodies_occlude_laser_beams() {
        let map = room();
        let me = Body {
            x: 3.0,
            y: 3.0,
            r: 0.25,
            beacon: None,
            height: PERSON_HEIGHT,
        };
        let other = Body {
            x: 5.0,
            y: 3.0,
            r: 0.25,
            beacon: None,
            height: PERSON_HEIGHT,
        };
        let bodies = grid(vec![me, other]);
        let mut scan = Vec::new();
        laser_scan(
            &map,
            &bodies,
            0,
            Pose {
                x: 3.0,
                y: 3.0,
                theta: 0.0,
            },
            &quiet_laser(),
            &mut rng(),
            &mut scan,
        );
        assert!(
            (scan[90] - 1.75).abs() < 1e-5,
            "the near side of the other robot: {}",
            scan[90]
        );
        // Half-angle asin(0.25/2) ≈ 7.2°: beams 83..=97 see it, 80 and 100 do not.
        assert!(scan[84] < 2.0 && scan[96] < 2.0);
        assert!(
            (scan[80] - 3.0 / 10f32.to_radians().cos()).abs() < 1e-3,
            "{}",
            scan[80]
        );
    }

    #[test]
    fn sonar_takes_the_nearest_echo_in_each_cone() {
        let map = room();
        let bodies = grid(vec![robot_at_3_3()]);
        let params = SonarParams {
            noise: 0.0,
            bearings_deg: vec![0.0, 90.0, 180.0],
            ..SonarParams::default()
        };
        let mut ring = Vec::new();
        sonar_ring(
            &map,
            &bodies,
            0,
            Pose {
                x: 3.0,
                y: 3.0,
                theta: 0.0,
            },
            &params,
            &mut rng(),
            &mut ring,
        );
        // Ahead: the wall at x = 6.0 is 3 m away straight on (the cone's edge rays are longer).
        assert!((ring[0] - 3.0).abs() < 1e-5, "{ring:?}");
        // Left: top wall 6.9 m, beyond the 5 m range.
        assert_eq!(ring[1], 5.0);
        // Behind: west wall face at x = 0.1, 2.9 m.
        assert!((ring[2] - 2.9).abs() < 1e-5);
    }

    #[test]
    fn beacons_are_seen_unless_a_wall_or_body_is_in_between() {
        let person = |x: f64, y: f64, beacon: Option<Colour>| Body {
            x,
            y,
            r: 0.25,
            beacon,
            height: PERSON_HEIGHT,
        };
        let me = person(3.0, 5.0, None);
        let red = person(5.0, 5.5, Some(Colour::Red));
        let behind_wall = person(8.0, 5.0, Some(Colour::Green));
        let det = look(vec![me, red, behind_wall], 3.0, 0.0);
        assert_eq!(det.len(), 1, "green is behind the wall: {det:?}");
        assert_eq!(det[0].colour, Colour::Red);
        assert!((det[0].bearing - 0.5f64.atan2(2.0)).abs() < 1e-9);
        assert!((det[0].range - 2.0f64.hypot(0.5)).abs() < 1e-9);
        // Panned away, nothing is in view; panned back with a body in between, red is hidden.
        assert!(look(vec![me, red, behind_wall], 3.0, 1.5).is_empty());
        let blocker = person(4.0, 5.25, None);
        let det = look(vec![me, red, behind_wall, blocker], 3.0, 0.0);
        assert!(det.is_empty(), "{det:?}");
        // Without the wall, green would be seen: check from the other side of it.
        let det = look(vec![person(7.0, 5.0, None), behind_wall], 7.0, 0.0);
        assert_eq!(det.len(), 1);
        assert_eq!(det[0].colour, Colour::Green);
    }

    #[test]
    fn a_robots_camera_sees_a_persons_beacon_over_another_robot_but_not_a_robots() {
        let robot = |x: f64, beacon: Option<Colour>| Body {
            x,
            y: 5.0,
            r: 0.25,
            beacon,
            height: ROBOT_HEIGHT,
        };
        let person = Body {
            x: 6.0,
            y: 5.0,
            r: 0.25,
            beacon: Some(Colour::Red),
            height: PERSON_HEIGHT,
        };
        let colours = |bodies| {
            look(bodies, 2.0, 0.0)
                .iter()
                .map(|d| d.colour)
                .collect::<Vec<_>>()
        };
        // A robot halfway between: its base is below the line of sight to her chest.
        assert_eq!(
            colours(vec![robot(2.0, None), robot(4.0, None), person]),
            vec![Colour::Red]
        );
        // A person halfway between hides her.
        let mut other = person;
        other.x = 4.0;
        other.beacon = None;
        assert!(colours(vec![robot(2.0, None), other, person]).is_empty());
        // A beacon on a robot's base, low, is hidden by a robot near it.
        let green = robot(6.0, Some(Colour::Green));
        assert!(colours(vec![robot(2.0, None), robot(5.2, None), green]).is_empty());
        assert_eq!(colours(vec![robot(2.0, None), green]), vec![Colour::Green]);
    }

    #[test]
    fn zoom_narrows_the_view_and_reaches_further() {
        let p = CameraParams::default();
        let (f1, r1) = camera_cone(&p, 1.0);
        let (f4, r4) = camera_cone(&p, 4.0);
        assert!((f1 / f4 - 4.0).abs() < 1e-12);
        assert!((r4 / r1 - 2.0).abs() < 1e-12);
        assert_eq!(camera_cone(&p, 100.0), (f4, r4), "zoom is clamped");
    }

    /// The sonar skips a body for a cone only when no ray of the cone can touch it: the
    /// ring equals every ray tested against every wall and body.
    #[test]
    fn sonar_equals_every_ray_against_every_body() {
        use rand::RngExt;
        let map = room();
        let mut r = rng();
        let params = SonarParams {
            noise: 0.0,
            ..SonarParams::default()
        };
        for round in 0..200 {
            let me = Body {
                x: 1.0 + r.random::<f64>() * 4.5,
                y: 1.0 + r.random::<f64>() * 8.0,
                r: 0.25,
                beacon: None,
                height: PERSON_HEIGHT,
            };
            let mut all = vec![me];
            for _ in 0..(round % 12) {
                all.push(Body {
                    x: me.x + (r.random::<f64>() - 0.5) * 8.0,
                    y: me.y + (r.random::<f64>() - 0.5) * 8.0,
                    r: 0.1 + r.random::<f64>() * 0.4,
                    beacon: None,
                    height: PERSON_HEIGHT,
                });
            }
            let g = grid(all.clone());
            let p = Pose {
                x: me.x,
                y: me.y,
                theta: r.random::<f64>() * 6.0 - 3.0,
            };
            let mut out = Vec::new();
            sonar_ring(&map, &g, 0, p, &params, &mut r, &mut out);
            let rays = params.rays_per_cone;
            let cone = params.cone_deg.to_radians();
            for (c, bearing) in params.bearings_deg.iter().enumerate() {
                let mut best = params.range;
                for k in 0..rays {
                    let a = p.theta + bearing.to_radians() - cone / 2.0
                        + cone * k as f64 / (rays - 1) as f64;
                    let (dx, dy) = (a.cos(), a.sin());
                    best = best.min(
                        map.raycast_dir(p.x, p.y, dx, dy, params.range)
                            .unwrap_or(params.range),
                    );
                    for b in &all[1..] {
                        if let Some(t) = ray_circle(p.x, p.y, dx, dy, b) {
                            best = best.min(t);
                        }
                    }
                }
                assert!(
                    (f64::from(out[c]) - best).abs() < 1e-5,
                    "round {round} cone {c}: {} vs {best}",
                    out[c]
                );
            }
        }
    }
}
