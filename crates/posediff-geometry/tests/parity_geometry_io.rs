//! Parity with `reference/full/geometry_io.safetensors`, produced by the official PoseDiffusion
//! code (pytorch3d 0.7.4) in float32: pose decode and encode, world-to-view matrices, camera
//! centres, OpenCV conversion at two image sizes, fundamental matrices (plain and mean-focal, as
//! GGS uses them) and Sampson errors.
//!
//! Tolerances: the fixture is float32, we compute in float64, so agreement is bounded by float32
//! rounding of the reference: ~1e-6 relative for single operations (README "~1e-6 relative"),
//! scaled by the magnitude of what is compared.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Point2, Vector2};
use posediff_fixtures::{SafetensorsFixture, Tensor, assert_close, fixture_path, flat, mean};
use posediff_geometry::{
    Camera, ImageSize, PoseEncoding, Pytorch3dCamera, QuaternionSign, fundamental_from_cameras,
    fundamental_official, sampson_error,
};

const N_CAMERAS: usize = 6;

fn fixture() -> SafetensorsFixture {
    SafetensorsFixture::open(&fixture_path("reference/full/geometry_io.safetensors"))
}

fn encodings(fx: &SafetensorsFixture) -> Vec<PoseEncoding> {
    let t = fx.tensor("pose_encoding");
    assert_eq!(t.shape, [1, N_CAMERAS, 9]);
    t.chunks(9)
        .iter()
        .map(|c| PoseEncoding(<[f64; 9]>::try_from(*c).unwrap()))
        .collect()
}

fn decoded(fx: &SafetensorsFixture) -> Vec<Pytorch3dCamera> {
    encodings(fx).iter().map(|e| e.decode().unwrap()).collect()
}

fn flat_matrices<const R: usize, const C: usize>(
    ms: impl IntoIterator<Item = nalgebra::SMatrix<f64, R, C>>,
) -> Vec<f64> {
    // Row-major, as the fixture stores them.
    ms.into_iter()
        .flat_map(|m| (0..R).flat_map(move |i| (0..C).map(move |j| m[(i, j)])))
        .collect()
}

/// The absolute tolerance for comparing against float32 values of magnitude up to `scale`.
fn f32_atol(scale: f64) -> f64 {
    2e-6 * scale.max(1.0)
}

fn max_abs(t: &Tensor) -> f64 {
    t.data.iter().fold(0.0, |m, v| m.max(v.abs()))
}

#[test]
fn decode_matches_official_pose_encoding_to_camera() {
    let fx = fixture();
    let cams = decoded(&fx);
    assert_close(
        "R",
        &flat_matrices(cams.iter().map(|c| c.r)),
        &fx.tensor("R").data,
        1e-6,
        0.0,
    );
    let t = flat(cams.iter().map(|c| c.t.into()));
    assert_close("T", &t, &fx.tensor("T").data, 0.0, 0.0);
    let f = flat(cams.iter().map(|c| c.intrinsics.focal.into()));
    let expected = fx.tensor("focal_length");
    assert_close("focal_length", &f, &expected.data, 0.0, 1e-6);
    // Cameras 4 and 5 are clamped to the focal range.
    assert_eq!(
        expected.data[8..12],
        [20.0, 20.0, 0.1f32 as f64, 0.1f32 as f64]
    );

    let w2v = fx.tensor("world_to_view_4x4");
    let scale = max_abs(&w2v);
    assert_close(
        "world_to_view_4x4",
        &flat_matrices(cams.iter().map(Pytorch3dCamera::world_to_view_matrix)),
        &w2v.data,
        f32_atol(scale),
        0.0,
    );
    let centers = fx.tensor("camera_centers");
    let c = flat(cams.iter().map(|c| c.camera_center().into()));
    assert_close(
        "camera_centers",
        &c,
        &centers.data,
        f32_atol(max_abs(&centers)),
        0.0,
    );
}

