//! Writers (and readers, for round trips) of the camera formats people feed next.
//!
//! | file | convention |
//! |---|---|
//! | `cameras.json` | OpenCV: `x_cam = R x_world + t`, K in pixels of the original image, pixel centres at integers (the schema of `../shared/data/*/cameras.json`) |
//! | COLMAP `sparse/0/{cameras,images,points3D}.{txt,bin}` | [`crate::io::colmap`]: one `PINHOLE` camera per distinct intrinsics; `QW QX QY QZ TX TY TZ` world-to-camera; pixel centres at `+0.5` |
//! | nerfstudio `transforms.json` | as nerfstudio's COLMAP converter: the world changed by `applied_transform` (`y ← z`, `z ← −y`), `transform_matrix` camera-to-world with OpenGL camera axes (x right, y up, z backwards), intrinsics at the top level when shared, pixel centres at `+0.5`, `ply_file_path` |
//! | `sparse_pc.ply` | binary little-endian `float x y z`, `uchar red green blue`, in the world of `transforms.json` |
//! | `pytorch3d.json` | what the official model returns: row-vector `R`, `T`, focal and principal point in NDC of the 224 crop |
//!
//! # Pitfalls
//! - COLMAP and nerfstudio put the top-left pixel's centre at `(0.5, 0.5)`; OpenCV at `(0, 0)`.
//! - nerfstudio wants camera-to-world, COLMAP world-to-camera; nerfstudio's world is COLMAP's
//!   after `applied_transform`, and its PLY is in nerfstudio's world.

use std::path::Path;

use nalgebra::{Matrix3, Matrix4, Vector3};
use posediff_geometry::camera_json::{CameraRecord, Pytorch3dParams};
use posediff_geometry::lens::{CameraModel, LensCamera};
use posediff_geometry::{Camera, ImageSize, Intrinsics, Pose, Pytorch3dCamera};
use serde::{Deserialize, Serialize};

use crate::error::{PosediffError, Result, read_text};
use crate::io::colmap::{ColmapFormat, ColmapModel};
use crate::reconstruction::{Reconstruction, ScenePoint};

pub use crate::io::colmap::PIXEL_CENTRE_OFFSET;
pub use crate::reconstruction::{ImageCamera, NamedCamera};

fn write(path: &Path, contents: &str) -> Result<()> {
    std::fs::write(path, contents).map_err(|source| PosediffError::Write {
        path: path.to_owned(),
        source,
    })
}

/// Writes `cameras.json`.
///
/// # Errors
/// I/O errors.
pub fn write_cameras_json(path: &Path, cameras: &[NamedCamera]) -> Result<()> {
    let records: Vec<CameraRecord> = cameras
        .iter()
        .map(|c| CameraRecord::from_camera(c.image.clone(), &c.camera))
        .collect();
    write(path, &serde_json::to_string_pretty(&records)?)
}

/// Reads `cameras.json` in which every camera is estimated.
///
/// # Errors
/// I/O, JSON or camera errors; an entry marked `"estimated": false` (read such files with
/// [`read_cameras_json_partial`]).
pub fn read_cameras_json(path: &Path) -> Result<Vec<NamedCamera>> {
    read_cameras_json_partial(path)?
        .into_iter()
        .map(|e| match e.camera {
            Some(camera) => Ok(NamedCamera {
                image: e.image,
                camera,
            }),
            None => Err(PosediffError::InvalidFile {
                path: path.to_owned(),
                reason: format!("the camera of {} was not estimated", e.image),
            }),
        })
        .collect()
}

/// The `cameras.json` entry of an image without a camera.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct MissingRecord {
    image: String,
    width: u32,
    height: u32,
    #[serde(rename = "K")]
    k: Option<[[f64; 3]; 3]>,
    #[serde(rename = "R")]
    r: Option<[[f64; 3]; 3]>,
    t: Option<[f64; 3]>,
    estimated: bool,
}

/// An estimated entry: the record plus `"estimated": true`.
#[derive(Debug, Clone, Serialize)]
struct EstimatedRecord {
    #[serde(flatten)]
    record: CameraRecord,
    estimated: bool,
}

