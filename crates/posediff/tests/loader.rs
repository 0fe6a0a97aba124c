//! The image loader against the official `load_and_preprocess_images`
//! (`reference/full/preprocess_io.safetensors`): crop boxes and the 224-px tensors of two
//! images, from raw pixels and through PNG files on disk.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use opencv::core::{Mat, Vector};
use opencv::prelude::*;
use posediff::PosediffError;
use posediff::io::loader::{image_files, load_images, preprocess_rgb};
use posediff_fixtures::{SafetensorsFixture, assert_close, shared_path};
use posediff_geometry::ImageSize;

const RAW: [(&str, u32, u32); 2] = [
    ("raw_a_h300_w400_uint8_HWC", 400, 300),
    ("raw_b_h410_w251_uint8_HWC", 251, 410),
];

fn fixture() -> SafetensorsFixture {
    SafetensorsFixture::open(&shared_path("reference/full/preprocess_io.safetensors"))
}

fn raw(fx: &SafetensorsFixture, name: &str) -> Vec<u8> {
    fx.tensor(name).data.iter().map(|v| *v as u8).collect()
}

#[test]
fn preprocessing_matches_the_official_loader() {
    let fx = fixture();
    let expected = fx.tensor("out_images").data;
    let plane = 3 * 224 * 224;
    for (k, (name, w, h)) in RAW.iter().enumerate() {
        let (crop, pixels) = preprocess_rgb(&raw(&fx, name), ImageSize::new(*w, *h).unwrap(), 224);
        let boxes = fx.tensor("bboxes_xyxy").data;
        assert_eq!(
            crop.bbox_xyxy().map(f64::from).to_vec(),
            boxes[4 * k..4 * k + 4]
        );
        let ours: Vec<f64> = pixels.iter().map(|v| f64::from(*v)).collect();
        // float32 bilinear in the reference: ~1 ulp of values ≤ 1.
        assert_close(
            &format!("out_images[{k}]"),
            &ours,
            &expected[k * plane..(k + 1) * plane],
            1e-6,
            0.0,
        );
    }
}

#[test]
fn files_are_found_sorted_read_as_rgb_and_bad_input_is_named() {
    let fx = fixture();
    let dir = std::env::temp_dir().join(format!("posediff-loader-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Written as b then a, upper-case extension for one: the loader sorts and accepts both.
    for (name, file) in [(RAW[1].0, "b.PNG"), (RAW[0].0, "a.png")] {
        let (_, w, h) = RAW.iter().find(|r| r.0 == name).copied().unwrap();
        let rgb = raw(&fx, name);
        let bgr: Vec<u8> = rgb.chunks(3).flat_map(|p| [p[2], p[1], p[0]]).collect();
        let mat = Mat::new_rows_cols_with_data(h as i32, (w * 3) as i32, &bgr)
            .unwrap()
            .reshape(3, h as i32)
            .unwrap()
            .try_clone()
            .unwrap();
        opencv::imgcodecs::imwrite(dir.join(file).to_str().unwrap(), &mat, &Vector::new()).unwrap();
    }
    std::fs::write(dir.join("notes.txt"), "not an image").unwrap();
    let files = image_files(&dir).unwrap();
    let names: Vec<_> = files
        .iter()
        .map(|p| p.file_name().unwrap().to_str().unwrap().to_owned())
        .collect();
    assert_eq!(names, ["a.png", "b.PNG"]);
    let loaded = load_images(&files).unwrap();
    let expected = fx.tensor("out_images").data;
    let ours: Vec<f64> = loaded
        .iter()
        .flat_map(|l| l.pixels.iter().map(|v| f64::from(*v)))
        .collect();
    assert_close("out_images via PNG files", &ours, &expected, 1e-6, 0.0);

    let corrupt = dir.join("c.jpg");
    std::fs::write(&corrupt, b"\xff\xd8\xff broken").unwrap();
    let err = load_images(std::slice::from_ref(&corrupt)).unwrap_err();
    assert!(
        matches!(
            &err,
            PosediffError::Matching(posediff_matching::MatchingError::CorruptImage { path, .. })
                if path == &corrupt
        ),
        "{err}"
    );
    assert!(err.to_string().contains("truncated JPEG"), "{err}");
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    assert!(matches!(
        image_files(&empty),
        Err(PosediffError::NoImages(_))
    ));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn rgb_written_as_png_reads_back_pixel_for_pixel() {
    let fx = fixture();
    let dir = std::env::temp_dir().join(format!("posediff-loader-png-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (name, w, h) = RAW[1];
    let rgb = raw(&fx, name);
    let path = dir.join("b.png");
    posediff::io::loader::write_rgb_png(&path, w, h, &rgb).unwrap();
    let (size, back) = posediff::io::loader::read_rgb(&path).unwrap();
    assert_eq!(size, ImageSize::new(w, h).unwrap());
    assert!(back == rgb, "pixels changed through the PNG");
    // A buffer of the wrong length is refused, naming both sizes.
    let err = posediff::io::loader::write_rgb_png(&path, w, h + 1, &rgb).unwrap_err();
    assert!(err.to_string().contains(&format!("{w}×{}", h + 1)), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
