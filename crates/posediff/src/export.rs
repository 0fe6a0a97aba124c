//! Writers (and readers, for round trips) of the camera formats people feed next.
//!
//! | file | convention |
//! |---|---|
//! | `cameras.json` | OpenCV: `x_cam = R x_world + t`, K in pixels of the original image, pixel centres at integers (the schema of `../shared/data/*/cameras.json`) |
//! | COLMAP `cameras.txt` / `images.txt` / `points3D.txt` | one `PINHOLE` camera per image; `QW QX QY QZ TX TY TZ` = world-to-camera rotation (Hamilton, w first) and translation; principal point in COLMAP pixels (pixel centres at `+0.5`, so `cx + 0.5`) |
//! | nerfstudio `transforms.json` | `transform_matrix` = camera-to-world with OpenGL camera axes (x right, y up, z backwards: the OpenCV y and z columns negated); per-frame `fl_x fl_y cx cy w h`, principal point with pixel centres at `+0.5` |
//! | `pytorch3d.json` | what the official model returns: row-vector `R`, `T`, focal and principal point in NDC of the 224 crop |
//!
//! # Pitfalls
//! - COLMAP and nerfstudio put the top-left pixel's centre at `(0.5, 0.5)`; OpenCV at `(0, 0)`.
//! - nerfstudio wants camera-to-world, COLMAP world-to-camera.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Matrix3, Matrix4, Vector3};
use posediff_geometry::camera_json::CameraRecord;
use posediff_geometry::{
    Camera, ImageSize, Intrinsics, Pose, Pytorch3dCamera, Quaternion, QuaternionSign,
};
use serde::{Deserialize, Serialize};

use crate::error::{PosediffError, Result, read_text};

/// COLMAP's and nerfstudio's pixel centres sit half a pixel from OpenCV's.
pub const PIXEL_CENTRE_OFFSET: f64 = 0.5;

/// One camera and the image it belongs to (path relative to the input folder).
#[derive(Debug, Clone, PartialEq)]
pub struct NamedCamera {
    /// Image path relative to the input folder.
    pub image: String,
    /// The camera, original image pixels.
    pub camera: Camera,
}

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

/// One image of a set and its camera, `None` where none was estimated.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageCamera {
    /// Image path relative to the input folder.
    pub image: String,
    /// The image's size.
    pub size: posediff_geometry::ImageSize,
    /// The camera.
    pub camera: Option<Camera>,
}

impl ImageCamera {
    /// The estimated cameras of `images` as named cameras (the others left out).
    pub fn estimated(images: &[ImageCamera]) -> Vec<NamedCamera> {
        images
            .iter()
            .filter_map(|e| {
                e.camera.map(|camera| NamedCamera {
                    image: e.image.clone(),
                    camera,
                })
            })
            .collect()
    }
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
/// true`, the others with `"K"`, `"R"` and `"t"` null and `"estimated": false`.
///
/// # Errors
/// I/O errors.
pub fn write_cameras_json_partial(path: &Path, images: &[ImageCamera]) -> Result<()> {
    let values = images
        .iter()
        .map(|e| match &e.camera {
            Some(c) => serde_json::to_value(EstimatedRecord {
                record: CameraRecord::from_camera(e.image.clone(), c),
                estimated: true,
            }),
            None => serde_json::to_value(MissingRecord {
                image: e.image.clone(),
                width: e.size.width(),
                height: e.size.height(),
                k: None,
                r: None,
                t: None,
                estimated: false,
            }),
        })
        .collect::<std::result::Result<Vec<_>, _>>()?;
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
                });
            }
            let r: CameraRecord = serde_json::from_value(v).map_err(entry)?;
            let camera = r.to_camera().map_err(|e| PosediffError::InvalidFile {
                path: path.to_owned(),
                reason: format!("entry {k} ({}): {e}", r.image),
            })?;
            Ok(ImageCamera {
                image: r.image,
                size: camera.image_size,
                camera: Some(camera),
            })
        })
        .collect()
}

