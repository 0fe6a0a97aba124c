//! COLMAP sparse models (`cameras`, `images`, `points3D` as `.txt` or `.bin`), written from a
//! [`Reconstruction`] and read back, in COLMAP's own layouts
//! (<https://colmap.github.io/format.html>).
//!
//! Conventions: `QW QX QY QZ TX TY TZ` is world-to-camera (Hamilton, w first); pixel
//! coordinates (principal points and 2-D points) put the top-left pixel's centre at
//! `(0.5, 0.5)`, half a pixel from OpenCV's, so [`PIXEL_CENTRE_OFFSET`] is added on writing and
//! taken off on reading. One camera is written per distinct set of intrinsics and image size
//! (a single one when the focal is shared). Image ids are the input index + 1 (images that were
//! not estimated are left out), point ids the point index + 1.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

use nalgebra::Vector3;
use posediff_geometry::lens::{CameraModel, LensCamera};
use posediff_geometry::{Camera, ImageSize, Intrinsics, Pose, Quaternion, QuaternionSign};

use crate::error::{PosediffError, Result, read_text};
use crate::reconstruction::{
    ImageCamera, ImageRecord, Keypoint, NamedCamera, Reconstruction, ScenePoint, TrackElement,
};

/// COLMAP's and nerfstudio's pixel centres sit half a pixel from OpenCV's.
pub const PIXEL_CENTRE_OFFSET: f64 = 0.5;

/// Text or binary model files.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ColmapFormat {
    /// `cameras.txt`, `images.txt`, `points3D.txt`.
    #[default]
    Text,
    /// `cameras.bin`, `images.bin`, `points3D.bin` (little-endian).
    Binary,
}

/// A camera of a model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    /// `CAMERA_ID`.
    pub id: u32,
    /// The model name (`PINHOLE`, `SIMPLE_RADIAL`, ...).
    pub model: String,
    /// Width, px.
    pub width: u64,
    /// Height, px.
    pub height: u64,
    /// The model's parameters, COLMAP pixels.
    pub params: Vec<f64>,
}

/// An image of a model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    /// `IMAGE_ID`.
    pub id: u32,
    /// World-to-camera rotation `[w, x, y, z]`.
    pub qvec: [f64; 4],
    /// World-to-camera translation.
    pub tvec: [f64; 3],
    /// `CAMERA_ID`.
    pub camera_id: u32,
    /// `NAME`.
    pub name: String,
    /// 2-D points, COLMAP pixels, with the id of the point they observe.
    pub points2d: Vec<([f64; 2], Option<u64>)>,
}

/// A point of a model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapPoint {
    /// `POINT3D_ID`.
    pub id: u64,
    /// Position.
    pub xyz: [f64; 3],
    /// Colour.
    pub rgb: [u8; 3],
    /// Mean reprojection error, px.
    pub error: f64,
    /// `(IMAGE_ID, POINT2D_IDX)`.
    pub track: Vec<(u32, u32)>,
}

/// A whole model.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ColmapModel {
    /// Cameras.
    pub cameras: Vec<ColmapCamera>,
    /// Registered images.
    pub images: Vec<ColmapImage>,
    /// Points.
    pub points: Vec<ColmapPoint>,
}

/// COLMAP's model ids and parameter counts (the pinhole-like models this crate reads).
const MODELS: [(&str, i32, usize); 6] = [
    ("SIMPLE_PINHOLE", 0, 3),
    ("PINHOLE", 1, 4),
    ("SIMPLE_RADIAL", 2, 4),
    ("RADIAL", 3, 5),
    ("OPENCV", 4, 8),
    ("OPENCV_FISHEYE", 5, 8),
];

/// COLMAP's numeric id of the camera model `name` (`SIMPLE_RADIAL` → 2).
///
/// # Errors
/// A model this crate does not write.
pub fn model_id_of(name: &str) -> Result<i64> {
    MODELS
        .iter()
        .find(|(n, _, _)| *n == name)
        .map(|(_, id, _)| i64::from(*id))
        .ok_or_else(|| PosediffError::InvalidArgument(format!("camera model {name}")))
}

