//! The result every writer reads: the images with their cameras and keypoints, and the sparse
//! points with their colours, errors and tracks (COLMAP's data model: a track element names an
//! image and the index of one of its keypoints).

use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use opencv::core::{Mat, Size, Vector};
use opencv::prelude::*;
use posediff_geometry::lens::LensCamera;
use posediff_geometry::{Camera, ImageSize, PairMatches};
use posediff_sfm::points::{PointOptions, PointsReport, triangulate_points};
use rayon::prelude::*;

use crate::error::{PosediffError, Result};

/// One camera and the image it belongs to (path relative to the input folder).
#[derive(Debug, Clone, PartialEq)]
pub struct NamedCamera {
    /// Image path relative to the input folder.
    pub image: String,
    /// The camera, original image pixels.
    pub camera: Camera,
}

/// One image of a set and its camera, `None` where none was estimated.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageCamera {
    /// Image path relative to the input folder.
    pub image: String,
    /// The image's size.
    pub size: ImageSize,
    /// The camera.
    pub camera: Option<Camera>,
    /// The lens, when it distorts (SIMPLE_RADIAL, OPENCV, …): its focal and principal point
    /// are `camera`'s. `camera` then maps to undistorted pixels, as do the record's keypoints;
    /// [`Self::photo_pixel`] maps those to the photo's pixels.
    pub lens: Option<LensCamera>,
}

impl ImageCamera {
    /// The photo's pixel of the undistorted pixel `xy` (`xy` itself without a lens).
    pub fn photo_pixel(&self, xy: [f64; 2]) -> [f64; 2] {
        match &self.lens {
            Some(lens) => lens.distort_pixel(&nalgebra::Vector2::from(xy)).into(),
            None => xy,
        }
    }

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

/// One keypoint of an image that occurs in a verified match (OpenCV pixels), and the point it
/// observes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    /// Pixel coordinates, pixel centres at integers; undistorted where the image's camera has a
    /// lens ([`ImageCamera::photo_pixel`] gives the photo's pixel).
    pub xy: [f64; 2],
    /// Index into [`Reconstruction::points`].
    pub point: Option<usize>,
}

/// One image: its name relative to the input folder, its camera and its keypoints.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageRecord {
    /// The camera and the image's name and size.
    pub camera: ImageCamera,
    /// The keypoints that occur in the matches, in keypoint-id order.
    pub keypoints: Vec<Keypoint>,
}

/// One element of a track: the image and the index into its [`ImageRecord::keypoints`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrackElement {
    /// Image index.
    pub image: usize,
    /// Keypoint index within the image's record.
    pub keypoint: usize,
}

/// One scene point.
#[derive(Debug, Clone, PartialEq)]
pub struct ScenePoint {
    /// World position, the cameras' frame.
    pub xyz: Vector3<f64>,
    /// Mean colour of its observations, sRGB.
    pub rgb: [u8; 3],
    /// Mean reprojection error, px.
    pub error_px: f64,
    /// Its observations.
    pub track: Vec<TrackElement>,
}

/// Cameras and points.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Reconstruction {
    /// Every image, in input order.
    pub images: Vec<ImageRecord>,
    /// The points.
    pub points: Vec<ScenePoint>,
}

impl Reconstruction {
    /// Cameras without points.
    pub fn from_cameras(images: Vec<ImageCamera>) -> Self {
        Self {
            images: images
                .into_iter()
                .map(|camera| ImageRecord {
                    camera,
                    keypoints: Vec::new(),
                })
                .collect(),
            points: Vec::new(),
        }
    }