/// Writes a COLMAP text model (`cameras.txt`, `images.txt`, empty `points3D.txt`) into `dir`.
///
/// # Errors
/// I/O errors, non-finite rotations.
pub fn write_colmap_text(dir: &Path, cameras: &[NamedCamera]) -> Result<()> {
    let mut cams = String::from(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
    );
    let _ = writeln!(cams, "# Number of cameras: {}", cameras.len());
    let mut imgs = String::from(
        "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n",
    );
    let _ = writeln!(
        imgs,
        "# Number of images: {}, mean observations per image: 0",
        cameras.len()
    );
    for (k, c) in cameras.iter().enumerate() {
        let id = k + 1;
        let i = &c.camera.intrinsics;
        let s = c.camera.image_size;
        let _ = writeln!(
            cams,
            "{id} PINHOLE {} {} {} {} {} {}",
            s.width(),
            s.height(),
            i.fx(),
            i.fy(),
            i.cx() + PIXEL_CENTRE_OFFSET,
            i.cy() + PIXEL_CENTRE_OFFSET
        );
        let q = Quaternion::from_rotation_matrix(
            &c.camera.cam_from_world.rotation,
            QuaternionSign::NonNegativeReal,
        )?;
        let t = c.camera.cam_from_world.translation;
        let _ = writeln!(
            imgs,
            "{id} {} {} {} {} {} {} {} {id} {}",
            q.w, q.x, q.y, q.z, t.x, t.y, t.z, c.image
        );
        imgs.push('\n');
    }
    write(&dir.join("cameras.txt"), &cams)?;
    write(&dir.join("images.txt"), &imgs)?;
    write(
        &dir.join("points3D.txt"),
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n# Number of points: 0, mean track length: 0\n",
    )
}

fn parse_err(path: &Path, what: &str) -> PosediffError {
    PosediffError::invalid(path, what)
}

/// Reads a COLMAP text model: the one [`write_colmap_text`] writes, or COLMAP's own (PINHOLE,
/// SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV cameras; distortion parameters are dropped,
/// so the cameras are pinhole approximations).
///
/// # Errors
/// I/O or format errors.
pub fn read_colmap_text(dir: &Path) -> Result<Vec<NamedCamera>> {
    let read = |name: &str| read_text(&dir.join(name));
    let cams_path = dir.join("cameras.txt");
    let mut intrinsics = std::collections::HashMap::new();
    for line in read("cameras.txt")?
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
    {
        let f: Vec<&str> = line.split_whitespace().collect();
        let n = |i: usize| {
            f.get(i)
                .and_then(|v| v.parse::<f64>().ok())
                .ok_or_else(|| parse_err(&cams_path, "missing or non-numeric camera parameter"))
        };
        // fx, fy, cx, cy and how many parameters the model has; distortion is not kept.
        let (fx, fy, cx, cy, count) = match f.get(1).copied() {
            Some("PINHOLE") => (n(4)?, n(5)?, n(6)?, n(7)?, 8),
            Some("SIMPLE_PINHOLE") => (n(4)?, n(4)?, n(5)?, n(6)?, 7),
            Some("SIMPLE_RADIAL") => (n(4)?, n(4)?, n(5)?, n(6)?, 8),
            Some("RADIAL") => (n(4)?, n(4)?, n(5)?, n(6)?, 9),
            Some("OPENCV") => (n(4)?, n(5)?, n(6)?, n(7)?, 12),
            _ => {
                return Err(parse_err(
                    &cams_path,
                    "expected a PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV camera",
                ));
            }
        };
        if f.len() != count {
            return Err(parse_err(&cams_path, "wrong number of camera parameters"));
        }
        let size = ImageSize::new(f[2].parse().unwrap_or(0), f[3].parse().unwrap_or(0))?;
        let k = Intrinsics::new(fx, fy, cx - PIXEL_CENTRE_OFFSET, cy - PIXEL_CENTRE_OFFSET)?;
        intrinsics.insert(f[0].to_owned(), (k, size));
    }
    let imgs_path = dir.join("images.txt");
    let text = read("images.txt")?;
    // Two lines per image: the pose, then its 2-D points (possibly empty).
    let lines: Vec<&str> = text.lines().filter(|l| !l.starts_with('#')).collect();
    let mut out = Vec::new();
    let mut k = 0;
    while k < lines.len() {
        let line = lines[k];
        if line.trim().is_empty() {
            k += 1;
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 10 {
            return Err(parse_err(
                &imgs_path,
                "expected `ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`",
            ));
        }
        let n = |i: usize| {
            f[i].parse::<f64>()
                .map_err(|_| parse_err(&imgs_path, "not a number"))
        };
        let r = Quaternion::new(n(1)?, n(2)?, n(3)?, n(4)?).to_rotation_matrix()?;
        let t = Vector3::new(n(5)?, n(6)?, n(7)?);
        let (k_cam, size) = *intrinsics
            .get(f[8])
            .ok_or_else(|| parse_err(&imgs_path, "unknown CAMERA_ID"))?;
        out.push(NamedCamera {
            image: f[9..].join(" "),
            camera: Camera::new(k_cam, Pose::new(r, t), size),
        });
        // Skip the points line.
        k += 2;
    }
    Ok(out)
}

/// One frame of nerfstudio's `transforms.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NerfstudioFrame {
    /// Image path relative to the input folder.
    pub file_path: String,
    /// Camera-to-world, OpenGL camera axes, rows.
    pub transform_matrix: [[f64; 4]; 4],
    /// Focal length x, px.
    pub fl_x: f64,
    /// Focal length y, px.
    pub fl_y: f64,
    /// Principal point x, px (pixel centres at +0.5).
    pub cx: f64,
    /// Principal point y, px (pixel centres at +0.5).
    pub cy: f64,
    /// Width, px.
    pub w: u32,
    /// Height, px.
    pub h: u32,
}

