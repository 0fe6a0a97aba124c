//! The training log: one row per iteration in `loss.csv`, and its plot `loss.png`.

use std::path::Path;

use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{PosediffError, Result};
use crate::plot::{font_bytes, plot_error};

/// One logged iteration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LogRow {
    /// Iteration (0-based).
    pub iteration: u64,
    /// L1 loss.
    pub loss: f64,
    /// Learning rate used.
    pub lr: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Sets × frames in the batch (before the repeat).
    pub images: usize,
}

/// Writes the loss log as CSV.
///
/// # Errors
/// I/O errors.
pub fn write_log(path: &Path, rows: &[LogRow]) -> Result<()> {
    let mut text = String::from("iteration,loss,lr,grad_norm,images\n");
    for r in rows {
        text.push_str(&format!(
            "{},{:e},{:e},{:e},{}\n",
            r.iteration, r.loss, r.lr, r.grad_norm, r.images
        ));
    }
    std::fs::write(path, text).map_err(|e| PosediffError::Write {
        path: path.to_owned(),
        source: e,
    })
}

/// Reads a loss log written by [`write_log`].
///
/// # Errors
/// Unreadable or malformed files.
pub fn read_log(path: &Path) -> Result<Vec<LogRow>> {
    let text = crate::error::read_text(path)?;
    text.lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|line| {
            let f: Vec<&str> = line.split(',').collect();
            let bad = || PosediffError::InvalidFile {
                path: path.to_owned(),
                reason: format!("malformed log line {line:?}"),
            };
            if f.len() != 5 {
                return Err(bad());
            }
            Ok(LogRow {
                iteration: f[0].parse().map_err(|_| bad())?,
                loss: f[1].parse().map_err(|_| bad())?,
                lr: f[2].parse().map_err(|_| bad())?,
                grad_norm: f[3].parse().map_err(|_| bad())?,
                images: f[4].parse().map_err(|_| bad())?,
            })
        })
        .collect()
}

/// The training loss curve (log scale) with a 50-iteration running mean, and the learning rate.
///
/// # Errors
/// No font, write errors; fewer than two rows draw nothing.
pub fn plot_loss(png: &Path, rows: &[LogRow]) -> Result<()> {
    if rows.len() < 2 {
        return Ok(());
    }
    plotters::style::register_font("sans-serif", FontStyle::Normal, font_bytes()?)
        .map_err(|_| plot_error(png, "cannot load the font"))?;
    let root = BitMapBackend::new(png, (1000, 500)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| plot_error(png, e))?;
    let last = rows.last().map_or(1, |r| r.iteration + 1);
    let (lo, hi) = rows
        .iter()
        .map(|r| r.loss)
        .fold((f64::INFINITY, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
    let mut chart = ChartBuilder::on(&root)
        .caption("training loss (L1, ε-prediction)", ("sans-serif", 22))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(60)
        .build_cartesian_2d(0u64..last, (lo.max(1e-6) * 0.9..hi * 1.1).log_scale())
        .map_err(|e| plot_error(png, e))?;
    chart
        .configure_mesh()
        .x_desc("iteration")
        .y_desc("loss")
        .y_label_formatter(&|v| format!("{v:.2}"))
        .draw()
        .map_err(|e| plot_error(png, e))?;
    chart
        .draw_series(LineSeries::new(
            rows.iter().map(|r| (r.iteration, r.loss)),
            RGBColor(170, 190, 230),
        ))
        .map_err(|e| plot_error(png, e))?
        .label("per iteration")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], RGBColor(170, 190, 230)));
    let window = 50;
    let smooth: Vec<(u64, f64)> = rows
        .iter()
        .enumerate()
        .map(|(k, r)| {
            let from = k.saturating_sub(window - 1);
            let part = &rows[from..=k];
            (
                r.iteration,
                part.iter().map(|x| x.loss).sum::<f64>() / part.len() as f64,
            )
        })
        .collect();
    chart
        .draw_series(LineSeries::new(smooth, BLUE.stroke_width(2)))
        .map_err(|e| plot_error(png, e))?
        .label("mean of 50")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLUE.stroke_width(2)));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| plot_error(png, e))?;
    root.present().map_err(|e| plot_error(png, e))?;
    Ok(())
}
