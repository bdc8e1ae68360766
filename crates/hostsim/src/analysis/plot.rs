//! A PNG of a run: the ground-truth path against the firmware's odometry, seen from above,
//! and the position error over time; or of several runs in one figure (`hostsim plot A B`:
//! an uncalibrated run beside a calibrated one).

use std::io::BufWriter;
use std::path::Path;

use drivelog::Staged;
use image::ImageEncoder;
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

use crate::engine::TrackPoint;

/// Why the plot could not be drawn.
#[derive(Debug, thiserror::Error)]
#[error("plot {path}: {message}")]
pub struct PlotError {
    path: String,
    message: String,
}

/// Draws a PNG of `size` pixels with `draw` and writes it to `path` through a [`Staged`] file:
/// the previous PNG there stays until the new one is whole.
fn png(
    path: &Path,
    size: (u32, u32),
    err: &dyn Fn(&dyn std::fmt::Display) -> PlotError,
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), PlotError>,
) -> Result<(), PlotError> {
    let mut pixels = vec![0_u8; size.0 as usize * size.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, size).into_drawing_area();
        draw(&root)?;
        root.present().map_err(|e| err(&e))?;
    }
    let mut out = Staged::create(path).map_err(|e| err(&e))?;
    image::codecs::png::PngEncoder::new(BufWriter::new(&mut out))
        .write_image(&pixels, size.0, size.1, image::ColorType::Rgb8)
        .map_err(|e| err(&e))?;
    out.commit().map_err(|e| err(&e))?;
    Ok(())
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
    plot_runs(path, title, &[("", points)])
}

/// The largest distance between odometry and ground truth along a track, m.
#[must_use]
pub fn max_drift(points: &[TrackPoint]) -> f64 {
    points
        .iter()
        .map(|p| (p.truth[0] - p.odom[0]).hypot(p.truth[1] - p.odom[1]))
        .fold(0.0, f64::max)
}

/// The colours of a run's ground truth and odometry: the first run's are blue and red, the
/// next ones' green and orange, purple and brown.
const COLOURS: [(RGBColor, RGBColor); 3] = [
    (BLUE, RED),
    (RGBColor(0, 140, 0), RGBColor(240, 140, 0)),
    (RGBColor(120, 0, 160), RGBColor(140, 90, 40)),
];

/// A panel of a figure.
type Panel<'a> = DrawingArea<BitMapBackend<'a>, Shift>;

/// A chart of two real axes on a panel.
type Chart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// What turns a drawing error into a [`PlotError`] naming the file.
type ToPlotError<'a> = dyn Fn(&dyn std::fmt::Display) -> PlotError + 'a;

/// Draws several runs, each `(label, points)`, into one figure as [`plot_run`] draws one: a
/// panel per run with its ground truth and odometry seen from above (the same equal axes for
/// all, the largest drift in the legend), then one panel of every run's position error over
/// time (600 x 600 pixels a panel). Say an uncalibrated run beside a calibrated one.
///
/// # Errors
/// [`PlotError`] if the file cannot be written.
pub fn plot_runs(
    path: &Path,
    title: &str,
    runs: &[(&str, &[TrackPoint])],
) -> Result<(), PlotError> {
    register_font();
    let err = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let panels = u32::try_from(runs.len().max(1) + 1).unwrap_or(u32::MAX);
    png(path, (600 * panels, 600), &err, |root| {
        root.fill(&WHITE).map_err(|e| err(&e))?;
        let areas = root.split_evenly((1, panels as usize));
        let (paths, right) = areas.split_at(areas.len() - 1);
        let view = equal_axes(runs);
        for (i, ((label, points), area)) in runs.iter().zip(paths).enumerate() {
            let caption = if label.is_empty() {
                format!("{title}: path seen from above")
            } else {
                format!("{label}: path seen from above")
            };
            let size = if label.is_empty() { 20 } else { 16 };
            let colours = COLOURS[i % COLOURS.len()];
            draw_path(area, (caption, size), points, colours, view, &err)?;
        }
        draw_errors(&right[0], runs, &err)
    })
}

/// Equal axes around every run's paths, with a margin: the centre and the side, m.
fn equal_axes(runs: &[(&str, &[TrackPoint])]) -> (f64, f64, f64) {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in runs.iter().flat_map(|r| r.1) {
        for [x, y] in [p.truth, p.odom] {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
    }
    if runs.iter().all(|r| r.1.is_empty()) {
        (x0, x1, y0, y1) = (-1.0, 1.0, -1.0, 1.0);
    }
    let span = (x1 - x0).max(y1 - y0).max(0.2) * 1.15;
    ((x0 + x1) / 2.0, (y0 + y1) / 2.0, span)
}

/// A run's ground truth and odometry seen from above, on `area` with `caption` (text and
/// size), in the colours `(truth, odom)`, on the axes `(cx, cy, span)`.
fn draw_path(
    area: &Panel<'_>,
    caption: (String, u32),
    points: &[TrackPoint],
    (truth, odom): (RGBColor, RGBColor),
    (cx, cy, span): (f64, f64, f64),
    err: &ToPlotError<'_>,
) -> Result<(), PlotError> {
    let mut chart = ChartBuilder::on(area)
        .caption(caption.0, ("sans-serif", caption.1))
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
            truth.stroke_width(3),
        ))
        .map_err(|e| err(&e))?
        .label("ground truth")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], truth.stroke_width(3)));
    chart
        .draw_series(LineSeries::new(
            points.iter().map(|p| (p.odom[0], p.odom[1])),
            odom.stroke_width(1),
        ))
        .map_err(|e| err(&e))?
        .label(format!(
            "odometry (firmware), max drift {:.1} mm",
            max_drift(points) * 1000.0
        ))
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], odom));
    legend(&mut chart, err)
}

