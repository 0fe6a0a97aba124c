//! `posediff plot`: camera frusta seen from above and from the side, optionally against the
//! ground truth (the estimate aligned to it first), with per-camera errors in the legend.
//!
//! "Above" and "side" are the principal axes of the (ground-truth, if given) camera centres:
//! the view from above looks along the axis of least spread, the side view along the middle one.
//! Labels use DejaVu Sans from Debian's `fonts-dejavu-core` (installed by `cargo xtask setup`).

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Point2, Point3, Vector3};
use plotters::prelude::*;
use posediff_geometry::{Camera, align_cameras_by_extrinsics};

use crate::error::{PosediffError, Result};
use crate::io::export::NamedCamera;

/// Where the label font is looked for.
pub const FONT_PATHS: [&str; 2] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
];

/// Image size of the plot.
const PLOT_SIZE: (u32, u32) = (1600, 700);

/// Per-camera errors of an estimate against the ground truth.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraErrors {
    /// Image name.
    pub image: String,
    /// Rotation error after alignment, degrees.
    pub rotation_deg: f64,
    /// Centre error after alignment, relative to the ground-truth scene extent.
    pub center_rel: f64,
}

/// Aligns `estimate` to `gt` (PyTorch3D's extrinsics alignment, as the official demo) and
/// returns the aligned cameras and the per-camera errors.
///
/// # Errors
/// Different camera counts, degenerate alignments.
pub fn align_and_compare(
    estimate: &[NamedCamera],
    gt: &[NamedCamera],
) -> Result<(Vec<Camera>, Vec<CameraErrors>)> {
    let est: Vec<Camera> = estimate.iter().map(|c| c.camera).collect();
    let truth: Vec<Camera> = gt.iter().map(|c| c.camera).collect();
    let sim = align_cameras_by_extrinsics(&est, &truth)?;
    let aligned: Vec<Camera> = est.iter().map(|c| sim.transform_camera(c)).collect();
    let centers: Vec<Point3<f64>> = truth.iter().map(Camera::center).collect();
    let mid = centers.iter().map(|p| p.coords).sum::<Vector3<f64>>() / centers.len().max(1) as f64;
    let extent = centers
        .iter()
        .map(|p| (p.coords - mid).norm())
        .fold(0.0, f64::max)
        .max(f64::EPSILON);
    let errors = aligned
        .iter()
        .zip(&truth)
        .zip(estimate)
        .map(|((a, t), n)| CameraErrors {
            image: n.image.clone(),
            rotation_deg: posediff_geometry::rotation_angle_between_deg(
                &t.cam_from_world.rotation,
                &a.cam_from_world.rotation,
            ),
            center_rel: (a.center() - t.center()).norm() / extent,
        })
        .collect();
    Ok((aligned, errors))
}

/// The projection basis: principal axes of the centres, largest spread first.
fn view_basis(centers: &[Point3<f64>]) -> (Vector3<f64>, Matrix3<f64>) {
    let n = centers.len().max(1) as f64;
    let mid = centers.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n;
    let cov = centers
        .iter()
        .map(|p| (p.coords - mid) * (p.coords - mid).transpose())
        .sum::<Matrix3<f64>>()
        / n;
    let eig = cov.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|a, b| eig.eigenvalues[*b].total_cmp(&eig.eigenvalues[*a]));
    let basis = Matrix3::from_columns(&order.map(|i| eig.eigenvectors.column(i).into_owned()));
    (mid, basis)
}

/// The frustum of a camera as world-space line segments (centre to the four image corners at
/// `depth`, and the image rectangle).
fn frustum(camera: &Camera, depth: f64) -> Vec<(Point3<f64>, Point3<f64>)> {
    let (w, h) = (
        f64::from(camera.image_size.width()) - 1.0,
        f64::from(camera.image_size.height()) - 1.0,
    );
    let corners = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)]
        .map(|(x, y)| camera.unproject(&Point2::new(x, y), depth));
    let c = camera.center();
    let mut segs: Vec<_> = corners.iter().map(|k| (c, *k)).collect();
    segs.extend((0..4).map(|i| (corners[i], corners[(i + 1) % 4])));
    segs
}

