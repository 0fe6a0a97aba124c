//! The frames of a synthetic capture video with exact cameras: a scene orbited at a frame
//! rate, optionally with a moving distractor (a textured figure walking around the objects)
//! and its masks. Rendering only: the umbrella's `posediff::io::synthetic_video` encodes the
//! frames (this crate stays free of OpenCV).

use nalgebra::{Rotation3, Vector3};
use posediff_geometry::{Camera, ImageSize};
use rayon::prelude::*;
use std::f64::consts::TAU;

use crate::render::Triangle;
use crate::scene::{Material, Object, PathKind, Pattern, Scene, Shape, trajectory_with};
use crate::{Result, SynthError, render_frame};

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
    /// A moving distractor object (and its masks), and how it moves.
    pub distractor: Option<Distractor>,
}

/// How a video's distractor moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Distractor {
    /// A figure walking half a circle around the objects over the video (a few percent of a
    /// frame; its matches across keyframes do not fit the scene's epipolar geometry).
    Walking,
    /// A larger figure that keeps its place in the camera's view, as a companion walking
    /// beside the camera or the photographer's shadow: its matches say the camera stands
    /// still, the failure masks are for.
    Companion,
    /// The companion nearer and in the middle of the view, covering about half of every frame
    /// (a close object in front of the scene, a car's dashboard): its matches outnumber the
    /// scene's, so they, not the scene, decide what a pair's geometry looks like unless masked.
    Cover,
}

impl Distractor {
    /// Its name (`walking`, `companion`, `cover`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Walking => "walking",
            Self::Companion => "companion",
            Self::Cover => "cover",
        }
    }
}

/// The scene of frame `i` of `n`, seen by `camera`: the objects, and the distractor (object
/// index `scene.objects.len()`, the ground after it) at its place at that time.
fn scene_at(
    base: &Scene,
    distractor: Option<(&Object, Distractor)>,
    camera: &Camera,
    i: usize,
    n: usize,
) -> Scene {
    let Some((d, kind)) = distractor else {
        return base.clone();
    };
    let s = i as f64 / n.max(2).saturating_sub(1) as f64;
    let mut scene = base.clone();
    let id = scene.objects.len() as u32;
    let mut obj = d.clone();
    match kind {
        Distractor::Walking => {
            // Half a circle around the objects over the video, bobbing.
            let angle = 0.3 + 0.5 * TAU * s;
            obj.center = base.target
                + Vector3::new(
                    1.05 * base.radius * angle.cos(),
                    1.05 * base.radius * angle.sin(),
                    0.0,
                );
            obj.center.z = d.scale.z * (1.0 + 0.05 * (TAU * 6.0 * s).sin());
            obj.rotation = Rotation3::from_axis_angle(&Vector3::z_axis(), angle);
        }
        Distractor::Companion | Distractor::Cover => {
            // Fixed in the camera's frame: to the right of the view and halfway to the
            // objects (the cover: a third of the way, nearer the middle), turned with the
            // camera, bobbing a little.
            let r_cw = camera.cam_from_world.rotation.transpose();
            let c = camera.center().coords;
            let (near, right) = match kind {
                Distractor::Cover => (0.33, 0.12),
                _ => (0.5, 0.3),
            };
            let depth = near * (base.target - c).norm();
            let bob = 0.02 * depth * (TAU * 6.0 * s).sin();
            obj.center = c + r_cw * Vector3::new(right * depth, 0.1 * depth + bob, depth);
            obj.rotation = Rotation3::from_matrix_unchecked(r_cw)
                * Rotation3::from_axis_angle(&Vector3::x_axis(), -0.5 * std::f64::consts::PI);
        }
    }
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

/// The distractor: a textured upright figure about a third of the scene's radius wide (the
/// companion: half that, as it stands nearer).
fn distractor(scene: &Scene, seed: u64, kind: Distractor) -> Object {
    use rand::SeedableRng;
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0xD157_AC70);
    let r = scene.radius
        * match kind {
            Distractor::Walking => 1.0,
            Distractor::Companion | Distractor::Cover => 1.5,
        };
    Object {
        shape: Shape::Superquadric { e1: 0.6, e2: 0.9 },
        center: scene.target,
        scale: Vector3::new(0.16 * r, 0.16 * r, 0.42 * r),
        rotation: Rotation3::identity(),
        deformation: (0.1, 2.0),
        material: match kind {
            Distractor::Walking => Material::random(&mut rng, 5.0),
            // The companion, near the camera: a black and white checkerboard, as many
            // corners as the scene behind it.
            Distractor::Companion | Distractor::Cover => Material {
                base: [0.05; 3],
                accent: [0.95; 3],
                pattern: Pattern::Checker,
                frequency: 6.0,
                seed: 7,
            },
        },
    }
}

/// One rendered frame of the video.
#[derive(Debug, Clone)]
pub struct VideoFrame {
    /// Its index.
    pub index: usize,
    /// 8-bit RGB, row-major.
    pub rgb: Vec<u8>,
    /// With a distractor: 0 on it (grown by [`MASK_MARGIN`] px), 255 elsewhere, row-major.
    pub mask: Option<Vec<u8>>,
}

/// Pixels the distractor's mask reaches beyond it (users' masks are generous).
pub const MASK_MARGIN: usize = 3;

/// Frames of `n` frames per second × seconds.
pub fn frame_count(spec: &VideoSpec) -> Result<usize> {
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
    Ok(n)
}

