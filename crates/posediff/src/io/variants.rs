//! Harder copies of a set with ground truth (`images/` + `cameras.json`), with their ground
//! truth transformed exactly: the "several cameras" variant zooms every `every`-th photo by a
//! factor drawn from a range (a centred crop resized back to the full size, so that photo's
//! focal is `z` times the original's). The copies are what the real-camera benchmarks and
//! tests run on; the shared sets are only read.

use std::path::{Path, PathBuf};

use opencv::core::{Mat, Rect, Size};
use opencv::prelude::*;
use posediff_geometry::camera_json::CameraRecord;
use posediff_geometry::{CameraModel, LensCamera};

use crate::error::{PosediffError, Result};

/// How a zoomed copy is made.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ZoomVariant {
    /// Every `every`-th photo (the 2nd, 4th, … for 2) is zoomed.
    pub every: usize,
    /// Zoom factors are drawn uniformly from this range.
    pub range: (f64, f64),
    /// Seed of the draw.
    pub seed: u64,
    /// Write EXIF into every copy as a phone would (`Make`, `Model`, `FocalLength` and the
    /// rounded `FocalLengthIn35mmFilm` of its true focal, [`variant_exif`]), so that a zoomed
    /// photo names another focal length, as a zoom lens's photos do.
    pub exif: bool,
}

/// The EXIF a variant writes for a photo of true focal `focal_px` and longer side `max_side`:
/// the 35 mm equivalent rounded to whole mm as cameras store it (a prior within
/// `0.5 / f_35` of the truth) and a focal length in mm at a phone's crop factor of 7.
pub fn variant_exif(focal_px: f64, max_side: u32) -> crate::io::exif::ExifCamera {
    let f35 = (focal_px / f64::from(max_side) * 35.0).round();
    crate::io::exif::ExifCamera {
        make: "posediff".into(),
        model: "variant camera".into(),
        focal: posediff_pipeline::options::ExifFocal {
            focal_mm: Some((f35 / 7.0 * 100.0).round() / 100.0),
            focal_35mm: Some(f35),
            ..Default::default()
        },
    }
}

impl Default for ZoomVariant {
    /// Issue 40's "several cameras": every second photo zoomed by 1.3–1.6×.
    fn default() -> Self {
        Self {
            every: 2,
            range: (1.3, 1.6),
            seed: 0,
            exif: false,
        }
    }
}

/// A 64-bit LCG's next uniform in `[0, 1)` (Knuth's MMIX constants; reproducible everywhere).
fn uniform(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6_364_136_223_846_793_005)
        .wrapping_add(1_442_695_040_888_963_407);
    (*state >> 11) as f64 / (1u64 << 53) as f64
}

fn read_records(set: &Path) -> Result<Vec<CameraRecord>> {
    let path = set.join("cameras.json");
    let text = std::fs::read_to_string(&path).map_err(|e| PosediffError::Read {
        path: path.clone(),
        source: e,
    })?;
    serde_json::from_str(&text).map_err(|e| PosediffError::invalid(&path, e))
}

fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| PosediffError::Write {
            path: dir.to_owned(),
            source: e,
        })?;
    }
    std::fs::write(path, bytes).map_err(|e| PosediffError::Write {
        path: path.to_owned(),
        source: e,
    })
}

/// `image` resampled: each output pixel `(x, y)` bilinearly from the pixel `source(x, y)` of
/// `image` (black outside it).
///
/// # Errors
/// `source`'s errors, OpenCV errors.
pub(crate) fn resample(image: &Mat, source: impl Fn(i32, i32) -> Result<[f64; 2]>) -> Result<Mat> {
    let (w, h) = (image.cols(), image.rows());
    let mut map_x = Mat::new_rows_cols_with_default(
        h,
        w,
        opencv::core::CV_32FC1,
        opencv::core::Scalar::all(0.0),
    )?;
    let mut map_y = map_x.try_clone()?;
    for y in 0..h {
        for x in 0..w {
            let [u, v] = source(x, y)?;
            *map_x.at_2d_mut::<f32>(y, x)? = u as f32;
            *map_y.at_2d_mut::<f32>(y, x)? = v as f32;
        }
    }
    let mut out = Mat::default();
    opencv::imgproc::remap(
        image,
        &mut out,
        &map_x,
        &map_y,
        opencv::imgproc::INTER_LINEAR,
        opencv::core::BORDER_CONSTANT,
        opencv::core::Scalar::all(0.0),
    )?;
    Ok(out)
}

