//! Matching on real images of `../shared/data` (ground-truth epipolar geometry) and on
//! synthetic images with known keypoint positions; clear errors for bad input.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use nalgebra::Point2;
use posediff_fixtures::shared_path;
use posediff_geometry::camera_json::CameraRecord;
use posediff_geometry::{Camera, fundamental_from_cameras, sampson_error};
use posediff_matching::features::{extract_from_grey, read_grey};
use posediff_matching::{
    Detector, FeatureConfig, MatchConfig, MatchingError, extract, match_images,
};

fn dataset(name: &str) -> (Vec<PathBuf>, Vec<Camera>) {
    let dir = shared_path(&format!("data/{name}"));
    let text = std::fs::read_to_string(dir.join("cameras.json")).unwrap();
    let records: Vec<CameraRecord> = serde_json::from_str(&text).unwrap();
    (
        records.iter().map(|r| dir.join(&r.image)).collect(),
        records.iter().map(|r| r.to_camera().unwrap()).collect(),
    )
}

/// A grey PNG image (only JPEG and PNG files reach the decoders).
fn write_png(path: &Path, width: usize, height: usize, pixel: impl Fn(usize, usize) -> u8) {
    use opencv::prelude::*;
    let mut bytes = Vec::with_capacity(width * height);
    for y in 0..height {
        for x in 0..width {
            bytes.push(pixel(x, y));
        }
    }
    let flat = opencv::core::Mat::from_slice(&bytes).unwrap();
    let img = flat.reshape(1, height as i32).unwrap().try_clone().unwrap();
    assert!(opencv::imgcodecs::imwrite_def(path.to_str().unwrap(), &img).unwrap());
}

#[test]
fn verified_matches_agree_with_ground_truth_geometry() {
    for (set, pairs) in [
        ("strecha_fountainP11", vec![(0, 1), (3, 4)]),
        ("middlebury_templeSR", vec![(0, 1)]),
    ] {
        let (images, cameras) = dataset(set);
        for detector in [Detector::Sift, Detector::Orb] {
            let mut config = MatchConfig::default();
            config.features.detector = detector;
            let (features, matches) = match_images(&images, Some(&pairs), &config).unwrap();
            assert_eq!(features.len(), images.len());
            for m in &matches {
                assert!(
                    m.len() >= 20,
                    "{set} {detector:?} ({}, {}): {} matches",
                    m.first,
                    m.second,
                    m.len()
                );
                let f = fundamental_from_cameras(&cameras[m.first], &cameras[m.second]);
                let good = m
                    .kp1
                    .iter()
                    .zip(&m.kp2)
                    .filter(|(a, b)| {
                        sampson_error(&f, &Point2::new(a[0], a[1]), &Point2::new(b[0], b[1]))
                            .unwrap()
                            < 4.0
                    })
                    .count();
                let frac = good as f64 / m.len() as f64;
                assert!(
                    frac >= 0.9,
                    "{set} {detector:?} ({}, {}): {frac:.3} within 4 px²",
                    m.first,
                    m.second
                );
            }
        }
    }
}

