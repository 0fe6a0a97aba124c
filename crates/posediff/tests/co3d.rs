//! CO3D annotations (`../shared/data/co3d_mini_annotations`): they load in file order, resolve
//! to the images, agree with the same sets' cameras.json, and the official frame choice follows
//! numpy's stream (the first draw of seed 0 for 20 frames is numpy's `choice(20, 10)`).

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff::io::co3d::{
    SEEN_CATEGORIES, UNSEEN_CATEGORIES, frame_path, load_annotations, normalized_ground_truth,
    official_frame_ids, usable_sequences,
};
use posediff::io::export::read_cameras_json;
use posediff_fixtures::shared_path;
use posediff_metrics::numpy_rng::LegacyRandomState;

#[test]
fn mini_annotations_load_and_agree_with_cameras_json() {
    let root = shared_path("data/co3d_mini_annotations");
    for (category, set, n) in [
        ("apple", "co3d_apple_posediffusion", 20),
        ("temple", "middlebury_templeSR", 16),
        ("fountain", "strecha_fountainP11", 11),
    ] {
        let seqs = load_annotations(&root.join(format!("{category}_test.jgz"))).unwrap();
        assert_eq!(seqs.len(), 1);
        assert_eq!(seqs[0].name, format!("{category}_seq0"));
        assert_eq!(seqs[0].frames.len(), n);
        let cams = read_cameras_json(&shared_path(&format!("data/{set}/cameras.json"))).unwrap();
        // File paths are relative to the data folder, the CO3D root of these sets.
        let images = shared_path("data");
        for (f, c) in seqs[0].frames.iter().zip(&cams) {
            assert!(frame_path(&images, f).is_file(), "{}", f.filepath);
            let pose = f.cam_from_world();
            assert!(
                (pose.rotation - c.camera.cam_from_world.rotation).norm() < 1e-6,
                "{}",
                f.filepath
            );
            assert!(
                (pose.translation - c.camera.cam_from_world.translation).norm() < 1e-5,
                "{}",
                f.filepath
            );
        }
        assert_eq!(usable_sequences(&seqs, n).len(), 1);
        assert!(usable_sequences(&seqs, n + 1).is_empty());
    }
}

#[test]
fn crop_cameras_and_normalised_ground_truth() {
    let root = shared_path("data/co3d_mini_annotations");
    let seqs = load_annotations(&root.join("apple_test.jgz")).unwrap();
    let cams =
        read_cameras_json(&shared_path("data/co3d_apple_posediffusion/cameras.json")).unwrap();
    let frames: Vec<_> = seqs[0].frames.iter().collect();
    let sizes: Vec<_> = cams.iter().map(|c| c.camera.image_size).collect();
    for ((f, c), s) in frames.iter().zip(&cams).zip(&sizes) {
        // The official NDC crop/scale equals mapping the pixel camera through the loader's crop.
        let ours = f.crop_camera(*s).unwrap();
        let via_pixels = posediff_geometry::CenterCrop::official(*s, 224)
            .camera_to_model(&c.camera)
            .unwrap();
        assert!(
            (ours.intrinsics.matrix() - via_pixels.intrinsics.matrix()).norm() < 1e-4,
            "{}",
            f.filepath
        );
    }
    let gt = normalized_ground_truth(&frames, &sizes).unwrap();
    let first = posediff_geometry::Pytorch3dCamera::from_opencv(&gt.cameras[0]);
    assert!((first.r - nalgebra::Matrix3::identity()).norm() < 1e-6 && first.t.norm() < 1e-6);
    // Unit distance of camera 0 to the optical-axis intersection.
    let hit = posediff_geometry::normalize::optical_axis_intersection(&gt.cameras).unwrap();
    assert!((hit.distances[0] - 1.0).abs() < 1e-6);
    assert!(normalized_ground_truth(&frames, &sizes[..3]).is_err());
}

#[test]
fn frame_choice_follows_numpy_and_category_lists_are_complete() {
    assert_eq!(SEEN_CATEGORIES.len(), 41);
    assert_eq!(UNSEEN_CATEGORIES.len(), 10);
    let root = shared_path("data/co3d_mini_annotations");
    let apple = load_annotations(&root.join("apple_test.jgz")).unwrap();
    let fountain = load_annotations(&root.join("fountain_test.jgz")).unwrap();
    // apple (20 frames) then fountain (11): numpy's choice(20, 10), then choice(11, 10).
    let seqs = [&apple[0], &fountain[0]];
    let ids = official_frame_ids(&seqs, 10, &mut LegacyRandomState::new(0)).unwrap();
    let mut expected = [18, 1, 19, 8, 10, 17, 6, 13, 4, 2];
    expected.sort_by(|a, b| {
        apple[0].frames[*a]
            .filepath
            .cmp(&apple[0].frames[*b].filepath)
    });
    assert_eq!(ids[0], expected);
    let mut numpy = LegacyRandomState::new(0);
    numpy.choice_without_replacement(20, 10).unwrap();
    let mut second = numpy.choice_without_replacement(11, 10).unwrap();
    second.sort_by(|a, b| {
        fountain[0].frames[*a]
            .filepath
            .cmp(&fountain[0].frames[*b].filepath)
    });
    assert_eq!(ids[1], second);
    // A sequence too short draws nothing and consumes nothing.
    let ids = official_frame_ids(
        &[&fountain[0], &apple[0]],
        12,
        &mut LegacyRandomState::new(0),
    )
    .unwrap();
    assert!(ids[0].is_empty());
    let mut fresh = LegacyRandomState::new(0);
    let mut first = fresh.choice_without_replacement(20, 12).unwrap();
    first.sort_by(|a, b| {
        apple[0].frames[*a]
            .filepath
            .cmp(&apple[0].frames[*b].filepath)
    });
    assert_eq!(ids[1], first);
}

#[test]
fn a_corrupt_annotation_file_names_the_file() {
    let path = std::env::temp_dir().join(format!("posediff-bad-{}.jgz", std::process::id()));
    std::fs::write(&path, b"not gzip").unwrap();
    let err = load_annotations(&path).unwrap_err().to_string();
    assert!(err.contains("posediff-bad-"), "{err}");
    std::fs::remove_file(&path).unwrap();
}
