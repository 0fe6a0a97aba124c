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

/// The result files of an output folder, by name (those that exist).
fn results(out: &Path) -> Vec<(String, Vec<u8>)> {
    [
        "run.json",
        "cameras.json",
        "sparse/0/cameras.txt",
        "sparse/0/images.txt",
        "sparse/0/points3D.txt",
        "transforms.json",
        "sparse_pc.ply",
        "pytorch3d.json",
        "view.html",
    ]
    .iter()
    .filter_map(|f| std::fs::read(out.join(f)).ok().map(|b| (f.to_string(), b)))
    .collect()
}

/// A write that fails part-way (the viewer's thumbnails cannot be made) leaves the previous
/// results byte for byte and nothing staged; a write that succeeds replaces them whole (a
/// viewer the new run does not write is not left behind).
#[test]
fn a_failed_write_leaves_the_previous_results() {
    let dir = posediff_fixtures::temp_dir("outputs-failed-write");
    let (inputs, recon) = three_frames(&dir);
    let out = dir.join("out");
    let with_view = OutputOptions {
        view: true,
        ..OutputOptions::default()
    };
    write_outputs(&out, &recon, &inputs, &report(), &with_view, None).unwrap();
    let before = results(&out);
    assert!(before.iter().any(|(f, _)| f == "view.html"));
    let mut short = inputs.clone();
    short.files.pop();
    let failed = write_outputs(&out, &recon, &short, &report(), &with_view, None);
    assert!(failed.is_err(), "the thumbnails need every image");
    assert_eq!(results(&out), before);
    assert!(!out.join(".posediff-staging").exists());
    write(&out, &recon, &inputs, ImagesMode::Link);
    let after = results(&out);
    assert!(
        after.iter().all(|(f, _)| f != "view.html"),
        "a stale viewer is left"
    );
    assert!(after.iter().any(|(f, _)| f == "run.json"));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A commit stopped after each of its renames in turn (as a kill between two would leave it)
/// is, once `recover` has looked at the folder, one run's whole results: the earlier run's
/// until run.json is in place, the new one's after. Every step is tried, so a rename order
/// that `recover` cannot undo fails here, not by chance in the kill test below.
#[test]
fn a_commit_stopped_after_any_rename_is_recovered_to_one_run() {
    let dir = posediff_fixtures::temp_dir("outputs-stopped");
    let (inputs, recon) = three_frames(&dir);
    // The second run did not estimate the first image.
    let mut other = recon.clone();
    other.images[0].camera.camera = None;
    let with_view = OutputOptions {
        view: true,
        ..OutputOptions::default()
    };
    let write_to = |out: &Path, r: &Reconstruction| {
        write_outputs(out, r, &inputs, &report(), &with_view, None).unwrap();
        results(out)
    };
    let (a, b) = (
        write_to(&dir.join("a"), &recon),
        write_to(&dir.join("b"), &other),
    );
    assert_ne!(a, b, "the two runs must differ");
    assert!(a.iter().any(|(f, _)| f == "view.html"));
    let out = dir.join("out");
    let (mut stopped, mut steps) = (0, 1);
    loop {
        remove_dir(&out);
        write_to(&out, &recon);
        let done = posediff::io::outputs::write_outputs_interrupted(
            &out,
            &other,
            &inputs,
            &report(),
            &with_view,
            steps,
        )
        .unwrap();
        posediff::io::outputs::recover(&out).unwrap();
        let now = results(&out);
        assert!(
            now == a || now == b,
            "stopped after {steps} renames: {:?}",
            now.iter().map(|(f, _)| f).collect::<Vec<_>>()
        );
        assert!(!out.join(".posediff-previous").exists());
        if done {
            assert_eq!(now, b);
            break;
        }
        stopped += 1;
        steps += 1;
    }
    // Seven entries aside, the marker, seven in: each a place a kill can land.
    assert_eq!(stopped, 15, "stopping points");
    std::fs::remove_dir_all(&dir).unwrap();
}

fn remove_dir(path: &Path) {
    if path.exists() {
        std::fs::remove_dir_all(path).unwrap();
    }
}

/// Runs killed while they write (from the moment their staging folder appears, 0 to 6 ms on:
/// the whole write and the renames take about 4 ms here) leave, once the next run's recovery
/// has looked at the folder, one run's whole results: the earlier run's or the killed one's,
/// never a mix of the two.
#[test]
fn a_run_killed_while_writing_leaves_one_runs_results() {
    let dir = posediff_fixtures::temp_dir("outputs-killed");
    let (inputs, _) = three_frames(&dir);
    let images = inputs.folder.unwrap();
    let run = |out: &Path, focal: &str| {
        let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_posediff"));
        c.arg("estimate")
            .arg(&images)
            .args(["--focal-px", focal, "--quiet", "--out"])
            .arg(out)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null());
        c
    };
    // The two runs' results, each written alone.
    let (ref_a, ref_b) = (dir.join("a"), dir.join("b"));
    assert!(run(&ref_a, "900").status().unwrap().success());
    assert!(run(&ref_b, "1400").status().unwrap().success());
    let (a, b) = (results(&ref_a), results(&ref_b));
    let same = |x: &[(String, Vec<u8>)], y: &[(String, Vec<u8>)]| {
        // run.json has the run's times: present in both, the rest byte for byte.
        x.len() == y.len()
            && x.iter()
                .zip(y)
                .all(|(p, q)| p.0 == q.0 && (p.0 == "run.json" || p.1 == q.1))
    };
    assert!(!same(&a, &b), "the two runs must differ");
    let out = dir.join("out");
    assert!(run(&out, "900").status().unwrap().success());
    let staging = out.join(".posediff-staging");
    let mut caught = 0;
    for k in 0..12 {
        let mut child = run(&out, if k % 2 == 0 { "1400" } else { "900" })
            .spawn()
            .unwrap();
        while !staging.exists() && child.try_wait().unwrap().is_none() {
            std::thread::sleep(std::time::Duration::from_micros(100));
        }
        std::thread::sleep(std::time::Duration::from_micros(500 * k));
        let _ = child.kill();
        child.wait().unwrap();
        caught += usize::from(staging.exists() || out.join(".posediff-previous").exists());
        posediff::io::outputs::recover(&out).unwrap();
        let now = results(&out);
        assert!(
            same(&now, &a) || same(&now, &b),
            "kill {k}: {:?}",
            now.iter().map(|(f, _)| f).collect::<Vec<_>>()
        );
    }
    // The kills did land while the results were being written (the check could fail).
    assert!(
        caught >= 3,
        "only {caught} of 12 kills caught a run writing"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
