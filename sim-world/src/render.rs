//! Draws the world as a PNG: walls, robots with headings, laser and camera coverage,
//! people with their beacon colours.

use crate::map::OccupancyMap;
use crate::sensors::camera_cone;
use crate::world::{World, PERSON_RADIUS};
use image::{Rgb, RgbImage};
use imageproc::drawing::{
    draw_filled_circle_mut, draw_filled_rect_mut, draw_hollow_circle_mut, draw_hollow_rect_mut,
    draw_line_segment_mut,
};
use imageproc::rect::Rect;

/// Pixels per metre.
pub const SCALE: f64 = 20.0;

/// The camera's view, cut at walls.
const CAMERA_VIEW: Rgb<u8> = Rgb([215, 215, 245]);
/// The camera cone's edges.
const CAMERA_EDGE: Rgb<u8> = Rgb([120, 120, 230]);

/// Renders `world` to an image (at most 4096 px on a side): what it shows, each robot
/// named beside it, and a legend.
pub fn render(world: &World) -> RgbImage {
    let (mut img, px) = map_image(world.map());
    let scale = scale_of(world.map());
    draw_world(&mut img, world, scale, &px);
    let mut placed = Vec::new();
    for r in world.robots() {
        let (cx, cy) = px(r.pose.x, r.pose.y);
        let rad = (r.spec.drive.radius * scale).round() as i32;
        label(
            &mut img,
            &mut placed,
            cx as i32 + rad + 3,
            cy as i32 - rad - 10,
            &r.spec.name,
        );
    }
    legend(
        &mut img,
        &[
            (CAMERA_VIEW, "camera view"),
            (LASER, "laser"),
            (ROBOT, "robot"),
            (Rgb([230, 40, 40]), "heading"),
        ],
        "people: beacon colour",
    );
    img
}

/// Text colour: pure black, which nothing else is drawn in.
pub const TEXT: Rgb<u8> = Rgb([0, 0, 0]);
/// Laser rays.
const LASER: Rgb<u8> = Rgb([170, 230, 170]);
/// Robot bodies.
const ROBOT: Rgb<u8> = Rgb([90, 90, 90]);

/// Writes `text` (ASCII, 8×8 glyphs of the public-domain font8x8) with its top-left
/// corner at (x, y), clipped to the image.
fn text(img: &mut RgbImage, x: i32, y: i32, text: &str, rgb: Rgb<u8>) {
    for (k, c) in text.chars().enumerate() {
        let glyph = font8x8::legacy::BASIC_LEGACY
            .get(c as usize)
            .copied()
            .unwrap_or(font8x8::legacy::BASIC_LEGACY[usize::from(b'?')]);
        for (row, bits) in glyph.iter().enumerate() {
            for col in 0..8 {
                if bits & (1 << col) != 0 {
                    let (px, py) = (x + 8 * k as i32 + col, y + row as i32);
                    if px >= 0 && py >= 0 && (px as u32) < img.width() && (py as u32) < img.height()
                    {
                        img.put_pixel(px as u32, py as u32, rgb);
                    }
                }
            }
        }
    }
}

/// A name on a white patch, so it reads over walls and rays; moved down below the
/// names already `placed` that it would cover.
fn label(img: &mut RgbImage, placed: &mut Vec<Rect>, x: i32, y: i32, name: &str) {
    let w = 8 * name.chars().count() as u32 + 2;
    let mut patch = Rect::at(x - 1, y - 1).of_size(w, 10);
    while let Some(below) = placed
        .iter()
        .filter(|p| p.intersect(patch).is_some())
        .map(|p| p.bottom() + 2)
        .max()
    {
        patch = Rect::at(patch.left(), below).of_size(w, 10);
    }
    draw_filled_rect_mut(img, patch, Rgb([255, 255, 255]));
    text(img, patch.left() + 1, patch.top() + 1, name, TEXT);
    placed.push(patch);
}

