//! Cameras split by the bundle adjustment, after the mapper, where the cameras are decided from
//! the data (no EXIF, no folders, no user: `cameras.mode = auto`).
//!
//! The view-graph calibration ([`crate::view_graph_calibration`]) sees pairs only. On
//! object-centric rings every optical axis passes near one point, the degenerate case of focal
//! self-calibration, and its per-image focals can be off by a factor of three and mixed up: on
//! the temple's zoomed copy it put three zoomed photos in the unzoomed photos' camera. A track
//! seen by many cameras fixes each camera's focal far better. So, after the mapper, one bundle
//! adjustment with a focal per image (COLMAP's default of a camera per image,
//! [`crate::bundle::adjust_lens`] with one group per image) measures each estimated image's
//! focal on the map's points, and [`group_by_focal`] turns those focals into cameras: the
//! largest set that agrees within `tolerance` is one camera, every other image a camera of its
//! own. When that differs from the mapper's cameras, the caller maps again with them (the
//! mapper's [`crate::mapper::MapperOptions::camera_split`]). After a keyframe bundle adjustment
//! (more than `keyframes.max_keyframes` images) the adjustment holds the keyframes, and each
//! other image's focal comes from its own pose-and-focal refinement on its `alone`
//! observations against the adjusted points.

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::bundle::keyframes::refine_pose;
use crate::bundle::{BundleOptions, LensAdjustment, LensKind, PINHOLE, Point, adjust_lens};
use crate::camera::CameraPose;
use crate::error::Result;
use crate::intrinsics::ImageIntrinsics;
use crate::view_graph_calibration::group_by_focal;

/// Settings of the split; chosen on the zoomed copies of the shared sets and the synthetic
/// zoomed orbit (`posediff bench-cameras --synthetic`, docs/BENCHMARKS.md, "Real cameras: cameras
/// split by the bundle adjustment").
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct CameraSplitOptions {
    /// Images whose adjusted focals lie within this relative span are one camera. The copies'
    /// zoom factors start at 1.3; the per-image adjustment spread the temple's eight unzoomed
    /// photos over 12 % (1511–1696 px for 1520) in the first round, and the four originals'
    /// photos over 1.0–6.3 % (one camera each, as they are).
    pub tolerance: f64,
    /// An image needs at least this many observations among the adjusted points for its focal
    /// to count (otherwise it joins the largest camera).
    pub min_observations: usize,
    /// Points adjusted at most, evenly spaced over the mapper's.
    pub max_points: usize,
    /// Maps made again at most with split cameras (each is kept only when it explains the
    /// matches better than the one before).
    pub rounds: usize,
}

impl Default for CameraSplitOptions {
    fn default() -> Self {
        Self {
            tolerance: 0.15,
            min_observations: 30,
            max_points: 20_000,
            rounds: 2,
        }
    }
}

/// What [`split_cameras`] found.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CameraSplit {
    /// Per image, its focal from the adjustment with a focal per image (pixels); `None` where
    /// the image is not estimated or has fewer than `min_observations` observations.
    pub image_focal: Vec<Option<f64>>,
    /// Per image, its camera (group 0: the largest agreeing set with every undetermined image).
    pub group: Vec<usize>,
    /// Per image, its focal scale with its camera's ratio folded in (`f_i = φ · scale_i`, `φ`
    /// the first camera's factor).
    pub scale: Vec<f64>,
    /// The first camera's focal factor on the `base` scales.
    pub phi: f64,
    /// The adjustment.
    pub adjustment: LensAdjustment,
}

impl CameraSplit {
    /// Whether its cameras group the images as `group` does (labels aside).
    pub fn same_cameras(&self, group: &[usize]) -> bool {
        canonical(&self.group) == canonical(group)
    }
}

/// Groups relabelled in order of first appearance.
fn canonical(group: &[usize]) -> Vec<usize> {
    let mut label = std::collections::HashMap::new();
    group
        .iter()
        .map(|g| {
            let next = label.len();
            *label.entry(*g).or_insert(next)
        })
        .collect()
}

