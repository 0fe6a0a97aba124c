//! A synthetic capture video with exact cameras: a scene orbited at a frame rate, encoded by
//! OpenCV's video writer (H.264 in MP4 through FFmpeg where the system's FFmpeg has an H.264
//! encoder, else Motion JPEG in AVI, which OpenCV writes itself), optionally with a moving
//! distractor (a textured figure walking around the objects) and its masks.
//!
//! Written: `capture.mp4` or `capture.avi`, `cameras.json` (every frame, named
//! `frame_<index:06>`), `masks/<index:06>.png` (zero on the distractor, dilated 3 px) when
//! there is one, `video.json` (codec, fps, frames, size, seed).

use std::f64::consts::TAU;
use std::path::{Path, PathBuf};

use nalgebra::{Rotation3, Vector3};
use opencv::core::{Mat, Size};
use opencv::prelude::*;
use opencv::videoio::VideoWriter;
use posediff_geometry::camera_json::CameraRecord;
use posediff_geometry::{Camera, ImageSize};
use rayon::prelude::*;
use serde::Serialize;

use crate::render::Triangle;
use crate::scene::{Material, Object, PathKind, Scene, Shape, trajectory_with};
use crate::{Result, SynthError, render_frame, write_file};

/// What to render.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoSpec {
    /// Scene and path seed.
    pub seed: u64,
    /// Frame size.
    pub size: ImageSize,
    /// Frames per second.
    pub fps: f64,
    /// Length, seconds.
    pub seconds: f64,
    /// A moving distractor object (and its masks).
    pub distractor: bool,
    /// Motion JPEG even where H.264 is available.
    pub mjpeg: bool,
}

/// What was written.
#[derive(Debug, Clone, Serialize)]
pub struct VideoSummary {
    /// The video file.
    pub video: PathBuf,
    /// `H264` or `MJPG`.
    pub codec: String,
    /// Frames.
    pub frames: usize,
    /// Frames per second.
    pub fps: f64,
    /// The masks folder, with a distractor.
    pub masks: Option<PathBuf>,
}

/// The scene of frame `i` of `n`: the objects, and the distractor (object index
/// `scene.objects.len()`, the ground after it) at its place at that time.
fn scene_at(base: &Scene, distractor: Option<&Object>, i: usize, n: usize) -> Scene {
    let Some(d) = distractor else {
        return base.clone();
    };
    let s = i as f64 / n.max(2).saturating_sub(1) as f64;
    let mut scene = base.clone();
    let id = scene.objects.len() as u32;
    // Half a circle around the objects over the video, bobbing.
    let angle = 0.3 + 0.5 * TAU * s;
    let mut obj = d.clone();
    obj.center = base.target
        + Vector3::new(
            1.05 * base.radius * angle.cos(),
            1.05 * base.radius * angle.sin(),
            0.0,
        );
    obj.center.z = d.scale.z * (1.0 + 0.05 * (TAU * 6.0 * s).sin());
    obj.rotation = Rotation3::from_axis_angle(&Vector3::z_axis(), angle);
    for t in &mut scene.triangles {
        if t.object == id {
            t.object = id + 1;
        }
    }
    let tris: Vec<Triangle> = obj.triangles(id);
    scene.triangles.extend(tris);
    scene.objects.push(obj);
    scene
}

/// The distractor: a textured upright figure about a third of the scene's radius wide.
fn distractor(scene: &Scene, seed: u64) -> Object {
    use rand::SeedableRng;
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0xD157_AC70);
    let r = scene.radius;
    Object {
        shape: Shape::Superquadric { e1: 0.6, e2: 0.9 },
        center: scene.target,
        scale: Vector3::new(0.16 * r, 0.16 * r, 0.42 * r),
        rotation: Rotation3::identity(),
        deformation: (0.1, 2.0),
        material: Material::random(&mut rng, 5.0),
    }
}

fn bgr(rgb: &[u8], size: ImageSize) -> Result<Mat> {
    let cv = |e: opencv::Error| SynthError::Invalid(format!("OpenCV: {e}"));
    let flat = Mat::from_slice(rgb).map_err(cv)?;
    let img = flat
        .reshape(3, size.height() as i32)
        .map_err(cv)?
        .try_clone()
        .map_err(cv)?;
    let mut out = Mat::default();
    opencv::imgproc::cvt_color_def(&img, &mut out, opencv::imgproc::COLOR_RGB2BGR).map_err(cv)?;
    Ok(out)
}

