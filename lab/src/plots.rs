//! Plots of an evaluation trial, each as PNG and SVG (plotters, pure Rust; text needs a TrueType
//! font: DejaVu Sans from Debian's fonts-dejavu-core, or the file named by `AMR_FONT`).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use amr_core::geometry::Polygon;
use amr_sim::eval::Trial;
use anyhow::Context as _;
use plotters::coord::Shift;
use plotters::prelude::*;

const FONT_PATHS: [&str; 2] =
    ["/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", "/usr/share/fonts/dejavu/DejaVuSans.ttf"];

fn register_font() -> anyhow::Result<()> {
    static DONE: OnceLock<Result<(), String>> = OnceLock::new();
    DONE.get_or_init(|| {
        let candidates: Vec<PathBuf> = std::env::var_os("AMR_FONT")
            .map(PathBuf::from)
            .into_iter()
            .chain(FONT_PATHS.iter().map(PathBuf::from))
            .collect();
        let bytes = candidates.iter().find_map(|p| std::fs::read(p).ok()).ok_or_else(|| {
            format!("no font for the plots: install fonts-dejavu-core or set AMR_FONT (tried {candidates:?})")
        })?;
        // plotters keeps the font for the life of the program.
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
            .map_err(|_| "the font file is not a usable TrueType font".to_owned())
    })
    .clone()
    .map_err(anyhow::Error::msg)
}

const COLOURS: [RGBColor; 4] =
    [RGBColor(214, 39, 40), RGBColor(255, 127, 14), RGBColor(44, 160, 44), RGBColor(31, 119, 180)];

fn walls<DB: DrawingBackend>(chart: &mut Chart<'_, DB>, site: &[Polygon]) -> Result<(), String> {
    for poly in site {
        let mut pts: Vec<(f64, f64)> = poly.vertices().iter().map(|v| (v[0], v[1])).collect();
        pts.extend(pts.first().copied());
        chart.draw_series(LineSeries::new(pts, BLACK.stroke_width(2))).map_err(|e| e.to_string())?;
    }
    Ok(())
}

type Chart<'a, DB> = ChartContext<
    'a,
    DB,
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
>;

/// A line with a legend entry.
fn labelled<DB: DrawingBackend>(
    chart: &mut Chart<'_, DB>,
    points: impl IntoIterator<Item = (f64, f64)>,
    colour: RGBColor,
    label: String,
) -> Result<(), String> {
    chart
        .draw_series(LineSeries::new(points, colour))
        .map_err(|e| e.to_string())?
        .label(label)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
    Ok(())
}

/// The legend box, then the picture out.
fn finish<'a, DB: DrawingBackend + 'a>(
    chart: &mut Chart<'a, DB>,
    area: &DrawingArea<DB, Shift>,
) -> Result<(), String> {
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| e.to_string())?;
    area.present().map_err(|e| e.to_string())
}

fn site_chart<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    caption: &str,
    site: &[Polygon],
) -> Result<Chart<'a, DB>, String> {
    let (mut x0, mut y0, mut x1, mut y1) =
        (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
    for p in site {
        let b = p.bounds();
        (x0, y0, x1, y1) = (x0.min(b.0), y0.min(b.1), x1.max(b.2), y1.max(b.3));
    }
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d((x0 - 0.3)..(x1 + 0.3), (y0 - 0.3)..(y1 + 0.3))
        .map_err(|e| e.to_string())?;
    chart.configure_mesh().x_desc("x (m)").y_desc("y (m)").draw().map_err(|e| e.to_string())?;
    walls(&mut chart, site)?;
    Ok(chart)
}

fn trajectories<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    trial: &Trial,
    site: &[Polygon],
) -> Result<(), String> {
    area.fill(&WHITE).map_err(|e| e.to_string())?;
    let mut chart = site_chart(area, "Trajectories: robots (grey) and V, true (black) and estimated", site)?;
    for track in &trial.truth_robots {
        chart
            .draw_series(LineSeries::new(track.iter().map(|p| (p[0], p[1])), RGBColor(150, 150, 150)))
            .map_err(|e| e.to_string())?;
    }
    chart
        .draw_series(LineSeries::new(trial.truth_v.iter().map(|p| (p[0], p[1])), BLACK.stroke_width(2)))
        .map_err(|e| e.to_string())?
        .label("V, true")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
    for ((c, s), colour) in trial.series.iter().zip(COLOURS) {
        labelled(
            &mut chart,
            s.estimates.iter().flatten().map(|p| (p[0], p[1])),
            colour,
            format!("V, {c:?}"),
        )?;
    }
    finish(&mut chart, area)
}