/// Writes `cameras.json` with every image: estimated cameras as usual plus `"estimated":
/// true` (and `model`/`params` for a distorting lens), the others with `"K"`, `"R"` and `"t"`
/// null and `"estimated": false`.
///
/// # Errors
/// I/O errors; a lens whose focal or principal point is not its camera's.
pub fn write_cameras_json_partial(path: &Path, images: &[ImageCamera]) -> Result<()> {
    let values = images
        .iter()
        .map(|e| match &e.camera {
            Some(c) => {
                let record = match &e.lens {
                    Some(lens) => CameraRecord::from_lens_camera(e.image.clone(), c, lens)?,
                    None => CameraRecord::from_camera(e.image.clone(), c),
                };
                Ok(serde_json::to_value(EstimatedRecord {
                    record,
                    estimated: true,
                })?)
            }
            None => Ok(serde_json::to_value(MissingRecord {
                image: e.image.clone(),
                width: e.size.width(),
                height: e.size.height(),
                k: None,
                r: None,
                t: None,
                estimated: false,
            })?),
        })
        .collect::<Result<Vec<_>>>()?;
    write(path, &serde_json::to_string_pretty(&values)?)
}

/// Reads `cameras.json`, with entries marked `"estimated": false` as images without a camera.
///
/// # Errors
/// I/O, JSON or camera errors (naming the entry).
pub fn read_cameras_json_partial(path: &Path) -> Result<Vec<ImageCamera>> {
    let text = read_text(path)?;
    let values: Vec<serde_json::Value> =
        serde_json::from_str(&text).map_err(|e| PosediffError::invalid(path, e))?;
    values
        .into_iter()
        .enumerate()
        .map(|(k, v)| {
            let entry = |e: serde_json::Error| PosediffError::InvalidFile {
                path: path.to_owned(),
                reason: format!("entry {k}: {e}"),
            };
            if v.get("estimated") == Some(&serde_json::Value::Bool(false)) {
                let m: MissingRecord = serde_json::from_value(v).map_err(entry)?;
                return Ok(ImageCamera {
                    image: m.image,
                    size: posediff_geometry::ImageSize::new(m.width, m.height)?,
                    camera: None,
                    lens: None,
                });
            }
            let r: CameraRecord = serde_json::from_value(v).map_err(entry)?;
            let invalid = |e: posediff_geometry::GeometryError| PosediffError::InvalidFile {
                path: path.to_owned(),
                reason: format!("entry {k} ({}): {e}", r.image),
            };
            let camera = r.to_camera().map_err(invalid)?;
            // A lens model must be whole and agree with K (its pinhole part is `camera`'s).
            let lens = r.lens().map_err(invalid)?;
            Ok(ImageCamera {
                image: r.image,
                size: camera.image_size,
                camera: Some(camera),
                lens: lens.is_distorted().then_some(lens),
            })
        })
        .collect()
}

/// The images of a cameras.json whose cameras carry lens distortion (`model`/`params`), for the
/// readers that take only pinhole cameras (`--intrinsics`, `--init`).
///
/// # Errors
/// As [`read_cameras_json_partial`].
pub fn distorted_images(path: &Path) -> Result<Vec<String>> {
    let text = std::fs::read_to_string(path).map_err(|e| PosediffError::Read {
        path: path.to_owned(),
        source: e,
    })?;
    let values: Vec<serde_json::Value> =
        serde_json::from_str(&text).map_err(|e| PosediffError::invalid(path, e))?;
    Ok(values
        .into_iter()
        .filter_map(|v| serde_json::from_value::<CameraRecord>(v).ok())
        .filter(|r| r.lens().is_ok_and(|l| l.is_distorted()))
        .map(|r| r.image)
        .collect())
}

/// The cameras of the COLMAP model in `dir` (text or binary; PINHOLE, SIMPLE_PINHOLE,
/// SIMPLE_RADIAL, RADIAL or OPENCV cameras, distortion dropped, so the cameras are pinhole
/// approximations), in the model's image order.
///
/// # Errors
/// I/O or format errors naming the file.
pub fn read_colmap_cameras(dir: &Path) -> Result<Vec<NamedCamera>> {
    ColmapModel::read(dir)?.named_cameras(dir)
}

/// Writes the COLMAP model of `r` into `dir`.
///
/// # Errors
/// I/O errors, non-finite rotations.
pub fn write_colmap(dir: &Path, r: &Reconstruction, format: ColmapFormat) -> Result<()> {
    ColmapModel::from_reconstruction(r)?.write(dir, format)
}