    /// The tracks of `pairs` triangulated with the cameras (robustly, reprojection-filtered:
    /// [`posediff_sfm::points`]), coloured from the image files `paths` (grey without).
    ///
    /// # Errors
    /// Pairs naming images out of range; an image that cannot be read for its colours.
    pub fn triangulate(
        images: Vec<ImageCamera>,
        paths: Option<&[PathBuf]>,
        pairs: &[PairMatches],
        options: &PointOptions,
    ) -> Result<(Self, PointsReport)> {
        let cameras: Vec<Option<Camera>> = images.iter().map(|e| e.camera).collect();
        let (points, report) = triangulate_points(&cameras, pairs, options)?;
        // Keypoint ids per image that occur in any match, sorted; then each id's slot.
        // Each keypoint kept once as it is first seen (every match's two ends listed before
        // deduplicating was 800 MB at 1000 frames).
        let mut seen: Vec<Vec<bool>> = vec![Vec::new(); images.len()];
        let mut ids: Vec<Vec<(u32, [f64; 2])>> = vec![Vec::new(); images.len()];
        for p in pairs {
            for k in 0..p.len() {
                for (image, id, xy) in [
                    (p.first, p.idx1[k], p.kp1[k]),
                    (p.second, p.idx2[k], p.kp2[k]),
                ] {
                    let (Some(marks), Some(list)) = (seen.get_mut(image), ids.get_mut(image))
                    else {
                        continue;
                    };
                    let at = id as usize;
                    if marks.len() <= at {
                        marks.resize(at + 1, false);
                    }
                    if !marks[at] {
                        marks[at] = true;
                        list.push((id, xy));
                    }
                }
            }
        }
        drop(seen);
        for list in &mut ids {
            list.sort_by_key(|(id, _)| *id);
        }
        let mut records: Vec<ImageRecord> = images
            .into_iter()
            .zip(&ids)
            .map(|(camera, list)| ImageRecord {
                camera,
                keypoints: list
                    .iter()
                    .map(|(_, xy)| Keypoint {
                        xy: *xy,
                        point: None,
                    })
                    .collect(),
            })
            .collect();
        let mut scene = Vec::with_capacity(points.len());
        for (index, p) in points.iter().enumerate() {
            let mut track = Vec::with_capacity(p.observations.len());
            for o in &p.observations {
                let slot = ids[o.image]
                    .binary_search_by_key(&o.keypoint, |(id, _)| *id)
                    .map_err(|_| {
                        PosediffError::InvalidArgument(format!(
                            "a track names keypoint {} of image {} that no match has",
                            o.keypoint, o.image
                        ))
                    })?;
                records[o.image].keypoints[slot].point = Some(index);
                track.push(TrackElement {
                    image: o.image,
                    keypoint: slot,
                });
            }
            scene.push(ScenePoint {
                xyz: p.xyz,
                rgb: [128; 3],
                error_px: p.error_px,
                track,
            });
        }
        let mut out = Self {
            images: records,
            points: scene,
        };
        out.photo_errors();
        if let Some(paths) = paths {
            out.colour_from(paths)?;
        }
        Ok((out, report))
    }

    /// Each point's error in the photos' pixels where its images have a lens (COLMAP's
    /// `ERROR`: between the lens's projection and the observed pixel), instead of the
    /// undistorted pixels it was triangulated in.
    fn photo_errors(&mut self) {
        if self.images.iter().all(|i| i.camera.lens.is_none()) {
            return;
        }
        // A point some camera cannot project (none: triangulation keeps points in front of
        // estimated cameras) keeps its error.
        'points: for p in &mut self.points {
            let mut sum = 0.0;
            for e in &p.track {
                let image = &self.images[e.image];
                let Some(camera) = &image.camera.camera else {
                    continue 'points;
                };
                let Some(q) = camera.project(&nalgebra::Point3::from(p.xyz)) else {
                    continue 'points;
                };
                let a = image.camera.photo_pixel([q.x, q.y]);
                let b = image.camera.photo_pixel(image.keypoints[e.keypoint].xy);
                sum += (a[0] - b[0]).hypot(a[1] - b[1]);
            }
            p.error_px = sum / p.track.len().max(1) as f64;
        }
    }

    /// The estimated images' indices.
    pub fn estimated(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.images.len()).filter(|&i| self.images[i].camera.camera.is_some())
    }

    /// Sets each point's colour to the mean of its observations' pixels in `paths` (one file
    /// per image; images without observations are not read).
    ///
    /// # Errors
    /// A count that does not match the images; an image that cannot be read.
    pub fn colour_from(&mut self, paths: &[PathBuf]) -> Result<()> {
        self.colour_and_thumbnails(paths, None).map(|_| ())
    }

    /// [`Self::colour_from`] and, with `thumbnail_side`, a JPEG thumbnail of each estimated
    /// image ([`thumbnail_jpeg`]) from the same decode: one read of each image.
    ///
    /// # Errors
    /// As [`Self::colour_from`].
    pub fn colour_and_thumbnails(
        &mut self,
        paths: &[PathBuf],
        thumbnail_side: Option<u32>,
    ) -> Result<Vec<Option<Vec<u8>>>> {
        if paths.len() != self.images.len() {
            return Err(PosediffError::InvalidArgument(format!(
                "{} image files for {} images",
                paths.len(),
                self.images.len()
            )));
        }
        // Per image, the (point, keypoint) observations to sample.
        let mut wanted: Vec<Vec<(usize, [f64; 2])>> = vec![Vec::new(); self.images.len()];
        for (index, p) in self.points.iter().enumerate() {
            for e in &p.track {
                let image = &self.images[e.image];
                let xy = image.camera.photo_pixel(image.keypoints[e.keypoint].xy);
                wanted[e.image].push((index, xy));
            }
        }
        let per_image: Vec<(Vec<Sample>, Option<Vec<u8>>)> = wanted
            .par_iter()
            .zip(paths)
            .zip(&self.images)
            .map(|((w, path), record)| {
                let thumb = thumbnail_side.filter(|_| record.camera.camera.is_some());
                if w.is_empty() && thumb.is_none() {
                    return Ok((Vec::new(), None));
                }
                let img = read_colour(path)?;
                let samples = w
                    .iter()
                    .map(|(index, xy)| (*index, sample(&img, *xy)))
                    .collect();
                let thumbnail = thumb.map(|side| thumbnail_jpeg(&img, side)).transpose()?;
                Ok((samples, thumbnail))
            })
            .collect::<Result<_>>()?;
        let (samples, thumbnails): (Vec<_>, Vec<_>) = per_image.into_iter().unzip();
        let mut sums = vec![[0u64; 4]; self.points.len()];
        for (index, rgb) in samples.into_iter().flatten() {
            let s = &mut sums[index];
            for c in 0..3 {
                s[c] += u64::from(rgb[c]);
            }
            s[3] += 1;
        }
        for (p, s) in self.points.iter_mut().zip(sums) {
            if s[3] > 0 {
                p.rgb = [0, 1, 2].map(|c| ((s[c] + s[3] / 2) / s[3]) as u8);
            }
        }
        Ok(thumbnails)
    }

    /// Mean over points of their recorded errors, px (`None` without points).
    pub fn mean_error_px(&self) -> Option<f64> {
        (!self.points.is_empty())
            .then(|| self.points.iter().map(|p| p.error_px).sum::<f64>() / self.points.len() as f64)
    }

    /// Mean track length (0 without points).
    pub fn mean_track_length(&self) -> f64 {
        if self.points.is_empty() {
            return 0.0;
        }
        self.points.iter().map(|p| p.track.len()).sum::<usize>() as f64 / self.points.len() as f64
    }
}

