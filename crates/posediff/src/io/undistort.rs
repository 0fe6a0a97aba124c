//! `--undistort`: what COLMAP's image undistorter writes for the tools that need pinhole cameras
//! (3D Gaussian splatting, gsplat, most NeRF code): each estimated photo whose camera has a lens
//! resampled onto its pinhole camera (same size and `K`; bilinear, pixels the photo does not
//! cover black — none for barrel distortion, whose undistorted corners lie inside the photo),
//! the others copied byte for byte, and a COLMAP model of PINHOLE cameras whose 2-D points are
//! the undistorted keypoints.

use std::path::{Path, PathBuf};

use posediff_geometry::lens::LensCamera;
use rayon::prelude::*;

use crate::error::{PosediffError, Result};
use crate::io::colmap::{ColmapFormat, ColmapModel};
use crate::reconstruction::Reconstruction;

/// Writes `dir/images/<name>` for every estimated image of `r` (photos `files`, one per image)
/// and the pinhole model `dir/sparse/0`; returns how many photos were resampled.
///
/// # Errors
/// A count of files that is not the images'; unreadable photos; I/O errors.
pub fn write_undistorted(
    dir: &Path,
    r: &Reconstruction,
    files: &[PathBuf],
    format: ColmapFormat,
) -> Result<usize> {
    if files.len() != r.images.len() {
        return Err(PosediffError::InvalidArgument(format!(
            "{} image files for {} images",
            files.len(),
            r.images.len()
        )));
    }
    let resampled = r
        .images
        .par_iter()
        .zip(files)
        .filter(|(record, _)| record.camera.camera.is_some())
        .map(|(record, file)| {
            let target = dir.join("images").join(&record.camera.image);
            if let Some(parent) = target.parent() {
                std::fs::create_dir_all(parent).map_err(|source| PosediffError::Write {
                    path: parent.to_owned(),
                    source,
                })?;
            }
            match &record.camera.lens {
                Some(lens) => {
                    let bytes = undistorted_photo(file, lens, &target)?;
                    std::fs::write(&target, bytes).map_err(|source| PosediffError::Write {
                        path: target.clone(),
                        source,
                    })?;
                    Ok(1)
                }
                None => {
                    std::fs::copy(file, &target).map_err(|source| PosediffError::Write {
                        path: target.clone(),
                        source,
                    })?;
                    Ok(0)
                }
            }
        })
        .sum::<Result<usize>>()?;
    let mut pinhole = r.clone();
    for record in &mut pinhole.images {
        record.camera.lens = None;
    }
    ColmapModel::from_reconstruction(&pinhole)?.write(&dir.join("sparse").join("0"), format)?;
    Ok(resampled)
}

/// The photo `file` resampled onto the pinhole part of `lens`, encoded as `target`'s extension.
fn undistorted_photo(file: &Path, lens: &LensCamera, target: &Path) -> Result<Vec<u8>> {
    let image = crate::reconstruction::read_colour(file)?;
    let out = crate::io::variants::resample(&image, |x, y| {
        let p = lens.distort_pixel(&nalgebra::Vector2::new(f64::from(x), f64::from(y)));
        Ok([p.x, p.y])
    })?;
    crate::io::variants::encode(target, &out)
}