/// Opens the writer: H.264 in MP4 where FFmpeg can encode it (unless `mjpeg`), else Motion
/// JPEG in AVI.
fn writer(out: &Path, spec: &VideoSpec) -> Result<(VideoWriter, PathBuf, String)> {
    let cv = |e: opencv::Error| SynthError::Invalid(format!("OpenCV: {e}"));
    let size = Size::new(spec.size.width() as i32, spec.size.height() as i32);
    let mut tries = Vec::new();
    if !spec.mjpeg {
        tries.push(("capture.mp4", ['a', 'v', 'c', '1'], "H264"));
    }
    tries.push(("capture.avi", ['M', 'J', 'P', 'G'], "MJPG"));
    for (name, c, codec) in tries {
        let path = out.join(name);
        let fourcc = VideoWriter::fourcc(c[0], c[1], c[2], c[3]).map_err(cv)?;
        let w = VideoWriter::new(&path, fourcc, spec.fps, size, true);
        if let Ok(w) = w
            && w.is_opened().unwrap_or(false)
        {
            return Ok((w, path, codec.to_owned()));
        }
        let _ = std::fs::remove_file(&path);
    }
    Err(SynthError::Invalid(
        "OpenCV's video writer opens neither H.264 (MP4) nor Motion JPEG (AVI)".into(),
    ))
}

/// Renders and encodes the video into `out` (created).
///
/// # Errors
/// A size or rate out of range; the writer cannot be opened; a write fails.
pub fn write_video(out: &Path, spec: &VideoSpec) -> Result<VideoSummary> {
    if !(spec.fps > 0.0 && spec.seconds > 0.0) {
        return Err(SynthError::Invalid(
            "fps and seconds must be positive".into(),
        ));
    }
    let n = (spec.fps * spec.seconds).round() as usize;
    if n < 2 {
        return Err(SynthError::Invalid(
            "the video needs at least 2 frames".into(),
        ));
    }
    std::fs::create_dir_all(out).map_err(|source| SynthError::Write {
        path: out.to_owned(),
        source,
    })?;
    let scene = Scene::random(spec.seed);
    let cameras: Vec<Camera> =
        trajectory_with(&scene, n, spec.size, spec.seed, Some(PathKind::Orbit));
    let extra = spec.distractor.then(|| distractor(&scene, spec.seed));
    let masks = spec.distractor.then(|| out.join("masks"));
    if let Some(m) = &masks {
        std::fs::create_dir_all(m).map_err(|source| SynthError::Write {
            path: m.clone(),
            source,
        })?;
    }
    let (mut w, video, codec) = writer(out, spec)?;
    let cv = |e: opencv::Error| SynthError::Invalid(format!("OpenCV: {e}"));
    let id = scene.objects.len() as u32;
    // Rendered in parallel a chunk at a time, encoded in order.
    for chunk in (0..n).collect::<Vec<_>>().chunks(16) {
        let frames: Vec<(Mat, Option<Mat>)> = chunk
            .par_iter()
            .map(|&i| {
                let s = scene_at(&scene, extra.as_ref(), i, n);
                let f = render_frame(&s, &cameras[i]);
                let img = bgr(&f.rgb, spec.size)?;
                let mask = match extra {
                    None => None,
                    Some(_) => {
                        let (w, h) = (f.buffers.width, f.buffers.height);
                        let mut m = vec![255u8; w * h];
                        for y in 0..h {
                            for x in 0..w {
                                if f.buffers.at(x, y).is_some_and(|hit| hit.object == id) {
                                    m[y * w + x] = 0;
                                }
                            }
                        }
                        let flat = Mat::from_slice(&m).map_err(cv)?;
                        let m = flat
                            .reshape(1, h as i32)
                            .map_err(cv)?
                            .try_clone()
                            .map_err(cv)?;
                        let mut eroded = Mat::default();
                        let kernel = opencv::imgproc::get_structuring_element_def(
                            opencv::imgproc::MORPH_RECT,
                            Size::new(7, 7),
                        )
                        .map_err(cv)?;
                        opencv::imgproc::erode_def(&m, &mut eroded, &kernel).map_err(cv)?;
                        Some(eroded)
                    }
                };
                Ok((img, mask))
            })
            .collect::<Result<_>>()?;
        for (&i, (img, mask)) in chunk.iter().zip(frames) {
            w.write(&img).map_err(cv)?;
            if let (Some(dir), Some(m)) = (&masks, mask) {
                let path = dir.join(format!("{i:06}.png"));
                let ok = opencv::imgcodecs::imwrite_def(&path, &m).map_err(cv)?;
                if !ok {
                    return Err(SynthError::Invalid(format!(
                        "cannot write {}",
                        path.display()
                    )));
                }
            }
        }
    }
    w.release().map_err(cv)?;
    let records: Vec<CameraRecord> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| CameraRecord::from_camera(format!("frame_{i:06}"), c))
        .collect();
    write_file(
        &out.join("cameras.json"),
        serde_json::to_string_pretty(&records)?.as_bytes(),
    )?;
    let summary = VideoSummary {
        video,
        codec,
        frames: n,
        fps: spec.fps,
        masks,
    };
    let meta = serde_json::json!({
        "generator": "posediff-synth",
        "seed": spec.seed,
        "codec": summary.codec,
        "frames": n,
        "fps": spec.fps,
        "width": spec.size.width(),
        "height": spec.size.height(),
        "distractor": spec.distractor,
        "cameras": "cameras.json: frame_<index> for every frame, OpenCV x_cam = R x_world + t",
    });
    write_file(
        &out.join("video.json"),
        serde_json::to_string_pretty(&meta)?.as_bytes(),
    )?;
    Ok(summary)
}