/// Every run's odometry position error over time, on `area`.
fn draw_errors(
    area: &Panel<'_>,
    runs: &[(&str, &[TrackPoint])],
    err: &ToPlotError<'_>,
) -> Result<(), PlotError> {
    let t_end = runs
        .iter()
        .filter_map(|r| r.1.last())
        .map(|p| p.t)
        .fold(1e-3, f64::max);
    let e_max = runs
        .iter()
        .map(|r| max_drift(r.1) * 1000.0)
        .fold(1.0, f64::max)
        * 1.1;
    let mut chart = ChartBuilder::on(area)
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
    for (i, (label, points)) in runs.iter().enumerate() {
        let (_, odom) = COLOURS[i % COLOURS.len()];
        let errs = points.iter().map(|p| {
            let e = (p.truth[0] - p.odom[0]).hypot(p.truth[1] - p.odom[1]);
            (p.t, e * 1000.0)
        });
        let prefix = if label.is_empty() {
            String::new()
        } else {
            format!("{label}: ")
        };
        chart
            .draw_series(LineSeries::new(errs, odom))
            .map_err(|e| err(&e))?
            .label(format!("{prefix}max {:.1} mm", max_drift(points) * 1000.0))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], odom));
    }
    if runs.len() > 1 {
        legend(&mut chart, err)?;
    }
    Ok(())
}

/// The legend of `chart`'s series, on white in a black frame.
fn legend<'a, 'b: 'a>(chart: &mut Chart<'a, 'b>, err: &ToPlotError<'_>) -> Result<(), PlotError> {
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(&e))
}

/// A logged run's track ([`track_from_log`]), with what the reader made of the file.
#[derive(Debug, Clone)]
pub struct LoggedTrack {
    /// The track.
    pub points: Vec<TrackPoint>,
    /// What was read, and where the log is damaged if it is (the track is its complete part).
    pub read: drivelog::ReadReport,
    /// The odometry messages that did not decode.
    pub undecodable: drivelog::Undecodable,
}

/// A logged run's track: the odometry (`/odom`) and the ground truth (`/ground_truth/odom`)
/// at the log times both have, from the log's start (as `hostsim run` draws it).
///
/// # Errors
/// A description naming the file if it cannot be read, is not MCAP, or has no odometry and
/// ground truth at the same times.
pub fn track_from_log(path: &Path) -> Result<LoggedTrack, String> {
    use drivelog::msg;
    let bytes = drivelog::read::read_log_file(path)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let (mut odom, mut truth) = (Vec::new(), Vec::new());
    let mut undecodable = drivelog::Undecodable::default();
    let read = drivelog::for_each_message(
        &bytes,
        |m| {
            let list = match m.topic {
                "/odom" => &mut odom,
                "/ground_truth/odom" => &mut truth,
                _ => return,
            };
            if let Some(o) = undecodable.decode::<msg::Odometry>(m) {
                let [x, y, _] = o.pose.pose.to_planar();
                list.push((m.log_time, [x, y]));
            }
        },
        |_, _| {},
    )
    .map_err(|e| format!("{}: not a readable MCAP file: {e}", path.display()))?;
    let truth: std::collections::BTreeMap<u64, [f64; 2]> = truth.into_iter().collect();
    let points: Vec<TrackPoint> = odom
        .into_iter()
        .filter_map(|(t, odom)| {
            Some(TrackPoint {
                t: t as f64 * 1e-9,
                truth: *truth.get(&t)?,
                odom,
            })
        })
        .collect();
    if points.is_empty() {
        return Err(format!(
            "{}: no odometry (/odom) and ground truth (/ground_truth/odom) at the same times: \
             nothing to plot",
            path.display()
        ));
    }
    Ok(LoggedTrack {
        points,
        read,
        undecodable,
    })
}

/// A scatter of `ys` against `xs` (a sweep's metric against its swept parameter), PNG,
/// 900 x 600.
///
/// # Errors
/// [`PlotError`] if the file cannot be written.
pub fn scatter(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    xs: &[f64],
    ys: &[f64],
) -> Result<(), PlotError> {
    register_font();
    let err = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let finite = |v: &[f64]| -> (f64, f64) {
        let (lo, hi) = v
            .iter()
            .filter(|x| x.is_finite())
            .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
        if lo > hi {
            (0.0, 1.0)
        } else {
            let pad = ((hi - lo) * 0.05).max(1e-9);
            (lo - pad, hi + pad)
        }
    };
    let (x0, x1) = finite(xs);
    let (y0, y1) = finite(ys);
    png(path, (900, 600), &err, |root| {
        root.fill(&WHITE).map_err(|e| err(&e))?;
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 20))
            .margin(15)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0.min(0.0)..y1)
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .draw()
            .map_err(|e| err(&e))?;
        chart
            .draw_series(
                xs.iter()
                    .zip(ys)
                    .filter(|(x, y)| x.is_finite() && y.is_finite())
                    .map(|(&x, &y)| Circle::new((x, y), 3, BLUE.mix(0.6).filled())),
            )
            .map_err(|e| err(&e))?;
        Ok(())
    })
}
