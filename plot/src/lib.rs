//! Line and scatter charts (and [`Heatmap`]s) written as SVG and PNG: named series, linear or log10 axes, axis
//! labels, a title and a legend. Text is drawn with DejaVu Sans embedded in the binary, so a
//! machine without system fonts or fontconfig renders the same PNG.

pub mod heatmap;
mod render;
pub mod ticks;

pub use heatmap::Heatmap;

use std::path::{Path, PathBuf};

/// Chart width in pixels (PNG) and user units (SVG).
pub const WIDTH: u32 = 960;
/// Chart height in pixels (PNG) and user units (SVG).
pub const HEIGHT: u32 = 640;

/// Number of palette colours ([`Series::with_color`] indices wrap around).
pub const PALETTE_LEN: usize = 12;

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Filled circles at the points (measurements).
    Points,
    /// A polyline through the points in order (fitted curves).
    Line,
}

/// One named data series.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend text; an empty name keeps the series out of the legend.
    pub name: String,
    /// (x, y) in data units. Non-finite points, and non-positive ones on a log axis, are skipped.
    pub points: Vec<(f64, f64)>,
    /// Markers or a line.
    pub style: Style,
    /// Palette index; `None` uses the series' position in the chart.
    pub color: Option<usize>,
}

impl Series {
    /// A scatter series (markers).
    pub fn points(name: impl Into<String>, points: Vec<(f64, f64)>) -> Self {
        Self {
            name: name.into(),
            points,
            style: Style::Points,
            color: None,
        }
    }

    /// A line series (e.g. a fitted curve, sampled densely enough by the caller).
    pub fn line(name: impl Into<String>, points: Vec<(f64, f64)>) -> Self {
        Self {
            name: name.into(),
            points,
            style: Style::Line,
            color: None,
        }
    }

    /// The same series drawn in palette colour `index` (to pair points with their fit).
    pub fn with_color(mut self, index: usize) -> Self {
        self.color = Some(index);
        self
    }
}

/// A 2-D chart: title, axis labels, optional log10 axes and its series.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Chart {
    /// Title above the plot.
    pub title: String,
    /// x-axis description.
    pub x_label: String,
    /// y-axis description.
    pub y_label: String,
    /// Log10 x axis.
    pub log_x: bool,
    /// Log10 y axis.
    pub log_y: bool,
    /// Explicit x tick positions in data units (default: chosen from the range and the data).
    pub x_ticks: Option<Vec<f64>>,
    /// The series, drawn in order.
    pub series: Vec<Series>,
}

/// Why a chart could not be drawn or written.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// No series has a drawable point.
    #[error(
        "chart {title:?} has no drawable points (empty, non-finite, or non-positive on a log axis)"
    )]
    NoData {
        /// The chart's title.
        title: String,
    },
    /// The embedded font could not be registered.
    #[error("embedded font rejected: {0}")]
    Font(String),
    /// The drawing backend failed.
    #[error("drawing chart {title:?}: {message}")]
    Draw {
        /// The chart's title.
        title: String,
        /// The backend's message.
        message: String,
    },
    /// Writing an output file failed.
    #[error("writing {}: {source}", path.display())]
    Io {
        /// The file being written.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
}

impl Chart {
    /// An empty chart with linear axes.
    pub fn new(
        title: impl Into<String>,
        x_label: impl Into<String>,
        y_label: impl Into<String>,
    ) -> Self {
        Self {
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            ..Self::default()
        }
    }

    /// The chart as an SVG document.
    pub fn svg(&self) -> Result<String, PlotError> {
        render::svg(self)
    }

    /// The chart as PNG bytes (RGB, [`WIDTH`] × [`HEIGHT`]).
    pub fn png(&self) -> Result<Vec<u8>, PlotError> {
        render::png(self)
    }

    /// Writes `STEM.svg` and `STEM.png` (each to a temporary file renamed into place) and
    /// returns their paths. The folder must exist.
    pub fn write(&self, stem: &Path) -> Result<[PathBuf; 2], PlotError> {
        write_pair(stem, &self.svg()?, &self.png()?)
    }
}

