//! The harnesses of the fuzz targets (`fuzz/`, libFuzzer through cargo-fuzz), shared with the
//! corpus replay test that CI runs (`tests/fuzz_corpus.rs`). Each takes arbitrary bytes, feeds
//! them to one reader as a file, and checks what must hold whatever the bytes: no panic (the
//! fuzzer reports it), and for what parses, the reader's own guarantees (finite cameras, a
//! COLMAP model that writes and reads back equal, a structurally checked image that decodes).

use std::path::PathBuf;

use crate::io::colmap::{ColmapFormat, ColmapModel};

/// The readers that have a fuzz target.
pub const TARGETS: [&str; 6] = [
    "checkpoint",
    "cameras_json",
    "colmap_text",
    "colmap_binary",
    "co3d_annotations",
    "image",
];

/// A scratch folder of this process (tmpfs when there is one).
fn scratch() -> PathBuf {
    let base = if std::path::Path::new("/dev/shm").is_dir() {
        PathBuf::from("/dev/shm")
    } else {
        std::env::temp_dir()
    };
    let dir = base.join(format!("posediff-fuzz-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    dir
}

fn file_with(name: &str, data: &[u8]) -> PathBuf {
    let path = scratch().join(name);
    if std::fs::write(&path, data).is_err() {
        // A full scratch disk is not the reader's fault.
        return PathBuf::from("/nonexistent");
    }
    path
}

/// Runs the harness of `target` on `data`.
///
/// # Panics
/// When an invariant of the reader does not hold (that is the finding), or for an unknown
/// target.
pub fn run(target: &str, data: &[u8]) {
    match target {
        "checkpoint" => checkpoint(data),
        "cameras_json" => cameras_json(data),
        "colmap_text" => colmap_text(data),
        "colmap_binary" => colmap_binary(data),
        "co3d_annotations" => co3d_annotations(data),
        "image" => image(data),
        other => panic!("no fuzz target {other}"),
    }
}

/// `.pth` (zip + pickle) and safetensors checkpoints: read, then validated as PoseDiffusion.
pub fn checkpoint(data: &[u8]) {
    let path = file_with("checkpoint.pth", data);
    if let Ok(tensors) = posediff_diffusion::checkpoint::read_tensors(&path) {
        let _ = posediff_diffusion::checkpoint::Checkpoint::from_tensors(tensors);
    }
}

/// cameras.json: whatever parses is a set of finite cameras.
pub fn cameras_json(data: &[u8]) {
    let path = file_with("cameras.json", data);
    if let Ok(entries) = crate::io::export::read_cameras_json_partial(&path) {
        for e in entries {
            if let Some(c) = e.camera {
                assert!(c.cam_from_world.ensure_finite().is_ok(), "non-finite pose");
                let k = c.intrinsics.matrix();
                assert!(k.iter().all(|v| v.is_finite()), "non-finite K");
            }
        }
    }
}

/// The three files of a text model from one input: split at the first two `\0` bytes.
pub fn colmap_text(data: &[u8]) {
    let mut parts = data.splitn(3, |&b| b == 0);
    let dir = scratch().join("colmap_text");
    let _ = std::fs::create_dir_all(&dir);
    for name in ["cameras.txt", "images.txt", "points3D.txt"] {
        let _ = std::fs::write(dir.join(name), parts.next().unwrap_or_default());
    }
    round_trip(ColmapModel::read_text(&dir), ColmapFormat::Text);
}

/// The three files of a binary model from one input: split at the first two occurrences of
/// the separator `"POSEDIFF"`.
pub fn colmap_binary(data: &[u8]) {
    let dir = scratch().join("colmap_binary");
    let _ = std::fs::create_dir_all(&dir);
    let mut rest = data;
    for name in ["cameras.bin", "images.bin", "points3D.bin"] {
        let cut = rest
            .windows(8)
            .position(|w| w == b"POSEDIFF")
            .unwrap_or(rest.len());
        let _ = std::fs::write(dir.join(name), &rest[..cut]);
        rest = rest.get(cut + 8..).unwrap_or_default();
    }
    round_trip(ColmapModel::read_binary(&dir), ColmapFormat::Binary);
}

/// A model that reads writes back and reads again equal, and converts without panicking.
fn round_trip(model: crate::Result<ColmapModel>, format: ColmapFormat) {
    let Ok(model) = model else { return };
    let dir = scratch().join("colmap_round_trip");
    let _ = std::fs::remove_dir_all(&dir);
    if model.write(&dir, format).is_ok() {
        // Names with a NUL or line breaks cannot be written back in COLMAP's formats.
        let writable = model.images.iter().all(|im| {
            !im.name.contains(['\0', '\n', '\r'])
                && im.name.trim() == im.name
                && !im.name.is_empty()
        });
        if writable {
            let back = ColmapModel::read(&dir);
            assert!(back.is_ok(), "a written model does not read back: {back:?}");
            if let Ok(back) = back {
                assert_eq!(back, model, "the model changed in a round trip");
            }
        }
    }
    let _ = model.to_reconstruction(&dir);
    let _ = model.recomputed_mean_error(&dir);
}

/// CO3D `.jgz` annotations (gzip JSON).
pub fn co3d_annotations(data: &[u8]) {
    let path = file_with("annotations.jgz", data);
    if let Ok(sequences) = crate::io::co3d::load_annotations(&path) {
        for s in &sequences {
            for f in &s.frames {
                let _ = f.cam_from_world();
            }
        }
    }
}

/// Image files: the structural check, then OpenCV's decoder on what passes.
pub fn image(data: &[u8]) {
    let path = file_with("image.bin", data);
    let (good, bad) = crate::io::loader::check_images(std::slice::from_ref(&path));
    assert_eq!(good.len() + bad.len(), 1);
    if !good.is_empty() {
        let _ = crate::io::loader::read_rgb(&path);
    }
}
