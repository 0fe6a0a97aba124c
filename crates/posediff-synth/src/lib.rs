//! Synthetic CO3D-style scenes with exact cameras, owned outright: for the demo, end-to-end
//! tests and training data.
//!
//! - [`scene`]: procedural shapes (spheres, boxes, tori, superquadrics, radially deformed by
//!   noise) with solid procedural textures (multi-octave noise, stripes, checkers, spots), a
//!   textured ground, a sky at infinity, Lambert shading; fly-around and forward camera paths.
//! - [`render`]: a z-buffer rasteriser with near-plane clipping and perspective-correct
//!   interpolation; every pixel knows the world point it shows.
//! - [`write_dataset`]: sequences rendered in parallel, written as PNG images plus
//!   `cameras.json` per sequence (the `../shared/data` schema) and `{category}_{split}.jgz`
//!   annotations (the CO3D layout the loaders read).
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod noise;
pub mod render;
pub mod scene;
pub mod video;

use std::io::Write as _;
use std::path::{Path, PathBuf};

use posediff_geometry::camera_json::{CameraRecord, Pytorch3dParams};
use posediff_geometry::lens::{CameraModel, LensCamera};
use posediff_geometry::{Camera, ImageSize, Intrinsics, Pytorch3dCamera};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::Serialize;

pub use render::{Buffers, Hit, Triangle, rasterise};
pub use scene::{PathKind, Scene, look_at, trajectory, trajectory_with};

/// The category name of the synthetic sequences.
pub const CATEGORY: &str = "synthetic";

/// Near-plane distance of the rasteriser (world units; objects are ~1 unit).
pub const NEAR: f64 = 0.05;

/// Errors of the synthetic data writer.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SynthError {
    /// Writing failed.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// PNG encoding failed.
    #[error("cannot encode {path}: {source}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// Why.
        source: image::ImageError,
    },
    /// An invalid request.
    #[error("{0}")]
    Invalid(String),
    /// JSON serialisation.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, SynthError>;

/// One rendered frame.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Its camera.
    pub camera: Camera,
    /// 8-bit RGB, row-major.
    pub rgb: Vec<u8>,
    /// What each pixel shows.
    pub buffers: Buffers,
}

impl Frame {
    /// The bounding box `[x0, y0, x1, y1]` of the pixels showing objects (not ground or sky),
    /// the whole image when none does.
    pub fn object_bbox(&self, n_objects: usize) -> [f64; 4] {
        let (w, h) = (self.buffers.width, self.buffers.height);
        let mut b = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        for y in 0..h {
            for x in 0..w {
                if self
                    .buffers
                    .at(x, y)
                    .is_some_and(|hit| (hit.object as usize) < n_objects)
                {
                    b[0] = b[0].min(x as f64);
                    b[1] = b[1].min(y as f64);
                    b[2] = b[2].max(x as f64);
                    b[3] = b[3].max(y as f64);
                }
            }
        }
        if b[0].is_finite() {
            b
        } else {
            [0.0, 0.0, (w - 1) as f64, (h - 1) as f64]
        }
    }
}

/// Renders `scene` through `camera`: colours from 2×2 supersampling (a camera of twice the
/// resolution, `u_hi = 2u + 0.5`, box-filtered), hits at the pixel centres.
pub fn render_frame(scene: &Scene, camera: &Camera) -> Frame {
    let buffers = rasterise(&scene.triangles, camera, NEAR);
    let k = &camera.intrinsics;
    let (w, h) = (
        camera.image_size.width() as usize,
        camera.image_size.height() as usize,
    );
    let rgb = match (
        posediff_geometry::Intrinsics::new(
            2.0 * k.fx(),
            2.0 * k.fy(),
            2.0 * k.cx() + 0.5,
            2.0 * k.cy() + 0.5,
        ),
        ImageSize::new(2 * w as u32, 2 * h as u32),
    ) {
        (Ok(k2), Ok(size2)) => {
            let fine = Camera::new(k2, camera.cam_from_world, size2);
            let hi = scene.shade(&rasterise(&scene.triangles, &fine, NEAR), &fine);
            let mut rgb = vec![0u8; w * h * 3];
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3 {
                        let at = |dx: usize, dy: usize| {
                            u32::from(hi[((2 * y + dy) * 2 * w + 2 * x + dx) * 3 + c])
                        };
                        let sum = at(0, 0) + at(1, 0) + at(0, 1) + at(1, 1);
                        rgb[(y * w + x) * 3 + c] = ((sum + 2) / 4) as u8;
                    }
                }
            }
            rgb
        }
        _ => scene.shade(&buffers, camera),
    };
    Frame {
        camera: *camera,
        rgb,
        buffers,
    }
}

