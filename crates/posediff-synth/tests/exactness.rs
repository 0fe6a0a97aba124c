//! The written cameras are exact: points seen at a pixel project back onto that pixel with the
//! cameras read from both layouts (cameras.json and the CO3D annotations); SIFT matches between
//! rendered views obey the ground-truth epipolar geometry; the data is deterministic.
#![allow(clippy::unwrap_used)]

use std::path::Path;

use nalgebra::Point2;
use posediff::io::co3d::load_annotations;
use posediff::io::export::read_cameras_json;
use posediff_geometry::epipolar::sampson_error;
use posediff_geometry::{Camera, ImageSize, fundamental_from_cameras};
use posediff_matching::{MatchConfig, match_images};
use posediff_synth::{DatasetSpec, LensSpec, render_frame, sequence, write_dataset};

fn spec(seed: u64) -> DatasetSpec {
    DatasetSpec {
        sequences: 2,
        frames: 4,
        seed,
        sizes: vec![
            ImageSize::new(200, 150).unwrap(),
            ImageSize::new(150, 200).unwrap(),
        ],
        test_every: 2,
        path: None,
        lens: LensSpec::default(),
    }
}

/// Largest distance (px) between a pixel centre and the projection, with `camera`, of the world
/// point the renderer saw there; and how many pixels were checked.
fn worst_reprojection(frame: &posediff_synth::Frame, camera: &Camera) -> (f64, usize) {
    let mut worst: f64 = 0.0;
    let mut count = 0;
    for y in (0..frame.buffers.height).step_by(3) {
        for x in (0..frame.buffers.width).step_by(3) {
            if let Some(hit) = frame.buffers.at(x, y) {
                let p = camera.project(&hit.world.into()).unwrap();
                worst = worst.max((p.x - x as f64).hypot(p.y - y as f64));
                count += 1;
            }
        }
    }
    (worst, count)
}

#[test]
fn both_layouts_reproject_rendered_points_onto_their_pixels() {
    let out = posediff_fixtures::temp_dir("synth-exact");
    let spec = spec(3);
    write_dataset(&out, &spec).unwrap();
    let mut co3d = load_annotations(&out.join("synthetic_train.jgz")).unwrap();
    co3d.extend(load_annotations(&out.join("synthetic_test.jgz")).unwrap());
    assert_eq!(co3d.len(), 2);
    for k in 0..spec.sequences {
        let seq = sequence(&spec, k);
        let dir = out.join("synthetic").join(&seq.name);
        let json = read_cameras_json(&dir.join("cameras.json")).unwrap();
        let annotated = co3d.iter().find(|s| s.name == seq.name).unwrap();
        assert_eq!(json.len(), spec.frames);
        assert_eq!(annotated.frames.len(), spec.frames);
        for (i, truth) in seq.cameras.iter().enumerate() {
            let frame = render_frame(&seq.scene, truth);
            // The image on disk is this frame.
            let png = image_pixels(&dir.join(&json[i].image));
            assert_eq!(png, frame.rgb);
            let size = truth.image_size;
            let from_co3d = annotated.frames[i].pytorch3d().to_opencv(size).unwrap();
            assert_eq!(
                posediff::io::co3d::frame_path(&out, &annotated.frames[i]),
                dir.join(&json[i].image)
            );
            for camera in [&json[i].camera, &from_co3d] {
                let (worst, count) = worst_reprojection(&frame, camera);
                assert!(count > 200, "{count} pixels checked");
                assert!(worst < 1e-3, "sequence {k} frame {i}: {worst} px");
            }
        }
    }
}

