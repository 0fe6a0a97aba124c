//! The output folder: `out/images` in each mode, transforms.json paths that resolve, the checks
//! made before any computation.

#![allow(clippy::unwrap_used)]

use std::path::Path;

use posediff::estimate::run_report::{MethodReport, RunReport};
use posediff::io::export::{ImageCamera, NerfstudioTransforms, read_cameras_json_partial};
use posediff::io::outputs::{
    ImagesMode, InputImages, OutputOptions, prepare_output_dir, write_outputs,
};
use posediff::reconstruction::Reconstruction;
use posediff_fixtures::shared_path;

/// Three apple frames (copied into `dir/in`) and their ground-truth cameras.
fn three_frames(dir: &Path) -> (InputImages, Reconstruction) {
    let set = shared_path("data/co3d_apple_posediffusion");
    let cams = read_cameras_json_partial(&set.join("cameras.json")).unwrap();
    let input = dir.join("in");
    std::fs::create_dir_all(&input).unwrap();
    let mut files = Vec::new();
    let mut images = Vec::new();
    for c in cams.iter().take(3) {
        let name = Path::new(&c.image).file_name().unwrap();
        std::fs::copy(set.join(&c.image), input.join(name)).unwrap();
        files.push(input.join(name));
        images.push(ImageCamera {
            image: name.to_string_lossy().into_owned(),
            ..c.clone()
        });
    }
    (
        InputImages {
            files,
            folder: Some(input),
            folder_given: true,
        },
        Reconstruction::from_cameras(images),
    )
}

fn report() -> RunReport {
    RunReport::new(
        Vec::new(),
        MethodReport::Geometric {
            refine: posediff::estimate::run::RefineMode::None,
            report: Box::default(),
        },
    )
}

fn options(images: ImagesMode) -> OutputOptions {
    OutputOptions {
        images,
        view: false,
        ..OutputOptions::default()
    }
}

/// `write_outputs` without the viewer, thumbnails made there.
fn write(out: &Path, recon: &Reconstruction, inputs: &InputImages, mode: ImagesMode) {
    write_outputs(out, recon, inputs, &report(), &options(mode), None).unwrap();
}

fn frame_paths(out: &Path) -> Vec<String> {
    let t: NerfstudioTransforms =
        serde_json::from_str(&std::fs::read_to_string(out.join("transforms.json")).unwrap())
            .unwrap();
    t.frames.into_iter().map(|f| f.file_path).collect()
}

#[test]
fn images_are_linked_copied_or_named_absolutely_and_every_frame_path_resolves() {
    let dir = posediff_fixtures::temp_dir("outputs-modes");
    let (inputs, recon) = three_frames(&dir);
    // A folder: one link to it.
    let out = dir.join("link");
    prepare_output_dir(&out, &inputs, ImagesMode::Link).unwrap();
    write(&out, &recon, &inputs, ImagesMode::Link);
    assert!(out.join("images").is_symlink());
    for p in frame_paths(&out) {
        assert!(p.starts_with("images/"), "{p}");
        assert!(out.join(&p).is_file(), "{p}");
    }
    // Files one by one: a real folder with a link per image.
    let files = InputImages {
        folder_given: false,
        ..inputs.clone()
    };
    let out = dir.join("files");
    write(&out, &recon, &files, ImagesMode::Link);
    assert!(out.join("images").is_dir() && !out.join("images").is_symlink());
    for p in frame_paths(&out) {
        assert!(out.join(&p).is_symlink(), "{p}");
        assert!(out.join(&p).is_file(), "{p}");
    }
    // Copies.
    let out = dir.join("copy");
    write(&out, &recon, &inputs, ImagesMode::Copy);
    for (p, f) in frame_paths(&out).iter().zip(&inputs.files) {
        assert!(!out.join(p).is_symlink());
        assert_eq!(
            std::fs::read(out.join(p)).unwrap(),
            std::fs::read(f).unwrap()
        );
    }
    // None: absolute paths.
    let out = dir.join("none");
    write(&out, &recon, &inputs, ImagesMode::None);
    assert!(!out.join("images").exists());
    for p in frame_paths(&out) {
        assert!(
            Path::new(&p).is_absolute() && Path::new(&p).is_file(),
            "{p}"
        );
    }
    // The output folder holding the images already (scene/images + scene/sparse/0).
    let out = dir.clone();
    let scene_inputs = InputImages {
        folder: Some(dir.join("images")),
        files: inputs
            .files
            .iter()
            .map(|f| dir.join("images").join(f.file_name().unwrap()))
            .collect(),
        folder_given: true,
    };
    std::fs::rename(dir.join("in"), dir.join("images")).unwrap();
    write(&out, &recon, &scene_inputs, ImagesMode::Link);
    assert!(!out.join("images").is_symlink());
    assert_eq!(frame_paths(&out).len(), 3);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_unusable_output_folder_fails_before_any_work() {
    let dir = posediff_fixtures::temp_dir("outputs-bad-out");
    let (inputs, _) = three_frames(&dir);
    // --out is a file.
    let file = dir.join("file");
    std::fs::write(&file, "x").unwrap();
    let e = prepare_output_dir(&file, &inputs, ImagesMode::Link)
        .unwrap_err()
        .to_string();
    assert!(e.contains("existing file"), "{e}");
    // out/images/<name> is someone's file that is not our image.
    let out = dir.join("taken");
    std::fs::create_dir_all(out.join("images")).unwrap();
    let name = inputs.files[0].file_name().unwrap();
    std::fs::write(out.join("images").join(name), "not the image").unwrap();
    let e = prepare_output_dir(&out, &inputs, ImagesMode::Link)
        .unwrap_err()
        .to_string();
    assert!(e.contains("is not a link"), "{e}");
    // Copy and none modes do not mind.
    prepare_output_dir(&out, &inputs, ImagesMode::Copy).unwrap();
    prepare_output_dir(&out, &inputs, ImagesMode::None).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_earlier_runs_link_is_replaced_never_written_through() {
    let dir = posediff_fixtures::temp_dir("outputs-relink");
    let (inputs, recon) = three_frames(&dir);
    let elsewhere = dir.join("elsewhere");
    std::fs::create_dir_all(&elsewhere).unwrap();
    let out = dir.join("out");
    std::fs::create_dir_all(&out).unwrap();
    std::os::unix::fs::symlink(&elsewhere, out.join("images")).unwrap();
    // Files one by one: a real folder replaces the link; the other folder stays empty.
    let files = InputImages {
        folder_given: false,
        ..inputs.clone()
    };
    prepare_output_dir(&out, &files, ImagesMode::Link).unwrap();
    write(&out, &recon, &files, ImagesMode::Link);
    assert!(!out.join("images").is_symlink() && out.join("images").is_dir());
    assert_eq!(std::fs::read_dir(&elsewhere).unwrap().count(), 0);
    // A folder: the link points at it.
    std::fs::remove_dir_all(out.join("images")).unwrap();
    std::os::unix::fs::symlink(&elsewhere, out.join("images")).unwrap();
    write(&out, &recon, &inputs, ImagesMode::Link);
    assert_eq!(
        out.join("images").canonicalize().unwrap(),
        inputs.folder.as_ref().unwrap().canonicalize().unwrap()
    );
    assert_eq!(std::fs::read_dir(&elsewhere).unwrap().count(), 0);
    for p in frame_paths(&out) {
        assert!(out.join(&p).is_file(), "{p}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