/// nerfstudio's `transforms.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NerfstudioTransforms {
    /// Always `"OPENCV"` (pinhole here; no distortion terms).
    pub camera_model: String,
    /// The frames.
    pub frames: Vec<NerfstudioFrame>,
}

/// `diag(1, −1, −1)`: OpenCV camera axes to OpenGL's.
fn opengl_from_opencv() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
}

/// Writes nerfstudio's `transforms.json`.
///
/// # Errors
/// I/O errors.
pub fn write_nerfstudio(path: &Path, cameras: &[NamedCamera]) -> Result<()> {
    let frames = cameras
        .iter()
        .map(|c| {
            let world_from_cam = c.camera.cam_from_world.inverse();
            let r = world_from_cam.rotation * opengl_from_opencv();
            let mut m = Matrix4::identity();
            m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
            m.fixed_view_mut::<3, 1>(0, 3)
                .copy_from(&world_from_cam.translation);
            let i = &c.camera.intrinsics;
            NerfstudioFrame {
                file_path: c.image.clone(),
                transform_matrix: [0, 1, 2, 3].map(|row| [0, 1, 2, 3].map(|col| m[(row, col)])),
                fl_x: i.fx(),
                fl_y: i.fy(),
                cx: i.cx() + PIXEL_CENTRE_OFFSET,
                cy: i.cy() + PIXEL_CENTRE_OFFSET,
                w: c.camera.image_size.width(),
                h: c.camera.image_size.height(),
            }
        })
        .collect();
    let t = NerfstudioTransforms {
        camera_model: "OPENCV".into(),
        frames,
    };
    write(path, &serde_json::to_string_pretty(&t)?)
}