/// The index of the principal point's `x` among `model`'s parameters.
fn principal_index(model: CameraModel) -> usize {
    match model {
        CameraModel::SimplePinhole | CameraModel::SimpleRadial | CameraModel::Radial => 1,
        CameraModel::Pinhole | CameraModel::OpenCv | CameraModel::OpenCvFisheye => 2,
    }
}

impl ColmapCamera {
    /// The camera's lens: its model and parameters with the principal point in OpenCV pixels.
    ///
    /// # Errors
    /// An unknown model, a wrong parameter count, invalid values.
    pub fn lens(&self) -> std::result::Result<LensCamera, String> {
        let model =
            CameraModel::from_name(&self.model).map_err(|e| format!("camera {}: {e}", self.id))?;
        if self.params.len() != model.num_params() {
            return Err(format!(
                "camera {}: {} has {} parameters, got {}",
                self.id,
                self.model,
                model.num_params(),
                self.params.len()
            ));
        }
        let mut params = self.params.clone();
        let i = principal_index(model);
        params[i] -= PIXEL_CENTRE_OFFSET;
        params[i + 1] -= PIXEL_CENTRE_OFFSET;
        LensCamera::new(model, params).map_err(|e| format!("camera {}: {e}", self.id))
    }

    /// Pinhole intrinsics in OpenCV pixels (distortion dropped).
    ///
    /// # Errors
    /// An unknown model, a wrong parameter count, invalid values.
    pub fn intrinsics(&self) -> std::result::Result<(Intrinsics, ImageSize), String> {
        let count = MODELS
            .iter()
            .find(|(name, _, _)| *name == self.model)
            .map(|m| m.2)
            .ok_or_else(|| {
                format!(
                    "camera {}: model {} (expected PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV or OPENCV_FISHEYE)",
                    self.id, self.model
                )
            })?;
        if self.params.len() != count {
            return Err(format!(
                "camera {}: {} has {count} parameters, got {}",
                self.id,
                self.model,
                self.params.len()
            ));
        }
        let p = &self.params;
        let (fx, fy, cx, cy) = match self.model.as_str() {
            "PINHOLE" | "OPENCV" | "OPENCV_FISHEYE" => (p[0], p[1], p[2], p[3]),
            _ => (p[0], p[0], p[1], p[2]),
        };
        let size = u32::try_from(self.width)
            .ok()
            .zip(u32::try_from(self.height).ok())
            .and_then(|(w, h)| ImageSize::new(w, h).ok())
            .ok_or_else(|| format!("camera {}: size {}x{}", self.id, self.width, self.height))?;
        let k = Intrinsics::new(fx, fy, cx - PIXEL_CENTRE_OFFSET, cy - PIXEL_CENTRE_OFFSET)
            .map_err(|e| format!("camera {}: {e}", self.id))?;
        Ok((k, size))
    }
}