/// `image` encoded as `path`'s extension says (JPEG at quality 95).
pub(crate) fn encode(path: &Path, image: &Mat) -> Result<Vec<u8>> {
    let ext = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_else(|| ".png".into());
    let mut bytes = opencv::core::Vector::<u8>::new();
    let ok = opencv::imgcodecs::imencode(
        &ext,
        image,
        &mut bytes,
        &opencv::core::Vector::from_slice(&[opencv::imgcodecs::IMWRITE_JPEG_QUALITY, 95]),
    )?;
    if ok {
        Ok(bytes.to_vec())
    } else {
        Err(PosediffError::InvalidFile {
            path: path.to_owned(),
            reason: "OpenCV could not encode the image".into(),
        })
    }
}

/// The intrinsics after a crop of `(x0, y0, w, h)` resized to `(width, height)`, OpenCV
/// pixel centres: `u' = (u − x0 + ½) · width / w − ½`.
fn cropped_k(k: &[[f64; 3]; 3], crop: (i32, i32, i32, i32), size: (u32, u32)) -> [[f64; 3]; 3] {
    let (x0, y0, w, h) = crop;
    let sx = f64::from(size.0) / f64::from(w);
    let sy = f64::from(size.1) / f64::from(h);
    let mut out = *k;
    out[0][0] = k[0][0] * sx;
    out[0][1] = k[0][1] * sx;
    out[0][2] = (k[0][2] - f64::from(x0) + 0.5) * sx - 0.5;
    out[1][1] = k[1][1] * sy;
    out[1][2] = (k[1][2] - f64::from(y0) + 0.5) * sy - 0.5;
    out
}

/// Writes the zoomed copy of `set` to `out` (`images/` and `cameras.json`); returns each
/// photo's zoom factor (1 where not zoomed).
///
/// # Errors
/// A set without cameras.json or with unreadable images, an invalid range, writing failures.
pub fn zoom_copy(set: &Path, out: &Path, variant: &ZoomVariant) -> Result<Vec<f64>> {
    let (lo, hi) = variant.range;
    if !(lo >= 1.0 && hi >= lo && hi.is_finite()) || variant.every == 0 {
        return Err(PosediffError::InvalidArgument(format!(
            "zoom range {lo}-{hi} every {}: factors must be at least 1",
            variant.every
        )));
    }
    let records = read_records(set)?;
    let mut state = variant.seed ^ 0x9e37_79b9_7f4a_7c15;
    let mut factors = Vec::with_capacity(records.len());
    let mut written = Vec::with_capacity(records.len());
    for (i, record) in records.iter().enumerate() {
        let source: PathBuf = set.join(&record.image);
        let image =
            posediff_matching::image_check::decode(&source, opencv::imgcodecs::IMREAD_COLOR)?;
        let (w, h) = (image.cols(), image.rows());
        if (w as u32, h as u32) != (record.width, record.height) {
            return Err(PosediffError::InvalidFile {
                path: source,
                reason: format!(
                    "the image is {w}×{h} but cameras.json says {}×{}",
                    record.width, record.height
                ),
            });
        }
        let zoom = if (i + 1) % variant.every == 0 {
            lo + (hi - lo) * uniform(&mut state)
        } else {
            1.0
        };
        let mut record = record.clone();
        let bytes = if zoom > 1.0 {
            let cw = ((f64::from(w) / zoom).round() as i32).clamp(1, w);
            let ch = ((f64::from(h) / zoom).round() as i32).clamp(1, h);
            let crop = ((w - cw) / 2, (h - ch) / 2, cw, ch);
            let roi = Mat::roi(&image, Rect::new(crop.0, crop.1, crop.2, crop.3))?;
            let mut resized = Mat::default();
            opencv::imgproc::resize(
                &roi,
                &mut resized,
                Size::new(w, h),
                0.0,
                0.0,
                opencv::imgproc::INTER_AREA,
            )?;
            record.k = cropped_k(&record.k, crop, (record.width, record.height));
            // The zoom actually applied (the crop is rounded to whole pixels).
            factors.push(f64::from(w) / f64::from(cw));
            encode(&out.join(&record.image), &resized)?
        } else {
            factors.push(1.0);
            // The photo itself, byte for byte (re-encoding would change its features); EXIF
            // goes in a segment of its own, the image data untouched.
            std::fs::read(&source).map_err(|e| PosediffError::Read {
                path: source.clone(),
                source: e,
            })?
        };
        let bytes = if variant.exif {
            let exif = variant_exif(record.k[0][0], record.width.max(record.height));
            crate::io::exif::with_exif(&bytes, &exif)?
        } else {
            bytes
        };
        write_bytes(&out.join(&record.image), &bytes)?;
        written.push(record);
    }
    let path = out.join("cameras.json");
    let text =
        serde_json::to_string_pretty(&written).map_err(|e| PosediffError::invalid(&path, e))?;
    std::fs::write(&path, text).map_err(|e| PosediffError::Write { path, source: e })?;
    Ok(factors)
}

