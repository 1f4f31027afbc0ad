//! A labelled matrix drawn as coloured cells with their values (e.g. the FID and R-precision
//! matrices of continual learning, rows = after step i, columns = dataset j).

use crate::render::{font, Figure};
use crate::{write_pair, PlotError};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};

/// A matrix with row and column labels.
#[derive(Debug, Clone, PartialEq)]
pub struct Heatmap {
    /// Title above the cells.
    pub title: String,
    /// Row labels, top to bottom.
    pub rows: Vec<String>,
    /// Column labels, left to right.
    pub columns: Vec<String>,
    /// `rows × columns` values; non-finite cells are left blank.
    pub values: Vec<Vec<f64>>,
}

/// Viridis stops (dark blue → yellow).
const STOPS: [(u8, u8, u8); 5] = [
    (68, 1, 84),
    (59, 82, 139),
    (33, 145, 140),
    (94, 201, 98),
    (253, 231, 37),
];

fn colour(t: f64) -> RGBColor {
    let x = t.clamp(0.0, 1.0) * (STOPS.len() - 1) as f64;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f64;
    let mix = |a: u8, b: u8| (f64::from(a) + (f64::from(b) - f64::from(a)) * f).round() as u8;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

impl Heatmap {
    /// The heat map as an SVG document.
    pub fn svg(&self) -> Result<String, PlotError> {
        crate::render::svg(self)
    }

    /// The heat map as PNG bytes.
    pub fn png(&self) -> Result<Vec<u8>, PlotError> {
        crate::render::png(self)
    }

    /// Writes `STEM.svg` and `STEM.png` atomically.
    pub fn write(&self, stem: &Path) -> Result<[PathBuf; 2], PlotError> {
        write_pair(stem, &self.svg()?, &self.png()?)
    }
}

impl Figure for Heatmap {
    fn title(&self) -> &str {
        &self.title
    }

    fn check(&self) -> Result<(), PlotError> {
        let finite = self.values.iter().flatten().any(|v| v.is_finite());
        let shaped = self.values.len() == self.rows.len()
            && self.values.iter().all(|r| r.len() == self.columns.len());
        if finite && shaped {
            Ok(())
        } else {
            Err(PlotError::NoData {
                title: self.title.clone(),
            })
        }
    }

    fn draw_on<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<(), String> {
        let err = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
        root.fill(&WHITE).map_err(err)?;
        let (width, height) = root.dim_in_pixel();
        let (left, top, right, bottom) = (200i32, 60i32, 20i32, 120i32);
        root.draw(&Text::new(
            self.title.clone(),
            (left, 20),
            font(22).into_text_style(root),
        ))
        .map_err(err)?;
        let (n_rows, n_cols) = (self.rows.len() as i32, self.columns.len() as i32);
        let cell_w = (width as i32 - left - right) / n_cols.max(1);
        let cell_h = (height as i32 - top - bottom) / n_rows.max(1);
        let finite: Vec<f64> = self
            .values
            .iter()
            .flatten()
            .copied()
            .filter(|v| v.is_finite())
            .collect();
        let lo = finite.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = finite.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let span = if hi > lo { hi - lo } else { 1.0 };
        let label = font(14).into_text_style(root);
        for (i, row) in self.values.iter().enumerate() {
            let y = top + i as i32 * cell_h;
            root.draw(&Text::new(
                self.rows[i].clone(),
                (10, y + cell_h / 2 - 7),
                label.clone(),
            ))
            .map_err(err)?;
            for (j, &v) in row.iter().enumerate() {
                let x = left + j as i32 * cell_w;
                if !v.is_finite() {
                    continue;
                }
                let t = (v - lo) / span;
                root.draw(&Rectangle::new(
                    [(x, y), (x + cell_w - 2, y + cell_h - 2)],
                    colour(t).filled(),
                ))
                .map_err(err)?;
                let ink = if t > 0.6 { BLACK } else { WHITE };
                root.draw(&Text::new(
                    format!("{v:.3}"),
                    (x + cell_w / 2 - 20, y + cell_h / 2 - 7),
                    font(14).color(&ink).into_text_style(root),
                ))
                .map_err(err)?;
            }
        }
        for (j, name) in self.columns.iter().enumerate() {
            let x = left + j as i32 * cell_w;
            root.draw(&Text::new(
                name.clone(),
                (x + 4, top + n_rows * cell_h + 10),
                label.clone(),
            ))
            .map_err(err)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map() -> Heatmap {
        Heatmap {
            title: "R-precision".into(),
            rows: vec!["after D1".into(), "after D2".into()],
            columns: vec!["D1".into(), "D2".into()],
            values: vec![vec![0.5, 0.1], vec![0.4, f64::NAN]],
        }
    }

    #[test]
    fn draws_every_finite_cell_with_its_value() {
        let svg = map().svg().unwrap();
        for text in ["R-precision", "after D2", "0.500", "0.100", "0.400"] {
            assert!(svg.contains(text), "{text} missing");
        }
        assert!(!svg.contains("NaN"));
        let png = map().png().unwrap();
        assert_eq!(&png[1..4], b"PNG");
    }

    #[test]
    fn refuses_a_ragged_or_empty_matrix() {
        let mut ragged = map();
        ragged.values[1].pop();
        assert!(matches!(ragged.svg(), Err(PlotError::NoData { .. })));
        let mut empty = map();
        empty.values = vec![vec![f64::NAN; 2]; 2];
        assert!(matches!(empty.png(), Err(PlotError::NoData { .. })));
    }

    #[test]
    fn colours_run_from_dark_to_light() {
        assert_eq!(colour(0.0), RGBColor(68, 1, 84));
        assert_eq!(colour(1.0), RGBColor(253, 231, 37));
    }
}
