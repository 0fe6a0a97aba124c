//! The Levenberg–Marquardt refinement recovers exact cameras and the focal from a perturbed
//! start on noise-free synthetic matches, and tolerates gross outliers.
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use posediff_guidance::bundle::{BundleConfig, build_tracks, bundle_adjust};
use posediff_guidance::refine::robust_cost;
use posediff_guidance::{ImageIntrinsics, MatchSet, RefineCamera, RefineConfig, refine_cameras};

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
    matches: MatchSet,
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
    let (mut kp1, mut kp2, mut frames) = (Vec::new(), Vec::new(), Vec::new());
    let mut s: u64 = 11;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    for i in 0..n {
        for j in i + 1..n {
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
                kp1.push(a);
                kp2.push(b);
                frames.push((i, j));
            }
        }
    }
    Scene {
        matches: MatchSet::new(n, &kp1, &kp2, &frames).unwrap(),
        intrinsics: ImageIntrinsics {
            principal: vec![[cx, cy]; n],
            scale: vec![W; n],
        },
        cameras,
        phi,
    }
}

fn perturbed(cameras: &[RefineCamera]) -> Vec<Option<RefineCamera>> {
    cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            if i == 0 {
                return Some(*c);
            }
            let d = Rotation3::from_euler_angles(0.02, -0.015 * i as f64, 0.01);
            Some(RefineCamera {
                rotation: d * c.rotation,
                center: c.center + Vector3::new(0.1, -0.05, 0.08 * i as f64),
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
            worst = worst.max((ra * rb.inverse()).angle().to_degrees());
        }
    }
    worst
}

#[test]
fn recovers_exact_cameras_and_focal() {
    let s = scene(6, 0);
    let mut cams = perturbed(&s.cameras);
    let mut phi = s.phi * 1.1;
    assert!(worst_rotation(&cams, &s.cameras) > 1.0);
    let report = refine_cameras(
        &s.matches,
        &s.intrinsics,
        &mut cams,
        &mut phi,
        0,
        &RefineConfig::default(),
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

#[test]
fn gross_outliers_do_not_pull_the_solution() {
    let s = scene(5, 7);
    let mut cams = perturbed(&s.cameras);
    let mut phi = s.phi * 0.95;
    let truth: Vec<Option<RefineCamera>> = s.cameras.iter().copied().map(Some).collect();
    let report = refine_cameras(
        &s.matches,
        &s.intrinsics,
        &mut cams,
        &mut phi,
        0,
        &RefineConfig::default(),
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
    let at_truth = robust_cost(&s.matches, &s.intrinsics, &truth, s.phi, 1.0, 10.0).unwrap();
    let ours = robust_cost(&s.matches, &s.intrinsics, &cams, phi, 1.0, 10.0).unwrap();
    assert!(ours <= at_truth * (1.0 + 1e-9), "{ours} vs {at_truth}");
}

#[test]
fn inputs_of_the_wrong_length_are_errors() {
    let s = scene(3, 0);
    let mut cams = vec![None; 2];
    let mut phi = 1.0;
    assert!(
        refine_cameras(
            &s.matches,
            &s.intrinsics,
            &mut cams,
            &mut phi,
            0,
            &RefineConfig::default()
        )
        .is_err()
    );
    let mut cams: Vec<Option<RefineCamera>> = vec![None; 3];
    assert!(
        refine_cameras(
            &s.matches,
            &s.intrinsics,
            &mut cams,
            &mut phi,
            0,
            &RefineConfig::default()
        )
        .is_err(),
        "the reference must be estimated"
    );
}

/// Points seen by every camera (tracks across all views), projected exactly.
fn multi_view_tracks(s: &Scene) -> Vec<posediff_guidance::bundle::Track> {
    let f = s.phi * W;
    let pp = s.intrinsics.principal[0];
    let mut seed: u64 = 5;
    let mut rnd = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    (0..150)
        .filter_map(|_| {
            let x = Vector3::new(rnd() * 2.0, rnd() * 2.0, rnd() * 2.0);
            s.cameras
                .iter()
                .enumerate()
                .map(|(i, c)| {
                    let p = c.rotation * (x - c.center);
                    (p.z > 0.1).then(|| posediff_guidance::bundle::Observation {
                        image: i,
                        xy: [f * p.x / p.z + pp[0], f * p.y / p.z + pp[1]],
                    })
                })
                .collect::<Option<Vec<_>>>()
        })
        .collect()
}

#[test]
fn bundle_adjustment_recovers_exact_cameras_and_focal() {
    let s = scene(5, 0);
    let tracks = multi_view_tracks(&s);
    assert!(tracks.len() > 100);
    // Small perturbation: the triangulation must still find the points in front.
    let mut cams: Vec<Option<RefineCamera>> = s
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            Some(if i == 0 {
                *c
            } else {
                RefineCamera {
                    rotation: Rotation3::from_euler_angles(0.004, -0.003 * i as f64, 0.002)
                        * c.rotation,
                    center: c.center + Vector3::new(0.02, -0.01, 0.015 * i as f64),
                }
            })
        })
        .collect();
    let mut phi = s.phi * 1.02;
    let config = BundleConfig {
        max_error_px: 1e3,
        ..BundleConfig::default()
    };
    let report = bundle_adjust(&tracks, &s.intrinsics, &mut cams, &mut phi, 0, &config).unwrap();
    assert_eq!(report.points, tracks.len());
    assert!(report.rms_px < 1e-6, "{report:?}");
    assert!((phi / s.phi - 1.0).abs() < 1e-7, "phi {phi}");
    assert!(worst_rotation(&cams, &s.cameras) < 1e-5);
}

#[test]
fn tracks_from_pairwise_matches_rebuild_the_multi_view_points() {
    let s = scene(4, 0);
    let truth = multi_view_tracks(&s);
    let mut pairs = Vec::new();
    for i in 0..4 {
        for j in i + 1..4 {
            let (a, b): (Vec<[f64; 2]>, Vec<[f64; 2]>) =
                truth.iter().map(|t| (t[i].xy, t[j].xy)).unzip();
            pairs.push((i, j, a, b));
        }
    }
    let tracks = build_tracks(4, pairs.iter().map(|(i, j, a, b)| (*i, *j, &a[..], &b[..])));
    assert_eq!(tracks.len(), truth.len());
    assert!(tracks.iter().all(|t| t.len() == 4));
}