/// One point's colour as seen in one image.
type Sample = (usize, [u8; 3]);

/// An image as 8-bit BGR, the file named on failure.
///
/// # Errors
/// [`PosediffError::UnreadableImage`].
pub fn read_colour(path: &Path) -> Result<Mat> {
    Ok(posediff_matching::image_check::decode(
        path,
        opencv::imgcodecs::IMREAD_COLOR,
    )?)
}

/// The RGB of the pixel nearest `xy` (clamped into the image).
fn sample(img: &Mat, xy: [f64; 2]) -> [u8; 3] {
    let clamp = |v: f64, n: i32| (v.round() as i32).clamp(0, n - 1);
    let (x, y) = (clamp(xy[0], img.cols()), clamp(xy[1], img.rows()));
    img.at_2d::<opencv::core::Vec3b>(y, x)
        .map_or([128; 3], |bgr| [bgr[2], bgr[1], bgr[0]])
}

/// A JPEG thumbnail whose longer side is at most `side` pixels.
///
/// # Errors
/// OpenCV errors.
pub fn thumbnail_jpeg(img: &Mat, side: u32) -> Result<Vec<u8>> {
    let longer = img.cols().max(img.rows()).max(1) as f64;
    let scale = (f64::from(side) / longer).min(1.0);
    let size = Size::new(
        ((img.cols() as f64 * scale).round() as i32).max(1),
        ((img.rows() as f64 * scale).round() as i32).max(1),
    );
    let mut small = Mat::default();
    opencv::imgproc::resize(img, &mut small, size, 0.0, 0.0, opencv::imgproc::INTER_AREA)?;
    let mut buf = Vector::<u8>::new();
    let params = Vector::<i32>::from_slice(&[opencv::imgcodecs::IMWRITE_JPEG_QUALITY, 80]);
    opencv::imgcodecs::imencode(".jpg", &small, &mut buf, &params)?;
    Ok(buf.to_vec())
}

/// The size of `img`.
///
/// # Errors
/// An empty image.
pub fn mat_size(img: &Mat, path: &Path) -> Result<ImageSize> {
    ImageSize::new(
        u32::try_from(img.cols()).unwrap_or(0),
        u32::try_from(img.rows()).unwrap_or(0),
    )
    .map_err(|_| PosediffError::UnreadableImage(path.to_owned()))
}