/// Reads a `transforms.json` written by [`write_nerfstudio`].
///
/// # Errors
/// I/O, JSON or camera errors.
pub fn read_nerfstudio(path: &Path) -> Result<Vec<NamedCamera>> {
    let text = read_text(path)?;
    let t: NerfstudioTransforms =
        serde_json::from_str(&text).map_err(|e| PosediffError::invalid(path, e))?;
    t.frames
        .iter()
        .map(|f| {
            let m = Matrix4::from_fn(|r, c| f.transform_matrix[r][c]);
            let r = m.fixed_view::<3, 3>(0, 0) * opengl_from_opencv();
            let world_from_cam = Pose::new(r, m.fixed_view::<3, 1>(0, 3).into());
            let k = Intrinsics::new(
                f.fl_x,
                f.fl_y,
                f.cx - PIXEL_CENTRE_OFFSET,
                f.cy - PIXEL_CENTRE_OFFSET,
            )?;
            Ok(NamedCamera {
                image: f.file_path.clone(),
                camera: Camera::new(k, world_from_cam.inverse(), ImageSize::new(f.w, f.h)?),
            })
        })
        .collect()
}

/// One camera as the official model returns it (224 crop, NDC).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pytorch3dRecord {
    /// Image path relative to the input folder.
    pub image: String,
    /// Row-vector rotation, rows: `X_cam = X_world · R + T`.
    #[serde(rename = "R")]
    pub r: [[f64; 3]; 3],
    /// Translation.
    #[serde(rename = "T")]
    pub t: [f64; 3],
    /// Focal length in NDC of the crop.
    pub focal_length: [f64; 2],
    /// Principal point in NDC of the crop.
    pub principal_point: [f64; 2],
}

/// Writes `pytorch3d.json`: each camera mapped into the 224 crop of its image, then converted
/// exactly as PyTorch3D's `cameras_from_opencv_projection`.
///
/// # Errors
/// I/O errors.
pub fn write_pytorch3d(
    path: &Path,
    cameras: &[(NamedCamera, posediff_geometry::CenterCrop)],
) -> Result<()> {
    let records = cameras
        .iter()
        .map(|(c, crop)| {
            let model = crop.camera_to_model(&c.camera)?;
            let p = Pytorch3dCamera::from_opencv(&model);
            Ok(Pytorch3dRecord {
                image: c.image.clone(),
                r: [0, 1, 2].map(|i| [0, 1, 2].map(|j| p.r[(i, j)])),
                t: [p.t.x, p.t.y, p.t.z],
                focal_length: [p.intrinsics.focal.x, p.intrinsics.focal.y],
                principal_point: [
                    p.intrinsics.principal_point.x,
                    p.intrinsics.principal_point.y,
                ],
            })
        })
        .collect::<Result<Vec<_>>>()?;
    write(path, &serde_json::to_string_pretty(&records)?)
}

/// The cameras of a COLMAP text model for the images of a folder, in the folder's order: an
/// image COLMAP did not register is not estimated. Names match the model's image names, or their
/// file names.
///
/// # Errors
/// An unreadable model, an image in the folder that cannot be read for its size.
pub fn colmap_for_images(
    model: &Path,
    images: &[std::path::PathBuf],
    root: &Path,
) -> Result<Vec<ImageCamera>> {
    let cams = read_colmap_text(model)?;
    let file_name = |s: &str| {
        Path::new(s)
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
    };
    images
        .iter()
        .map(|path| {
            let name = path
                .strip_prefix(root)
                .unwrap_or(path)
                .to_string_lossy()
                .into_owned();
            let found = cams.iter().find(|c| c.image == name).or_else(|| {
                cams.iter()
                    .find(|c| file_name(&c.image) == file_name(&name))
            });
            match found {
                Some(c) => Ok(ImageCamera {
                    image: name,
                    size: c.camera.image_size,
                    camera: Some(c.camera),
                }),
                None => {
                    let img = opencv::imgcodecs::imread(
                        path.as_os_str(),
                        opencv::imgcodecs::IMREAD_UNCHANGED,
                    )?;
                    let size = posediff_geometry::ImageSize::new(
                        u32::try_from(opencv::prelude::MatTraitConst::cols(&img)).unwrap_or(0),
                        u32::try_from(opencv::prelude::MatTraitConst::rows(&img)).unwrap_or(0),
                    )
                    .map_err(|_| PosediffError::UnreadableImage(path.clone()))?;
                    Ok(ImageCamera {
                        image: name,
                        size,
                        camera: None,
                    })
                }
            }
        })
        .collect()
}
