//! Parity with `reference/full/normalize_io.safetensors`: the official CO3D loader's crop and
//! resize of NDC intrinsics, the optical-axis intersection and the canonicalisation
//! (`normalize_cameras` with and without `compute_optical`, then `first_camera_transform`), and
//! the pose encoding of the result (the training target).
//!
//! The fixture is float32; values are compared at float32 precision scaled by their magnitude.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Vector2, Vector3};
use posediff_fixtures::{SafetensorsFixture, assert_close, fixture_path, flat};
use posediff_geometry::normalize::optical_axis_intersection;
use posediff_geometry::pytorch3d::CropBox;
use posediff_geometry::{
    Camera, Canonicalized, ImageSize, NdcIntrinsics, PoseEncoding, Pytorch3dCamera, QuaternionSign,
    canonicalize, canonicalize_without_optical_axis,
};

const N: usize = 8;

fn fixture() -> SafetensorsFixture {
    SafetensorsFixture::open(&fixture_path("reference/full/normalize_io.safetensors"))
}

fn vec2s(fx: &SafetensorsFixture, name: &str) -> Vec<Vector2<f64>> {
    fx.tensor(name)
        .chunks(2)
        .iter()
        .map(|c| Vector2::new(c[0], c[1]))
        .collect()
}

/// The crop-adjusted raw cameras, as the loader builds them.
fn cropped_cameras(fx: &SafetensorsFixture) -> Vec<Pytorch3dCamera> {
    let r = fx.tensor("raw_R");
    let t = fx.tensor("raw_T");
    let size = fx.tensor("orig_size_wh").data;
    let bbox = fx.tensor("crop_bbox_xyxy").data;
    let crop = CropBox {
        x0: bbox[0],
        y0: bbox[1],
        width: bbox[2] - bbox[0],
        height: bbox[3] - bbox[1],
    };
    let focal = vec2s(fx, "raw_focal_ndc_orig");
    let pp = vec2s(fx, "raw_pp_ndc_orig");
    (0..N)
        .map(|i| {
            let raw = NdcIntrinsics {
                focal: focal[i],
                principal_point: pp[i],
            };
            Pytorch3dCamera {
                r: Matrix3::from_row_slice(r.chunks(9)[i]),
                t: Vector3::from_row_slice(t.chunks(3)[i]),
                intrinsics: raw
                    .adjusted_to_crop(size[0], size[1], &crop)
                    .adjusted_to_scale((crop.width, crop.height), (224.0, 224.0)),
            }
        })
        .collect()
}

fn opencv(cams: &[Pytorch3dCamera]) -> Vec<Camera> {
    let size = ImageSize::new(224, 224).unwrap();
    cams.iter().map(|c| c.to_opencv(size).unwrap()).collect()
}

#[test]
fn crop_and_resize_of_ndc_intrinsics_match_the_official_loader() {
    let fx = fixture();
    let cams = cropped_cameras(&fx);
    let f = flat(cams.iter().map(|c| c.intrinsics.focal.into()));
    let p = flat(cams.iter().map(|c| c.intrinsics.principal_point.into()));
    assert_close(
        "focal_after_crop_resize",
        &f,
        &fx.tensor("focal_after_crop_resize").data,
        0.0,
        1e-6,
    );
    assert_close(
        "pp_after_crop_resize",
        &p,
        &fx.tensor("pp_after_crop_resize").data,
        1e-6,
        0.0,
    );
}

#[test]
fn optical_axis_intersection_matches_official() {
    let fx = fixture();
    let hit = optical_axis_intersection(&opencv(&cropped_cameras(&fx))).unwrap();
    assert_close(
        "optical_axis_intersection",
        hit.point.coords.as_slice(),
        &fx.tensor("optical_axis_intersection").data,
        2e-6,
        0.0,
    );
    assert_close(
        "dist_to_intersection",
        &hit.distances,
        &fx.tensor("dist_to_intersection").data,
        0.0,
        2e-6,
    );
}

fn check_canonical(
    fx: &SafetensorsFixture,
    canon: &Canonicalized,
    prefix: &str,
    original: &[Camera],
) {
    let back: Vec<Pytorch3dCamera> = canon
        .cameras
        .iter()
        .map(Pytorch3dCamera::from_opencv)
        .collect();
    // Row-major: nalgebra stores columns, so the transpose's storage is R's rows.
    let r: Vec<f64> = back
        .iter()
        .flat_map(|c| c.r.transpose().as_slice().to_vec())
        .collect();
    assert_close(
        &format!("{prefix}_R"),
        &r,
        &fx.tensor(&format!("{prefix}_R")).data,
        2e-6,
        0.0,
    );
    let t = flat(back.iter().map(|c| c.t.into()));
    assert_close(
        &format!("{prefix}_T"),
        &t,
        &fx.tensor(&format!("{prefix}_T")).data,
        2e-6,
        0.0,
    );
    // Camera 0 is the PyTorch3D identity (up to the float32 rounding of the raw rotations,
    // which are orthonormal to ~1e-7 only).
    assert!((back[0].r - Matrix3::identity()).norm() < 1e-6);
    assert!(back[0].t.norm() < 1e-6);
    assert!(
        (canon.cameras[0].cam_from_world.rotation - posediff_geometry::pytorch3d::axis_flip())
            .norm()
            < 1e-6
    );
    // And the canonicalisation is undone.
    for (a, b) in canon.restore(&canon.cameras).iter().zip(original) {
        assert!((a.cam_from_world.rotation - b.cam_from_world.rotation).norm() < 1e-6);
        assert!((a.cam_from_world.translation - b.cam_from_world.translation).norm() < 1e-5);
    }
}

#[test]
fn canonicalisation_matches_official_normalize_cameras() {
    let fx = fixture();
    let cams = opencv(&cropped_cameras(&fx));
    let canon = canonicalize(&cams).unwrap();
    check_canonical(&fx, &canon, "norm", &cams);
    // Unit distance of camera 0 to the intersection in the canonical frame.
    let hit = optical_axis_intersection(&canon.cameras).unwrap();
    assert!((hit.distances[0] - 1.0).abs() < 1e-6);

    let back: Vec<Pytorch3dCamera> = canon
        .cameras
        .iter()
        .map(Pytorch3dCamera::from_opencv)
        .collect();
    let f = flat(back.iter().map(|c| c.intrinsics.focal.into()));
    assert_close("norm_focal", &f, &fx.tensor("norm_focal").data, 0.0, 1e-6);
    let p = flat(back.iter().map(|c| c.intrinsics.principal_point.into()));
    assert_close("norm_pp", &p, &fx.tensor("norm_pp").data, 1e-6, 0.0);
    let enc = flat(back.iter().map(|c| {
        PoseEncoding::encode(c, QuaternionSign::LargestComponentPositive)
            .unwrap()
            .0
    }));
    assert_close(
        "norm_pose_encoding",
        &enc,
        &fx.tensor("norm_pose_encoding").data,
        2e-6,
        0.0,
    );
}

#[test]
fn canonicalisation_without_optical_axis_matches_official() {
    let fx = fixture();
    let cams = opencv(&cropped_cameras(&fx));
    let canon = canonicalize_without_optical_axis(&cams).unwrap();
    check_canonical(&fx, &canon, "norm_noopt", &cams);
}
