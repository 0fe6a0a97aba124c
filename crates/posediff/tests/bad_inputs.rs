//! Bad inputs, as a new user gives them: every case exits non-zero with a message that names
//! the problem, never a panic, and the checks that need no computation fail before any
//! expensive stage starts (no `stage:` line in the info log: no image loading or feature
//! extraction) and before anything is written.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::ffi::OsString;
use std::os::unix::ffi::OsStrExt as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use posediff_fixtures::shared_path;

fn apple() -> PathBuf {
    shared_path("data/co3d_apple_posediffusion/images")
}

fn apple_files() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(apple())
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    v
}

/// One bad invocation: its arguments, a piece of the message it must print, and whether it
/// must fail before any computation (no stage started, nothing written to `--out`).
struct Case {
    name: &'static str,
    args: Vec<OsString>,
    message: &'static str,
    early: bool,
}

fn case(name: &'static str, args: &[&dyn AsRef<std::ffi::OsStr>], message: &'static str) -> Case {
    owned_case(
        name,
        args.iter().map(|a| a.as_ref().to_owned()).collect(),
        message,
    )
}

fn owned_case(name: &'static str, args: Vec<std::ffi::OsString>, message: &'static str) -> Case {
    Case {
        name,
        args,
        message,
        early: true,
    }
}

fn run_cases(cases: &[Case], out: Option<&Path>) {
    for c in cases {
        let start = Instant::now();
        let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
            .args(&c.args)
            .env("RUST_BACKTRACE", "0")
            .env("RUST_LOG", "info")
            .output()
            .unwrap();
        let seconds = start.elapsed().as_secs_f64();
        let stderr = String::from_utf8_lossy(&r.stderr);
        assert!(!r.status.success(), "{}: exited successfully", c.name);
        assert!(
            !stderr.contains("panicked"),
            "{}: panicked: {stderr}",
            c.name
        );
        assert!(
            stderr.contains(c.message),
            "{}: the message does not say {:?}: {stderr}",
            c.name,
            c.message
        );
        if c.early {
            assert!(
                !stderr.contains(posediff::estimate::run::WORK_STARTS),
                "{}: failed only after a stage started ({seconds:.1} s): {stderr}",
                c.name
            );
            if let Some(out) = out {
                assert!(
                    !out.join("cameras.json").exists() && !out.join("run.json").exists(),
                    "{}: wrote outputs before failing",
                    c.name
                );
            }
        }
    }
}

fn write(path: &Path, bytes: &[u8]) -> PathBuf {
    std::fs::write(path, bytes).unwrap();
    path.to_owned()
}

/// A folder with three good apple frames and `extra` (name, bytes).
fn folder_with(dir: &Path, tag: &str, extra: (&str, &[u8])) -> PathBuf {
    let f = dir.join(tag);
    std::fs::create_dir_all(&f).unwrap();
    for p in apple_files().iter().take(3) {
        std::fs::copy(p, f.join(p.file_name().unwrap())).unwrap();
    }
    write(&f.join(extra.0), extra.1);
    f
}