#[test]
fn encode_matches_official_camera_to_pose_encoding_both_sign_conventions() {
    let fx = fixture();
    let cams = decoded(&fx);
    let v074 = flat(cams.iter().map(|c| {
        PoseEncoding::encode(c, QuaternionSign::LargestComponentPositive)
            .unwrap()
            .0
    }));
    assert_close(
        "roundtrip_encoding_pt3d_v074",
        &v074,
        &fx.tensor("roundtrip_encoding_pt3d_v074").data,
        2e-6,
        0.0,
    );
    let std = flat(cams.iter().map(|c| {
        PoseEncoding::encode(c, QuaternionSign::NonNegativeReal)
            .unwrap()
            .quaternion()
            .to_wxyz()
    }));
    assert_close(
        "roundtrip_quat_standardized",
        &std,
        &fx.tensor("roundtrip_quat_standardized").data,
        2e-6,
        0.0,
    );
    // The fixture does exercise both conventions: at least one quaternion differs in sign.
    let a = fx.tensor("roundtrip_encoding_pt3d_v074");
    let b = fx.tensor("roundtrip_quat_standardized");
    assert!(
        a.chunks(9)
            .iter()
            .zip(b.chunks(4))
            .any(|(e, q)| (e[3] - q[0]).abs() > 0.1)
    );
}

fn check_opencv(fx: &SafetensorsFixture, size: ImageSize, suffix: &str) {
    let cams: Vec<Camera> = decoded(fx)
        .iter()
        .map(|c| c.to_opencv(size).unwrap())
        .collect();
    let r = flat_matrices(cams.iter().map(|c| c.cam_from_world.rotation));
    assert_close(
        &format!("opencv_R_{suffix}"),
        &r,
        &fx.tensor(&format!("opencv_R_{suffix}")).data,
        1e-6,
        0.0,
    );
    let t = flat(cams.iter().map(|c| c.cam_from_world.translation.into()));
    assert_close(
        &format!("opencv_t_{suffix}"),
        &t,
        &fx.tensor(&format!("opencv_t_{suffix}")).data,
        0.0,
        0.0,
    );
    let k = fx.tensor(&format!("opencv_K_{suffix}"));
    assert_close(
        &format!("opencv_K_{suffix}"),
        &flat_matrices(cams.iter().map(|c| c.intrinsics.matrix())),
        &k.data,
        0.0,
        1e-6,
    );
    // And back: PyTorch3D cameras from the OpenCV ones.
    for (cv, p3d) in cams.iter().zip(decoded(fx)) {
        let back = Pytorch3dCamera::from_opencv(cv);
        assert!((back.r - p3d.r).norm() < 1e-12);
        assert!((back.t - p3d.t).norm() < 1e-12);
        assert!((back.intrinsics.focal - p3d.intrinsics.focal).norm() < 1e-12);
        assert!(back.intrinsics.principal_point.norm() < 1e-12);
    }
}

#[test]
fn opencv_conversion_matches_official_at_224() {
    check_opencv(&fixture(), ImageSize::new(224, 224).unwrap(), "224");
}

#[test]
fn opencv_conversion_matches_official_at_h180_w320() {
    check_opencv(&fixture(), ImageSize::new(320, 180).unwrap(), "h180w320");
}

fn cameras_224(fx: &SafetensorsFixture, mean_focal: bool) -> Vec<Camera> {
    let mut cams = decoded(fx);
    if mean_focal {
        let mean = cams
            .iter()
            .map(|c| c.intrinsics.focal)
            .sum::<Vector2<f64>>()
            / cams.len() as f64;
        for c in &mut cams {
            c.intrinsics.focal = mean;
        }
    }
    let size = ImageSize::new(224, 224).unwrap();
    cams.iter().map(|c| c.to_opencv(size).unwrap()).collect()
}

/// Bound on float32 rounding of each entry of `F = K₂⁻ᵀ E K₁⁻¹` in the reference: the entries
/// are sums of products whose magnitudes `|K₂⁻ᵀ| |E| |K₁⁻¹|` can exceed the result by orders of
/// magnitude, and the reference was computed in float32 from float32 R, T and focal lengths.
fn fundamental_rounding_scale(cam1: &Camera, cam2: &Camera) -> Matrix3<f64> {
    let rel = posediff_geometry::relative_pose(&cam1.cam_from_world, &cam2.cam_from_world);
    let t = rel.rotation.transpose() * rel.translation;
    let abs = |m: Matrix3<f64>| m.map(f64::abs);
    abs(cam2.intrinsics.inverse_matrix().transpose())
        * abs(rel.rotation)
        * abs(posediff_geometry::epipolar::skew(&t))
        * abs(cam1.intrinsics.inverse_matrix())
        * F32_ROUNDING
}

/// Relative float32 rounding allowed on the terms of the reference's F: the README's ~1e-6 per
/// operation, compounded over the decode → R₁₂, t₁₂ → E → K⁻ᵀ E K⁻¹ chain of float32 products.
const F32_ROUNDING: f64 = 4e-6;

