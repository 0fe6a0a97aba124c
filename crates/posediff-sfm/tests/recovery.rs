//! The refinements recover exact cameras and the focal from a perturbed start on noise-free
//! synthetic matches and tolerate gross outliers; tracks rebuild multi-view points from pairs
//! by keypoint id; the sparse bundle adjustment equals the dense reference at 200 cameras.
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use posediff_geometry::PairMatches;
use posediff_sfm::bundle::{BundleOptions, BundleReport, KeyframeOptions, bundle_adjust};
use posediff_sfm::sampson_refine::{SampsonRefineOptions, refine_sampson, robust_cost};
use posediff_sfm::tracks::{Observation, Track, build_tracks};
use posediff_sfm::{CameraPose as RefineCamera, ImageIntrinsics, Solver};

const W: f64 = 640.0;
const H: f64 = 480.0;

fn look_at(center: Vector3<f64>) -> RefineCamera {
    let z = (-center).normalize();
    let x = Vector3::z().cross(&z).normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    RefineCamera {
        rotation: Rotation3::from_matrix_unchecked(r),
        center,
    }
}

struct Scene {
    cameras: Vec<RefineCamera>,
    matches: Vec<PairMatches>,
    intrinsics: ImageIntrinsics,
    phi: f64,
}

fn scene(n: usize, outliers_every: usize) -> Scene {
    let phi = 0.9;
    let f = phi * W;
    let (cx, cy) = ((W - 1.0) / 2.0, (H - 1.0) / 2.0);
    let cameras: Vec<RefineCamera> = (0..n)
        .map(|i| {
            let a = 0.35 * i as f64;
            look_at(Vector3::new(
                4.0 * a.cos(),
                4.0 * a.sin(),
                1.0 + 0.2 * i as f64,
            ))
        })
        .collect();
    let project = |c: &RefineCamera, x: &Point3<f64>| -> Option<[f64; 2]> {
        let p = c.rotation * (x.coords - c.center);
        (p.z > 0.1).then(|| [f * p.x / p.z + cx, f * p.y / p.z + cy])
    };
    let mut matches = Vec::new();
    let mut next_id = vec![0u32; n];
    let mut s: u64 = 11;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    for i in 0..n {
        for j in i + 1..n {
            let mut pair = PairMatches {
                first: i,
                second: j,
                ..PairMatches::default()
            };
            for k in 0..80 {
                let x = Point3::new(rnd() * 2.0, rnd() * 2.0, rnd() * 2.0);
                let (Some(a), Some(mut b)) = (project(&cameras[i], &x), project(&cameras[j], &x))
                else {
                    continue;
                };
                if outliers_every > 0 && k % outliers_every == 0 {
                    // 15–25 px away in x and y: gross, though some fall near their epipolar line.
                    b = [b[0] + 20.0 + 10.0 * rnd(), b[1] - 20.0 + 10.0 * rnd()];
                }
                pair.kp1.push(a);
                pair.kp2.push(b);
                pair.idx1.push(next_id[i]);
                pair.idx2.push(next_id[j]);
                next_id[i] += 1;
                next_id[j] += 1;
            }
            matches.push(pair);
        }
    }
    Scene {
        matches,
        intrinsics: ImageIntrinsics::new(vec![[cx, cy]; n], vec![W; n]),
        cameras,
        phi,
    }
}

fn refs(m: &[PairMatches]) -> Vec<&PairMatches> {
    m.iter().collect()
}

/// `cameras` with every one but the first turned and moved, more the later it is: Euler angles
/// `(0.02, −0.015·i, 0.01)` and a shift `(0.1, −0.05, 0.08·i)`, both times `size`.
fn perturbed(cameras: &[RefineCamera], size: f64) -> Vec<Option<RefineCamera>> {
    cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            if i == 0 {
                return Some(*c);
            }
            let d =
                Rotation3::from_euler_angles(0.02 * size, -0.015 * size * i as f64, 0.01 * size);
            Some(RefineCamera {
                rotation: d * c.rotation,
                center: c.center + Vector3::new(0.1, -0.05, 0.08 * i as f64) * size,
            })
        })
        .collect()
}