impl ColmapModel {
    /// The model of the estimated images of `r`.
    ///
    /// # Errors
    /// A camera whose rotation is not a rotation.
    pub fn from_reconstruction(r: &Reconstruction) -> Result<Self> {
        let mut model = Self::default();
        let mut camera_ids: HashMap<Vec<u64>, u32> = HashMap::new();
        let mut image_ids = vec![None; r.images.len()];
        for (index, record) in r.images.iter().enumerate() {
            let Some(cam) = &record.camera.camera else {
                continue;
            };
            let s = cam.image_size;
            let lens = record
                .camera
                .lens
                .clone()
                .unwrap_or_else(|| LensCamera::pinhole(&cam.intrinsics));
            let mut params = lens.params().to_vec();
            let principal = principal_index(lens.model());
            params[principal] += PIXEL_CENTRE_OFFSET;
            params[principal + 1] += PIXEL_CENTRE_OFFSET;
            let mut key = vec![u64::from(s.width()), u64::from(s.height())];
            key.push(lens.model().colmap_id() as u64);
            key.extend(params.iter().map(|p| p.to_bits()));
            let next = model.cameras.len() as u32 + 1;
            let camera_id = *camera_ids.entry(key).or_insert_with(|| {
                model.cameras.push(ColmapCamera {
                    id: next,
                    model: lens.model().name().into(),
                    width: u64::from(s.width()),
                    height: u64::from(s.height()),
                    params,
                });
                next
            });
            let q = Quaternion::from_rotation_matrix(
                &cam.cam_from_world.rotation,
                QuaternionSign::NonNegativeReal,
            )?;
            let t = cam.cam_from_world.translation;
            let id = index as u32 + 1;
            image_ids[index] = Some(id);
            model.images.push(ColmapImage {
                id,
                qvec: [q.w, q.x, q.y, q.z],
                tvec: [t.x, t.y, t.z],
                camera_id,
                name: record.camera.image.clone(),
                points2d: record
                    .keypoints
                    .iter()
                    .map(|kp| {
                        // The photo's pixel: COLMAP's 2-D points are where the lens images.
                        let xy = record.camera.photo_pixel(kp.xy);
                        (
                            [xy[0] + PIXEL_CENTRE_OFFSET, xy[1] + PIXEL_CENTRE_OFFSET],
                            kp.point.map(|p| p as u64 + 1),
                        )
                    })
                    .collect(),
            });
        }
        for (index, p) in r.points.iter().enumerate() {
            let track: Vec<(u32, u32)> = p
                .track
                .iter()
                .filter_map(|e| image_ids[e.image].map(|id| (id, e.keypoint as u32)))
                .collect();
            if track.len() < 2 {
                continue;
            }
            model.points.push(ColmapPoint {
                id: index as u64 + 1,
                xyz: [p.xyz.x, p.xyz.y, p.xyz.z],
                rgb: p.rgb,
                error: p.error_px,
                track,
            });
        }
        Ok(model)
    }

    /// The registered images' cameras (pinhole approximations), in the model's image order.
    ///
    /// # Errors
    /// An image naming an unknown camera, an unreadable camera, an invalid rotation.
    pub fn named_cameras(&self, dir: &Path) -> Result<Vec<NamedCamera>> {
        self.images
            .iter()
            .zip(self.image_cameras(dir)?)
            .map(|(im, cam)| {
                let (k, size) = cam
                    .intrinsics()
                    .map_err(|e| PosediffError::invalid(dir, e))?;
                let [w, x, y, z] = im.qvec;
                let r = Quaternion::new(w, x, y, z).to_rotation_matrix()?;
                Ok(NamedCamera {
                    image: im.name.clone(),
                    camera: Camera::new(k, Pose::new(r, Vector3::from(im.tvec)), size),
                })
            })
            .collect()
    }

    /// Each registered image's camera, in the model's image order.
    ///
    /// # Errors
    /// An image naming an unknown camera.
    fn image_cameras(&self, dir: &Path) -> Result<Vec<&ColmapCamera>> {
        let cams: HashMap<u32, &ColmapCamera> = self.cameras.iter().map(|c| (c.id, c)).collect();
        self.images
            .iter()
            .map(|im| {
                cams.get(&im.camera_id).copied().ok_or_else(|| {
                    PosediffError::invalid(
                        dir,
                        format!("image {} names unknown camera {}", im.id, im.camera_id),
                    )
                })
            })
            .collect()
    }