/// What to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetSpec {
    /// Number of sequences.
    pub sequences: usize,
    /// Frames per sequence.
    pub frames: usize,
    /// Master seed.
    pub seed: u64,
    /// Image sizes, used in turn by the sequences.
    pub sizes: Vec<ImageSize>,
    /// Every `test_every`-th sequence goes to the test split (0: all train).
    pub test_every: usize,
    /// The camera path of every sequence (`None`: drawn per sequence, a forward approach with
    /// probability 1/4).
    pub path: Option<PathKind>,
    /// Real-camera effects: zoomed frames (a focal of their own) and lens distortion.
    pub lens: LensSpec,
}

/// Real-camera effects of a dataset, with exact cameras: every `zoom_every`-th frame's focal
/// multiplied by a factor drawn from `zoom` (a zoom lens: a camera of its own), and every frame
/// seen through SIMPLE_RADIAL's `radial_k` (`x_d = x_u (1 + k r_u²)` in coordinates normalised
/// by the frame's focal), written to cameras.json as `model`/`params`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensSpec {
    /// Zoom every N-th frame (the N-th, 2N-th, …; 0: none).
    pub zoom_every: usize,
    /// The zoom factors' range.
    pub zoom: (f64, f64),
    /// SIMPLE_RADIAL's `k` (0: pinhole). Distorted frames are resampled from the pinhole
    /// rendering (bilinear), and the CO3D annotations, which carry no distortion, are not
    /// written.
    pub radial_k: f64,
}

impl Default for LensSpec {
    fn default() -> Self {
        Self {
            zoom_every: 0,
            zoom: (1.3, 1.6),
            radial_k: 0.0,
        }
    }
}

impl LensSpec {
    /// Frame `camera`'s lens (SIMPLE_RADIAL with its focal and principal point).
    ///
    /// # Errors
    /// A non-finite coefficient.
    pub fn lens(&self, camera: &Camera) -> Result<LensCamera> {
        let k = &camera.intrinsics;
        LensCamera::new(
            CameraModel::SimpleRadial,
            vec![k.fx(), k.cx(), k.cy(), self.radial_k],
        )
        .map_err(|e| SynthError::Invalid(format!("lens: {e}")))
    }

    /// # Errors
    /// A zoom range that is not positive and ordered, a non-finite coefficient.
    pub fn check(&self) -> Result<()> {
        let (lo, hi) = self.zoom;
        if self.zoom_every > 0 && !(lo > 0.0 && hi >= lo && hi.is_finite()) {
            return Err(SynthError::Invalid(format!(
                "zoom {lo}:{hi}: factors must be positive, the first not above the second"
            )));
        }
        if !self.radial_k.is_finite() {
            return Err(SynthError::Invalid(format!("radial k {}", self.radial_k)));
        }
        Ok(())
    }

    /// The zoomed frames' focals multiplied by their drawn factors (a spec that fails
    /// [`Self::check`] zooms nothing).
    fn zoomed(&self, cameras: &mut [Camera], seed: u64) {
        if self.zoom_every == 0 || self.check().is_err() {
            return;
        }
        let (lo, hi) = self.zoom;
        let mut rng = StdRng::seed_from_u64(seed);
        for (i, c) in cameras.iter_mut().enumerate() {
            if i % self.zoom_every == self.zoom_every - 1 {
                let z = if hi > lo {
                    rng.random_range(lo..hi)
                } else {
                    lo
                };
                let k = &c.intrinsics;
                if let Ok(zoomed) = Intrinsics::new(z * k.fx(), z * k.fy(), k.cx(), k.cy()) {
                    c.intrinsics = zoomed;
                }
            }
        }
    }
}