/// A legend in the top-left corner: a swatch and a line per entry, and a closing line.
fn legend(img: &mut RgbImage, entries: &[(Rgb<u8>, &str)], last: &str) {
    let lines = entries.len() as u32 + 1;
    let width = 8 * entries
        .iter()
        .map(|(_, t)| t.len() + 3)
        .chain([last.len()])
        .max()
        .unwrap_or(0) as u32
        + 12;
    let (x0, y0) = (6i32, 6i32);
    let rect = Rect::at(x0, y0).of_size(width, 12 * lines + 8);
    draw_filled_rect_mut(img, rect, Rgb([255, 255, 255]));
    draw_hollow_rect_mut(img, rect, Rgb([120, 120, 120]));
    for (i, (rgb, name)) in entries.iter().enumerate() {
        let y = y0 + 6 + 12 * i as i32;
        draw_filled_rect_mut(img, Rect::at(x0 + 6, y).of_size(16, 8), *rgb);
        text(img, x0 + 30, y, name, TEXT);
    }
    text(img, x0 + 6, y0 + 6 + 12 * entries.len() as i32, last, TEXT);
}

fn scale_of(map: &OccupancyMap) -> f64 {
    let (w, h) = map.size();
    SCALE.min(4096.0 / w.max(h))
}

/// The map's walls on white, and the metres → pixels mapping.
fn map_image(map: &OccupancyMap) -> (RgbImage, impl Fn(f64, f64) -> (f32, f32)) {
    let (w, h) = map.size();
    let scale = scale_of(map);
    let (iw, ih) = ((w * scale).ceil() as u32, (h * scale).ceil() as u32);
    let mut img = RgbImage::from_pixel(iw.max(1), ih.max(1), Rgb([255, 255, 255]));
    let (ox, oy) = map.origin();
    let px = move |x: f64, y: f64| {
        (
            ((x - ox) * scale) as f32,
            (ih as f64 - (y - oy) * scale) as f32,
        )
    };
    // Walls: every pixel whose centre is in an occupied cell.
    for j in 0..ih {
        for i in 0..iw {
            let (x, y) = (
                ox + (f64::from(i) + 0.5) / scale,
                oy + (f64::from(ih - j) - 0.5) / scale,
            );
            if map.blocked(x, y) {
                img.put_pixel(i, j, Rgb([40, 40, 40]));
            }
        }
    }
    (img, px)
}

/// A path to draw: points in metres, an RGB colour and what it is ("T3", "person").
pub type Path<'a> = (Vec<(f64, f64)>, [u8; 3], &'a str);

/// Consecutive points of a path further apart than this (metres) and than four times
/// its typical step are not joined: a track lost and found again elsewhere, not a walk
/// through walls.
const JUMP: f64 = 2.0;

/// Draws paths (polylines in metres, each in its colour, with a dot and its name where
/// it ends) over the map, with a legend: the picture of a run, like the paper's Figure 3.
pub fn render_paths(map: &OccupancyMap, paths: &[Path]) -> RgbImage {
    let (mut img, px) = map_image(map);
    let len = |w: &[(f64, f64)]| (w[1].0 - w[0].0).hypot(w[1].1 - w[0].1);
    for (path, rgb, _) in paths {
        let mut steps: Vec<f64> = path.windows(2).map(len).collect();
        steps.sort_by(f64::total_cmp);
        let typical = steps.get(steps.len() / 2).copied().unwrap_or(0.0);
        for w in path.windows(2) {
            if len(w) > JUMP && len(w) > 4.0 * typical {
                continue;
            }
            let (a, b) = (px(w[0].0, w[0].1), px(w[1].0, w[1].1));
            // Two pixels wide.
            draw_line_segment_mut(&mut img, a, b, Rgb(*rgb));
            draw_line_segment_mut(&mut img, (a.0 + 1.0, a.1), (b.0 + 1.0, b.1), Rgb(*rgb));
        }
    }
    for (path, rgb, _) in paths {
        if let Some(&(x, y)) = path.last() {
            let (cx, cy) = px(x, y);
            draw_filled_circle_mut(&mut img, (cx as i32, cy as i32), 5, Rgb(*rgb));
        }
    }
    // Names last, so no dot covers one.
    let mut placed = Vec::new();
    for (path, _, name) in paths {
        if let Some(&(x, y)) = path.last() {
            let (cx, cy) = px(x, y);
            label(&mut img, &mut placed, cx as i32 + 8, cy as i32 - 14, name);
        }
    }
    // Only what is drawn is in the legend.
    let entries: Vec<(Rgb<u8>, &str)> = paths
        .iter()
        .filter(|(path, _, _)| !path.is_empty())
        .map(|(_, rgb, name)| (Rgb(*rgb), *name))
        .collect();
    legend(&mut img, &entries, "dot: where it ended");
    img
}