/// The "wide-angle" variant: every photo seen through an OpenCV radial distortion
/// (`x_d = x (1 + k1 r² + k2 r⁴)` in normalised coordinates of its own `K`), so the copy's
/// ground truth is the same `K` with an OPENCV model `[fx, fy, cx, cy, k1, k2, 0, 0]`; or,
/// with `fisheye`, through OpenCV's fisheye model (`r_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ +
/// k4 θ⁸)`, `θ = atan r`: OPENCV_FISHEYE `[fx, fy, cx, cy, k1, k2, k3, k4]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RadialVariant {
    /// `k1`.
    pub k1: f64,
    /// `k2`.
    pub k2: f64,
    /// OPENCV_FISHEYE's `k3, k4` (`None`: the OPENCV model, whose tangential terms are 0).
    pub fisheye: Option<[f64; 2]>,
}

impl Default for RadialVariant {
    /// Issue 40's "wide-angle": `k1 = −0.12`, `k2 = 0.02`.
    fn default() -> Self {
        Self {
            k1: -0.12,
            k2: 0.02,
            fisheye: None,
        }
    }
}

impl RadialVariant {
    /// The lens at focal `(fx, fy)` and centre `(cx, cy)`.
    fn lens(&self, (fx, fy): (f64, f64), (cx, cy): (f64, f64)) -> Result<LensCamera> {
        let (model, rest) = match self.fisheye {
            None => (CameraModel::OpenCv, [0.0, 0.0]),
            Some(k34) => (CameraModel::OpenCvFisheye, k34),
        };
        Ok(LensCamera::new(
            model,
            vec![fx, fy, cx, cy, self.k1, self.k2, rest[0], rest[1]],
        )?)
    }

    /// How errors name it.
    fn describe(&self) -> String {
        match self.fisheye {
            None => format!("radial variant k1 {} k2 {}", self.k1, self.k2),
            Some([k3, k4]) => format!(
                "fisheye variant k1 {} k2 {} k3 {k3} k4 {k4}",
                self.k1, self.k2
            ),
        }
    }
}

/// Writes the distorted copy of `set` to `out` (`images/` and `cameras.json` with each
/// camera's lens): each output pixel takes the original's colour at its undistorted position
/// (bilinear). A barrel lens (`k1 < 0`) sees more than the original at the same focal, so the
/// copy's focal is the original's times the smallest factor `α ≥ 1` that keeps every corner's
/// undistorted position inside the original (no black border, as a real lens has none);
/// cameras.json holds that focal.
///
/// # Errors
/// A set without cameras.json or with unreadable images, a distortion that folds inside an
/// image, writing failures.
pub fn radial_copy(set: &Path, out: &Path, variant: &RadialVariant) -> Result<()> {
    let records = read_records(set)?;
    let mut written = Vec::with_capacity(records.len());
    for record in &records {
        let source: PathBuf = set.join(&record.image);
        let image =
            posediff_matching::image_check::decode(&source, opencv::imgcodecs::IMREAD_COLOR)?;
        let (w, h) = (image.cols(), image.rows());
        let alpha = inside_factor(&record.k, (w, h), variant)?;
        let mut k = record.k;
        k[0][0] *= alpha;
        k[1][1] *= alpha;
        let original = record.k;
        let lens = variant.lens((k[0][0], k[1][1]), (k[0][2], k[1][2]))?;
        let distorted = resample(&image, |x, y| {
            let ray = lens
                .unproject(&nalgebra::Vector2::new(f64::from(x), f64::from(y)))
                .map_err(|e| {
                    PosediffError::InvalidArgument(format!(
                        "{}: pixel ({x}, {y}) of {}: {e}",
                        variant.describe(),
                        source.display()
                    ))
                })?;
            Ok([
                original[0][0] * ray.x + k[0][2],
                original[1][1] * ray.y + k[1][2],
            ])
        })?;
        let target = out.join(&record.image);
        write_bytes(&target, &encode(&target, &distorted)?)?;
        let mut record = record.clone();
        record.k = k;
        let camera = record.to_camera()?;
        written.push(CameraRecord::from_lens_camera(
            record.image.clone(),
            &camera,
            &lens,
        )?);
    }
    let path = out.join("cameras.json");
    let text =
        serde_json::to_string_pretty(&written).map_err(|e| PosediffError::invalid(&path, e))?;
    std::fs::write(&path, text).map_err(|e| PosediffError::Write { path, source: e })?;
    Ok(())
}

