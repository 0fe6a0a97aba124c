//! The official demo/test image loader (`util/load_img_folder.py`, SPEC.md §7.1): files ending in
//! .png/.jpg/.jpeg (any case) sorted by path, RGB in `[0, 1]`, the centre square of side
//! `min(W, H)` ([`CenterCrop`]), resized to 224 px bilinearly by size (`align_corners=False`, no
//! antialiasing): output index `d` samples the crop at `(d + 0.5)·m/224 − 0.5`, clamped at 0.

use std::path::{Path, PathBuf};

use opencv::core::Mat;
use opencv::prelude::*;
use posediff_geometry::{CenterCrop, ImageSize, MODEL_INPUT_SIDE};

use crate::error::{PosediffError, Result};

/// The extensions the official loader accepts (compared case-insensitively).
const EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// One loaded image.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadedImage {
    /// The file.
    pub path: PathBuf,
    /// Its size.
    pub size: ImageSize,
    /// The crop that produced the model input.
    pub crop: CenterCrop,
    /// `3 × 224 × 224` RGB in `[0, 1]`, channel-major.
    pub pixels: Vec<f32>,
}

/// The image files of a folder, sorted by path, as the official loader picks them.
///
/// # Errors
/// An unreadable folder, or one without images.
pub fn image_files(folder: &Path) -> Result<Vec<PathBuf>> {
    let entries =
        std::fs::read_dir(folder).map_err(|_| PosediffError::NoImages(folder.to_owned()))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            // A link to a missing file is listed too, so that the check names it (a broken
            // image is an error, or skipped and listed, never dropped unsaid).
            (p.is_file() || p.is_symlink())
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(PosediffError::NoImages(folder.to_owned()));
    }
    Ok(files)
}

/// Taps of a size-based bilinear resize: for each output index, `(i0, i1, w0, w1)`. The source
/// coordinate is computed in float32 as PyTorch's CPU kernel does (`(float)in/out`, then
/// `scale·(d + 0.5) − 0.5`): in float64 the weights would differ by up to ~5e-6 at 300 px.
fn bilinear_taps(len_in: usize, len_out: usize) -> Vec<(usize, usize, f64, f64)> {
    let scale = len_in as f32 / len_out as f32;
    (0..len_out)
        .map(|d| {
            let src = (scale * (d as f32 + 0.5) - 0.5).max(0.0);
            let i0 = (src.floor() as usize).min(len_in - 1);
            let i1 = (i0 + 1).min(len_in - 1);
            let l1 = f64::from(src - i0 as f32);
            (i0, i1, 1.0 - l1, l1)
        })
        .collect()
}

/// The official preprocessing of interleaved RGB bytes (`H × W × 3`): crop, scale to `[0, 1]`,
/// resize to `target`. Returns `3 × target × target`, channel-major.
pub fn preprocess_rgb(rgb: &[u8], size: ImageSize, target: u32) -> (CenterCrop, Vec<f32>) {
    let crop = CenterCrop::official(size, target);
    let (w, m, t) = (size.width() as usize, crop.side as usize, target as usize);
    let (left, top) = (crop.left as usize, crop.top as usize);
    let taps = bilinear_taps(m, t);
    let mut out = vec![0f32; 3 * t * t];
    // Rows first (m × m → t × m), then columns, per channel.
    let mut rows = vec![0f64; t * m];
    for c in 0..3 {
        let px = |y: usize, x: usize| f64::from(rgb[((top + y) * w + left + x) * 3 + c]) / 255.0;
        for (r, &(i0, i1, w0, w1)) in taps.iter().enumerate() {
            for x in 0..m {
                rows[r * m + x] = w0 * px(i0, x) + w1 * px(i1, x);
            }
        }
        for r in 0..t {
            for (col, &(j0, j1, w0, w1)) in taps.iter().enumerate() {
                out[(c * t + r) * t + col] = (w0 * rows[r * m + j0] + w1 * rows[r * m + j1]) as f32;
            }
        }
    }
    (crop, out)
}

