//! Reverse diffusion started from an initial estimate: the cameras go into the model's frame as
//! in training (224 crops, official normalisation) and come back; a start at step 0 returns
//! the initial cameras up to the one denoising step, whatever world frame they were given in.
#![allow(clippy::unwrap_used)]

use std::path::PathBuf;

use candle_core::{DType, Device};
use nalgebra::{Rotation3, Vector3};
use posediff::estimate::geometric::KnownIntrinsics;
use posediff::io::export::read_cameras_json;
use posediff::{EstimateConfig, EstimateInput, Estimator, Silent};
use posediff_diffusion::PoseDiffusionModel;
use posediff_fixtures::shared_path;
use posediff_geometry::epipolar::relative_pose;
use posediff_geometry::{Camera, Sim3};

fn estimator(intrinsics: KnownIntrinsics) -> Estimator {
    let model = PoseDiffusionModel::load(
        &shared_path("reference/tiny/model_tiny.safetensors"),
        DType::F32,
        &Device::Cpu,
    )
    .unwrap();
    let config = EstimateConfig {
        ggs: false,
        intrinsics,
        ..EstimateConfig::default()
    };
    Estimator::from_model(model, Device::Cpu, config)
}

fn fountain(n: usize) -> (Vec<PathBuf>, Vec<Camera>) {
    let dir = shared_path("data/strecha_fountainP11");
    let gt = read_cameras_json(&dir.join("cameras.json")).unwrap();
    (
        gt.iter().take(n).map(|c| dir.join(&c.image)).collect(),
        gt.iter().take(n).map(|c| c.camera).collect(),
    )
}

fn worst_relative_rotation(a: &[Camera], b: &[Camera]) -> f64 {
    let mut worst = 0.0f64;
    for i in 0..a.len() {
        for j in i + 1..a.len() {
            let ra = relative_pose(&a[i].cam_from_world, &a[j].cam_from_world).rotation;
            let rb = relative_pose(&b[i].cam_from_world, &b[j].cam_from_world).rotation;
            worst = worst.max(posediff_geometry::rotation_angle_between_deg(&rb, &ra));
        }
    }
    worst
}

/// The estimate started from `cameras` noised to `step`.
fn from_init(
    est: &Estimator,
    images: &[PathBuf],
    cameras: &[Camera],
    step: usize,
) -> posediff::Result<posediff::Estimate> {
    est.estimate(
        EstimateInput {
            init: Some((cameras, step)),
            ..EstimateInput::new(images)
        },
        &mut Silent,
    )
}

#[test]
fn step_zero_returns_the_initial_cameras_in_any_world_frame() {
    let (images, gt) = fountain(4);
    let est = estimator(KnownIntrinsics::Unknown);
    let a = from_init(&est, &images, &gt, 0).unwrap();
    let a: Vec<Camera> = a.samples[0].iter().map(|c| c.camera).collect();
    // One denoising step at β₀ = 1e-4 moves the encoding by √β₀·(ε − ε̂) ≈ 0.01·(a few) with
    // random weights: several degrees at most (the exact round trip is tested below).
    let worst = worst_relative_rotation(&a, &gt);
    assert!(worst < 10.0, "worst relative rotation {worst}°");
    for (c, g) in a.iter().zip(&gt) {
        assert!((c.intrinsics.fx() / g.intrinsics.fx() - 1.0).abs() < 0.1);
    }

    // The same cameras in another world frame (rotated, moved, scaled) give the same result.
    let sim = Sim3 {
        rotation: *Rotation3::from_euler_angles(0.3, -1.1, 2.0).matrix(),
        translation: Vector3::new(3.0, -2.0, 7.0),
        scale: 4.5,
    };
    let moved: Vec<Camera> = gt.iter().map(|c| sim.transform_camera(c)).collect();
    let b = from_init(&est, &images, &moved, 0).unwrap();
    let b: Vec<Camera> = b.samples[0].iter().map(|c| c.camera).collect();
    assert!(worst_relative_rotation(&a, &b) < 1e-3);
}

#[test]
fn a_late_start_forgets_the_initial_cameras() {
    let (images, gt) = fountain(3);
    let est = estimator(KnownIntrinsics::Unknown);
    let early = from_init(&est, &images, &gt, 0).unwrap();
    let late = from_init(&est, &images, &gt, 99).unwrap();
    let early: Vec<Camera> = early.samples[0].iter().map(|c| c.camera).collect();
    let late: Vec<Camera> = late.samples[0].iter().map(|c| c.camera).collect();
    // Random weights: from step 99 the result is the random model's, far from the start.
    assert!(worst_relative_rotation(&late, &gt) > 5.0 * worst_relative_rotation(&early, &gt));
    assert!(
        from_init(&est, &images, &gt, 100).is_err(),
        "start step outside the 100-step schedule"
    );
    assert!(
        from_init(&est, &images, &gt[..2], 0).is_err(),
        "one initial camera per image"
    );
}

#[test]
fn known_focal_is_returned_exactly() {
    let (images, gt) = fountain(3);
    let est = estimator(KnownIntrinsics::FocalPx(900.0));
    let e = est
        .estimate(EstimateInput::new(&images), &mut Silent)
        .unwrap();
    for c in &e.samples[0] {
        assert_eq!(c.camera.intrinsics.fx(), 900.0);
        assert_eq!(c.camera.intrinsics.fy(), 900.0);
        assert_eq!(c.camera.intrinsics.cx(), 511.5);
        assert_eq!(c.camera.intrinsics.cy(), 341.0);
    }
    assert_eq!(e.samples[0].len(), gt.len());
}

#[test]
fn model_encodings_round_trip_exactly() {
    let (_, gt) = fountain(4);
    let crops: Vec<_> = gt
        .iter()
        .map(|c| posediff_geometry::CenterCrop::official(c.image_size, 224))
        .collect();
    let in_crops: Vec<Camera> = gt
        .iter()
        .zip(&crops)
        .map(|(c, crop)| crop.camera_to_model(c).unwrap())
        .collect();
    let x = posediff::estimate::estimator::model_encodings(&in_crops, &Device::Cpu).unwrap();
    let values: Vec<f32> = x.flatten_all().unwrap().to_vec1().unwrap();
    let size = posediff_geometry::ImageSize::new(224, 224).unwrap();
    let back: Vec<Camera> = values
        .chunks(9)
        .zip(&crops)
        .zip(&gt)
        .map(|((e, crop), g)| {
            let mut row = [0.0; 9];
            for (r, v) in row.iter_mut().zip(e) {
                *r = f64::from(*v);
            }
            let at_224 = posediff_geometry::PoseEncoding(row)
                .to_camera(size)
                .unwrap();
            crop.camera_from_model(&at_224, g.image_size).unwrap()
        })
        .collect();
    // F32 encodings: ~1e-7 relative.
    assert!(worst_relative_rotation(&back, &gt) < 1e-4);
    for (b, g) in back.iter().zip(&gt) {
        assert!((b.intrinsics.fx() / g.intrinsics.fx() - 1.0).abs() < 1e-5);
    }
    // Camera 0 sits at the canonical origin, looking down +z in PyTorch3D terms.
    assert!(values[..3].iter().all(|v| v.abs() < 1e-5));
}