/// Each image's focal from a bundle adjustment of at most `max_points` of `points` with a focal
/// per image, starting from the mapper's (`intrinsics.focal(phi, i)`), and the cameras that
/// follow; `base[i]` is image `i`'s focal scale before any camera ratio (the longer side). The
/// cameras and points given are not changed.
///
/// # Errors
/// As [`adjust_lens`]: inputs of the wrong length, a reduced system that is not positive
/// definite at any damping.
pub fn split_cameras(
    points: &[Point],
    (intrinsics, phi, base): (&ImageIntrinsics, f64, &[f64]),
    cameras: &[Option<CameraPose>],
    bundle: &BundleOptions,
    options: &CameraSplitOptions,
) -> Result<CameraSplit> {
    let n = intrinsics.len();
    let Some(reference) = cameras.iter().position(Option::is_some) else {
        return Ok(CameraSplit {
            image_focal: vec![None; n],
            group: vec![0; n],
            scale: base.to_vec(),
            phi,
            adjustment: LensAdjustment::default(),
        });
    };
    let mut each = intrinsics.clone();
    each.group = (0..n).collect();
    let step = points.len().div_ceil(options.max_points.max(1)).max(1);
    let subset: Vec<Point> = points.iter().step_by(step).cloned().collect();
    let mut factors = vec![phi; n];
    let mut ks = vec![PINHOLE; n];
    let mut adjusted = cameras.to_vec();
    let bundle = BundleOptions {
        refine_focal: true,
        ..*bundle
    };
    let (kept, adjustment) = adjust_lens(
        subset,
        &each,
        &mut adjusted,
        (&mut factors, &mut ks, &vec![0; n]),
        LensKind::Brown,
        reference,
        &bundle,
    )?;
    let mut seen = vec![0usize; n];
    for p in &kept {
        for o in &p.observations {
            if let Some(s) = seen.get_mut(o.image) {
                *s += 1;
            }
        }
    }
    // The cameras refined alone after a keyframe adjustment (their observations are the
    // points' `alone` ones): each one's pose and focal alone against the adjusted points.
    let mut alone: Vec<Vec<(Vector3<f64>, [f64; 2])>> = vec![Vec::new(); n];
    for p in &kept {
        for o in &p.alone {
            if let Some(list) = alone.get_mut(o.image) {
                list.push((p.xyz, o.xy));
            }
        }
    }
    let alone_options = bundle.keyframes.unwrap_or_default();
    let alone_focal: Vec<Option<(f64, usize)>> = alone
        .par_iter()
        .enumerate()
        .map(|(i, list)| {
            let Some(start) = adjusted[i].filter(|_| !list.is_empty()) else {
                return Ok(None);
            };
            let f = factors[i] * each.scale[i];
            let refined = refine_pose(
                (start, Some(f)),
                list,
                (f, each.principal[i]),
                &bundle,
                &alone_options,
            )?;
            Ok(refined.map(|r| (r.focal, r.inliers.len())))
        })
        .collect::<Result<_>>()?;
    for (i, a) in alone_focal.iter().enumerate() {
        if let Some((f, count)) = a {
            factors[i] = f / each.scale[i];
            seen[i] = *count;
        }
    }
    let image_focal: Vec<Option<f64>> = (0..n)
        .map(|i| {
            let f = factors[i] * each.scale[i];
            (adjusted[i].is_some()
                && seen[i] >= options.min_observations
                && f.is_finite()
                && f > 0.0)
                .then_some(f)
        })
        .collect();
    let ratio: Vec<f64> = (0..n)
        .map(|i| image_focal[i].map_or(1.0, |f| f / base[i]))
        .collect();
    let determined: Vec<bool> = image_focal.iter().map(Option::is_some).collect();
    let (group, ratios, first) = group_by_focal(&ratio, &determined, options.tolerance);
    let scale = (0..n).map(|i| base[i] * ratios[group[i]]).collect();
    Ok(CameraSplit {
        image_focal,
        group,
        scale,
        phi: first,
        adjustment,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::tracks::Observation;

    /// Ten cameras on a ring around a cloud of points, image `i` with focal `focal(i)` (640×480
    /// photos): the exact points and cameras, and intrinsics that give every image the first
    /// image's focal (one camera, as a mapper that could not tell the zoom would have it).
    fn ring(
        focal: &dyn Fn(usize) -> f64,
    ) -> (Vec<Option<CameraPose>>, ImageIntrinsics, Vec<Point>) {
        let ring = crate::test_scenes::Ring {
            cameras: 10,
            step: 0.3,
            lift: 0.5,
            points: 400,
            extent: [1.2, 1.0, 1.2],
            seed: 99,
        };
        let (cameras, points) = ring.scene(focal, [319.5, 239.5], (LensKind::Brown, PINHOLE));
        let intrinsics = ImageIntrinsics::new(vec![[319.5, 239.5]; 10], vec![640.0; 10]);
        (cameras, intrinsics, points)
    }

    /// [`split_cameras`] of a [`ring`] mapped at the first image's focal (600 of 640), with
    /// the default options.
    fn split(
        points: &[Point],
        intrinsics: &ImageIntrinsics,
        cameras: &[Option<CameraPose>],
    ) -> CameraSplit {
        split_cameras(
            points,
            (intrinsics, 600.0 / 640.0, &[640.0; 10]),
            cameras,
            &options(),
            &CameraSplitOptions::default(),
        )
        .unwrap()
    }

    fn options() -> BundleOptions {
        BundleOptions {
            max_error_px: 1e3,
            tolerance: 1e-12,
            ..BundleOptions::default()
        }
    }

    /// Images 3 and 7 zoomed 1.5× and 1.35× but mapped with the others' focal: the adjustment
    /// with a focal per image finds every focal, and the zoomed images get cameras of their
    /// own (group 0 the eight unzoomed), with the zoom folded into their scales.
    #[test]
    fn zoomed_images_are_split_into_cameras_of_their_own() {
        let zoom = |i: usize| match i {
            3 => 1.5,
            7 => 1.35,
            _ => 1.0,
        };
        let (cameras, intrinsics, points) = ring(&|i| 600.0 * zoom(i));
        let base = vec![640.0; 10];
        let split = split_cameras(
            &points,
            (&intrinsics, 600.0 / 640.0, &base),
            &cameras,
            &options(),
            &CameraSplitOptions::default(),
        )
        .unwrap();
        assert!(split.adjustment.rms_before_px > 5.0, "{split:?}");
        assert!(split.adjustment.rms_after_px < 1e-3, "{split:?}");
        for (i, f) in split.image_focal.iter().enumerate() {
            let f = f.unwrap();
            assert!((f / (600.0 * zoom(i)) - 1.0).abs() < 1e-3, "image {i}: {f}");
        }
        assert_eq!(split.group, [0, 0, 0, 1, 0, 0, 0, 2, 0, 0]);
        assert!(!split.same_cameras(&[0; 10]));
        assert!(split.same_cameras(&[5, 5, 5, 2, 5, 5, 5, 0, 5, 5]));
        for i in 0..10 {
            let f = split.phi * split.scale[i];
            assert!((f / (600.0 * zoom(i)) - 1.0).abs() < 1e-3, "image {i}: {f}");
        }
    }

    /// After a keyframe adjustment, images refined alone (their observations are the points'
    /// `alone` ones) get their focal alone: the zoomed image 3, not a keyframe, is a camera of
    /// its own.
    #[test]
    fn an_image_refined_alone_is_split_by_its_own_focal() {
        let zoom = |i: usize| if i == 3 { 1.5 } else { 1.0 };
        let (cameras, intrinsics, mut points) = ring(&|i| 600.0 * zoom(i));
        let alone = [2, 3, 5];
        for p in &mut points {
            let (joint, other): (Vec<Observation>, Vec<Observation>) = p
                .observations
                .iter()
                .partition(|o| !alone.contains(&o.image));
            p.observations = joint;
            p.alone = other;
        }
        let split = split(&points, &intrinsics, &cameras);
        for (i, f) in split.image_focal.iter().enumerate() {
            let f = f.unwrap();
            assert!((f / (600.0 * zoom(i)) - 1.0).abs() < 1e-3, "image {i}: {f}");
        }
        assert_eq!(split.group, [0, 0, 0, 1, 0, 0, 0, 0, 0, 0]);
    }

    /// One focal for all: one camera (the mapper's own, so nothing is mapped again); an image
    /// that is not estimated has no focal and stays in it.
    #[test]
    fn one_lens_stays_one_camera() {
        let (mut cameras, intrinsics, points) = ring(&|_| 600.0);
        cameras[4] = None;
        let split = split(&points, &intrinsics, &cameras);
        assert!(split.image_focal[4].is_none());
        assert_eq!(split.image_focal.iter().flatten().count(), 9);
        assert!(split.same_cameras(&[0; 10]), "{split:?}");
        // Too few observations: no focal counts, one camera.
        let strict = CameraSplitOptions {
            min_observations: 10_000,
            ..CameraSplitOptions::default()
        };
        let split = split_cameras(
            &points,
            (&intrinsics, 600.0 / 640.0, &[640.0; 10]),
            &cameras,
            &options(),
            &strict,
        )
        .unwrap();
        assert!(split.image_focal.iter().all(Option::is_none));
        assert_eq!(split.group, [0; 10]);
    }
}