/// Worst relative-rotation error (degrees) between solutions.
fn worst_rotation(a: &[Option<RefineCamera>], b: &[RefineCamera]) -> f64 {
    let mut worst = 0.0f64;
    for i in 0..b.len() {
        for j in i + 1..b.len() {
            let (ai, aj) = (a[i].unwrap(), a[j].unwrap());
            let ra = aj.rotation * ai.rotation.inverse();
            let rb = b[j].rotation * b[i].rotation.inverse();
            worst = worst.max(posediff_geometry::rotation_angle(&(ra * rb.inverse())).to_degrees());
        }
    }
    worst
}

#[test]
fn recovers_exact_cameras_and_focal() {
    let s = scene(6, 0);
    let mut cams = perturbed(&s.cameras, 1.0);
    let mut phi = s.phi * 1.1;
    assert!(worst_rotation(&cams, &s.cameras) > 1.0);
    let report = refine_sampson(
        &refs(&s.matches),
        &s.intrinsics,
        &mut cams,
        &mut phi,
        0,
        &SampsonRefineOptions::default(),
    )
    .unwrap();
    assert!(report.converged, "{report:?}");
    assert!(
        report.final_cost < 1e-12 * report.initial_cost.max(1.0),
        "{report:?}"
    );
    assert!((phi / s.phi - 1.0).abs() < 1e-6, "phi {phi}");
    assert!(worst_rotation(&cams, &s.cameras) < 1e-4);
    // Centres up to the scale: unit mean distance from camera 0.
    let d = |c: &[Vector3<f64>]| -> Vec<Vector3<f64>> {
        let mean = c.iter().map(|x| (x - c[0]).norm()).sum::<f64>() / c.len() as f64;
        c.iter().map(|x| (x - c[0]) / mean).collect()
    };
    let got = d(&cams.iter().map(|c| c.unwrap().center).collect::<Vec<_>>());
    let want = d(&s.cameras.iter().map(|c| c.center).collect::<Vec<_>>());
    for (g, w) in got.iter().zip(&want) {
        assert!((g - w).norm() < 1e-6, "{g} vs {w}");
    }
}

/// With at most 20 of each pair's 80 matches (evenly spaced) the exact solution is still the
/// minimum and the report counts the matches used; below `thin_above_matches` nothing is
/// thinned; a cap of 0 is an error.
#[test]
fn a_cap_on_the_matches_per_pair_keeps_the_exact_solution() {
    let s = scene(6, 0);
    let mut cams = perturbed(&s.cameras, 1.0);
    let mut phi = s.phi * 1.1;
    let pairs = s.matches.iter().filter(|p| !p.is_empty()).count();
    let total: usize = s.matches.iter().map(|p| p.len()).sum();
    let options = SampsonRefineOptions {
        max_matches_per_pair: Some(20),
        thin_above_matches: 0,
        ..SampsonRefineOptions::default()
    };
    let report = refine_sampson(
        &refs(&s.matches),
        &s.intrinsics,
        &mut cams,
        &mut phi,
        0,
        &options,
    )
    .unwrap();
    assert!(s.matches.iter().all(|p| p.len() > 20));
    assert_eq!(report.matches, 20 * pairs, "{report:?}");
    assert_eq!(report.per_pair_cap, Some(20));
    assert_eq!(
        (report.tolerance, report.step_tolerance),
        (
            options.large_set_tolerance,
            options.large_set_step_tolerance
        ),
        "a thinned set is large"
    );
    assert!(report.converged, "{report:?}");
    assert!((phi / s.phi - 1.0).abs() < 1e-6, "phi {phi}");
    assert!(worst_rotation(&cams, &s.cameras) < 1e-4);
    let whole = refine_sampson(
        &refs(&s.matches),
        &s.intrinsics,
        &mut perturbed(&s.cameras, 1.0),
        &mut phi,
        0,
        &SampsonRefineOptions {
            thin_above_matches: total,
            ..options
        },
    )
    .unwrap();
    assert_eq!((whole.matches, whole.per_pair_cap), (total, None));
    assert_eq!(
        (whole.tolerance, whole.step_tolerance),
        (options.tolerance, 0.0),
        "a whole set keeps the tight tolerance and no step tolerance"
    );
    // Settings that cannot work are errors naming them.
    let zero = SampsonRefineOptions {
        max_matches_per_pair: Some(0),
        ..SampsonRefineOptions::default()
    };
    let nan_step = SampsonRefineOptions {
        large_set_step_tolerance: f64::NAN,
        ..SampsonRefineOptions::default()
    };
    for (bad, name) in [
        (zero, "max_matches_per_pair"),
        (nan_step, "large_set_step_tolerance"),
    ] {
        let err = refine_sampson(
            &refs(&s.matches),
            &s.intrinsics,
            &mut perturbed(&s.cameras, 1.0),
            &mut phi,
            0,
            &bad,
        )
        .unwrap_err();
        assert!(err.to_string().contains(name), "{err}");
    }
}

