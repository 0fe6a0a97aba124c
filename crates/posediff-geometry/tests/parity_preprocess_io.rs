//! The official crop boxes and keypoint mapping (`reference/full/preprocess_io.safetensors`):
//! `load_and_preprocess_images` crop boxes and scales, and `colmap_keypoint_to_pytorch3d`,
//! reproduced from OpenCV-convention keypoints (COLMAP − 0.5) through [`CenterCrop`].

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff_fixtures::{SafetensorsFixture, assert_close, shared_path};
use posediff_geometry::{CenterCrop, ImageSize};

#[test]
fn crop_boxes_and_keypoint_mapping_match_official() {
    let fx = SafetensorsFixture::open(&shared_path("reference/full/preprocess_io.safetensors"));
    let crops = [
        CenterCrop::official(ImageSize::new(400, 300).unwrap(), 224),
        CenterCrop::official(ImageSize::new(251, 410).unwrap(), 224),
    ];
    let boxes: Vec<f64> = crops
        .iter()
        .flat_map(|c| c.bbox_xyxy().map(f64::from))
        .collect();
    assert_eq!(boxes, fx.tensor("bboxes_xyxy").data);
    let scales: Vec<f64> = crops.iter().map(CenterCrop::scale).collect();
    assert_close(
        "resized_scales",
        &scales,
        &fx.tensor("resized_scales").data,
        0.0,
        1e-15,
    );

    // Matches of image ids 1 and 2 (COLMAP convention), converted to OpenCV keypoints.
    let (k1, k2) = (
        fx.rows::<2>("colmap_kp_img1"),
        fx.rows::<2>("colmap_kp_img2"),
    );
    let pairs = fx.tensor("colmap_matches_1_2");
    let mut ours1 = Vec::new();
    let mut ours2 = Vec::new();
    for m in pairs.chunks(2) {
        let to_cv = |kp: [f64; 2]| [kp[0] - 0.5, kp[1] - 0.5];
        ours1.extend(crops[0].to_model(to_cv(k1[m[0] as usize])));
        ours2.extend(crops[1].to_model(to_cv(k2[m[1] as usize])));
    }
    assert_close(
        "match_kp1",
        &ours1,
        &fx.tensor("match_kp1").data,
        1e-12,
        0.0,
    );
    assert_close(
        "match_kp2",
        &ours2,
        &fx.tensor("match_kp2").data,
        1e-12,
        0.0,
    );
    // And back to the original OpenCV keypoints.
    let back = crops[0].from_model([ours1[0], ours1[1]]);
    let first = k1[pairs.data[0] as usize];
    assert!((back[0] - (first[0] - 0.5)).abs() < 1e-9 && (back[1] - (first[1] - 0.5)).abs() < 1e-9);
}