/// `rgb` (pinhole, `w × h`) as `lens` images it: each pixel bilinearly sampled where the
/// pinhole camera sees its ray (black where that is outside).
fn distorted(rgb: &[u8], w: usize, h: usize, lens: &LensCamera) -> Result<Vec<u8>> {
    let ((f, _), (cx, cy)) = (lens.focal(), lens.principal());
    let mut out = vec![0u8; rgb.len()];
    for y in 0..h {
        for x in 0..w {
            let ray = lens
                .unproject(&nalgebra::Vector2::new(x as f64, y as f64))
                .map_err(|e| SynthError::Invalid(format!("lens at ({x}, {y}): {e}")))?;
            let (u, v) = (f * ray.x + cx, f * ray.y + cy);
            let (x0, y0) = (u.floor(), v.floor());
            if x0 < 0.0 || y0 < 0.0 || x0 + 1.0 >= w as f64 || y0 + 1.0 >= h as f64 {
                continue;
            }
            let (ax, ay) = (u - x0, v - y0);
            let (x0, y0) = (x0 as usize, y0 as usize);
            for c in 0..3 {
                let at = |xx: usize, yy: usize| f64::from(rgb[(yy * w + xx) * 3 + c]);
                let top = at(x0, y0) * (1.0 - ax) + at(x0 + 1, y0) * ax;
                let bottom = at(x0, y0 + 1) * (1.0 - ax) + at(x0 + 1, y0 + 1) * ax;
                out[(y * w + x) * 3 + c] = (top * (1.0 - ay) + bottom * ay).round() as u8;
            }
        }
    }
    Ok(out)
}

/// A CO3D annotation frame (PyTorch3D conventions, NDC of the image's shorter half side).
#[derive(Debug, Clone, Serialize)]
struct Co3dFrameOut {
    filepath: String,
    bbox: [f64; 4],
    #[serde(flatten)]
    camera: Pytorch3dParams,
}

/// What was written.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DatasetSummary {
    /// Sequence folders (relative to the output), each with `images/` and `cameras.json`.
    pub sequences: Vec<String>,
    /// The annotation files.
    pub annotations: Vec<String>,
    /// Frames written.
    pub frames: usize,
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|source| SynthError::Write {
            path: dir.to_owned(),
            source,
        })?;
    }
    std::fs::write(path, bytes).map_err(|source| SynthError::Write {
        path: path.to_owned(),
        source,
    })
}

/// The seed of sequence `k` of a dataset seeded `seed`.
pub fn sequence_seed(seed: u64, k: usize) -> u64 {
    seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(k as u64)
        .rotate_left(17)
}

/// One sequence of a dataset: its scene and cameras.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// `synthetic_NNNN`.
    pub name: String,
    /// Its seed.
    pub seed: u64,
    /// The scene.
    pub scene: Scene,
    /// One camera per frame.
    pub cameras: Vec<Camera>,
}

/// Sequence `k` of `spec` (what [`write_dataset`] renders), at least one frame.
pub fn sequence(spec: &DatasetSpec, k: usize) -> Sequence {
    let seed = sequence_seed(spec.seed, k);
    let scene = Scene::random(seed);
    let size = match spec.sizes.get(k % spec.sizes.len().max(1)) {
        Some(s) => *s,
        None => match ImageSize::new(320, 240) {
            Ok(s) => s,
            Err(_) => unreachable!("a valid size"),
        },
    };
    let mut cameras = trajectory_with(&scene, spec.frames.max(1), size, seed ^ 0x7A7A, spec.path);
    // Drawn after the path, from a seed of its own: the path is the same with or without zoom.
    spec.lens.zoomed(&mut cameras, seed ^ 0x200E);
    Sequence {
        name: format!("{CATEGORY}_{k:04}"),
        seed,
        scene,
        cameras,
    }
}