fn check_fundamentals(fx: &SafetensorsFixture, name: &str, mean_focal: bool) {
    let cams = cameras_224(fx, mean_focal);
    let expected = fx.tensor(name);
    let i1 = fx.tensor("pair_i1").data;
    let i2 = fx.tensor("pair_i2").data;
    let overall = max_abs(&expected);
    let mut worst_ratio = 0.0f64;
    for (p, f_exp) in expected.chunks(9).iter().enumerate() {
        let (a, b) = (i1[p] as usize, i2[p] as usize);
        assert_eq!(p, a * N_CAMERAS + b, "pair order is the 'ij' meshgrid");
        let f = fundamental_official(&cams[a], &cams[b]);
        if a == b {
            // Zero up to the float32 rounding of R Rᵀ in the reference.
            assert!(f.norm() < 1e-12 * overall, "self pair {p}: {f}");
            assert!(
                f_exp.iter().all(|v| v.abs() < 1e-9 * overall),
                "self pair {p} of the fixture is not ~0"
            );
            continue;
        }
        let bound = fundamental_rounding_scale(&cams[a], &cams[b]);
        for k in 0..9 {
            let (r, c) = (k / 3, k % 3);
            let err = (f[(r, c)] - f_exp[k]).abs();
            assert!(
                err <= bound[(r, c)],
                "{name}[{p}][{r},{c}]: got {}, expected {} (|diff| {err:e} > {:e})",
                f[(r, c)],
                f_exp[k],
                bound[(r, c)]
            );
            worst_ratio = worst_ratio.max(err / bound[(r, c)] * F32_ROUNDING);
        }
        // The plain (OpenCV) fundamental matrix is the same up to sign.
        let plain = fundamental_from_cameras(&cams[a], &cams[b]);
        assert!((plain + f).norm() <= 1e-9 * f.norm());
    }
    eprintln!("{name}: worst error / rounding scale of its entry {worst_ratio:.3e}");
}

#[test]
fn fundamental_matrices_match_official_get_fundamental_matrices() {
    check_fundamentals(&fixture(), "F_2to1_all_pairs", false);
}

#[test]
fn mean_focal_fundamental_matrices_match_what_ggs_uses() {
    check_fundamentals(&fixture(), "F_2to1_all_pairs_meanfocal", true);
}

struct Matches {
    kp1: Vec<Point2<f64>>,
    kp2: Vec<Point2<f64>>,
    i12: Vec<(usize, usize)>,
}

fn matches(fx: &SafetensorsFixture) -> Matches {
    let pts = |name: &str| -> Vec<Point2<f64>> {
        fx.tensor(name)
            .chunks(2)
            .iter()
            .map(|c| Point2::new(c[0], c[1]))
            .collect()
    };
    let i12 = fx
        .tensor("i12")
        .chunks(2)
        .iter()
        .map(|c| (c[0] as usize, c[1] as usize))
        .collect();
    Matches {
        kp1: pts("kp1"),
        kp2: pts("kp2"),
        i12,
    }
}

/// Sampson errors of the fixture's matches under our mean-focal F (optionally transposed), and
/// for each the float32 rounding bound of `√sampson` in the reference (px): the error of
/// `x2ᵀ F x1` is bounded by `Σ |x2_i| (rounding of F_ij) |x1_j|` plus the rounding of the final
/// dot product, divided by the Sampson denominator's square root.
fn sampson_all(fx: &SafetensorsFixture, transpose: bool) -> (Vec<f64>, Vec<f64>) {
    let cams = cameras_224(fx, true);
    let m = matches(fx);
    let pair_idx = fx.tensor("pair_idx").data;
    m.i12
        .iter()
        .enumerate()
        .map(|(k, &(a, b))| {
            assert_eq!(pair_idx[k] as usize, a * N_CAMERAS + b);
            let f: Matrix3<f64> = fundamental_official(&cams[a], &cams[b]);
            let f = if transpose { f.transpose() } else { f };
            let s = sampson_error(&f, &m.kp1[k], &m.kp2[k]).unwrap();
            let (h1, h2) = (m.kp1[k].to_homogeneous(), m.kp2[k].to_homogeneous());
            let (l2, l1) = (f * h1, f.transpose() * h2);
            let den = (l2.x * l2.x + l2.y * l2.y + l1.x * l1.x + l1.y * l1.y).sqrt();
            let terms = h2.abs().dot(&(f.abs() * h1.abs())) * F32_ROUNDING;
            let f_err = h2
                .abs()
                .dot(&(fundamental_rounding_scale(&cams[a], &cams[b]) * h1.abs()));
            (s, (terms + f_err) / den)
        })
        .unzip()
}

