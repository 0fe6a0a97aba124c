//! The fuzz inputs (`fuzz/seeds/<target>/`: the seeds of `fuzz/make_seeds.py` and the inputs
//! that once crashed; `fuzz/corpus/<target>/`: what the fuzzers kept, minimised) replayed
//! through the same harnesses as the fuzz targets, uninstrumented: what once passed keeps
//! passing. The seeds are also checked to reach the readers' success paths, so the fuzzers start
//! from inputs that parse.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};

fn inputs(kind: &str, target: &str) -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fuzz")
        .join(kind)
        .join(target);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    files
}

#[test]
fn the_harnesses_are_the_fuzz_targets_cargo_fuzz_builds() {
    // The `[[bin]]` names of fuzz/Cargo.toml (what `cargo xtask fuzz` runs) are the targets the
    // harnesses serve.
    let manifest = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/Cargo.toml"),
    )
    .unwrap();
    let mut bins = Vec::new();
    let mut in_bin = false;
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            in_bin = line == "[[bin]]";
        } else if in_bin && line.starts_with("name") {
            bins.push(line.split('"').nth(1).unwrap().to_owned());
        }
    }
    assert_eq!(bins, posediff::fuzzing::TARGETS);
}

#[test]
fn every_corpus_input_passes_its_harness() {
    for target in posediff::fuzzing::TARGETS {
        let seeds = inputs("seeds", target);
        assert!(!seeds.is_empty(), "no seeds for {target}");
        for f in seeds.into_iter().chain(inputs("corpus", target)) {
            let data = std::fs::read(&f).unwrap();
            posediff::fuzzing::run(target, &data);
        }
    }
}

#[test]
fn the_seeds_parse() {
    let seed = |target: &str, name: &str| {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../fuzz/seeds")
            .join(target)
            .join(name)
    };
    for name in ["small.pth", "small.safetensors"] {
        let t = posediff_diffusion::checkpoint::read_tensors(&seed("checkpoint", name)).unwrap();
        assert_eq!(t.len(), 2, "{name}");
    }
    let cams = posediff::io::export::read_cameras_json_partial(&seed("cameras_json", "three.json"))
        .unwrap();
    assert_eq!(cams.len(), 3);
    let co3d = posediff::io::co3d::load_annotations(&seed("co3d_annotations", "one.jgz")).unwrap();
    assert_eq!(co3d[0].frames.len(), 2);
    let files: Vec<PathBuf> = ["small.jpg", "small.png", "progressive.jpg"]
        .iter()
        .map(|n| seed("image", n))
        .collect();
    let (good, bad) = posediff::io::loader::check_images(&files);
    assert_eq!(good.len(), 3, "{bad:?}");
    // The COLMAP seeds: split as the harnesses split them.
    let text = std::fs::read(seed("colmap_text", "model.txt")).unwrap();
    let dir = std::env::temp_dir().join(format!("posediff-seed-colmap-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (name, part) in ["cameras.txt", "images.txt", "points3D.txt"]
        .iter()
        .zip(text.split(|&b| b == 0))
    {
        std::fs::write(dir.join(name), part).unwrap();
    }
    let model = posediff::io::colmap::ColmapModel::read_text(&dir).unwrap();
    assert_eq!(
        (model.cameras.len(), model.images.len(), model.points.len()),
        (2, 2, 1)
    );
    let bin = std::fs::read(seed("colmap_binary", "model.bin")).unwrap();
    let parts: Vec<&[u8]> = split_at_separator(&bin);
    for (name, part) in ["cameras.bin", "images.bin", "points3D.bin"]
        .iter()
        .zip(parts)
    {
        std::fs::write(dir.join(name), part).unwrap();
    }
    let model = posediff::io::colmap::ColmapModel::read_binary(&dir).unwrap();
    assert_eq!(
        (model.cameras.len(), model.images.len(), model.points.len()),
        (1, 1, 1)
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

fn split_at_separator(data: &[u8]) -> Vec<&[u8]> {
    let mut out = Vec::new();
    let mut rest = data;
    while let Some(cut) = rest.windows(8).position(|w| w == b"POSEDIFF") {
        out.push(&rest[..cut]);
        rest = &rest[cut + 8..];
    }
    out.push(rest);
    out
}