/// Renders and writes a dataset under `out`: `synthetic/<sequence>/images/frameNNNNNN.png`,
/// `synthetic/<sequence>/cameras.json`, and `synthetic_train.jgz` / `synthetic_test.jgz` whose
/// file paths are relative to `out`. Deterministic for a spec.
///
/// # Errors
/// An empty spec, I/O and encoding errors.
pub fn write_dataset(out: &Path, spec: &DatasetSpec) -> Result<DatasetSummary> {
    if spec.sequences == 0 || spec.frames == 0 || spec.sizes.is_empty() {
        return Err(SynthError::Invalid(
            "need at least one sequence, one frame and one image size".into(),
        ));
    }
    spec.lens.check()?;
    let mut splits: [(String, serde_json::Map<String, serde_json::Value>); 2] = [
        ("train".into(), serde_json::Map::new()),
        ("test".into(), serde_json::Map::new()),
    ];
    let mut names = Vec::new();
    for k in 0..spec.sequences {
        let Sequence {
            name,
            seed,
            scene,
            cameras,
        } = sequence(spec, k);
        let size = cameras[0].image_size;
        let dir = out.join(CATEGORY).join(&name);
        let frames: Vec<Co3dFrameOut> = cameras
            .par_iter()
            .enumerate()
            .map(|(i, cam)| -> Result<Co3dFrameOut> {
                let mut frame = render_frame(&scene, cam);
                if spec.lens.radial_k != 0.0 {
                    let (w, h) = (size.width() as usize, size.height() as usize);
                    frame.rgb = distorted(&frame.rgb, w, h, &spec.lens.lens(cam)?)?;
                }
                let file = format!("images/frame{i:06}.png");
                let path = dir.join(&file);
                let img = image::RgbImage::from_raw(size.width(), size.height(), frame.rgb.clone())
                    .ok_or_else(|| SynthError::Invalid("image buffer size".into()))?;
                if let Some(parent) = path.parent() {
                    std::fs::create_dir_all(parent).map_err(|source| SynthError::Write {
                        path: parent.to_owned(),
                        source,
                    })?;
                }
                img.save(&path).map_err(|source| SynthError::Encode {
                    path: path.clone(),
                    source,
                })?;
                let p = Pytorch3dCamera::from_opencv(cam);
                Ok(Co3dFrameOut {
                    filepath: format!("{CATEGORY}/{name}/{file}"),
                    bbox: frame.object_bbox(scene.objects.len()),
                    camera: Pytorch3dParams::from(&p),
                })
            })
            .collect::<Result<_>>()?;
        let records: Vec<CameraRecord> = cameras
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let name = format!("images/frame{i:06}.png");
                if spec.lens.radial_k == 0.0 {
                    return Ok(CameraRecord::from_camera(name, c));
                }
                CameraRecord::from_lens_camera(name, c, &spec.lens.lens(c)?)
                    .map_err(|e| SynthError::Invalid(format!("lens: {e}")))
            })
            .collect::<Result<_>>()?;
        write_file(
            &dir.join("cameras.json"),
            serde_json::to_string_pretty(&records)?.as_bytes(),
        )?;
        let meta = serde_json::json!({
            "generator": "posediff-synth",
            "seed": seed,
            "objects": scene.objects.iter().map(|o| format!("{:?}", o.shape)).collect::<Vec<_>>(),
            "convention": "x_cam = R x_world + t, OpenCV pixel coords",
        });
        write_file(
            &dir.join("meta.json"),
            serde_json::to_string_pretty(&meta)?.as_bytes(),
        )?;
        let split = usize::from(spec.test_every > 0 && k % spec.test_every == spec.test_every - 1);
        splits[split]
            .1
            .insert(name.clone(), serde_json::to_value(&frames)?);
        names.push(format!("{CATEGORY}/{name}"));
    }
    let mut annotations = Vec::new();
    // CO3D's annotations carry no distortion: not written for a distorted dataset.
    let splits = if spec.lens.radial_k == 0.0 {
        splits.as_slice()
    } else {
        &[]
    };
    for (split, map) in splits {
        let file = format!("{CATEGORY}_{split}.jgz");
        let json = serde_json::to_vec(map)?;
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        let path = out.join(&file);
        let bytes = gz
            .write_all(&json)
            .and_then(|()| gz.finish())
            .map_err(|source| SynthError::Write {
                path: path.clone(),
                source,
            })?;
        write_file(&path, &bytes)?;
        annotations.push(file);
    }
    Ok(DatasetSummary {
        sequences: names,
        annotations,
        frames: spec.sequences * spec.frames,
    })
}

/// Parses `WxH`.
///
/// # Errors
/// Anything else.
pub fn parse_size(s: &str) -> Result<ImageSize> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| SynthError::Invalid(format!("size {s:?}: expected WxH")))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| SynthError::Invalid(format!("size {s:?}: expected WxH")))
    };
    ImageSize::new(parse(w)?, parse(h)?)
        .map_err(|e| SynthError::Invalid(format!("size {s:?}: {e}")))
}