/// `mask` (0 = masked) with every masked pixel grown by `r` px (a square window), by a
/// separable minimum filter.
fn grow_masked(mask: &[u8], w: usize, h: usize, r: usize) -> Vec<u8> {
    let mut rows = vec![255u8; w * h];
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
            rows[y * w + x] = mask[y * w + a..=y * w + b]
                .iter()
                .copied()
                .min()
                .unwrap_or(255);
        }
    }
    let mut out = vec![255u8; w * h];
    for y in 0..h {
        let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (a..=b).map(|yy| rows[yy * w + x]).min().unwrap_or(255);
        }
    }
    out
}

/// Renders the video: the cameras of every frame, and each frame handed to `sink` in order
/// (rendered in parallel a chunk at a time).
///
/// # Errors
/// A rate or length out of range; whatever `sink` returns.
pub fn render_video(
    spec: &VideoSpec,
    mut sink: impl FnMut(VideoFrame) -> Result<()>,
) -> Result<Vec<Camera>> {
    let n = frame_count(spec)?;
    let scene = Scene::random(spec.seed);
    let cameras: Vec<Camera> =
        trajectory_with(&scene, n, spec.size, spec.seed, Some(PathKind::Orbit));
    let extra = spec
        .distractor
        .map(|kind| (distractor(&scene, spec.seed, kind), kind));
    let id = scene.objects.len() as u32;
    for chunk in (0..n).collect::<Vec<_>>().chunks(16) {
        let frames: Vec<VideoFrame> = chunk
            .par_iter()
            .map(|&i| {
                let s = scene_at(
                    &scene,
                    extra.as_ref().map(|(o, k)| (o, *k)),
                    &cameras[i],
                    i,
                    n,
                );
                let f = render_frame(&s, &cameras[i]);
                let mask = extra.as_ref().map(|_| {
                    let (w, h) = (f.buffers.width, f.buffers.height);
                    let mut m = vec![255u8; w * h];
                    for y in 0..h {
                        for x in 0..w {
                            if f.buffers.at(x, y).is_some_and(|hit| hit.object == id) {
                                m[y * w + x] = 0;
                            }
                        }
                    }
                    grow_masked(&m, w, h, MASK_MARGIN)
                });
                VideoFrame {
                    index: i,
                    rgb: f.rgb,
                    mask,
                }
            })
            .collect();
        for f in frames {
            sink(f)?;
        }
    }
    Ok(cameras)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_masked_pixel_grows_into_a_square() {
        let (w, h) = (9, 7);
        let mut m = vec![255u8; w * h];
        m[3 * w + 4] = 0;
        let g = grow_masked(&m, w, h, 2);
        for y in 0..h {
            for x in 0..w {
                let inside = (2..=6).contains(&x) && (1..=5).contains(&y);
                assert_eq!(g[y * w + x] == 0, inside, "({x}, {y})");
            }
        }
    }

    #[test]
    fn the_distractor_moves_and_is_masked() {
        let spec = VideoSpec {
            seed: 3,
            size: ImageSize::new(64, 48).unwrap_or_else(|_| unreachable!()),
            fps: 4.0,
            seconds: 1.0,
            distractor: Some(Distractor::Walking),
        };
        let mut masks = Vec::new();
        let cams = render_video(&spec, |f| {
            masks.push(f.mask.unwrap_or_default());
            Ok(())
        })
        .unwrap_or_default();
        assert_eq!(cams.len(), 4);
        assert!(masks.iter().any(|m| m.contains(&0)));
        assert_ne!(masks[0], masks[3]);
    }

    /// The companion stays where it is in the view while the camera moves (its masks overlap
    /// almost wholly from the first frame to the last, the walking figure's do not), and
    /// covers a large part of it.
    #[test]
    fn the_companion_keeps_its_place_in_the_view() {
        let masks = |distractor| {
            let spec = VideoSpec {
                seed: 3,
                size: ImageSize::new(64, 48).unwrap_or_else(|_| unreachable!()),
                fps: 4.0,
                seconds: 2.0,
                distractor: Some(distractor),
            };
            let mut masks = Vec::new();
            render_video(&spec, |f| {
                masks.push(f.mask.unwrap_or_default());
                Ok(())
            })
            .unwrap_or_default();
            masks
        };
        // Intersection over union of the masked pixels of the first and last frames.
        let iou = |m: &[Vec<u8>]| {
            let (a, b) = (&m[0], &m[m.len() - 1]);
            let both = a
                .iter()
                .zip(b)
                .filter(|(x, y)| **x == 0 && **y == 0)
                .count();
            let either = a
                .iter()
                .zip(b)
                .filter(|(x, y)| **x == 0 || **y == 0)
                .count();
            both as f64 / either.max(1) as f64
        };
        let covered = |m: &[Vec<u8>]| {
            m.iter()
                .map(|f| f.iter().filter(|v| **v == 0).count() as f64 / (64.0 * 48.0))
                .fold(f64::INFINITY, f64::min)
        };
        let companion = masks(Distractor::Companion);
        assert!(covered(&companion) > 0.15, "{}", covered(&companion));
        assert!(iou(&companion) > 0.8, "{}", iou(&companion));
        // The cover: half of every frame or more, in place.
        let cover = masks(Distractor::Cover);
        assert!(covered(&cover) > 0.45, "{}", covered(&cover));
        assert!(iou(&cover) > 0.8, "{}", iou(&cover));
        assert!(iou(&masks(Distractor::Walking)) < 0.5);
    }
}