#[test]
fn gross_outliers_do_not_pull_the_solution() {
    let s = scene(5, 7);
    let mut cams = perturbed(&s.cameras, 1.0);
    let mut phi = s.phi * 0.95;
    let truth: Vec<Option<RefineCamera>> = s.cameras.iter().copied().map(Some).collect();
    let report = refine_sampson(
        &refs(&s.matches),
        &s.intrinsics,
        &mut cams,
        &mut phi,
        0,
        &SampsonRefineOptions::default(),
    )
    .unwrap();
    assert!(report.converged);
    assert!(
        report.inliers < report.matches,
        "the outliers are recognised"
    );
    assert!((phi / s.phi - 1.0).abs() < 2e-3, "phi {phi}");
    let worst = worst_rotation(&cams, &s.cameras);
    // An outlier that lands near its epipolar line cannot be told from an inlier; the rest must
    // not matter (the start is off by more than 1°).
    assert!(worst < 0.05, "{worst}° phi {phi} {report:?}");
    // The refined solution is no worse than the truth under the robust cost.
    let at_truth = robust_cost(&refs(&s.matches), &s.intrinsics, &truth, s.phi, 1.0, 10.0).unwrap();
    let ours = robust_cost(&refs(&s.matches), &s.intrinsics, &cams, phi, 1.0, 10.0).unwrap();
    assert!(ours <= at_truth * (1.0 + 1e-9), "{ours} vs {at_truth}");
}

#[test]
fn inputs_of_the_wrong_length_are_errors() {
    let s = scene(3, 0);
    let mut cams = vec![None; 2];
    let mut phi = 1.0;
    assert!(
        refine_sampson(
            &refs(&s.matches),
            &s.intrinsics,
            &mut cams,
            &mut phi,
            0,
            &SampsonRefineOptions::default()
        )
        .is_err()
    );
    let mut cams: Vec<Option<RefineCamera>> = vec![None; 3];
    assert!(
        refine_sampson(
            &refs(&s.matches),
            &s.intrinsics,
            &mut cams,
            &mut phi,
            0,
            &SampsonRefineOptions::default()
        )
        .is_err(),
        "the reference must be estimated"
    );
}

/// Points seen by every camera (tracks across all views), projected exactly.
fn multi_view_tracks(s: &Scene) -> Vec<Track> {
    multi_view_tracks_with(s, &|_| s.phi * W)
}

/// [`multi_view_tracks`] with image `i` projected at focal `focal(i)`.
fn multi_view_tracks_with(s: &Scene, focal: &dyn Fn(usize) -> f64) -> Vec<Track> {
    let pp = s.intrinsics.principal[0];
    let mut seed: u64 = 5;
    let mut rnd = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    (0..150)
        .enumerate()
        .filter_map(|(id, _)| {
            let x = Vector3::new(rnd() * 2.0, rnd() * 2.0, rnd() * 2.0);
            s.cameras
                .iter()
                .enumerate()
                .map(|(i, c)| {
                    let p = c.rotation * (x - c.center);
                    let f = focal(i);
                    (p.z > 0.1).then(|| Observation {
                        image: i,
                        keypoint: id as u32,
                        xy: [f * p.x / p.z + pp[0], f * p.y / p.z + pp[1]],
                    })
                })
                .collect::<Option<Vec<_>>>()
        })
        .collect()
}

/// Adjusts `scene(n, 0)`'s tracks from cameras perturbed by a fifth of [`perturbed`] and a
/// focal 2 % off with `keyframes`; the cameras and the focal must come back exactly.
fn exactly_adjusted(
    n: usize,
    keyframes: Option<KeyframeOptions>,
) -> (Vec<Track>, Vec<posediff_sfm::bundle::Point>, BundleReport) {
    let s = scene(n, 0);
    let tracks = multi_view_tracks(&s);
    assert!(tracks.len() > 100);
    // Small perturbation: the triangulation must still find the points in front.
    let mut cams = perturbed(&s.cameras, 0.2);
    let mut phi = s.phi * 1.02;
    let config = BundleOptions {
        max_error_px: 1e3,
        keyframes,
        ..BundleOptions::default()
    };
    let (points, report) = bundle_adjust(
        &tracks,
        &s.intrinsics,
        &mut cams,
        std::slice::from_mut(&mut phi),
        0,
        &config,
    )
    .unwrap();
    assert_eq!(points.len(), report.points);
    assert!(report.converged, "{report:?}");
    assert!(report.rms_px < 1e-6, "{report:?}");
    assert!((phi / s.phi - 1.0).abs() < 1e-7, "phi {phi}");
    assert!(worst_rotation(&cams, &s.cameras) < 1e-5);
    (tracks, points, report)
}