/// Intrinsics of nerfstudio frames (pixel centres at `+0.5`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NerfstudioIntrinsics {
    /// Focal length x, px.
    pub fl_x: f64,
    /// Focal length y, px.
    pub fl_y: f64,
    /// Principal point x, px.
    pub cx: f64,
    /// Principal point y, px.
    pub cy: f64,
    /// Width, px.
    pub w: u32,
    /// Height, px.
    pub h: u32,
    /// Radial distortion (OPENCV's `k1`; 0 for a pinhole camera).
    #[serde(default)]
    pub k1: f64,
    /// Radial distortion (`k2`).
    #[serde(default)]
    pub k2: f64,
    /// Tangential distortion (`p1`).
    #[serde(default)]
    pub p1: f64,
    /// Tangential distortion (`p2`).
    #[serde(default)]
    pub p2: f64,
    /// OPENCV_FISHEYE's `k3` (its `k1, k2` above; written only when not 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub k3: f64,
    /// OPENCV_FISHEYE's `k4`.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub k4: f64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

impl NerfstudioIntrinsics {
    /// `c`'s intrinsics with `lens`'s distortion as nerfstudio's OPENCV model (OPENCV_FISHEYE's
    /// `k1…k4` for a fisheye lens).
    fn of(c: &Camera, lens: Option<&LensCamera>) -> Self {
        let i = &c.intrinsics;
        let d = lens.map_or(&[][..], LensCamera::distortion);
        let at = |k: usize| d.get(k).copied().unwrap_or(0.0);
        let ((k1, k2, p1, p2), (k3, k4)) = match lens.map(LensCamera::model) {
            None | Some(CameraModel::SimplePinhole | CameraModel::Pinhole) => {
                ((0.0, 0.0, 0.0, 0.0), (0.0, 0.0))
            }
            Some(CameraModel::SimpleRadial | CameraModel::Radial) => {
                ((at(0), at(1), 0.0, 0.0), (0.0, 0.0))
            }
            Some(CameraModel::OpenCv) => ((at(0), at(1), at(2), at(3)), (0.0, 0.0)),
            Some(CameraModel::OpenCvFisheye) => ((at(0), at(1), 0.0, 0.0), (at(2), at(3))),
        };
        Self {
            fl_x: i.fx(),
            fl_y: i.fy(),
            cx: i.cx() + PIXEL_CENTRE_OFFSET,
            cy: i.cy() + PIXEL_CENTRE_OFFSET,
            w: c.image_size.width(),
            h: c.image_size.height(),
            k1,
            k2,
            p1,
            p2,
            k3,
            k4,
        }
    }
}

/// One frame of nerfstudio's `transforms.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NerfstudioFrame {
    /// Image path, relative to the folder of `transforms.json` (or absolute).
    pub file_path: String,
    /// Camera-to-world with OpenGL camera axes, in the world after `applied_transform`, rows.
    pub transform_matrix: [[f64; 4]; 4],
    /// The image id in `sparse/0`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub colmap_im_id: Option<u32>,
    /// Per-frame intrinsics, present when the frames' intrinsics differ.
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<NerfstudioIntrinsics>,
}

/// nerfstudio's `transforms.json`, with the fields its own COLMAP converter writes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NerfstudioTransforms {
    /// `"OPENCV"` (`k1 k2 p1 p2`, 0 for pinhole cameras), or `"OPENCV_FISHEYE"` (`k1…k4`) when
    /// the cameras are fisheye.
    pub camera_model: String,
    /// Shared intrinsics and distortion, when every frame has the same (then at the top level,
    /// otherwise in each frame: nerfstudio reads per-frame distortion only when the top level
    /// has none).
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<NerfstudioIntrinsics>,
    /// The frames.
    pub frames: Vec<NerfstudioFrame>,
    /// The 3×4 transform from the COLMAP world to this file's world (nerfstudio's
    /// converter: `y ← z`, `z ← −y`).
    #[serde(default = "identity_3x4")]
    pub applied_transform: [[f64; 4]; 3],
    /// The points, in this file's world, relative to this file's folder.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ply_file_path: Option<String>,
}

fn identity_3x4() -> [[f64; 4]; 3] {
    [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ]
}

/// nerfstudio's converter's world change: rows `x, z, −y` of the COLMAP world.
pub fn nerfstudio_applied_transform() -> Matrix4<f64> {
    Matrix4::new(
        1.0, 0.0, 0.0, 0.0, //
        0.0, 0.0, 1.0, 0.0, //
        0.0, -1.0, 0.0, 0.0, //
        0.0, 0.0, 0.0, 1.0,
    )
}

/// `diag(1, −1, −1)`: OpenCV camera axes to OpenGL's.
fn opengl_from_opencv() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
}