/// Writes `svg` to `STEM.svg` and `png` to `STEM.png`, atomically; returns the paths.
fn write_pair(stem: &Path, svg: &str, png: &[u8]) -> Result<[PathBuf; 2], PlotError> {
    let svg_path = with_suffix(stem, "svg");
    let png_path = with_suffix(stem, "png");
    write_atomic(&svg_path, svg.as_bytes())?;
    write_atomic(&png_path, png)?;
    Ok([svg_path, png_path])
}

/// `stem` with `.ext` appended (a dot inside the stem, as in `n_opt_vs_1e18`, is kept).
fn with_suffix(stem: &Path, ext: &str) -> PathBuf {
    let mut name = stem.as_os_str().to_owned();
    name.push(".");
    name.push(ext);
    PathBuf::from(name)
}

/// Writes `bytes` to `path` atomically, into a folder that exists (a mistyped folder is an
/// error, not created).
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), PlotError> {
    let io = |source| PlotError::Io {
        path: path.to_path_buf(),
        source,
    };
    if let Some(dir) = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty() && !d.is_dir())
    {
        let missing = format!("the folder {} does not exist", dir.display());
        return Err(io(std::io::Error::new(
            std::io::ErrorKind::NotFound,
            missing,
        )));
    }
    motionscale_core::write_atomic(path, bytes).map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sweep_chart() -> Chart {
        let sizes: [f64; 5] = [256.0, 1024.0, 4096.0, 16384.0, 65536.0];
        let mut chart = Chart::new("Codebook sweep", "codebook size", "utilisation");
        chart.log_x = true;
        chart.series.push(Series::points(
            "FSQ",
            sizes
                .iter()
                .map(|&v| (v, 0.99 - v.log2() * 0.001))
                .collect(),
        ));
        chart.series.push(Series::line(
            "VQ",
            (0..50)
                .map(|k| 256.0 * 1.12f64.powi(k))
                .map(|v| (v, 1.2 - v.log2() * 0.06))
                .collect(),
        ));
        chart
    }

    #[test]
    fn svg_has_title_labels_ticks_and_legend() {
        let svg = sweep_chart().svg().unwrap();
        assert!(svg.starts_with("<svg"), "{}", &svg[..80]);
        for text in [
            "Codebook sweep",
            "codebook size",
            "utilisation",
            "1024",
            "4096",
            "FSQ",
            "VQ",
        ] {
            assert!(
                svg.contains(&format!("\n{text}\n</text>")),
                "missing text {text:?}"
            );
        }
        assert!(svg.contains("<circle"), "markers are drawn");
        assert!(
            svg.contains("\n16384\n</text>"),
            "powers-of-two ticks from the markers"
        );
        assert!(svg.contains("<polyline"), "the line is drawn");
    }

    #[test]
    fn png_decodes_and_has_dark_text_pixels_in_the_title_band() {
        let png = sweep_chart().png().unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(png));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (WIDTH, HEIGHT));
        assert_eq!(info.color_type, png::ColorType::Rgb);
        // The title is the only thing drawn in the top 40 rows: glyphs must have put ink there.
        let row = 3 * WIDTH as usize;
        let dark = buf[..40 * row]
            .chunks(3)
            .filter(|p| p.iter().all(|&c| c < 100))
            .count();
        assert!(dark > 100, "only {dark} dark pixels in the title band");
    }

    #[test]
    fn write_creates_both_files_atomically() {
        let dir = tempfile::tempdir().unwrap();
        let stem = dir.path().join("sweep.v1");
        let [svg, png] = sweep_chart().write(&stem).unwrap();
        assert_eq!(svg, dir.path().join("sweep.v1.svg"));
        assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
        let files = std::fs::read_dir(dir.path()).unwrap().count();
        assert_eq!(files, 2, "no temporary files left behind");
    }

    #[test]
    fn empty_or_unplottable_chart_is_an_error() {
        let mut chart = Chart::new("empty", "x", "y");
        assert!(matches!(chart.svg(), Err(PlotError::NoData { .. })));
        chart.log_y = true;
        chart
            .series
            .push(Series::points("neg", vec![(1.0, -1.0), (f64::NAN, 2.0)]));
        assert!(matches!(chart.png(), Err(PlotError::NoData { .. })));
    }

    #[test]
    fn missing_folder_names_the_file() {
        let err = sweep_chart()
            .write(Path::new("/nonexistent-dir/x"))
            .unwrap_err();
        assert!(err.to_string().contains("/nonexistent-dir/x.svg"), "{err}");
    }
}
