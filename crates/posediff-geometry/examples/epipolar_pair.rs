//! Fundamental matrix and Sampson errors for an image pair of a real data set with
//! ground-truth cameras.
//!
//! ```text
//! cargo run --release -p posediff-geometry --features serde --example epipolar_pair -- \
//!     [DATASET_DIR (default ../shared/data/strecha_fountainP11)] [I (default 0)] [J (default 1)]
//! ```
//!
//! The 3-D points are placed around the least-squares intersection of all optical axes (where
//! the cameras look), projected into both images with the ground-truth cameras, and then one
//! copy of each match is moved by 2 px across the epipolar line to show how the error grows.
#![allow(clippy::print_stdout)]

use std::path::PathBuf;

use anyhow::{Context, bail};
use nalgebra::{Point2, Vector3};
use posediff_geometry::camera_json::CameraRecord;
use posediff_geometry::normalize::optical_axis_intersection;
use posediff_geometry::{
    Camera, fundamental_from_cameras, sampson_error, symmetric_epipolar_distance_sq,
};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = PathBuf::from(
        args.next()
            .unwrap_or_else(|| "../shared/data/strecha_fountainP11".into()),
    );
    let i: usize = args
        .next()
        .map_or(Ok(0), |s| s.parse())
        .context("image index I")?;
    let j: usize = args
        .next()
        .map_or(Ok(1), |s| s.parse())
        .context("image index J")?;

    let path = dir.join("cameras.json");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let records: Vec<CameraRecord> =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    if i >= records.len() || j >= records.len() || i == j {
        bail!(
            "need two different image indices below {}, got {i} and {j}",
            records.len()
        );
    }
    let cameras = records
        .iter()
        .map(CameraRecord::to_camera)
        .collect::<Result<Vec<Camera>, _>>()
        .with_context(|| format!("cameras in {}", path.display()))?;
    let (c1, c2) = (&cameras[i], &cameras[j]);

    let f = fundamental_from_cameras(c1, c2);
    let f_unit = f / f.norm();
    println!("data set   {}", dir.display());
    println!("pair       {} -> {}", records[i].image, records[j].image);
    println!(
        "baseline   {:.4} (world units)",
        (c1.center() - c2.center()).norm()
    );
    println!("F (x2^T F x1 = 0, scaled to unit Frobenius norm):");
    for r in 0..3 {
        println!(
            "  [{:>13.6e} {:>13.6e} {:>13.6e}]",
            f_unit[(r, 0)],
            f_unit[(r, 1)],
            f_unit[(r, 2)]
        );
    }

    let target = optical_axis_intersection(&cameras)?.point;
    let radius = 0.1 * (c1.center() - target).norm();
    println!(
        "scene point (optical-axis intersection) {:.3} {:.3} {:.3}, radius {radius:.3}",
        target.x, target.y, target.z
    );
    println!(
        "{:>22} {:>22} {:>12} {:>12} {:>14}",
        "x1 (px)", "x2 (px)", "Sampson px2", "sym. px2", "+2px Sampson"
    );
    let offsets = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [-1.0, 0.5, -0.5],
        [0.7, -0.7, 0.3],
    ];
    for o in offsets {
        let x = target + Vector3::new(o[0], o[1], o[2]) * radius;
        let (Some(p1), Some(p2)) = (c1.project(&x), c2.project(&x)) else {
            println!("point behind a camera, skipped");
            continue;
        };
        let line = f * p1.to_homogeneous();
        let normal = Vector3::new(line.x, line.y, 0.0).normalize();
        let moved = Point2::new(p2.x + 2.0 * normal.x, p2.y + 2.0 * normal.y);
        println!(
            "{:>10.2} {:>10.2}  {:>10.2} {:>10.2}  {:>12.3e} {:>12.3e} {:>14.4}",
            p1.x,
            p1.y,
            p2.x,
            p2.y,
            sampson_error(&f, &p1, &p2)?,
            symmetric_epipolar_distance_sq(&f, &p1, &p2)?,
            sampson_error(&f, &p1, &moved)?,
        );
    }
    Ok(())
}