#[test]
fn bundle_adjustment_recovers_exact_cameras_and_focal() {
    let (tracks, points, report) = exactly_adjusted(5, Some(KeyframeOptions::default()));
    assert_eq!(report.points, tracks.len());
    // Five cameras: all adjusted jointly.
    assert!(report.keyframes.is_none());
    assert!(points.iter().all(|p| p.alone.is_empty()));
}

/// With more cameras than `keyframes.max_keyframes`, the keyframes are adjusted with the
/// points and the others refined alone: every camera and the focal still come back exactly,
/// the others' observations are the points' `alone` ones, and the report says so.
#[test]
fn keyframe_bundle_adjustment_recovers_exact_cameras_and_focal() {
    let options = KeyframeOptions {
        max_keyframes: 5,
        ..KeyframeOptions::default()
    };
    let (_, points, report) = exactly_adjusted(12, Some(options));
    let k = report.keyframes.unwrap();
    assert_eq!(
        (k.keyframes, k.promoted, k.refined_alone, k.unrefined),
        (5, 0, 7, 0)
    );
    // Keyframes 0, 3, 6, 8, 11 (evenly spaced) in the joint adjustment, the others alone.
    for p in &points {
        assert!(
            p.observations
                .iter()
                .all(|o| [0, 3, 6, 8, 11].contains(&o.image))
        );
        assert!(p.alone.iter().all(|o| ![0, 3, 6, 8, 11].contains(&o.image)));
        assert_eq!(p.observations.len() + p.alone.len(), 12);
    }
    // Without keyframes: all twelve jointly.
    let (_, points, report) = exactly_adjusted(12, None);
    assert!(report.keyframes.is_none());
    assert!(points.iter().all(|p| p.alone.is_empty()));
}

/// Two cameras (every second image through a 1.4× zoom): each group's focal comes back,
/// shared by its images, from starts 2 % and 3 % off.
#[test]
fn bundle_adjustment_recovers_each_cameras_focal() {
    let mut s = scene(6, 0);
    let zoom = 1.4;
    let focal = |i: usize| s.phi * W * if i % 2 == 1 { zoom } else { 1.0 };
    let tracks = multi_view_tracks_with(&s, &focal);
    assert!(tracks.len() > 100);
    s.intrinsics.group = (0..6).map(|i| i % 2).collect();
    let mut cams: Vec<Option<RefineCamera>> = s.cameras.iter().copied().map(Some).collect();
    let mut factors = vec![s.phi * 1.02, s.phi * zoom * 0.97];
    let config = BundleOptions {
        max_error_px: 1e3,
        ..BundleOptions::default()
    };
    let (_, report) =
        bundle_adjust(&tracks, &s.intrinsics, &mut cams, &mut factors, 0, &config).unwrap();
    assert!(report.rms_px < 1e-6, "{report:?}");
    assert!((factors[0] / s.phi - 1.0).abs() < 1e-7, "{factors:?}");
    assert!(
        (factors[1] / (s.phi * zoom) - 1.0).abs() < 1e-7,
        "{factors:?}"
    );
    assert!(worst_rotation(&cams, &s.cameras) < 1e-5);
    // One factor per group, or an error naming them.
    let mut one = vec![s.phi];
    assert!(bundle_adjust(&tracks, &s.intrinsics, &mut cams, &mut one, 0, &config).is_err());
}