    /// The model as a [`Reconstruction`]: the registered images in the model's order, their
    /// 2-D points as keypoints, the points with their tracks.
    ///
    /// # Errors
    /// As [`Self::named_cameras`]; a track naming an unknown image or 2-D point.
    pub fn to_reconstruction(&self, dir: &Path) -> Result<Reconstruction> {
        let named = self.named_cameras(dir)?;
        let index: HashMap<u32, usize> = self
            .images
            .iter()
            .enumerate()
            .map(|(k, im)| (im.id, k))
            .collect();
        let lenses = self.image_lenses(dir)?;
        let mut images = Vec::with_capacity(self.images.len());
        for ((im, n), lens) in self.images.iter().zip(named).zip(lenses) {
            // The keypoints live in undistorted pixels, where the pinhole camera projects.
            let keypoints = im
                .points2d
                .iter()
                .enumerate()
                .map(|(j, (xy, _))| {
                    let photo = [xy[0] - PIXEL_CENTRE_OFFSET, xy[1] - PIXEL_CENTRE_OFFSET];
                    let xy = match &lens {
                        Some(lens) => lens
                            .undistort_pixel(&nalgebra::Vector2::from(photo))
                            .map_err(|e| {
                                PosediffError::invalid(
                                    dir,
                                    format!("image {}: 2-D point {j}: {e}", im.name),
                                )
                            })?
                            .into(),
                        None => photo,
                    };
                    Ok(Keypoint { xy, point: None })
                })
                .collect::<Result<Vec<_>>>()?;
            images.push(ImageRecord {
                camera: ImageCamera {
                    image: n.image,
                    size: n.camera.image_size,
                    camera: Some(n.camera),
                    lens,
                },
                keypoints,
            });
        }
        let mut points = Vec::with_capacity(self.points.len());
        for (k, p) in self.points.iter().enumerate() {
            let mut track = Vec::with_capacity(p.track.len());
            for (image, idx) in &p.track {
                let bad =
                    |what: String| PosediffError::invalid(dir, format!("point {}: {what}", p.id));
                let i = *index
                    .get(image)
                    .ok_or_else(|| bad(format!("unknown image {image}")))?;
                let slot = images[i]
                    .keypoints
                    .get_mut(*idx as usize)
                    .ok_or_else(|| bad(format!("image {image} has no 2-D point {idx}")))?;
                slot.point = Some(k);
                track.push(TrackElement {
                    image: i,
                    keypoint: *idx as usize,
                });
            }
            points.push(ScenePoint {
                xyz: Vector3::from(p.xyz),
                rgb: p.rgb,
                error_px: p.error,
                track,
            });
        }
        Ok(Reconstruction { images, points })
    }

    /// Each registered image's lens when its camera distorts, in the model's image order.
    ///
    /// # Errors
    /// An image naming an unknown camera, an unreadable camera.
    pub fn image_lenses(&self, dir: &Path) -> Result<Vec<Option<LensCamera>>> {
        self.image_cameras(dir)?
            .into_iter()
            .map(|cam| {
                let lens = cam.lens().map_err(|e| PosediffError::invalid(dir, e))?;
                Ok(lens.is_distorted().then_some(lens))
            })
            .collect()
    }

    /// Mean over points of the reprojection error recomputed from the cameras and 2-D points
    /// (`None` without points).
    ///
    /// # Errors
    /// As [`Self::named_cameras`]; a track naming an unknown image or 2-D point.
    pub fn recomputed_mean_error(&self, dir: &Path) -> Result<Option<f64>> {
        let named = self.named_cameras(dir)?;
        let lenses = self.image_lenses(dir)?;
        let by_id: HashMap<u32, (usize, &Camera)> = self
            .images
            .iter()
            .zip(&named)
            .enumerate()
            .map(|(k, (im, n))| (im.id, (k, &n.camera)))
            .collect();
        let mut total = 0.0;
        for p in &self.points {
            let mut sum = 0.0;
            for (image, idx) in &p.track {
                let (k, cam) = by_id.get(image).ok_or_else(|| {
                    PosediffError::invalid(
                        dir,
                        format!("point {} sees unknown image {image}", p.id),
                    )
                })?;
                let (xy, _) = self.images[*k].points2d.get(*idx as usize).ok_or_else(|| {
                    PosediffError::invalid(dir, format!("point {} names 2-D point {idx}", p.id))
                })?;
                let q = cam
                    .project(&nalgebra::Point3::from(Vector3::from(p.xyz)))
                    .ok_or_else(|| {
                        PosediffError::invalid(dir, format!("point {} behind image {image}", p.id))
                    })?;
                let q = match &lenses[*k] {
                    Some(lens) => lens.distort_pixel(&q.coords),
                    None => q.coords,
                };
                sum += (q.x + PIXEL_CENTRE_OFFSET - xy[0]).hypot(q.y + PIXEL_CENTRE_OFFSET - xy[1]);
            }
            total += sum / p.track.len().max(1) as f64;
        }
        Ok((!self.points.is_empty()).then(|| total / self.points.len() as f64))
    }