fn errors<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    trial: &Trial,
    _site: &[Polygon],
) -> Result<(), String> {
    area.fill(&WHITE).map_err(|e| e.to_string())?;
    let t_max = trial.times_s.last().copied().unwrap_or(1.0);
    let e2d = |s: &amr_sim::eval::Series| -> Vec<(f64, f64)> {
        s.estimates
            .iter()
            .zip(&trial.times_s)
            .zip(&trial.truth_v)
            .filter_map(|((e, t), v)| e.map(|e| (*t, (e[0] - v[0]).hypot(e[1] - v[1]))))
            .collect()
    };
    let y_max = trial.series.iter().flat_map(|(_, s)| e2d(s)).map(|(_, e)| e).fold(0.05, f64::max).min(1.0);
    let mut chart = ChartBuilder::on(area)
        .caption("2D error of V against the truth", ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(35)
        .y_label_area_size(55)
        .build_cartesian_2d(0.0..t_max, 0.0..y_max * 1.05)
        .map_err(|e| e.to_string())?;
    chart.configure_mesh().x_desc("t (s)").y_desc("error (m)").draw().map_err(|e| e.to_string())?;
    for ((c, s), colour) in trial.series.iter().zip(COLOURS) {
        labelled(&mut chart, e2d(s), colour, format!("{c:?}"))?;
    }
    finish(&mut chart, area)
}

fn particles<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    trial: &Trial,
    site: &[Polygon],
) -> Result<(), String> {
    area.fill(&WHITE).map_err(|e| e.to_string())?;
    let mut chart = site_chart(area, "T4's particle cloud after the last scan (true V: cross)", site)?;
    chart
        .draw_series(
            trial.final_particles_t4.iter().map(|p| Circle::new((p[0], p[1]), 1, COLOURS[3].filled())),
        )
        .map_err(|e| e.to_string())?;
    if let Some(v) = trial.truth_v.last() {
        chart
            .draw_series(std::iter::once(Cross::new((v[0], v[1]), 6, BLACK.stroke_width(2))))
            .map_err(|e| e.to_string())?;
    }
    area.present().map_err(|e| e.to_string())
}

fn draw<DB: DrawingBackend>(
    name: &str,
    area: &DrawingArea<DB, Shift>,
    trial: &Trial,
    site: &[Polygon],
) -> Result<(), String> {
    match name {
        "trajectories" => trajectories(area, trial, site),
        "error" => errors(area, trial, site),
        _ => particles(area, trial, site),
    }
}

/// Draw every plot of `trial` into `dir` as `<name>.png` and `<name>.svg`.
pub fn write_all(dir: &Path, trial: &Trial, site: &[Polygon]) -> anyhow::Result<Vec<PathBuf>> {
    register_font()?;
    let mut written = Vec::new();
    for name in ["trajectories", "error", "particles"] {
        let png_path = dir.join(format!("{name}.png"));
        let svg_path = dir.join(format!("{name}.svg"));
        draw(name, &BitMapBackend::new(&png_path, (1200, 600)).into_drawing_area(), trial, site)
            .map_err(anyhow::Error::msg)
            .with_context(|| format!("drawing {}", png_path.display()))?;
        draw(name, &SVGBackend::new(&svg_path, (1200, 600)).into_drawing_area(), trial, site)
            .map_err(anyhow::Error::msg)
            .with_context(|| format!("drawing {}", svg_path.display()))?;
        written.extend([png_path, svg_path]);
    }
    Ok(written)
}

/// One line per entry of `series` (its label and points), with points marked.
fn lines_chart<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    caption: &str,
    axes: (&str, &str),
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<(), String> {
    area.fill(&WHITE).map_err(|e| e.to_string())?;
    let all = || series.iter().flat_map(|(_, p)| p.iter().copied());
    let (x0, x1) = all().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), (x, _)| (a.min(x), b.max(x)));
    let y1 = all().map(|(_, y)| y).fold(0.0, f64::max);
    let (x0, x1) = if x0.is_finite() { (x0 - 0.1, x1 + 0.1) } else { (0.0, 1.0) };
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(35)
        .y_label_area_size(55)
        .build_cartesian_2d(x0..x1, 0.0..(y1 * 1.1).max(1e-3))
        .map_err(|e| e.to_string())?;
    chart.configure_mesh().x_desc(axes.0).y_desc(axes.1).draw().map_err(|e| e.to_string())?;
    let palette =
        [COLOURS[0], COLOURS[1], COLOURS[2], COLOURS[3], RGBColor(148, 103, 189), RGBColor(140, 86, 75)];
    for (k, (label, points)) in series.iter().enumerate() {
        let colour = palette[k % palette.len()];
        labelled(&mut chart, points.clone(), colour, label.clone())?;
        chart
            .draw_series(points.iter().map(|p| Circle::new(*p, 3, colour.filled())))
            .map_err(|e| e.to_string())?;
    }
    finish(&mut chart, area)
}

/// A line chart as `<stem>.png` and `<stem>.svg` in `dir`.
pub fn write_lines(
    dir: &Path,
    stem: &str,
    caption: &str,
    axes: (&str, &str),
    series: &[(String, Vec<(f64, f64)>)],
) -> anyhow::Result<Vec<PathBuf>> {
    register_font()?;
    let png = dir.join(format!("{stem}.png"));
    let svg = dir.join(format!("{stem}.svg"));
    lines_chart(&BitMapBackend::new(&png, (900, 500)).into_drawing_area(), caption, axes, series)
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("drawing {}", png.display()))?;
    lines_chart(&SVGBackend::new(&svg, (900, 500)).into_drawing_area(), caption, axes, series)
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("drawing {}", svg.display()))?;
    Ok(vec![png, svg])
}