/// Compares Sampson errors as distances (`√sampson`, px) within the rounding bounds.
#[track_caller]
fn assert_sampson_close(what: &str, ours: &[f64], bounds: &[f64], expected: &[f64]) {
    assert_eq!(ours.len(), expected.len(), "{what}: count");
    let mut worst_px = 0.0f64;
    let mut worst_ratio = 0.0f64;
    for (k, ((s, bound), e)) in ours.iter().zip(bounds).zip(expected).enumerate() {
        let err = (s.sqrt() - e.sqrt()).abs();
        assert!(
            err <= *bound,
            "{what}[{k}]: √ got {}, expected {} (|diff| {err:e} px > {bound:e})",
            s.sqrt(),
            e.sqrt()
        );
        worst_px = worst_px.max(err);
        worst_ratio = worst_ratio.max(err / bound);
    }
    eprintln!(
        "{what}: worst |√ours − √ref| {worst_px:.3e} px, worst fraction of the rounding bound {worst_ratio:.3}"
    );
}

#[test]
fn sampson_errors_match_official_compute_sampson_distance() {
    let fx = fixture();
    let (ours, bounds) = sampson_all(&fx, false);
    assert_sampson_close(
        "sampson_all",
        &ours,
        &bounds,
        &fx.tensor("sampson_all").data,
    );

    let (valid, valid_bounds): (Vec<f64>, Vec<f64>) = ours
        .iter()
        .zip(&bounds)
        .filter(|(s, _)| **s < 10.0)
        .map(|(s, b)| (*s, *b))
        .unzip();
    assert_sampson_close(
        "sampson_valid_lt10",
        &valid,
        &valid_bounds,
        &fx.tensor("sampson_valid_lt10").data,
    );
    // Means: each value may be off by (√s + b)² − s = 2√s·b + b².
    let value_bound = |s: f64, b: f64| 2.0 * s.sqrt() * b + b * b;
    let clamped = mean(ours.iter().map(|s| s.min(10.0)));
    let clamped_bound = mean(
        ours.iter()
            .zip(&bounds)
            .map(|(s, b)| value_bound(s.min(10.0), *b)),
    );
    let loss = mean(valid.iter().copied());
    let loss_bound = mean(
        valid
            .iter()
            .zip(&valid_bounds)
            .map(|(s, b)| value_bound(*s, *b)),
    );
    for (name, ours, bound) in [
        ("sampson_print_clamped_mean", clamped, clamped_bound),
        ("loss_all", loss, loss_bound),
    ] {
        assert_close(name, &[ours], &fx.tensor(name).data, bound, 0.0);
    }
}

/// Asserts that most Sampson errors of a deliberately wrong computation fall outside the
/// parity bounds: the parity check would catch that mistake.
#[track_caller]
fn assert_parity_would_fail(wrong: &[f64], bounds: &[f64], expected: &[f64]) {
    let off = wrong
        .iter()
        .zip(bounds)
        .zip(expected)
        .filter(|((s, b), e)| (s.sqrt() - e.sqrt()).abs() > **b)
        .count();
    assert!(
        off > expected.len() / 2,
        "only {off} of {} differ",
        expected.len()
    );
}

#[test]
fn a_transposed_fundamental_matrix_would_fail_the_parity_check() {
    let fx = fixture();
    let (wrong, bounds) = sampson_all(&fx, true);
    let expected = fx.tensor("sampson_all").data;
    assert_parity_would_fail(&wrong, &bounds, &expected);
}

#[test]
fn flipped_pytorch3d_signs_would_fail_the_parity_check() {
    // Converting without negating T's x and y (a common slip) moves the epipoles: the Sampson
    // errors of the fixture's matches no longer agree.
    let fx = fixture();
    let m = matches(&fx);
    let (_, bounds) = sampson_all(&fx, false);
    let mut cams = cameras_224(&fx, true);
    for c in &mut cams {
        c.cam_from_world.translation.x *= -1.0;
        c.cam_from_world.translation.y *= -1.0;
    }
    let wrong: Vec<f64> = m
        .i12
        .iter()
        .enumerate()
        .map(|(k, (a, b))| {
            sampson_error(
                &fundamental_official(&cams[*a], &cams[*b]),
                &m.kp1[k],
                &m.kp2[k],
            )
            .unwrap()
        })
        .collect();
    let expected = fx.tensor("sampson_all").data;
    assert_parity_would_fail(&wrong, &bounds, &expected);
}