/// One camera for [`write_nerfstudio`]: the camera, the frame's `file_path` and its COLMAP id.
#[derive(Debug, Clone)]
pub struct NerfstudioCamera {
    /// The camera.
    pub camera: Camera,
    /// `file_path`.
    pub file_path: String,
    /// `colmap_im_id`.
    pub colmap_id: Option<u32>,
    /// The lens, when it distorts (its pinhole part is `camera`'s intrinsics).
    pub lens: Option<LensCamera>,
}

/// Writes nerfstudio's `transforms.json` as its COLMAP converter does: the world changed by
/// [`nerfstudio_applied_transform`] (recorded as `applied_transform`), camera-to-world with
/// OpenGL axes, intrinsics at the top level when shared, `ply_file_path` when given.
///
/// # Errors
/// I/O errors; fisheye and other cameras in one set (nerfstudio takes one model per file).
pub fn write_nerfstudio(
    path: &Path,
    cameras: &[NerfstudioCamera],
    ply_file_path: Option<&str>,
) -> Result<()> {
    let applied = nerfstudio_applied_transform();
    let all: Vec<NerfstudioIntrinsics> = cameras
        .iter()
        .map(|c| NerfstudioIntrinsics::of(&c.camera, c.lens.as_ref()))
        .collect();
    // nerfstudio has one camera model per file: fisheye for all frames or for none.
    let fisheye = |c: &NerfstudioCamera| {
        c.lens
            .as_ref()
            .is_some_and(|l| l.model() == CameraModel::OpenCvFisheye)
    };
    let fisheyes = cameras.iter().filter(|c| fisheye(c)).count();
    if fisheyes > 0 && fisheyes < cameras.len() {
        return Err(PosediffError::InvalidArgument(format!(
            "transforms.json: {fisheyes} of {} cameras are OPENCV_FISHEYE and nerfstudio takes \
             one camera model per file; write COLMAP's model (sparse/0) instead",
            cameras.len()
        )));
    }
    let shared = all
        .first()
        .filter(|first| all.iter().all(|i| i == *first))
        .copied();
    let frames = cameras
        .iter()
        .zip(&all)
        .map(|(c, intrinsics)| {
            let world_from_cam = c.camera.cam_from_world.inverse();
            let mut m = Matrix4::identity();
            m.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(world_from_cam.rotation * opengl_from_opencv()));
            m.fixed_view_mut::<3, 1>(0, 3)
                .copy_from(&world_from_cam.translation);
            let m = applied * m;
            NerfstudioFrame {
                file_path: c.file_path.clone(),
                transform_matrix: [0, 1, 2, 3].map(|row| [0, 1, 2, 3].map(|col| m[(row, col)])),
                colmap_im_id: c.colmap_id,
                intrinsics: shared.is_none().then_some(*intrinsics),
            }
        })
        .collect();
    let t = NerfstudioTransforms {
        camera_model: if fisheyes > 0 {
            "OPENCV_FISHEYE"
        } else {
            "OPENCV"
        }
        .into(),
        intrinsics: shared,
        frames,
        applied_transform: [0, 1, 2].map(|row| [0, 1, 2, 3].map(|col| applied[(row, col)])),
        ply_file_path: ply_file_path.map(str::to_owned),
    };
    write(path, &serde_json::to_string_pretty(&t)?)
}

/// Reads a `transforms.json` (with or without `applied_transform`, intrinsics shared or per
/// frame) back into cameras in the COLMAP world, named by their `file_path`s.
///
/// # Errors
/// I/O, JSON or camera errors; a frame without intrinsics.
pub fn read_nerfstudio(path: &Path) -> Result<Vec<NamedCamera>> {
    let text = read_text(path)?;
    let t: NerfstudioTransforms =
        serde_json::from_str(&text).map_err(|e| PosediffError::invalid(path, e))?;
    let mut applied = Matrix4::identity();
    for (row, values) in t.applied_transform.iter().enumerate() {
        for (col, v) in values.iter().enumerate() {
            applied[(row, col)] = *v;
        }
    }
    let undo = applied
        .try_inverse()
        .ok_or_else(|| PosediffError::invalid(path, "applied_transform is not invertible"))?;
    t.frames
        .iter()
        .map(|f| {
            let i = f.intrinsics.or(t.intrinsics).ok_or_else(|| {
                PosediffError::invalid(path, format!("frame {} has no intrinsics", f.file_path))
            })?;
            let m = undo * Matrix4::from_fn(|r, c| f.transform_matrix[r][c]);
            let r = m.fixed_view::<3, 3>(0, 0) * opengl_from_opencv();
            let world_from_cam = Pose::new(r, m.fixed_view::<3, 1>(0, 3).into());
            let k = Intrinsics::new(
                i.fl_x,
                i.fl_y,
                i.cx - PIXEL_CENTRE_OFFSET,
                i.cy - PIXEL_CENTRE_OFFSET,
            )?;
            Ok(NamedCamera {
                image: f.file_path.clone(),
                camera: Camera::new(k, world_from_cam.inverse(), ImageSize::new(i.w, i.h)?),
            })
        })
        .collect()
}

