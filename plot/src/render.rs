//! Drawing a [`Chart`] with plotters onto the SVG and bitmap backends.

use crate::ticks::{format_tick, linear_ticks, log_ticks};
use crate::{Chart, PlotError, Style, HEIGHT, WIDTH};
use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint, Ranged};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::ops::Range;
use std::sync::OnceLock;

/// Line and marker colours (colour-blind-safe Okabe–Ito order, black, grey, then three more).
const PALETTE: [RGBColor; crate::PALETTE_LEN] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
    RGBColor(120, 94, 240),
    RGBColor(0, 0, 0),
    RGBColor(128, 128, 128),
    RGBColor(140, 86, 75),
    RGBColor(150, 150, 0),
    RGBColor(0, 128, 128),
];

/// Font family name the embedded DejaVu Sans is registered under.
const FONT: &str = "sans-serif";

/// The embedded font at `size` pixels.
pub(crate) fn font(size: u32) -> FontDesc<'static> {
    (FONT, f64::from(size)).into_font()
}

/// Registers the embedded font once per process.
fn ensure_font() -> Result<(), PlotError> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular())
                .map_err(|_| "DejaVu Sans could not be parsed".to_string())
        })
        .clone()
        .map_err(PlotError::Font)
}

/// A figure the SVG and bitmap backends can draw.
pub(crate) trait Figure {
    /// Title (named in errors).
    fn title(&self) -> &str;
    /// Whether there is anything to draw.
    fn check(&self) -> Result<(), PlotError> {
        Ok(())
    }
    /// Draw onto `root` (already sized [`WIDTH`] × [`HEIGHT`]).
    fn draw_on<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String>;
}

impl Figure for Chart {
    fn title(&self) -> &str {
        &self.title
    }

    fn check(&self) -> Result<(), PlotError> {
        Layout::new(self).map(|_| ())
    }

    fn draw_on<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String> {
        let layout = Layout::new(self).map_err(|e| e.to_string())?;
        draw(self, &layout, root)
    }
}

fn draw_error(title: &str, message: String) -> PlotError {
    PlotError::Draw {
        title: title.to_string(),
        message,
    }
}

/// The figure as an SVG document.
pub(crate) fn svg(figure: &impl Figure) -> Result<String, PlotError> {
    figure.check()?;
    ensure_font()?;
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (WIDTH, HEIGHT)).into_drawing_area();
        figure
            .draw_on(&root)
            .and_then(|()| root.present().map_err(|e| e.to_string()))
    }
    .map_err(|message| draw_error(figure.title(), message))?;
    Ok(out)
}

/// The figure as PNG bytes.
pub(crate) fn png(figure: &impl Figure) -> Result<Vec<u8>, PlotError> {
    figure.check()?;
    ensure_font()?;
    let mut rgb = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (WIDTH, HEIGHT)).into_drawing_area();
        figure
            .draw_on(&root)
            .and_then(|()| root.present().map_err(|e| e.to_string()))
    }
    .map_err(|message| draw_error(figure.title(), message))?;
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, WIDTH, HEIGHT);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .and_then(|mut w| w.write_image_data(&rgb))
        .map_err(|e| draw_error(figure.title(), format!("PNG encoding: {e}")))?;
    Ok(bytes)
}

/// One axis in plotting coordinates (log10 of the data on a log axis).
struct Axis {
    log: bool,
    lo: f64,
    hi: f64,
    ticks: Vec<f64>,
}

impl Axis {
    /// `values` set the range; `marks` (the measured points) choose between tick systems.
    fn new(log: bool, values: &[f64], marks: &[f64], explicit: Option<&[f64]>) -> Self {
        let (mut lo, mut hi) = values
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let to_plot = |v: f64| if log { v.log10() } else { v };
        let (mut plo, mut phi) = (to_plot(lo), to_plot(hi));
        if phi - plo < 1e-12 * plo.abs().max(1.0) {
            let half = if log { 0.5 } else { plo.abs().max(1.0) * 0.5 };
            plo -= half;
            phi += half;
        }
        let pad = 0.05 * (phi - plo);
        plo -= pad;
        phi += pad;
        let from_plot = |v: f64| if log { 10f64.powf(v) } else { v };
        lo = from_plot(plo);
        hi = from_plot(phi);
        let ticks = match explicit {
            Some(t) => t.to_vec(),
            None if log => log_ticks(lo, hi, marks),
            None => linear_ticks(lo, hi),
        };
        let ticks = ticks
            .into_iter()
            .filter(|&t| t.is_finite() && (!log || t > 0.0))
            .map(to_plot)
            .filter(|&t| t >= plo && t <= phi)
            .collect();
        Self {
            log,
            lo: plo,
            hi: phi,
            ticks,
        }
    }

    fn to_plot(&self, v: f64) -> f64 {
        if self.log {
            v.log10()
        } else {
            v
        }
    }

    fn label(&self, v: f64) -> String {
        format_tick(if self.log { 10f64.powf(v) } else { v })
    }
}

/// Axes, transformed series and the legend corner, computed before drawing.
struct Layout {
    x: Axis,
    y: Axis,
    series: Vec<Vec<(f64, f64)>>,
    legend: SeriesLabelPosition,
}