/// Reads an image as interleaved RGB bytes (JPEG or PNG, structurally checked first).
///
/// # Errors
/// A missing, unreadable, corrupt or truncated file, named.
pub fn read_rgb(path: &Path) -> Result<(ImageSize, Vec<u8>)> {
    let bgr = posediff_matching::image_check::decode(path, opencv::imgcodecs::IMREAD_COLOR)?;
    let mut rgb = Mat::default();
    opencv::imgproc::cvt_color_def(&bgr, &mut rgb, opencv::imgproc::COLOR_BGR2RGB)?;
    let rgb = if rgb.is_continuous() {
        rgb
    } else {
        rgb.try_clone()?
    };
    let size = ImageSize::new(rgb.cols() as u32, rgb.rows() as u32)
        .map_err(|_| PosediffError::UnreadableImage(path.to_owned()))?;
    Ok((size, rgb.data_bytes()?.to_vec()))
}

/// Loads and preprocesses images in the given order.
///
/// # Errors
/// Unreadable images, named.
pub fn load_images(paths: &[PathBuf]) -> Result<Vec<LoadedImage>> {
    paths
        .iter()
        .map(|p| {
            let (size, rgb) = read_rgb(p)?;
            let (crop, pixels) = preprocess_rgb(&rgb, size, MODEL_INPUT_SIDE);
            Ok(LoadedImage {
                path: p.clone(),
                size,
                crop,
                pixels,
            })
        })
        .collect()
}

/// Writes an RGB image (`height × width × 3` bytes, row-major) as a lossless PNG: the same
/// pixels come back from [`read_rgb`].
///
/// # Errors
/// A buffer that is not `width × height × 3` bytes; an empty image; OpenCV or I/O errors.
pub fn write_rgb_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    let expected = width as usize * height as usize * 3;
    if width == 0 || height == 0 || rgb.len() != expected {
        return Err(PosediffError::InvalidArgument(format!(
            "an image of {width}×{height} RGB pixels needs {expected} bytes, got {}",
            rgb.len()
        )));
    }
    let flat = Mat::from_slice(rgb)?;
    let shaped = flat.reshape(3, height as i32)?;
    let mut bgr = Mat::default();
    opencv::imgproc::cvt_color_def(&shaped, &mut bgr, opencv::imgproc::COLOR_RGB2BGR)?;
    let mut bytes = opencv::core::Vector::<u8>::new();
    opencv::imgcodecs::imencode(".png", &bgr, &mut bytes, &opencv::core::Vector::new())?;
    std::fs::write(path, bytes.as_slice()).map_err(|source| PosediffError::Write {
        path: path.to_owned(),
        source,
    })
}

/// The files that can be used and, for the others, why not (missing, unreadable, empty, not
/// a JPEG or PNG, corrupt or truncated: [`posediff_matching::image_check::image_problem`]). Files are read in parallel; no
/// image is decoded.
pub fn check_images(files: &[PathBuf]) -> (Vec<PathBuf>, Vec<(PathBuf, String)>) {
    use rayon::prelude::*;
    let verdicts: Vec<Option<String>> = files
        .par_iter()
        .map(|f| match std::fs::read(f) {
            // Checked first: the outputs name every image in JSON and COLMAP's text files.
            _ if f.to_str().is_none() => Some(
                "its path is not valid UTF-8, which the outputs (JSON, COLMAP's text) cannot \
                 name: rename it"
                    .into(),
            ),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound && f.is_symlink() => {
                Some(std::fs::read_link(f).map_or_else(
                    |_| "a symbolic link to a missing file".into(),
                    |to| format!("a symbolic link to a missing file ({})", to.display()),
                ))
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                Some("no such file or directory".into())
            }
            Err(e) => Some(format!("cannot read: {e}")),
            Ok(bytes) => posediff_matching::image_check::image_problem(&bytes),
        })
        .collect();
    let mut good = Vec::new();
    let mut bad = Vec::new();
    for (f, v) in files.iter().zip(verdicts) {
        match v {
            None => good.push(f.clone()),
            Some(why) => bad.push((f.clone(), why)),
        }
    }
    (good, bad)
}

/// A path relative to `root` when under it, else its file name.
pub fn relative_name(path: &Path, root: Option<&Path>) -> String {
    root.and_then(|r| path.strip_prefix(r).ok())
        .or_else(|| path.file_name().map(Path::new))
        .unwrap_or(path)
        .to_string_lossy()
        .into_owned()
}
