//! A PNG of a run: the ground-truth path against the firmware's odometry, seen from above,
//! and the position error over time.

use std::path::Path;

use plotters::prelude::*;

/// One sample of the trajectories: time s, truth `[x, y]`, odometry `[x, y]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackPoint {
    /// Simulated time, s.
    pub t: f64,
    /// Ground-truth position, m.
    pub truth: [f64; 2],
    /// Odometry position, m.
    pub odom: [f64; 2],
}

/// Why the plot could not be drawn.
#[derive(Debug, thiserror::Error)]
#[error("plot {path}: {message}")]
pub struct PlotError {
    path: String,
    message: String,
}

fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // The font is compiled in; registration only fails on a malformed font.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

/// Draws `points` to `path` (PNG, 1200 x 600): left the paths on equal axes, right the
/// odometry position error over time.
///
/// # Errors
/// [`PlotError`] if the file cannot be written.
pub fn plot_run(path: &Path, title: &str, points: &[TrackPoint]) -> Result<(), PlotError> {
    register_font();
    let err = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let root = BitMapBackend::new(path, (1200, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (left, right) = root.split_horizontally(600);

    // Equal axes around both paths, with a margin.
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in points {
        for [x, y] in [p.truth, p.odom] {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
    }
    if points.is_empty() {
        (x0, x1, y0, y1) = (-1.0, 1.0, -1.0, 1.0);
    }
    let span = (x1 - x0).max(y1 - y0).max(0.2) * 1.15;
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let mut chart = ChartBuilder::on(&left)
        .caption(format!("{title}: path seen from above"), ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(
            cx - span / 2.0..cx + span / 2.0,
            cy - span / 2.0..cy + span / 2.0,
        )
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("x [m]")
        .y_desc("y [m]")
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(LineSeries::new(
            points.iter().map(|p| (p.truth[0], p.truth[1])),
            BLUE.stroke_width(3),
        ))
        .map_err(|e| err(&e))?
        .label("ground truth")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(3)));
    chart
        .draw_series(LineSeries::new(
            points.iter().map(|p| (p.odom[0], p.odom[1])),
            RED.stroke_width(1),
        ))
        .map_err(|e| err(&e))?
        .label("odometry (firmware)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(&e))?;

    let t_end = points.last().map_or(1.0, |p| p.t).max(1e-3);
    let errs: Vec<(f64, f64)> = points
        .iter()
        .map(|p| {
            let e = (p.truth[0] - p.odom[0]).hypot(p.truth[1] - p.odom[1]);
            (p.t, e * 1000.0)
        })
        .collect();
    let e_max = errs.iter().map(|e| e.1).fold(1.0, f64::max) * 1.1;
    let mut chart = ChartBuilder::on(&right)
        .caption("odometry position error", ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(0.0..t_end, 0.0..e_max)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("t [s]")
        .y_desc("error [mm]")
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(LineSeries::new(errs, RED))
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