impl Layout {
    fn new(chart: &Chart) -> Result<Self, PlotError> {
        let keep = |(x, y): &(f64, f64)| {
            x.is_finite()
                && y.is_finite()
                && (!chart.log_x || *x > 0.0)
                && (!chart.log_y || *y > 0.0)
        };
        let kept: Vec<Vec<(f64, f64)>> = chart
            .series
            .iter()
            .map(|s| s.points.iter().copied().filter(keep).collect())
            .collect();
        let xs: Vec<f64> = kept.iter().flatten().map(|p| p.0).collect();
        let ys: Vec<f64> = kept.iter().flatten().map(|p| p.1).collect();
        if xs.is_empty() {
            return Err(PlotError::NoData {
                title: chart.title.clone(),
            });
        }
        // Tick systems follow the measured points (markers), not sampled fitted curves.
        let marks = |pick: fn(&(f64, f64)) -> f64| -> Vec<f64> {
            let m: Vec<f64> = chart
                .series
                .iter()
                .zip(&kept)
                .filter(|(s, _)| s.style == Style::Points)
                .flat_map(|(_, pts)| pts.iter().map(pick))
                .collect();
            if m.is_empty() {
                kept.iter().flatten().map(pick).collect()
            } else {
                m
            }
        };
        let x = Axis::new(chart.log_x, &xs, &marks(|p| p.0), chart.x_ticks.as_deref());
        let y = Axis::new(chart.log_y, &ys, &marks(|p| p.1), None);
        let series: Vec<Vec<(f64, f64)>> = kept
            .into_iter()
            .map(|pts| {
                pts.into_iter()
                    .map(|(a, b)| (x.to_plot(a), y.to_plot(b)))
                    .collect()
            })
            .collect();
        let legend = emptiest_corner(&x, &y, &series);
        Ok(Self {
            x,
            y,
            series,
            legend,
        })
    }
}

/// The plot corner (a third of each axis) holding the fewest points, for the legend.
fn emptiest_corner(x: &Axis, y: &Axis, series: &[Vec<(f64, f64)>]) -> SeriesLabelPosition {
    let fx = |v: f64| (v - x.lo) / (x.hi - x.lo);
    let fy = |v: f64| (v - y.lo) / (y.hi - y.lo);
    let corners = [
        (SeriesLabelPosition::UpperRight, true, true),
        (SeriesLabelPosition::UpperLeft, false, true),
        (SeriesLabelPosition::LowerRight, true, false),
        (SeriesLabelPosition::LowerLeft, false, false),
    ];
    corners
        .into_iter()
        .min_by_key(|&(_, right, upper)| {
            series
                .iter()
                .flatten()
                .filter(|&&(px, py)| {
                    let (u, v) = (fx(px), fy(py));
                    (if right { u > 0.6 } else { u < 0.4 })
                        && (if upper { v > 0.55 } else { v < 0.45 })
                })
                .count()
        })
        .map(|(pos, _, _)| pos)
        .unwrap_or(SeriesLabelPosition::UpperRight)
}

/// A linear coordinate over plotting units whose ticks are exactly the given positions.
struct TickAxis {
    lo: f64,
    hi: f64,
    ticks: Vec<f64>,
}

impl TickAxis {
    fn of(axis: &Axis) -> Self {
        Self {
            lo: axis.lo,
            hi: axis.hi,
            ticks: axis.ticks.clone(),
        }
    }
}

impl Ranged for TickAxis {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, v: &f64, limit: (i32, i32)) -> i32 {
        let frac = (v - self.lo) / (self.hi - self.lo);
        limit.0 + ((limit.1 - limit.0) as f64 * frac).round() as i32
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            Vec::new()
        } else {
            self.ticks.clone()
        }
    }

    fn range(&self) -> Range<f64> {
        self.lo..self.hi
    }
}

fn draw<DB: DrawingBackend>(
    chart: &Chart,
    layout: &Layout,
    root: &DrawingArea<DB, Shift>,
) -> Result<(), String> {
    ensure_font().map_err(|e| e.to_string())?;
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    root.fill(&WHITE).map_err(err)?;
    let (x, y) = (&layout.x, &layout.y);
    let mut ctx = ChartBuilder::on(root)
        .caption(&chart.title, (FONT, 28))
        .margin(18)
        .x_label_area_size(58)
        .y_label_area_size(92)
        .build_cartesian_2d(TickAxis::of(x), TickAxis::of(y))
        .map_err(err)?;
    let x_fmt = |v: &f64| x.label(*v);
    let y_fmt = |v: &f64| y.label(*v);
    ctx.configure_mesh()
        .x_desc(chart.x_label.as_str())
        .y_desc(chart.y_label.as_str())
        .x_label_formatter(&x_fmt)
        .y_label_formatter(&y_fmt)
        .label_style((FONT, 19))
        .axis_desc_style((FONT, 21))
        .bold_line_style(RGBColor(225, 225, 225))
        .light_line_style(TRANSPARENT)
        .draw()
        .map_err(err)?;
    let mut any_label = false;
    for (i, (s, pts)) in chart.series.iter().zip(&layout.series).enumerate() {
        let color = PALETTE[s.color.unwrap_or(i) % PALETTE.len()];
        let anno = match s.style {
            Style::Points => ctx
                .draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled())))
                .map_err(err)?,
            Style::Line => ctx
                .draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))
                .map_err(err)?,
        };
        if !s.name.is_empty() {
            any_label = true;
            let style = s.style;
            anno.label(s.name.as_str())
                .legend(move |(lx, ly)| match style {
                    Style::Points => Circle::new((lx + 10, ly), 4, color.filled()).into_dyn(),
                    Style::Line => {
                        PathElement::new(vec![(lx, ly), (lx + 20, ly)], color.stroke_width(2))
                            .into_dyn()
                    }
                });
        }
    }
    if any_label {
        ctx.configure_series_labels()
            .position(layout.legend.clone())
            .label_font((FONT, 18))
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(160, 160, 160))
            .draw()
            .map_err(err)?;
    }
    Ok(())
}