#[test]
fn keypoints_are_in_original_pixels_after_downscaling() {
    // A bright Gaussian blob centred at a non-integer pixel (OpenCV convention: pixel centres
    // at integers) in a 640×480 image, detected on a 320-px copy: SIFT must report it where it
    // is in the original image.
    let dir = posediff_fixtures::temp_dir("matching-blob");
    let path = dir.join("blob.png");
    let (cx, cy, sigma) = (301.3, 207.6, 6.0);
    write_png(&path, 640, 480, |x, y| {
        let d2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
        (30.0 + 200.0 * (-d2 / (2.0 * sigma * sigma)).exp()).round() as u8
    });
    let blob_at = |max_side: u32| -> [f64; 2] {
        let config = FeatureConfig {
            max_image_side: max_side,
            contrast_threshold: 0.01,
            ..FeatureConfig::default()
        };
        let f = extract(&path, &config).unwrap();
        assert_eq!((f.image_size.width(), f.image_size.height()), (640, 480));
        let dist = |k: &[f64; 2]| ((k[0] - cx).powi(2) + (k[1] - cy).powi(2)).sqrt();
        *f.keypoints
            .iter()
            .min_by(|a, b| dist(a).total_cmp(&dist(b)))
            .unwrap()
    };
    let full = blob_at(640);
    let half = blob_at(320);
    eprintln!(
        "blob at ({cx}, {cy}): full-size detection {full:?}, half-size detection mapped back {half:?}"
    );
    // SIFT's own localisation of the blob is within half a pixel...
    for k in [full, half] {
        assert!((k[0] - cx).abs() < 0.5 && (k[1] - cy).abs() < 0.5, "{k:?}");
    }
    // ...and the two detections agree after mapping: scaling pixel corners instead of pixel
    // centres (x / s) would put the half-size one 0.5 px down and right of the full-size one.
    assert!(
        (half[0] - full[0]).abs() < 0.25 && (half[1] - full[1]).abs() < 0.25,
        "{full:?} vs {half:?}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_featureless_image_has_no_matches_and_bad_input_is_named() {
    let dir = posediff_fixtures::temp_dir("matching-bad");
    let flat = dir.join("flat.png");
    write_png(&flat, 200, 150, |_, _| 128);
    let (images, _) = dataset("strecha_fountainP11");
    let (features, matches) = match_images(
        &[images[0].clone(), flat.clone()],
        None,
        &MatchConfig::default(),
    )
    .unwrap();
    assert!(features[1].keypoints.is_empty());
    assert!(matches[0].is_empty());

    let corrupt = dir.join("corrupt.jpg");
    std::fs::write(&corrupt, b"\xff\xd8\xff not really a jpeg").unwrap();
    let err = match_images(
        &[images[0].clone(), corrupt.clone()],
        None,
        &MatchConfig::default(),
    )
    .unwrap_err();
    assert!(
        matches!(&err, MatchingError::CorruptImage { path, .. } if path == &corrupt),
        "{err}"
    );
    assert!(err.to_string().contains("corrupt.jpg"));
    assert!(err.to_string().contains("JPEG"), "{err}");
    let missing = dir.join("missing.png");
    assert!(matches!(
        read_grey(&missing),
        Err(MatchingError::UnreadableImage { .. })
    ));
    assert!(matches!(
        match_images(&[images[0].clone()], None, &MatchConfig::default()),
        Err(MatchingError::TooFewImages { got: 1 })
    ));
    assert!(matches!(
        match_images(&images[..2], Some(&[(0, 0)]), &MatchConfig::default()),
        Err(MatchingError::InvalidPair { .. })
    ));
    let grey = read_grey(&flat).unwrap();
    let bad = FeatureConfig {
        max_keypoints: 0,
        ..FeatureConfig::default()
    };
    assert!(matches!(
        extract_from_grey(&grey, &bad),
        Err(MatchingError::InvalidConfig(_))
    ));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The size a JPEG's or PNG's header states is the size OpenCV decodes, on every shared image
/// (JPEG and PNG), and anything else has none.
#[test]
fn header_sizes_are_the_decoded_sizes() {
    use opencv::prelude::*;
    use posediff_matching::image_check::{decode, header_size, header_size_of};
    let mut checked = 0;
    for set in [
        "strecha_fountainP11",
        "middlebury_templeSR",
        "co3d_apple_posediffusion",
    ] {
        for (path, _) in dataset(set).0.iter().zip(0..3) {
            let bytes = std::fs::read(path).unwrap();
            let m = decode(path, opencv::imgcodecs::IMREAD_COLOR).unwrap();
            assert_eq!(
                header_size(&bytes),
                Some((m.cols() as u32, m.rows() as u32)),
                "{}",
                path.display()
            );
            assert_eq!(header_size_of(path).unwrap(), header_size(&bytes));
            checked += 1;
        }
    }
    assert_eq!(checked, 9);
    assert_eq!(header_size(b"GIF89a"), None);
    assert_eq!(header_size(&[0xFF, 0xD8, 0xFF, 0xD9]), None);
}