    /// Writes the three files into `dir` (created if missing).
    ///
    /// # Errors
    /// I/O errors.
    pub fn write(&self, dir: &Path, format: ColmapFormat) -> Result<()> {
        std::fs::create_dir_all(dir).map_err(|source| PosediffError::Write {
            path: dir.to_owned(),
            source,
        })?;
        match format {
            ColmapFormat::Text => {
                write_file(&dir.join("cameras.txt"), self.cameras_text().as_bytes())?;
                write_file(&dir.join("images.txt"), self.images_text().as_bytes())?;
                write_file(&dir.join("points3D.txt"), self.points_text().as_bytes())
            }
            ColmapFormat::Binary => {
                write_file(&dir.join("cameras.bin"), &self.cameras_binary())?;
                write_file(&dir.join("images.bin"), &self.images_binary())?;
                write_file(&dir.join("points3D.bin"), &self.points_binary())
            }
        }
    }

    fn cameras_text(&self) -> String {
        let mut s = String::from(
            "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
        );
        let _ = writeln!(s, "# Number of cameras: {}", self.cameras.len());
        for c in &self.cameras {
            let _ = write!(s, "{} {} {} {}", c.id, c.model, c.width, c.height);
            for p in &c.params {
                let _ = write!(s, " {p}");
            }
            s.push('\n');
        }
        s
    }

    fn images_text(&self) -> String {
        let observations: usize = self
            .images
            .iter()
            .map(|im| im.points2d.iter().filter(|p| p.1.is_some()).count())
            .sum();
        let mut s = String::from(
            "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n",
        );
        let _ = writeln!(
            s,
            "# Number of images: {}, mean observations per image: {}",
            self.images.len(),
            observations as f64 / self.images.len().max(1) as f64
        );
        for im in &self.images {
            let [qw, qx, qy, qz] = im.qvec;
            let [tx, ty, tz] = im.tvec;
            let _ = writeln!(
                s,
                "{} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {} {}",
                im.id, im.camera_id, im.name
            );
            let mut first = true;
            for (xy, point) in &im.points2d {
                if !first {
                    s.push(' ');
                }
                first = false;
                match point {
                    Some(id) => {
                        let _ = write!(s, "{} {} {id}", xy[0], xy[1]);
                    }
                    None => {
                        let _ = write!(s, "{} {} -1", xy[0], xy[1]);
                    }
                }
            }
            s.push('\n');
        }
        s
    }

    fn points_text(&self) -> String {
        let length: usize = self.points.iter().map(|p| p.track.len()).sum();
        let mut s = String::from(
            "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
        );
        let _ = writeln!(
            s,
            "# Number of points: {}, mean track length: {}",
            self.points.len(),
            length as f64 / self.points.len().max(1) as f64
        );
        for p in &self.points {
            let [x, y, z] = p.xyz;
            let [r, g, b] = p.rgb;
            let _ = write!(s, "{} {x} {y} {z} {r} {g} {b} {}", p.id, p.error);
            for (image, idx) in &p.track {
                let _ = write!(s, " {image} {idx}");
            }
            s.push('\n');
        }
        s
    }

    fn cameras_binary(&self) -> Vec<u8> {
        let mut b = Vec::new();
        put_u64(&mut b, self.cameras.len() as u64);
        for c in &self.cameras {
            let id = MODELS.iter().find(|m| m.0 == c.model).map_or(-1, |m| m.1);
            b.extend_from_slice(&c.id.to_le_bytes());
            b.extend_from_slice(&id.to_le_bytes());
            put_u64(&mut b, c.width);
            put_u64(&mut b, c.height);
            for p in &c.params {
                b.extend_from_slice(&p.to_le_bytes());
            }
        }
        b
    }

    fn images_binary(&self) -> Vec<u8> {
        let mut b = Vec::new();
        put_u64(&mut b, self.images.len() as u64);
        for im in &self.images {
            b.extend_from_slice(&im.id.to_le_bytes());
            for v in im.qvec.iter().chain(&im.tvec) {
                b.extend_from_slice(&v.to_le_bytes());
            }
            b.extend_from_slice(&im.camera_id.to_le_bytes());
            b.extend_from_slice(im.name.as_bytes());
            b.push(0);
            put_u64(&mut b, im.points2d.len() as u64);
            for (xy, point) in &im.points2d {
                b.extend_from_slice(&xy[0].to_le_bytes());
                b.extend_from_slice(&xy[1].to_le_bytes());
                put_u64(&mut b, point.unwrap_or(u64::MAX));
            }
        }
        b
    }