#[test]
fn bad_images_are_named_before_any_work() {
    let dir = posediff_fixtures::temp_dir("bad-images");
    let out = dir.join("out");
    let jpeg = std::fs::read(&apple_files()[0]).unwrap();
    let png =
        std::fs::read(shared_path("data/middlebury_templeSR/images").join("templeSR0001.png"))
            .unwrap();
    let mut bad_crc = png.clone();
    let mid = bad_crc.len() / 2;
    bad_crc[mid] ^= 0x55;
    let truncated_jpeg = folder_with(&dir, "tj", ("zz.jpg", &jpeg[..jpeg.len() / 2]));
    let truncated_png = folder_with(&dir, "tp", ("zz.png", &png[..png.len() - 30]));
    let crc = folder_with(&dir, "crc", ("zz.png", &bad_crc));
    let empty_file = folder_with(&dir, "ef", ("zz.jpg", b""));
    let text = folder_with(&dir, "tx", ("zz.jpg", b"this is not an image\n"));
    let no_eoi = folder_with(&dir, "ne", ("zz.jpg", &jpeg[..jpeg.len() - 2]));
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let single = dir.join("single");
    std::fs::create_dir_all(&single).unwrap();
    std::fs::copy(&apple_files()[0], single.join("a.jpg")).unwrap();
    let twin_a = dir.join("twin_a");
    let twin_b = dir.join("twin_b");
    for t in [&twin_a, &twin_b] {
        std::fs::create_dir_all(t).unwrap();
        std::fs::copy(&apple_files()[0], t.join("same.jpg")).unwrap();
    }
    let dangling = folder_with(&dir, "dl", ("keep.txt", b""));
    std::os::unix::fs::symlink(dir.join("moved-away.jpg"), dangling.join("zz.jpg")).unwrap();
    let not_utf8 = folder_with(&dir, "nu", ("keep.txt", b""));
    std::fs::copy(
        &apple_files()[4],
        not_utf8.join(std::ffi::OsStr::from_bytes(b"caf\xe9.jpg")),
    )
    .unwrap();
    let files = apple_files();
    let cases = vec![
        case(
            "dangling symbolic link",
            &[&"estimate", &dangling, &"--out", &out],
            "zz.jpg: a symbolic link to a missing file",
        ),
        case(
            "name that is not UTF-8",
            &[&"estimate", &not_utf8, &"--out", &out],
            "is not valid UTF-8",
        ),
        case(
            "missing path",
            &[&"estimate", &dir.join("nope"), &"--out", &out],
            "no such file or directory",
        ),
        case(
            "missing file among files",
            &[
                &"estimate",
                &files[0],
                &dir.join("gone.jpg"),
                &"--out",
                &out,
            ],
            "no such file or directory",
        ),
        case(
            "empty folder",
            &[&"estimate", &empty, &"--out", &out],
            "no .png/.jpg/.jpeg images",
        ),
        case(
            "one image",
            &[&"estimate", &single, &"--out", &out],
            "need at least 2 images, got 1",
        ),
        case(
            "truncated JPEG",
            &[&"estimate", &truncated_jpeg, &"--out", &out],
            "zz.jpg: truncated JPEG",
        ),
        case(
            "JPEG without its end marker",
            &[&"estimate", &no_eoi, &"--out", &out],
            "zz.jpg: truncated JPEG",
        ),
        case(
            "truncated PNG",
            &[&"estimate", &truncated_png, &"--out", &out],
            "zz.png: truncated PNG",
        ),
        case(
            "PNG with a bad CRC",
            &[&"estimate", &crc, &"--out", &out],
            "fails its CRC",
        ),
        case(
            "empty image file",
            &[&"estimate", &empty_file, &"--out", &out],
            "zz.jpg: empty file",
        ),
        case(
            "text named .jpg",
            &[&"estimate", &text, &"--out", &out],
            "not a JPEG or PNG image",
        ),
        case(
            "bad image hint",
            &[&"estimate", &truncated_jpeg, &"--out", &out],
            "--skip-bad-images",
        ),
        case(
            "folder among files",
            &[&"estimate", &files[0], &empty, &"--out", &out],
            "is a folder",
        ),
        case(
            "same name twice",
            &[
                &"estimate",
                &twin_a.join("same.jpg"),
                &twin_b.join("same.jpg"),
                &files[1],
                &"--out",
                &out,
            ],
            "have the same name",
        ),
        case(
            "skipping leaves one",
            &[
                &"estimate",
                &files[0],
                &dir.join("tj/zz.jpg"),
                &"--skip-bad-images",
                &"--out",
                &out,
            ],
            "after skipping 1 unusable",
        ),
    ];
    run_cases(&cases, Some(&out));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_options_fail_before_any_work() {
    let dir = posediff_fixtures::temp_dir("bad-options");
    let out = dir.join("out");
    let file_out = write(&dir.join("a-file"), b"x");
    let a = apple();
    let init = shared_path("data/co3d_apple_posediffusion/cameras.json");
    let cases = vec![
        case(
            "focal 0",
            &[&"estimate", &a, &"--out", &out, &"--focal-px", &"0"],
            "--focal-px must be a positive",
        ),
        case(
            "focal nan",
            &[&"estimate", &a, &"--out", &out, &"--focal-px", &"nan"],
            "--focal-px must be a positive",
        ),
        case(
            "focal inf",
            &[&"estimate", &a, &"--out", &out, &"--focal-px", &"inf"],
            "--focal-px must be a positive",
        ),
        case(
            "focal negative",
            &[&"estimate", &a, &"--out", &out, &"--focal-px=-5"],
            "--focal-px must be a positive",
        ),
        case(
            "focal text",
            &[&"estimate", &a, &"--out", &out, &"--focal-px", &"wide"],
            "invalid value 'wide'",
        ),
        case(
            "no samples",
            &[&"estimate", &a, &"--out", &out, &"--samples", &"0"],
            "--samples must be at least 1",
        ),
        case(
            "start step 100",
            &[
                &"estimate",
                &a,
                &"--out",
                &out,
                &"--init",
                &init,
                &"--start-step",
                &"100",
            ],
            "--start-step must be 0-99",
        ),
        case(
            "start step without init",
            &[&"estimate", &a, &"--out", &out, &"--start-step", &"10"],
            "--start-step needs --init",
        ),
        case(
            "pairs rule",
            &[&"estimate", &a, &"--out", &out, &"--pairs", &"everything"],
            "--pairs",
        ),
        case(
            "refine mode",
            &[&"estimate", &a, &"--out", &out, &"--refine", &"harder"],
            "invalid value 'harder'",
        ),
        case(
            "matcher",
            &[&"estimate", &a, &"--out", &out, &"--matcher", &"magic"],
            "invalid value 'magic'",
        ),
        case(
            "focal and intrinsics",
            &[
                &"estimate",
                &a,
                &"--out",
                &out,
                &"--focal-px",
                &"500",
                &"--intrinsics",
                &init,
            ],
            "cannot be used with",
        ),
        case(
            "out is a file",
            &[&"estimate", &a, &"--out", &file_out],
            "is an existing file",
        ),
        case(
            "out cannot be created",
            &[&"estimate", &a, &"--out", &"/proc/posediff-out"],
            "cannot write /proc/posediff-out",
        ),
        case(
            "cuda without weights",
            &[&"estimate", &a, &"--out", &out, &"--device", &"cuda"],
            "needs --weights",
        ),
        case(
            "colmap format",
            &[&"estimate", &a, &"--out", &out, &"--colmap-format", &"xml"],
            "invalid value 'xml'",
        ),
        case(
            "images mode",
            &[&"estimate", &a, &"--out", &out, &"--images", &"move"],
            "invalid value 'move'",
        ),
    ];
    run_cases(&cases, Some(&out));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The tiny random-weight checkpoint with `edit` applied to its tensors, saved as safetensors.
fn edited_checkpoint(
    path: &Path,
    edit: impl FnOnce(&mut std::collections::HashMap<String, candle_core::Tensor>),
) -> PathBuf {
    let mut t = candle_core::safetensors::load(
        shared_path("reference/tiny/model_tiny.safetensors"),
        &candle_core::Device::Cpu,
    )
    .unwrap();
    edit(&mut t);
    candle_core::safetensors::save(&t, path).unwrap();
    path.to_owned()
}

#[test]
fn broken_checkpoints_are_reported_at_load() {
    let dir = posediff_fixtures::temp_dir("bad-weights");
    let out = dir.join("out");
    let a = apple();
    let text = write(&dir.join("weights.pth"), b"not a checkpoint");
    let tiny = std::fs::read(shared_path("reference/tiny/model_tiny.safetensors")).unwrap();
    let truncated = write(&dir.join("truncated.safetensors"), &tiny[..tiny.len() / 3]);
    let zip = write(
        &dir.join("zip.pth"),
        b"PK\x03\x04 garbage that is not a zip archive",
    );
    let key = "image_feature_extractor._net.patch_embed.proj.weight";
    let nan = edited_checkpoint(&dir.join("nan.safetensors"), |t| {
        let w = &t[key];
        let bad = (w * f64::NAN).unwrap();
        t.insert(key.to_owned(), bad);
    });
    let missing = edited_checkpoint(&dir.join("missing.safetensors"), |t| {
        t.remove(key);
    });
    let shape = edited_checkpoint(&dir.join("shape.safetensors"), |t| {
        let w = t[key].flatten_all().unwrap();
        t.insert(key.to_owned(), w);
    });
    let cases = vec![
        case(
            "missing weights",
            &[
                &"estimate",
                &a,
                &"--out",
                &out,
                &"--weights",
                &dir.join("none.pth"),
            ],
            "--weights: no such file",
        ),
        case(
            "not a checkpoint",
            &[&"estimate", &a, &"--out", &out, &"--weights", &text],
            "neither a PyTorch",
        ),
        case(
            "truncated safetensors",
            &[&"estimate", &a, &"--out", &out, &"--weights", &truncated],
            "truncated.safetensors",
        ),
        case(
            "broken zip",
            &[&"estimate", &a, &"--out", &out, &"--weights", &zip],
            "zip.pth",
        ),
        case(
            "NaN weights",
            &[&"estimate", &a, &"--out", &out, &"--weights", &nan],
            "NaN or infinite values in: image_feature_extractor._net.patch_embed.proj.weight",
        ),
        case(
            "missing key",
            &[&"estimate", &a, &"--out", &out, &"--weights", &missing],
            "missing: image_feature_extractor._net.patch_embed.proj.weight",
        ),
        case(
            "wrong shape",
            &[&"estimate", &a, &"--out", &out, &"--weights", &shape],
            "wrong shape: image_feature_extractor._net.patch_embed.proj.weight",
        ),
    ];
    run_cases(&cases, None);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The apple frames' file names, and 20 names of images that are not there.
fn apple_and_other_names() -> (Vec<String>, Vec<String>) {
    let names = apple_files()
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    (names, (0..20).map(|k| format!("other{k:03}.jpg")).collect())
}

/// cameras.json entries for `names` (the apple ground truth's cameras, renamed).
fn cameras_json(path: &Path, names: &[&str], estimated: bool) -> PathBuf {
    let truth: Vec<serde_json::Value> = serde_json::from_str(
        &std::fs::read_to_string(shared_path("data/co3d_apple_posediffusion/cameras.json"))
            .unwrap(),
    )
    .unwrap();
    let entries: Vec<serde_json::Value> = names
        .iter()
        .zip(truth.iter().cycle())
        .map(|(n, t)| {
            let mut t = t.clone();
            t["image"] = serde_json::json!(n);
            if !estimated {
                t["estimated"] = serde_json::json!(false);
                t["K"] = serde_json::Value::Null;
                t["R"] = serde_json::Value::Null;
                t["t"] = serde_json::Value::Null;
            }
            t
        })
        .collect();
    write(
        path,
        serde_json::to_string_pretty(&entries).unwrap().as_bytes(),
    )
}

#[test]
fn per_image_files_must_name_the_images() {
    let dir = posediff_fixtures::temp_dir("bad-records");
    let out = dir.join("out");
    let a = apple();
    let (names, other) = apple_and_other_names();
    let other_refs: Vec<&str> = other.iter().map(String::as_str).collect();
    let name_refs: Vec<&str> = names.iter().map(String::as_str).collect();
    let foreign = cameras_json(&dir.join("foreign.json"), &other_refs, true);
    let partial = cameras_json(&dir.join("partial.json"), &name_refs[..19], true);
    let twice = cameras_json(
        &dir.join("twice.json"),
        &[&name_refs[..20], &[name_refs[0]]].concat(),
        true,
    );
    let unestimated = cameras_json(&dir.join("unestimated.json"), &name_refs, false);
    let malformed = write(&dir.join("malformed.json"), b"[{\"image\": ");
    let cases = vec![
        case(
            "init for other images",
            &[&"estimate", &a, &"--out", &out, &"--init", &foreign],
            "does not match the images by name",
        ),
        case(
            "init names listed",
            &[&"estimate", &a, &"--out", &out, &"--init", &foreign],
            "other000.jpg",
        ),
        case(
            "init malformed",
            &[&"estimate", &a, &"--out", &out, &"--init", &malformed],
            "reading --init",
        ),
        case(
            "init missing",
            &[
                &"estimate",
                &a,
                &"--out",
                &out,
                &"--init",
                &dir.join("gone.json"),
            ],
            "gone.json",
        ),
        case(
            "init nothing estimated",
            &[&"estimate", &a, &"--out", &out, &"--init", &unestimated],
            "none of its cameras is estimated",
        ),
        case(
            "intrinsics partial",
            &[&"estimate", &a, &"--out", &out, &"--intrinsics", &partial],
            "1 image(s) have no entry",
        ),
        case(
            "intrinsics foreign",
            &[&"estimate", &a, &"--out", &out, &"--intrinsics", &foreign],
            "20 entr(y/ies) name no input image",
        ),
        case(
            "intrinsics twice",
            &[&"estimate", &a, &"--out", &out, &"--intrinsics", &twice],
            "both name image",
        ),
    ];
    run_cases(&cases, Some(&out));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn other_commands_name_what_is_wrong() {
    let dir = posediff_fixtures::temp_dir("bad-commands");
    let gt = shared_path("data/co3d_apple_posediffusion/cameras.json");
    let (names, other) = apple_and_other_names();
    let other_refs: Vec<&str> = other.iter().map(String::as_str).collect();
    let name_refs: Vec<&str> = names.iter().map(String::as_str).collect();
    let foreign = cameras_json(&dir.join("foreign.json"), &other_refs, true);
    let fewer = cameras_json(&dir.join("fewer.json"), &name_refs[..10], true);
    let malformed = write(&dir.join("malformed.json"), b"{");
    let model = dir.join("model");
    std::fs::create_dir_all(&model).unwrap();
    write(
        &model.join("cameras.txt"),
        b"1 PINHOLE 640 480 500 500 320\n",
    );
    write(&model.join("images.txt"), b"");
    let unknown_model = dir.join("unknown");
    std::fs::create_dir_all(&unknown_model).unwrap();
    write(
        &unknown_model.join("cameras.txt"),
        b"1 FISHEYE_MAGIC 640 480 1 2 3\n",
    );
    write(&unknown_model.join("images.txt"), b"");
    let out = dir.join("out.json");
    let subsets = dir.join("s.json");
    // `bench-real` on this folder (no subsets.json in it) with `extra` arguments.
    let bench = |extra: &[&dyn AsRef<std::ffi::OsStr>]| -> Vec<std::ffi::OsString> {
        let base: [&dyn AsRef<std::ffi::OsStr>; 7] = [
            &"bench-real",
            &"--data",
            &dir,
            &"--subsets",
            &subsets,
            &"--out",
            &out,
        ];
        base.iter()
            .chain(extra)
            .map(|a| a.as_ref().to_owned())
            .collect()
    };
    let cases = vec![
        case(
            "score for other images",
            &[&"score", &foreign, &"--gt", &gt],
            "does not match the images by name",
        ),
        case(
            "score with fewer",
            &[&"score", &fewer, &"--gt", &gt],
            "10 entr(y/ies) name no input image",
        ),
        case(
            "score malformed",
            &[&"score", &malformed, &"--gt", &gt],
            "malformed.json",
        ),
        case(
            "score missing gt",
            &[&"score", &gt, &"--gt", &dir.join("nope.json")],
            "nope.json",
        ),
        case(
            "plot for other images",
            &[&"plot", &foreign, &"--gt", &gt, &"-o", &dir.join("p.png")],
            "does not match the images by name",
        ),
        case(
            "import no model",
            &[&"import-colmap", &dir, &"--out", &out],
            "no COLMAP model",
        ),
        case(
            "import short camera line",
            &[&"import-colmap", &model, &"--out", &out],
            "PINHOLE has 4 parameters, got 3",
        ),
        case(
            "import unknown model",
            &[&"import-colmap", &unknown_model, &"--out", &out],
            "FISHEYE_MAGIC",
        ),
        case(
            "view without output",
            &[&"view", &dir],
            "is not a posediff output folder",
        ),
        owned_case("bench without subsets", bench(&[]), "s.json"),
        owned_case(
            "bench with a misspelt option",
            bench(&[&"--set", &"matching.min_verifed=15"]),
            "min_verifed",
        ),
        owned_case(
            "bench options for the ground truth",
            bench(&[
                &"--method",
                &"ground-truth",
                &"--set",
                &"matching.min_verified=15",
            ]),
            "apply to --method geometric",
        ),
    ];
    run_cases(&cases, None);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn ground_truths_in_another_order_score_the_same() {
    let dir = posediff_fixtures::temp_dir("bad-shuffled");
    let gt = shared_path("data/co3d_apple_posediffusion/cameras.json");
    let mut entries: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(&gt).unwrap()).unwrap();
    // An estimate: the ground truth with image 3 turned, so that the score is not perfect.
    entries[3]["R"] = serde_json::json!([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]);
    let est = write(
        &dir.join("est.json"),
        serde_json::to_string(&entries).unwrap().as_bytes(),
    );
    let mut shuffled: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(&gt).unwrap()).unwrap();
    shuffled.reverse();
    shuffled.swap(2, 11);
    let shuffled = write(
        &dir.join("shuffled.json"),
        serde_json::to_string(&shuffled).unwrap().as_bytes(),
    );
    let score = |gt: &Path| {
        let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
            .args([
                OsString::from("score"),
                est.clone().into(),
                "--gt".into(),
                gt.into(),
            ])
            .output()
            .unwrap();
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        String::from_utf8_lossy(&r.stdout).into_owned()
    };
    let (a, b) = (score(&gt), score(&shuffled));
    assert_eq!(a, b);
    assert!(!a.contains("mAA(30) 1.000"), "{a}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn skipped_images_are_listed_and_the_rest_estimated() {
    let dir = posediff_fixtures::temp_dir("bad-skip");
    let jpeg = std::fs::read(&apple_files()[0]).unwrap();
    let set = dir.join("set");
    std::fs::create_dir_all(&set).unwrap();
    for p in apple_files().iter().take(8) {
        std::fs::copy(p, set.join(p.file_name().unwrap())).unwrap();
    }
    write(&set.join("broken.jpg"), &jpeg[..jpeg.len() / 3]);
    // A link whose file moved away and a name that is not UTF-8 are skipped and listed too.
    std::os::unix::fs::symlink(dir.join("moved-away.jpg"), set.join("dangling.jpg")).unwrap();
    std::fs::copy(
        &apple_files()[9],
        set.join(std::ffi::OsStr::from_bytes(b"caf\xe9.jpg")),
    )
    .unwrap();
    let out = dir.join("out");
    let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args([
            OsString::from("estimate"),
            set.clone().into(),
            "--out".into(),
            out.clone().into(),
            "--skip-bad-images".into(),
            "--quiet".into(),
            "--no-view".into(),
        ])
        .env("RUST_LOG", "info")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&r.stderr);
    assert!(r.status.success(), "{stderr}");
    // A run that does work says so: the early cases' "no stage started" can fail.
    assert!(
        stderr.contains(posediff::estimate::run::WORK_STARTS),
        "{stderr}"
    );
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    let skipped = run["skipped_images"].as_array().unwrap();
    assert_eq!(skipped.len(), 3, "{skipped:?}");
    for (name, reason) in [
        ("broken.jpg", "truncated JPEG"),
        ("dangling.jpg", "a symbolic link to a missing file"),
        ("caf\u{fffd}.jpg", "not valid UTF-8"),
    ] {
        assert!(
            skipped.iter().any(|s| {
                s["image"].as_str().unwrap().ends_with(name)
                    && s["reason"].as_str().unwrap().contains(reason)
            }),
            "{name}: {skipped:?}"
        );
    }
    let cams: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json")).unwrap()).unwrap();
    assert_eq!(cams.len(), 8);
    assert!(cams.iter().all(|c| c["image"] != "broken.jpg"));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_same_inputs_give_byte_identical_outputs_on_one_or_two_threads() {
    let dir = posediff_fixtures::temp_dir("bad-determinism");
    let images = shared_path("data/middlebury_templeSR/images");
    let run = |threads: &str, tag: &str| {
        let out = dir.join(tag);
        let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
            .args([
                OsString::from("estimate"),
                images.clone().into(),
                "--out".into(),
                out.clone().into(),
                "--quiet".into(),
                "--no-view".into(),
            ])
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .unwrap();
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        out
    };
    let (a, b, c) = (run("1", "one"), run("2", "two"), run("2", "again"));
    for f in [
        "cameras.json",
        "sparse/0/images.txt",
        "sparse/0/points3D.txt",
        "sparse_pc.ply",
    ] {
        let x = std::fs::read(a.join(f)).unwrap();
        assert_eq!(x, std::fs::read(b.join(f)).unwrap(), "{f}: 1 vs 2 threads");
        assert_eq!(x, std::fs::read(c.join(f)).unwrap(), "{f}: two runs");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn initial_cameras_are_matched_by_name_in_any_order() {
    let dir = posediff_fixtures::temp_dir("bad-init-order");
    let set = shared_path("data/middlebury_templeSR");
    let mut gt: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(set.join("cameras.json")).unwrap()).unwrap();
    gt.reverse();
    gt.swap(1, 7);
    let missing = gt.pop().unwrap();
    let init = write(
        &dir.join("init.json"),
        serde_json::to_string(&gt).unwrap().as_bytes(),
    );
    let out = dir.join("out");
    let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args([
            OsString::from("estimate"),
            set.join("images").into(),
            "--out".into(),
            out.clone().into(),
            "--init".into(),
            init.into(),
            "--refine".into(),
            "none".into(),
            "--quiet".into(),
            "--no-view".into(),
        ])
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let cams: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json")).unwrap()).unwrap();
    let file = |v: &serde_json::Value| {
        Path::new(v["image"].as_str().unwrap())
            .file_name()
            .unwrap()
            .to_owned()
    };
    for c in &cams {
        if file(c) == file(&missing) {
            assert_eq!(c["estimated"], false, "no initial camera: not estimated");
            continue;
        }
        let g = gt.iter().find(|g| file(g) == file(c)).unwrap();
        assert_eq!(c["R"], g["R"], "{}", c["image"]);
        assert_eq!(c["t"], g["t"], "{}", c["image"]);
    }
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    let warnings = run["warnings"].to_string();
    assert!(
        warnings.contains("1 image(s) have no entry") && warnings.contains("start uninitialised"),
        "{warnings}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn every_real_image_passes_the_structural_check() {
    for set in [
        "co3d_apple_posediffusion",
        "middlebury_templeSR",
        "strecha_fountainP11",
    ] {
        let files =
            posediff::io::loader::image_files(&shared_path(&format!("data/{set}/images"))).unwrap();
        let (good, bad) = posediff::io::loader::check_images(&files);
        assert!(bad.is_empty(), "{set}: {bad:?}");
        assert_eq!(good.len(), files.len());
    }
}