pub(crate) fn font_bytes() -> Result<&'static [u8]> {
    for p in FONT_PATHS {
        if let Ok(bytes) = std::fs::read(p) {
            return Ok(Box::leak(bytes.into_boxed_slice()));
        }
    }
    Err(PosediffError::read(
        &PathBuf::from(FONT_PATHS[0]),
        std::io::Error::new(
            std::io::ErrorKind::NotFound,
            "no DejaVu Sans font: apt-get install fonts-dejavu-core",
        ),
    ))
}

pub(crate) fn plot_error(path: &Path, e: impl std::fmt::Display) -> PosediffError {
    PosediffError::Write {
        path: path.to_owned(),
        source: std::io::Error::other(e.to_string()),
    }
}

/// Writes the plot to `png`.
///
/// # Errors
/// No font, a degenerate alignment, write errors.
pub fn plot_cameras(
    png: &Path,
    estimate: &[NamedCamera],
    gt: Option<&[NamedCamera]>,
) -> Result<Vec<CameraErrors>> {
    plotters::style::register_font("sans-serif", FontStyle::Normal, font_bytes()?)
        .map_err(|_| plot_error(png, "cannot load the font"))?;
    let (shown, errors) = match gt {
        Some(g) => {
            let (aligned, errors) = align_and_compare(estimate, g)?;
            (aligned, errors)
        }
        None => (estimate.iter().map(|c| c.camera).collect(), Vec::new()),
    };
    let reference: Vec<Camera> =
        gt.map_or_else(|| shown.clone(), |g| g.iter().map(|c| c.camera).collect());
    let centers: Vec<Point3<f64>> = reference.iter().map(Camera::center).collect();
    let (mid, basis) = view_basis(&centers);
    let extent = centers
        .iter()
        .map(|p| (p.coords - mid).norm())
        .fold(0.0, f64::max)
        .max(1e-9);
    let depth = 0.15 * extent;
    let root = BitMapBackend::new(png, PLOT_SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(|e| plot_error(png, e))?;
    let (views, legend) = root.split_horizontally(1150);
    let panels = views.split_evenly((1, 2));
    for (panel, (a, b, title)) in panels
        .iter()
        .zip([(0usize, 1usize, "from above"), (0, 2, "from the side")])
    {
        let lim = 1.3 * extent;
        let mut chart = ChartBuilder::on(panel)
            .caption(title, ("sans-serif", 24))
            .margin(10)
            .x_label_area_size(30)
            .y_label_area_size(40)
            .build_cartesian_2d(-lim..lim, -lim..lim)
            .map_err(|e| plot_error(png, e))?;
        chart
            .configure_mesh()
            .draw()
            .map_err(|e| plot_error(png, e))?;
        let to2d = |p: &Point3<f64>| {
            let q = basis.transpose() * (p.coords - mid);
            (q[a], q[b])
        };
        let mut draw = |cams: &[Camera], color: RGBColor| -> Result<()> {
            for cam in cams {
                for (s, e) in frustum(cam, depth) {
                    chart
                        .draw_series(LineSeries::new([to2d(&s), to2d(&e)], &color))
                        .map_err(|e| plot_error(png, e))?;
                }
            }
            Ok(())
        };
        if gt.is_some() {
            draw(&reference, RGBColor(30, 150, 60))?;
        }
        draw(&shown, RGBColor(30, 80, 200))?;
    }
    let mut lines = vec![if gt.is_some() {
        "blue: estimate (aligned), green: ground truth".to_owned()
    } else {
        "blue: estimate".to_owned()
    }];
    lines.extend(errors.iter().map(|e| {
        format!(
            "{}: {:.1} deg, centre {:.3}",
            e.image, e.rotation_deg, e.center_rel
        )
    }));
    for (i, line) in lines.iter().enumerate().take(30) {
        legend
            .draw(&Text::new(
                line.clone(),
                (10, 20 + 22 * i as i32),
                ("sans-serif", 16).into_font(),
            ))
            .map_err(|e| plot_error(png, e))?;
    }
    root.present().map_err(|e| plot_error(png, e))?;
    Ok(errors)
}