    fn points_binary(&self) -> Vec<u8> {
        let mut b = Vec::new();
        put_u64(&mut b, self.points.len() as u64);
        for p in &self.points {
            put_u64(&mut b, p.id);
            for v in &p.xyz {
                b.extend_from_slice(&v.to_le_bytes());
            }
            b.extend_from_slice(&p.rgb);
            b.extend_from_slice(&p.error.to_le_bytes());
            put_u64(&mut b, p.track.len() as u64);
            for (image, idx) in &p.track {
                b.extend_from_slice(&image.to_le_bytes());
                b.extend_from_slice(&idx.to_le_bytes());
            }
        }
        b
    }

    /// Reads the model in `dir`: the `.bin` files where `cameras.bin` exists (as COLMAP
    /// prefers), else the `.txt` files. `points3D` may be missing or empty.
    ///
    /// # Errors
    /// Missing or malformed files, with the file and what is wrong.
    pub fn read(dir: &Path) -> Result<Self> {
        if dir.join("cameras.bin").is_file() {
            Self::read_binary(dir)
        } else if dir.join("cameras.txt").is_file() {
            Self::read_text(dir)
        } else {
            Err(PosediffError::invalid(
                dir,
                "no COLMAP model here: expected cameras.txt, images.txt (and points3D.txt) or the .bin files",
            ))
        }
    }