#[test]
fn tracks_from_pairwise_matches_rebuild_the_multi_view_points() {
    let s = scene(4, 0);
    let truth = multi_view_tracks(&s);
    let mut pairs = Vec::new();
    for i in 0..4 {
        for j in i + 1..4 {
            pairs.push(PairMatches {
                first: i,
                second: j,
                kp1: truth.iter().map(|t| t[i].xy).collect(),
                kp2: truth.iter().map(|t| t[j].xy).collect(),
                idx1: truth.iter().map(|t| t[i].keypoint).collect(),
                idx2: truth.iter().map(|t| t[j].keypoint).collect(),
            });
        }
    }
    let (tracks, report) = build_tracks(4, &pairs).unwrap();
    assert_eq!(report.inconsistent, 0);
    assert_eq!(tracks.len(), truth.len());
    assert!(tracks.iter().all(|t| t.len() == 4));
}

/// 200 cameras on a ring around a point cloud, tracks of every point seen by its neighbours:
/// the bundle adjustment with the sparse reduced camera system and with the dense reference
/// take the same steps and agree to 1e-9 relative.
#[test]
fn sparse_and_dense_bundle_adjustments_agree_at_200_cameras() {
    let n = 200;
    let phi = 0.8;
    let (cx, cy) = ((W - 1.0) / 2.0, (H - 1.0) / 2.0);
    let cameras: Vec<RefineCamera> = (0..n)
        .map(|i| {
            let a = std::f64::consts::TAU * i as f64 / n as f64;
            look_at(Vector3::new(
                6.0 * a.cos(),
                6.0 * a.sin(),
                0.5 * (3.0 * a).sin(),
            ))
        })
        .collect();
    let intrinsics = ImageIntrinsics::new(vec![[cx, cy]; n], vec![W; n]);
    let mut seed: u64 = 99;
    let mut rnd = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    let mut tracks: Vec<Track> = Vec::new();
    for k in 0..2000 {
        let x = Vector3::new(rnd() * 3.0, rnd() * 3.0, rnd() * 1.5);
        let start = (k * 7) % n;
        let track: Track = (0..4)
            .filter_map(|d| {
                let i = (start + 3 * d) % n;
                let c = cameras[i];
                let p = c.rotation * (x - c.center);
                let f = phi * W;
                (p.z > 0.1).then(|| Observation {
                    image: i,
                    keypoint: k as u32,
                    // Half-pixel noise, so the minimum is not at zero cost.
                    xy: [
                        f * p.x / p.z + cx + 0.5 * rnd(),
                        f * p.y / p.z + cy + 0.5 * rnd(),
                    ],
                })
            })
            .collect();
        if track.len() >= 3 {
            let mut t = track;
            t.sort_by_key(|o| o.image);
            tracks.push(t);
        }
    }
    let start: Vec<Option<RefineCamera>> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            Some(if i == 0 {
                *c
            } else {
                RefineCamera {
                    rotation: Rotation3::from_euler_angles(0.001 * (i % 3) as f64, -0.002, 0.001)
                        * c.rotation,
                    center: c.center + Vector3::new(0.01, -0.01 * (i % 5) as f64, 0.005),
                }
            })
        })
        .collect();
    let run = |solver: Solver| {
        let mut cams = start.clone();
        let mut f = phi * 1.01;
        let options = BundleOptions {
            solver,
            max_iterations: 20,
            ..BundleOptions::default()
        };
        let (points, report) = bundle_adjust(
            &tracks,
            &intrinsics,
            &mut cams,
            std::slice::from_mut(&mut f),
            0,
            &options,
        )
        .unwrap();
        (cams, f, points, report)
    };
    let (sparse, f_sparse, p_sparse, r_sparse) = run(Solver::Sparse);
    let (dense, f_dense, p_dense, r_dense) = run(Solver::Dense);
    assert!(r_sparse.points > 1000, "{r_sparse:?}");
    assert_eq!(r_sparse.iterations, r_dense.iterations);
    assert!(r_sparse.rms_px < 0.5, "{r_sparse:?}");
    assert!((f_sparse / f_dense - 1.0).abs() < 1e-9);
    let scale = 6.0;
    for (a, b) in sparse.iter().zip(&dense) {
        let (a, b) = (a.unwrap(), b.unwrap());
        assert!(
            (a.center - b.center).norm() < 1e-9 * scale,
            "{} vs {}",
            a.center,
            b.center
        );
        let angle = posediff_geometry::rotation_angle(&(a.rotation * b.rotation.inverse()));
        assert!(angle < 1e-9, "{angle}");
    }
    for (a, b) in p_sparse.iter().zip(&p_dense) {
        assert!((a.xyz - b.xyz).norm() < 1e-9 * scale);
    }
}