fn image_pixels(path: &Path) -> Vec<u8> {
    let img = opencv::imgcodecs::imread(path.as_os_str(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
    let bgr = opencv::prelude::MatTraitConstManual::data_bytes(&img).unwrap();
    bgr.chunks(3).flat_map(|p| [p[2], p[1], p[0]]).collect()
}

#[test]
fn sift_matches_between_rendered_views_obey_the_true_epipolar_geometry() {
    let out = posediff_fixtures::temp_dir("synth-sift");
    let spec = DatasetSpec {
        sequences: 1,
        frames: 20,
        seed: 11,
        sizes: vec![ImageSize::new(320, 240).unwrap()],
        test_every: 0,
        path: None,
        lens: LensSpec::default(),
    };
    write_dataset(&out, &spec).unwrap();
    let dir = out.join("synthetic/synthetic_0000");
    let cams = read_cameras_json(&dir.join("cameras.json")).unwrap();
    // Neighbouring frames of a 20-frame path: 5–18° apart.
    let (a, b) = (4, 5);
    let config = MatchConfig {
        verification: None,
        ..MatchConfig::default()
    };
    let (_, pairs) = match_images(
        &[dir.join(&cams[a].image), dir.join(&cams[b].image)],
        None,
        &config,
    )
    .unwrap();
    let f = fundamental_from_cameras(&cams[a].camera, &cams[b].camera);
    let mut errors: Vec<f64> = pairs[0]
        .kp1
        .iter()
        .zip(&pairs[0].kp2)
        .map(|(p, q)| {
            sampson_error(&f, &Point2::new(p[0], p[1]), &Point2::new(q[0], q[1])).unwrap()
        })
        .collect();
    assert!(errors.len() >= 20, "{} matches", errors.len());
    eprintln!("{} matches", errors.len());
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    assert!(median < 1.0, "median Sampson error {median} px²");
}

#[test]
fn the_same_seed_gives_the_same_bytes() {
    let spec = DatasetSpec {
        sequences: 1,
        frames: 2,
        ..spec(5)
    };
    let (a, b, c) = (
        posediff_fixtures::temp_dir("synth-det-a"),
        posediff_fixtures::temp_dir("synth-det-b"),
        posediff_fixtures::temp_dir("synth-det-c"),
    );
    write_dataset(&a, &spec).unwrap();
    write_dataset(&b, &spec).unwrap();
    write_dataset(
        &c,
        &DatasetSpec {
            seed: 6,
            ..spec.clone()
        },
    )
    .unwrap();
    let file = "synthetic/synthetic_0000/images/frame000001.png";
    let read = |d: &Path, f: &str| std::fs::read(d.join(f)).unwrap();
    assert_eq!(read(&a, file), read(&b, file));
    assert_eq!(
        read(&a, "synthetic_train.jgz"),
        read(&b, "synthetic_train.jgz")
    );
    assert_ne!(read(&a, file), read(&c, file));
}

#[test]
fn an_empty_spec_is_an_error() {
    let out = posediff_fixtures::temp_dir("synth-empty");
    assert!(
        write_dataset(
            &out,
            &DatasetSpec {
                sequences: 0,
                ..spec(1)
            }
        )
        .is_err()
    );
    assert!(posediff_synth::parse_size("320by240").is_err());
    assert_eq!(
        posediff_synth::parse_size("320x240").unwrap(),
        ImageSize::new(320, 240).unwrap()
    );
}

#[test]
fn the_co3d_protocol_reads_the_synthetic_test_split() {
    let out = posediff_fixtures::temp_dir("synth-co3d");
    let spec = DatasetSpec {
        sequences: 2,
        frames: 12,
        seed: 2,
        sizes: vec![ImageSize::new(160, 120).unwrap()],
        test_every: 1,
        path: None,
        lens: LensSpec::default(),
    };
    write_dataset(&out, &spec).unwrap();
    let report = posediff::bench::bench_co3d(
        &out,
        &out,
        &["synthetic".to_owned()],
        10,
        10,
        0,
        &posediff::bench::GroundTruth,
    )
    .unwrap();
    assert_eq!(report.sequences.len(), 2);
    // The annotated cameras scored against themselves: the metric ceiling.
    assert_eq!(report.mean.maa_30, 1.0);
}

/// A zoom lens changes only the zoomed frames' focal (every second frame by 1.3–1.6×, the path
/// the same); a SIMPLE_RADIAL lens is written as cameras.json's model and params, without the
/// CO3D annotations (which carry no distortion), and each world point the pinhole rendering
/// shows appears where the lens projects it, not where the pinhole camera does.
#[test]
fn zoom_and_radial_lenses_are_exact() {
    let base = DatasetSpec {
        sequences: 1,
        frames: 6,
        sizes: vec![ImageSize::new(240, 180).unwrap()],
        test_every: 0,
        ..spec(9)
    };
    let zoomed = DatasetSpec {
        lens: LensSpec {
            zoom_every: 2,
            ..LensSpec::default()
        },
        ..base.clone()
    };
    let (plain, zoom) = (sequence(&base, 0), sequence(&zoomed, 0));
    for (i, (a, b)) in plain.cameras.iter().zip(&zoom.cameras).enumerate() {
        assert_eq!(a.cam_from_world, b.cam_from_world);
        let ratio = b.intrinsics.fx() / a.intrinsics.fx();
        if i % 2 == 1 {
            assert!((1.3..1.6).contains(&ratio), "frame {i}: {ratio}");
        } else {
            assert_eq!(ratio, 1.0);
        }
    }
    let k = -0.1;
    let radial = DatasetSpec {
        lens: LensSpec {
            radial_k: k,
            ..LensSpec::default()
        },
        ..base.clone()
    };
    let dir = posediff_fixtures::temp_dir("synth-lens");
    write_dataset(&dir, &radial).unwrap();
    assert!(!dir.join("synthetic_train.jgz").exists());
    let seq = dir.join("synthetic/synthetic_0000");
    let raw: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(seq.join("cameras.json")).unwrap()).unwrap();
    let first = &raw[0];
    assert_eq!(first["model"], "SIMPLE_RADIAL");
    assert_eq!(first["params"][3], k);
    let camera = plain.cameras[0];
    let lens = LensSpec {
        radial_k: k,
        ..LensSpec::default()
    }
    .lens(&camera)
    .unwrap();
    let pinhole = render_frame(&plain.scene, &camera);
    let photo = image::open(seq.join("images/frame000000.png"))
        .unwrap()
        .to_rgb8();
    let grey = |rgb: [u8; 3]| (f64::from(rgb[0]) + f64::from(rgb[1]) + f64::from(rgb[2])) / 3.0;
    let (mut right, mut wrong, mut n) = (0.0, 0.0, 0);
    for y in (0..180).step_by(2) {
        for x in (0..240).step_by(2) {
            let Some(hit) = pinhole.buffers.at(x, y) else {
                continue;
            };
            let xc = camera.cam_from_world.transform_point(&hit.world.into());
            let p = lens.project(&xc.coords).unwrap();
            let (u, v) = (p.x.round(), p.y.round());
            if u < 0.0
                || v < 0.0
                || u >= 240.0
                || v >= 180.0
                || (p.x - x as f64).hypot(p.y - y as f64) < 3.0
            {
                continue;
            }
            let seen = grey(pinhole.rgb[(y * 240 + x) * 3..][..3].try_into().unwrap());
            right += (grey(photo.get_pixel(u as u32, v as u32).0) - seen).abs();
            wrong += (grey(photo.get_pixel(x as u32, y as u32).0) - seen).abs();
            n += 1;
        }
    }
    assert!(n > 200, "{n} pixels the lens moves by 3 px or more");
    assert!(
        right < 0.5 * wrong,
        "{} against {}",
        right / n as f64,
        wrong / n as f64
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