    /// Reads `cameras.txt`, `images.txt` and (if present) `points3D.txt`.
    ///
    /// # Errors
    /// As [`Self::read`].
    pub fn read_text(dir: &Path) -> Result<Self> {
        let mut model = Self::default();
        let path = dir.join("cameras.txt");
        for (n, line) in data_lines(&read_text(&path)?) {
            let f: Vec<&str> = line.split_whitespace().collect();
            let bad = |what: &str| PosediffError::invalid(&path, format!("line {n}: {what}"));
            if f.len() < 4 {
                return Err(bad("expected `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`"));
            }
            let camera = ColmapCamera {
                id: f[0].parse().map_err(|_| bad("CAMERA_ID is not a number"))?,
                model: f[1].to_owned(),
                width: f[2].parse().map_err(|_| bad("WIDTH is not a number"))?,
                height: f[3].parse().map_err(|_| bad("HEIGHT is not a number"))?,
                params: f[4..]
                    .iter()
                    .map(|v| {
                        parse_finite(v).ok_or_else(|| bad("a parameter is not a finite number"))
                    })
                    .collect::<Result<_>>()?,
            };
            // Every camera must convert, used or not (a model that reads also writes back).
            camera.intrinsics().map_err(|e| bad(&e))?;
            model.cameras.push(camera);
        }
        let path = dir.join("images.txt");
        let text = read_text(&path)?;
        // Two lines per image: the pose, then its 2-D points (possibly empty). Comments are
        // skipped but empty lines are not: an empty points line is a line.
        let lines: Vec<(usize, &str)> = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.starts_with('#'))
            .map(|(n, l)| (n + 1, l))
            .collect();
        let mut k = 0;
        while k < lines.len() {
            let (n, line) = lines[k];
            if line.trim().is_empty() {
                k += 1;
                continue;
            }
            let bad =
                |n: usize, what: &str| PosediffError::invalid(&path, format!("line {n}: {what}"));
            let f: Vec<&str> = line.split_whitespace().collect();
            if f.len() < 10 {
                return Err(bad(
                    n,
                    "expected `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`",
                ));
            }
            let num = |i: usize| parse_finite(f[i]).ok_or_else(|| bad(n, "not a finite number"));
            let points_line = lines.get(k + 1).map_or("", |l| l.1);
            let p: Vec<&str> = points_line.split_whitespace().collect();
            if !p.len().is_multiple_of(3) {
                return Err(bad(n + 1, "POINTS2D must be triples X Y POINT3D_ID"));
            }
            let points2d = p
                .chunks(3)
                .map(|t| {
                    let x =
                        parse_finite(t[0]).ok_or_else(|| bad(n + 1, "X is not a finite number"))?;
                    let y =
                        parse_finite(t[1]).ok_or_else(|| bad(n + 1, "Y is not a finite number"))?;
                    let id: i64 = t[2]
                        .parse()
                        .map_err(|_| bad(n + 1, "POINT3D_ID is not an integer"))?;
                    Ok(([x, y], u64::try_from(id).ok()))
                })
                .collect::<Result<_>>()?;
            model.images.push(ColmapImage {
                id: f[0]
                    .parse()
                    .map_err(|_| bad(n, "IMAGE_ID is not a number"))?,
                qvec: [num(1)?, num(2)?, num(3)?, num(4)?],
                tvec: [num(5)?, num(6)?, num(7)?],
                camera_id: f[8]
                    .parse()
                    .map_err(|_| bad(n, "CAMERA_ID is not a number"))?,
                name: f[9..].join(" "),
                points2d,
            });
            k += 2;
        }
        let path = dir.join("points3D.txt");
        if path.is_file() {
            for (n, line) in data_lines(&read_text(&path)?) {
                let f: Vec<&str> = line.split_whitespace().collect();
                let bad = |what: &str| PosediffError::invalid(&path, format!("line {n}: {what}"));
                if f.len() < 8 || !(f.len() - 8).is_multiple_of(2) {
                    return Err(bad(
                        "expected `POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)...`",
                    ));
                }
                let num = |i: usize| parse_finite(f[i]).ok_or_else(|| bad("not a finite number"));
                let byte = |i: usize| f[i].parse::<u8>().map_err(|_| bad("colour is not 0-255"));
                model.points.push(ColmapPoint {
                    id: f[0]
                        .parse()
                        .map_err(|_| bad("POINT3D_ID is not a number"))?,
                    xyz: [num(1)?, num(2)?, num(3)?],
                    rgb: [byte(4)?, byte(5)?, byte(6)?],
                    error: num(7)?,
                    track: f[8..]
                        .chunks(2)
                        .map(|t| {
                            Ok((
                                t[0].parse().map_err(|_| bad("IMAGE_ID is not a number"))?,
                                t[1].parse()
                                    .map_err(|_| bad("POINT2D_IDX is not a number"))?,
                            ))
                        })
                        .collect::<Result<_>>()?,
                });
            }
        }
        Ok(model)
    }

    /// Reads `cameras.bin`, `images.bin` and (if present) `points3D.bin`. Counts in the headers
    /// are checked against the bytes left before anything is allocated.
    ///
    /// # Errors
    /// As [`Self::read`].
    pub fn read_binary(dir: &Path) -> Result<Self> {
        let mut model = Self::default();
        let read = |name: &str| -> Result<(std::path::PathBuf, Vec<u8>)> {
            let path = dir.join(name);
            let bytes = std::fs::read(&path).map_err(|source| PosediffError::Read {
                path: path.clone(),
                source,
            })?;
            Ok((path, bytes))
        };
        let (path, bytes) = read("cameras.bin")?;
        let mut r = Reader::new(&path, &bytes);
        let n = r.count(24)?;
        for _ in 0..n {
            let id = r.u32()?;
            let model_id = r.i32()?;
            let (name, count) = MODELS
                .iter()
                .find(|m| m.1 == model_id)
                .map(|m| (m.0, m.2))
                .ok_or_else(|| r.error(&format!("camera {id}: unsupported model id {model_id}")))?;
            let width = r.u64()?;
            let height = r.u64()?;
            let params = (0..count).map(|_| r.f64()).collect::<Result<_>>()?;
            let camera = ColmapCamera {
                id,
                model: name.into(),
                width,
                height,
                params,
            };
            camera.intrinsics().map_err(|e| r.error(&e))?;
            model.cameras.push(camera);
        }
        r.finish()?;
        let (path, bytes) = read("images.bin")?;
        let mut r = Reader::new(&path, &bytes);
        let n = r.count(73)?;
        for _ in 0..n {
            let id = r.u32()?;
            let q = [r.f64()?, r.f64()?, r.f64()?, r.f64()?];
            let t = [r.f64()?, r.f64()?, r.f64()?];
            let camera_id = r.u32()?;
            let name = r.c_string()?;
            let m = r.count(24)?;
            let points2d = (0..m)
                .map(|_| {
                    let xy = [r.f64()?, r.f64()?];
                    let id = r.u64()?;
                    Ok((xy, (id != u64::MAX).then_some(id)))
                })
                .collect::<Result<_>>()?;
            model.images.push(ColmapImage {
                id,
                qvec: q,
                tvec: t,
                camera_id,
                name,
                points2d,
            });
        }
        r.finish()?;
        let path = dir.join("points3D.bin");
        if path.is_file() {
            let (path, bytes) = read("points3D.bin")?;
            let mut r = Reader::new(&path, &bytes);
            let n = r.count(51)?;
            for _ in 0..n {
                let id = r.u64()?;
                let xyz = [r.f64()?, r.f64()?, r.f64()?];
                let rgb = [r.u8()?, r.u8()?, r.u8()?];
                let error = r.f64()?;
                let m = r.count(8)?;
                let track = (0..m)
                    .map(|_| Ok((r.u32()?, r.u32()?)))
                    .collect::<Result<_>>()?;
                model.points.push(ColmapPoint {
                    id,
                    xyz,
                    rgb,
                    error,
                    track,
                });
            }
            r.finish()?;
        }
        Ok(model)
    }
}