/// Writes the points as a binary little-endian PLY (`float x y z`, `uchar red green blue`),
/// each position mapped by `transform` (e.g. [`nerfstudio_applied_transform`]).
///
/// # Errors
/// I/O errors.
pub fn write_ply(path: &Path, points: &[ScenePoint], transform: &Matrix4<f64>) -> Result<()> {
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\ncomment posediff sparse points\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    )
    .into_bytes();
    b.reserve(points.len() * 15);
    for p in points {
        let x = transform.transform_point(&nalgebra::Point3::from(p.xyz));
        for v in [x.x, x.y, x.z] {
            b.extend_from_slice(&(v as f32).to_le_bytes());
        }
        b.extend_from_slice(&p.rgb);
    }
    std::fs::write(path, b).map_err(|source| PosediffError::Write {
        path: path.to_owned(),
        source,
    })
}

/// Reads a PLY written by [`write_ply`]: positions and colours.
///
/// # Errors
/// I/O errors, another layout, a truncated file.
pub fn read_ply(path: &Path) -> Result<Vec<([f32; 3], [u8; 3])>> {
    let bytes = std::fs::read(path).map_err(|source| PosediffError::Read {
        path: path.to_owned(),
        source,
    })?;
    let marker = b"end_header\n";
    let end = bytes
        .windows(marker.len())
        .position(|w| w == marker)
        .ok_or_else(|| PosediffError::invalid(path, "no end_header"))?
        + marker.len();
    let header = std::str::from_utf8(&bytes[..end])
        .map_err(|_| PosediffError::invalid(path, "header is not text"))?;
    let expected = "property float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n";
    if !header.contains("format binary_little_endian 1.0") || !header.contains(expected) {
        return Err(PosediffError::invalid(
            path,
            "expected binary little-endian float x y z, uchar red green blue",
        ));
    }
    let n: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .and_then(|v| v.trim().parse().ok())
        .ok_or_else(|| PosediffError::invalid(path, "no vertex count"))?;
    let body = &bytes[end..];
    if body.len() != n.saturating_mul(15) {
        return Err(PosediffError::invalid(
            path,
            format!(
                "{n} vertices need {} bytes, the file has {}",
                n.saturating_mul(15),
                body.len()
            ),
        ));
    }
    Ok(body
        .chunks_exact(15)
        .map(|c| {
            let f = |k: usize| f32::from_le_bytes([c[k], c[k + 1], c[k + 2], c[k + 3]]);
            ([f(0), f(4), f(8)], [c[12], c[13], c[14]])
        })
        .collect())
}

/// One camera as the official model returns it (224 crop, NDC).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pytorch3dRecord {
    /// Image path relative to the input folder.
    pub image: String,
    /// The camera (NDC of the crop).
    #[serde(flatten)]
    pub camera: Pytorch3dParams,
}

/// Writes `pytorch3d.json`: each estimated camera mapped into the 224 crop of its image (the
/// loader's crop, `CenterCrop::official`, a function of the image size alone), then converted
/// exactly as PyTorch3D's `cameras_from_opencv_projection`. Images without a camera are left
/// out.
///
/// # Errors
/// I/O errors.
pub fn write_pytorch3d(path: &Path, images: &[ImageCamera]) -> Result<()> {
    let records = images
        .iter()
        .filter_map(|e| e.camera.map(|c| (e, c)))
        .map(|(c, camera)| {
            let crop = posediff_geometry::CenterCrop::official(
                camera.image_size,
                posediff_geometry::MODEL_INPUT_SIDE,
            );
            let model = crop.camera_to_model(&camera)?;
            let p = Pytorch3dCamera::from_opencv(&model);
            Ok(Pytorch3dRecord {
                image: c.image.clone(),
                camera: Pytorch3dParams::from(&p),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    write(path, &serde_json::to_string_pretty(&records)?)
}