fn draw_world(img: &mut RgbImage, world: &World, scale: f64, px: &impl Fn(f64, f64) -> (f32, f32)) {
    for r in world.robots() {
        let p = r.pose;
        let from = px(p.x, p.y);
        if let Some(c) = &r.spec.camera {
            // What the camera can see: its cone, cut where walls stop the view (rays
            // about a pixel apart at the cone's far end), with its edges drawn darker.
            let (fov, range) = camera_cone(c, r.ptz.zoom);
            let axis = p.theta + r.ptz.pan;
            let reach = |a: f64| world.map().raycast(p.x, p.y, a, range).unwrap_or(range);
            let rays = ((fov * range * scale).ceil() as usize).clamp(2, 2000);
            for k in 0..=rays {
                let a = axis - fov / 2.0 + fov * k as f64 / rays as f64;
                let d = reach(a);
                let edge = k == 0 || k == rays;
                draw_line_segment_mut(
                    img,
                    from,
                    px(p.x + d * a.cos(), p.y + d * a.sin()),
                    if edge { CAMERA_EDGE } else { CAMERA_VIEW },
                );
            }
        }
    }
    // Laser rays over every camera's view, so both show.
    for r in world.robots() {
        let p = r.pose;
        let from = px(p.x, p.y);
        if let Some(l) = &r.spec.laser {
            let n = r.laser.len();
            let fov = l.fov_deg.to_radians();
            let step = if n > 1 { fov / (n - 1) as f64 } else { 0.0 };
            for (k, range) in r.laser.iter().enumerate().step_by(3) {
                let a = p.theta - fov / 2.0 + step * k as f64;
                let d = f64::from(*range);
                draw_line_segment_mut(img, from, px(p.x + d * a.cos(), p.y + d * a.sin()), LASER);
            }
        }
    }
    for r in world.robots() {
        let p = r.pose;
        let (cx, cy) = px(p.x, p.y);
        let rad = (r.spec.drive.radius * scale).round() as i32;
        draw_filled_circle_mut(img, (cx as i32, cy as i32), rad.max(2), ROBOT);
        if let Some(b) = r.spec.beacon {
            draw_hollow_circle_mut(img, (cx as i32, cy as i32), rad.max(2), Rgb(b.rgb()));
        }
        let nose = px(
            p.x + r.spec.drive.radius * 1.6 * p.theta.cos(),
            p.y + r.spec.drive.radius * 1.6 * p.theta.sin(),
        );
        draw_line_segment_mut(img, (cx, cy), nose, Rgb([230, 40, 40]));
    }
    for person in world.people() {
        let (cx, cy) = px(person.pose.x, person.pose.y);
        let rad = (PERSON_RADIUS * scale).round() as i32;
        draw_filled_circle_mut(
            img,
            (cx as i32, cy as i32),
            rad.max(2),
            Rgb(person.beacon.rgb()),
        );
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::scenario::Scenario;

    #[test]
    fn the_paper_world_renders_with_its_parts_in_their_colours() {
        let mut w = World::new(&Scenario::paper(), None).unwrap();
        w.step(1.0);
        let img = render(&w);
        assert_eq!((img.width(), img.height()), (800, 400));
        // A wall pixel (outer wall at the bottom) is dark, a corridor pixel white or a ray.
        assert_eq!(img.get_pixel(400, 399), &Rgb([40, 40, 40]));
        // Each person is drawn in its beacon colour at its position.
        for p in w.people() {
            let (x, y) = ((p.pose.x * SCALE) as u32, (400.0 - p.pose.y * SCALE) as u32);
            assert_eq!(img.get_pixel(x, y), &Rgb(p.beacon.rgb()), "{}", p.name);
        }
        // Each robot's body is grey.
        let t1 = &w.robots()[0];
        let (x, y) = (
            (t1.pose.x * SCALE) as u32,
            (400.0 - t1.pose.y * SCALE) as u32,
        );
        assert_ne!(img.get_pixel(x + 2, y + 2), &Rgb([255, 255, 255]));
    }

    #[test]
    fn robots_are_named_and_a_legend_says_what_is_what() {
        let mut w = World::new(&Scenario::paper(), None).unwrap();
        w.step(1.0);
        let img = render(&w);
        let text_in = |x0: u32, y0: u32, wd: u32, ht: u32| {
            (x0..(x0 + wd).min(img.width()))
                .flat_map(|x| (y0..(y0 + ht).min(img.height())).map(move |y| (x, y)))
                .filter(|&(x, y)| img.get_pixel(x, y) == &TEXT)
                .count()
        };
        let mut names = Vec::new();
        for r in w.robots() {
            let (x, y) = ((r.pose.x * SCALE) as u32, (400.0 - r.pose.y * SCALE) as u32);
            let rad = (r.spec.drive.radius * SCALE).round() as u32;
            // The name's glyphs, right of the robot and a little above it.
            let n = r.spec.name.len() as u32;
            let ink = text_in(x + rad + 3, y.saturating_sub(rad + 10), 8 * n, 8);
            assert!(ink >= 6 * n as usize, "{}: {ink} text pixels", r.spec.name);
            names.push(r.spec.name.clone());
        }
        assert_eq!(names, ["T1", "T2", "T3", "D1"]);
        // The legend's five lines of text in the top-left corner.
        assert!(text_in(6, 6, 200, 68) > 5 * 40);
    }

    #[test]
    fn paths_are_drawn_named_at_their_ends_with_a_legend() {
        let map = OccupancyMap::office();
        let img = render_paths(
            &map,
            &[
                (vec![(5.0, 3.0), (15.0, 3.0)], [220, 30, 30], "person"),
                (vec![(5.0, 17.0), (30.0, 17.0)], [30, 90, 230], "D1"),
            ],
        );
        let h = f64::from(img.height());
        let at = |x: f64, y: f64| ((x * SCALE) as u32, (h - y * SCALE) as u32);
        // Along each path, its colour.
        let (x, y) = at(10.0, 3.0);
        assert_eq!(img.get_pixel(x, y), &Rgb([220, 30, 30]));
        // Beside each end, its name in text.
        for (end, name) in [((15.0, 3.0), "person"), ((30.0, 17.0), "D1")] {
            let (x, y) = at(end.0, end.1);
            let ink = (x + 8..x + 8 + 8 * name.len() as u32)
                .flat_map(|i| (y - 14..y - 6).map(move |j| (i, j)))
                .filter(|&(i, j)| img.get_pixel(i, j) == &TEXT)
                .count();
            assert!(ink >= 6 * name.len(), "{name}: {ink} text pixels");
        }
        // A jump (a track lost and found elsewhere) is not joined.
        let jumpy = render_paths(
            &map,
            &[(
                vec![(5.0, 3.0), (5.5, 3.0), (6.0, 3.0), (6.5, 3.0), (15.0, 3.0)],
                [220, 30, 30],
                "track",
            )],
        );
        let (x, y) = at(5.5, 3.0);
        assert_eq!(jumpy.get_pixel(x, y), &Rgb([220, 30, 30]));
        let (x, y) = at(10.0, 3.0);
        assert_ne!(jumpy.get_pixel(x, y), &Rgb([220, 30, 30]));
        // The legend: a swatch per path in its colour.
        assert_eq!(img.get_pixel(14, 16), &Rgb([220, 30, 30]));
        assert_eq!(img.get_pixel(14, 28), &Rgb([30, 90, 230]));
        // A path with no points (a track never sent) has no swatch: the next one takes
        // its place.
        let skipped = render_paths(
            &map,
            &[
                (Vec::new(), [150, 220, 150], "track (green)"),
                (vec![(5.0, 17.0), (30.0, 17.0)], [30, 90, 230], "D1"),
            ],
        );
        assert_eq!(skipped.get_pixel(14, 16), &Rgb([30, 90, 230]));
        assert!(!skipped.pixels().any(|p| *p == Rgb([150, 220, 150])));
    }

    #[test]
    fn names_of_paths_ending_together_do_not_cover_each_other() {
        let map = OccupancyMap::office();
        let one = |name| (vec![(5.0, 3.0), (15.0, 3.0)], [220, 30, 30], name);
        let alone = render_paths(&map, &[one("person")]);
        let both = render_paths(&map, &[one("person"), one("track")]);
        let ink = |img: &RgbImage| img.pixels().filter(|p| **p == TEXT).count();
        let mut blank = RgbImage::from_pixel(64, 16, Rgb([255, 255, 255]));
        text(&mut blank, 0, 0, "track", TEXT);
        // "track" adds its glyphs twice (beside the end and in the legend), and the
        // first name keeps all of its own.
        assert_eq!(ink(&both), ink(&alone) + 2 * ink(&blank));
    }

    #[test]
    fn the_camera_view_stops_at_walls() {
        let mut w = World::new(&Scenario::paper(), None).unwrap();
        w.step(1.0);
        let img = render(&w);
        let (h, map) = (f64::from(img.height()), w.map());
        let pixel = |x: f64, y: f64| *img.get_pixel((x * SCALE) as u32, (h - y * SCALE) as u32);
        let mut checked = 0;
        for r in w.robots() {
            let Some(c) = &r.spec.camera else { continue };
            let (fov, range) = camera_cone(c, r.ptz.zoom);
            let axis = r.pose.theta + r.ptz.pan;
            for k in 0..=40 {
                let a = axis - fov / 2.0 + fov * f64::from(k) / 40.0;
                let (x, y) = (r.pose.x, r.pose.y);
                let Some(d) = map.raycast(x, y, a, range) else {
                    continue;
                };
                // A free spot behind the wall, still within the camera's range: hidden.
                let behind = d + 0.6;
                let (bx, by) = (x + behind * a.cos(), y + behind * a.sin());
                let inside = bx > 0.1 && by > 0.1 && bx < 39.9 && by < 19.9;
                // Another camera may see it, rightly, or a ray through a door beside the
                // wall pass within a pixel or two of it: only a spot no camera sees from
                // anywhere near counts.
                let near: Vec<(f64, f64)> = [
                    (0.0, 0.0),
                    (0.15, 0.0),
                    (-0.15, 0.0),
                    (0.0, 0.15),
                    (0.0, -0.15),
                ]
                .iter()
                .map(|(ex, ey)| (bx + ex, by + ey))
                .collect();
                let seen_by_any = near.iter().any(|&(bx, by)| {
                    w.robots().iter().any(|o| {
                        let Some(oc) = &o.spec.camera else {
                            return false;
                        };
                        let (ofov, orange) = camera_cone(oc, o.ptz.zoom);
                        let (dx, dy) = (bx - o.pose.x, by - o.pose.y);
                        let dist = dx.hypot(dy);
                        let off = (dy.atan2(dx) - o.pose.theta - o.ptz.pan + std::f64::consts::PI)
                            .rem_euclid(std::f64::consts::TAU)
                            - std::f64::consts::PI;
                        off.abs() <= ofov / 2.0 + 0.05
                            && dist <= orange + 0.2
                            && map
                                .raycast(o.pose.x, o.pose.y, dy.atan2(dx), dist)
                                .is_none_or(|hit| hit >= dist - 0.2)
                    })
                });
                if behind < range && inside && !map.blocked(bx, by) && !seen_by_any {
                    let seen = pixel(bx, by);
                    assert!(
                        seen != CAMERA_VIEW && seen != CAMERA_EDGE,
                        "{} sees through the wall at ({bx:.1}, {by:.1}): {seen:?}, wall at {d:.2} m along {a:.2} rad from ({x:.2}, {y:.2}), range {range:.1}",
                        r.spec.name
                    );
                    checked += 1;
                }
            }
            // And in front of the camera, its view is drawn.
            let d = map
                .raycast(r.pose.x, r.pose.y, axis, range)
                .unwrap_or(range);
            let near = (d * 0.5).min(1.0);
            let front = pixel(r.pose.x + near * axis.cos(), r.pose.y + near * axis.sin());
            assert!(
                front == CAMERA_VIEW || front == CAMERA_EDGE || front != Rgb([255, 255, 255]),
                "{}: nothing drawn in front of the camera",
                r.spec.name
            );
        }
        assert!(
            checked > 0,
            "no camera ray met a wall with free space behind it"
        );
    }
}