/// The smallest focal factor `α ≥ 1` at which every corner of a `w × h` image, undistorted
/// through `variant` at focal `α f`, falls inside the original at `f` (bisection; 1 when the
/// lens shrinks nothing).
fn inside_factor(k: &[[f64; 3]; 3], (w, h): (i32, i32), variant: &RadialVariant) -> Result<f64> {
    let (fx, fy, cx, cy) = (k[0][0], k[1][1], k[0][2], k[1][2]);
    let corners = [
        (0.0, 0.0),
        (f64::from(w - 1), 0.0),
        (0.0, f64::from(h - 1)),
        (f64::from(w - 1), f64::from(h - 1)),
    ];
    let inside = |alpha: f64| -> Result<bool> {
        let lens = variant.lens((alpha * fx, alpha * fy), (cx, cy))?;
        for (u, v) in corners {
            let Ok(ray) = lens.unproject(&nalgebra::Vector2::new(u, v)) else {
                return Ok(false);
            };
            let (x, y) = (fx * ray.x + cx, fy * ray.y + cy);
            if !(-0.5..=f64::from(w) - 0.5).contains(&x)
                || !(-0.5..=f64::from(h) - 0.5).contains(&y)
            {
                return Ok(false);
            }
        }
        Ok(true)
    };
    if inside(1.0)? {
        return Ok(1.0);
    }
    let (mut lo, mut hi) = (1.0, 2.0);
    if !inside(hi)? {
        return Err(PosediffError::InvalidArgument(format!(
            "{}: the lens sees beyond the photo even at twice its focal",
            variant.describe()
        )));
    }
    for _ in 0..50 {
        let mid = 0.5 * (lo + hi);
        if inside(mid)? {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Ok(hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A crop's intrinsics map a world point to the same image content: the centre of the crop
    /// goes to the centre of the new image, and the focal scales by the zoom.
    #[test]
    fn cropped_intrinsics_follow_the_pixels() {
        let k = [[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]];
        let z = cropped_k(&k, (80, 60, 480, 360), (640, 480));
        let s = 640.0 / 480.0;
        assert!((z[0][0] - 500.0 * s).abs() < 1e-12);
        // The old principal point (the old centre) is the crop's centre: the new centre.
        assert!((z[0][2] - 319.5).abs() < 1e-9, "{}", z[0][2]);
        assert!((z[1][2] - 239.5).abs() < 1e-9, "{}", z[1][2]);
        // Pixel 80 (the crop's first column centre) maps to u' = (0.5) s − 0.5.
        let u = 80.0;
        let x = (u - k[0][2]) / k[0][0];
        let u_new = z[0][0] * x + z[0][2];
        assert!((u_new - (0.5 * s - 0.5)).abs() < 1e-9, "{u_new}");
        let mut state = 1;
        let draws: Vec<f64> = (0..100).map(|_| uniform(&mut state)).collect();
        assert!(draws.iter().all(|d| (0.0..1.0).contains(d)));
        assert!(draws.iter().any(|d| *d > 0.9) && draws.iter().any(|d| *d < 0.1));
    }
}