/// Non-comment, non-empty lines with their 1-based numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.starts_with('#') && !l.trim().is_empty())
        .map(|(n, l)| (n + 1, l))
}

fn parse_finite(s: &str) -> Option<f64> {
    s.parse::<f64>().ok().filter(|v| v.is_finite())
}

fn put_u64(b: &mut Vec<u8>, v: u64) {
    b.extend_from_slice(&v.to_le_bytes());
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|source| PosediffError::Write {
        path: path.to_owned(),
        source,
    })
}

/// A little-endian cursor that names its file and offset on failure.
struct Reader<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn new(path: &'a Path, bytes: &'a [u8]) -> Self {
        Self { path, bytes, at: 0 }
    }

    fn error(&self, what: &str) -> PosediffError {
        PosediffError::invalid(self.path, format!("at byte {}: {what}", self.at))
    }

    fn take<const N: usize>(&mut self) -> Result<[u8; N]> {
        let end = self.at.checked_add(N).filter(|&e| e <= self.bytes.len());
        let Some(end) = end else {
            return Err(self.error("file ends early (truncated?)"));
        };
        let mut out = [0u8; N];
        out.copy_from_slice(&self.bytes[self.at..end]);
        self.at = end;
        Ok(out)
    }

    fn u8(&mut self) -> Result<u8> {
        Ok(self.take::<1>()?[0])
    }
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take()?))
    }
    fn i32(&mut self) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take()?))
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take()?))
    }
    fn f64(&mut self) -> Result<f64> {
        let v = f64::from_le_bytes(self.take()?);
        if v.is_finite() {
            Ok(v)
        } else {
            Err(self.error("a value is not finite"))
        }
    }

    /// A count of records of at least `min_bytes` each, no more than the bytes left can hold.
    fn count(&mut self, min_bytes: usize) -> Result<usize> {
        let n = self.u64()?;
        let left = (self.bytes.len() - self.at) as u64;
        if n > left / min_bytes as u64 {
            return Err(self.error(&format!(
                "a count of {n} records cannot fit in the {left} bytes left"
            )));
        }
        Ok(n as usize)
    }

    fn c_string(&mut self) -> Result<String> {
        let rest = &self.bytes[self.at..];
        let Some(end) = rest.iter().position(|&b| b == 0) else {
            return Err(self.error("an image name without its terminating NUL"));
        };
        let s = std::str::from_utf8(&rest[..end])
            .map_err(|_| self.error("an image name that is not UTF-8"))?
            .to_owned();
        self.at += end + 1;
        Ok(s)
    }

    fn finish(&self) -> Result<()> {
        if self.at == self.bytes.len() {
            Ok(())
        } else {
            Err(self.error(&format!(
                "{} bytes after the last record",
                self.bytes.len() - self.at
            )))
        }
    }
}
