//! `response-times.png` for `muster stress --report`: response times by message type
//! over the run, with the number of users online (the paper's Figure 4).

use anyhow::anyhow;
use plotters::prelude::*;
use serde_json::Value;
use std::path::Path;

/// Image size, pixels.
pub const SIZE: (u32, u32) = (1000, 500);

fn series(timeline: &[Value], kind: &str, q: &str) -> Vec<(f64, f64)> {
    timeline
        .iter()
        .filter_map(|s| Some((s["t_s"].as_f64()? + 0.5, s[kind][q].as_f64()?.max(1.0))))
        .collect()
}

/// Registers the font every plot uses: it ships inside the binary, so no system fonts
/// are needed.
pub fn register_font() -> anyhow::Result<()> {
    plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular())
        .map_err(|_| anyhow!("cannot load the embedded font"))
}

/// Draws the timeline of a stress report into a PNG at `path`.
pub fn draw(timeline: &[Value], title: &str, path: &Path) -> anyhow::Result<()> {
    register_font()?;
    let last_t = timeline
        .iter()
        .filter_map(|s| s["t_s"].as_f64())
        .fold(1.0, f64::max)
        + 1.0;
    let max_us = ["list", "service_request"]
        .iter()
        .flat_map(|k| series(timeline, k, "p99_us"))
        .map(|(_, v)| v)
        .fold(10.0, f64::max)
        * 2.0;
    let max_online = timeline
        .iter()
        .filter_map(|s| s["online"].as_f64())
        .fold(1.0, f64::max)
        * 1.1;
    let root = BitMapBackend::new(path, SIZE).into_drawing_area();
    let err = |e: &dyn std::fmt::Display| anyhow!("drawing {}: {e}", path.display());
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .right_y_label_area_size(60)
        .build_cartesian_2d(0.0..last_t, (1.0..max_us).log_scale())
        .map_err(|e| err(&e))?
        .set_secondary_coord(0.0..last_t, 0.0..max_online);
    chart
        .configure_mesh()
        .x_desc("time since the first user started (s)")
        .y_desc("response time (µs, log)")
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .configure_secondary_axes()
        .y_desc("users online")
        .draw()
        .map_err(|e| err(&e))?;
    let lines: [(&str, &str, &str, RGBColor); 4] = [
        (
            "service_request",
            "p99_us",
            "service request p99",
            RGBColor(200, 30, 30),
        ),
        (
            "service_request",
            "p50_us",
            "service request p50",
            RGBColor(240, 140, 40),
        ),
        ("list", "p99_us", "list request p99", RGBColor(30, 60, 200)),
        ("list", "p50_us", "list request p50", RGBColor(60, 170, 220)),
    ];
    for (kind, q, label, colour) in lines {
        chart
            .draw_series(LineSeries::new(
                series(timeline, kind, q),
                colour.stroke_width(2),
            ))
            .map_err(|e| err(&e))?
            .label(label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
            });
    }
    let online: Vec<(f64, f64)> = timeline
        .iter()
        .filter_map(|s| Some((s["t_s"].as_f64()? + 0.5, s["online"].as_f64()?)))
        .collect();
    chart
        .draw_secondary_series(LineSeries::new(online, BLACK.stroke_width(1)))
        .map_err(|e| err(&e))?
        .label("users online (right axis)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
