//! The outputs read by the real clients users feed them to: pycolmap (the COLMAP model, text
//! and binary, with the reprojection error recomputed), plyfile (sparse_pc.ply), nerfstudio's
//! path rules (transforms.json), headless Chromium (view.html renders without console errors
//! and draws something), and our own `import-colmap` (the round trip, points included).
//!
//! Needs what `cargo xtask setup` installs: the Python environment `target/client-venv`
//! (scripts/requirements-clients.txt) and Debian's `chromium`. Without them these tests fail
//! and say so.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::Command;

use posediff::io::colmap::{ColmapFormat, ColmapModel};
use posediff::io::export::read_cameras_json_partial;
use posediff_fixtures::shared_path;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn python() -> PathBuf {
    let p = workspace().join("target/client-venv/bin/python");
    assert!(
        p.is_file(),
        "{} is missing: run `cargo xtask setup` (it creates the client venv)",
        p.display()
    );
    p
}

fn chromium() -> PathBuf {
    let p = PathBuf::from("/usr/bin/chromium");
    assert!(
        p.is_file(),
        "/usr/bin/chromium is missing: run `cargo xtask setup` (Debian package chromium)"
    );
    p
}

fn posediff(args: &[&std::ffi::OsStr]) -> std::process::Output {
    let out = Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "posediff {:?}: {}",
        args,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// `posediff score`'s mAA(30) of `cameras` against `gt` (its JSON written into `dir`).
fn maa_30(cameras: &Path, gt: &Path, dir: &Path) -> f64 {
    let score = dir.join("score.json");
    posediff(&[
        "score".as_ref(),
        cameras.as_os_str(),
        "--gt".as_ref(),
        gt.as_os_str(),
        "--out".as_ref(),
        score.as_os_str(),
    ]);
    let score: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(score).unwrap()).unwrap();
    score["scores"]["maa_30"].as_f64().unwrap()
}

/// pycolmap and plyfile on an output folder: the script's JSON summary.
fn check_with_python(out: &Path, min_points: usize) -> serde_json::Value {
    let r = Command::new(python())
        .arg(workspace().join("scripts/check_outputs.py"))
        .arg(out)
        .args([
            "--max-error",
            "1.0",
            "--min-points",
            &min_points.to_string(),
        ])
        .output()
        .unwrap();
    assert!(
        r.status.success(),
        "check_outputs.py {}: {}",
        out.display(),
        String::from_utf8_lossy(&r.stderr)
    );
    serde_json::from_slice(&r.stdout).unwrap()
}

/// Loads `page` in headless Chromium: the DOM after the page settled, the console lines, and
/// a screenshot.
fn load_in_chromium(page: &Path, shot: &Path, profile: &Path) -> (String, Vec<String>) {
    let url = format!("file://{}", page.canonicalize().unwrap().display());
    let common = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--enable-unsafe-swiftshader",
        "--use-angle=swiftshader",
        "--window-size=1000,700",
        "--virtual-time-budget=20000",
        "--enable-logging=stderr",
        "--v=0",
    ];
    let dom = Command::new(chromium())
        .args(common)
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("--dump-dom")
        .arg(&url)
        .output()
        .unwrap();
    assert!(
        dom.status.success(),
        "{}",
        String::from_utf8_lossy(&dom.stderr)
    );
    let console: Vec<String> = String::from_utf8_lossy(&dom.stderr)
        .lines()
        .filter(|l| l.contains(":CONSOLE"))
        // SwiftShader's own performance notes about reading pixels back, not the page's.
        .filter(|l| !l.contains("GL Driver Message"))
        .map(str::to_owned)
        .collect();
    let s = Command::new(chromium())
        .args(common)
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--screenshot={}", shot.display()))
        .arg(&url)
        .output()
        .unwrap();
    assert!(s.status.success(), "{}", String::from_utf8_lossy(&s.stderr));
    (String::from_utf8_lossy(&dom.stdout).into_owned(), console)
}

/// Fraction of the screenshot's pixels right of the panel (x ≥ 450) away from the page's
/// background colour (30, 31, 36).
fn drawn_fraction(shot: &Path) -> f64 {
    use opencv::prelude::*;
    let img =
        opencv::imgcodecs::imread(shot.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
    assert!(!img.empty(), "no screenshot at {}", shot.display());
    let mut drawn = 0usize;
    let total = (img.rows() * (img.cols() - 450)) as usize;
    for y in 0..img.rows() {
        for x in 450..img.cols() {
            let p = img.at_2d::<opencv::core::Vec3b>(y, x).unwrap();
            let d = (i32::from(p[0]) - 36).abs()
                + (i32::from(p[1]) - 31).abs()
                + (i32::from(p[2]) - 30).abs();
            if d > 40 {
                drawn += 1;
            }
        }
    }
    drawn as f64 / total as f64
}

#[test]
fn fountain_outputs_load_in_pycolmap_plyfile_chromium_and_import_colmap() {
    let images = shared_path("data/strecha_fountainP11/images");
    let dir = posediff_fixtures::temp_dir("clients-fountain");
    let out = dir.join("out");
    posediff(&[
        "estimate".as_ref(),
        images.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--quiet".as_ref(),
    ]);
    for f in [
        "cameras.json",
        "sparse/0/cameras.txt",
        "sparse/0/images.txt",
        "sparse/0/points3D.txt",
        "sparse_pc.ply",
        "transforms.json",
        "pytorch3d.json",
        "view.html",
        "run.json",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // out/images is a link to the input folder.
    assert_eq!(
        out.join("images").canonicalize().unwrap(),
        images.canonicalize().unwrap()
    );
    let summary = check_with_python(&out, 1000);
    assert_eq!(summary["images"], 11);
    assert_eq!(
        summary["cameras"], 1,
        "the shared focal is one COLMAP camera"
    );
    assert!(summary["points"].as_u64().unwrap() > 1000, "{summary}");

    // The binary model reads the same in pycolmap.
    let bin = dir.join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    for f in [
        "cameras.json",
        "run.json",
        "transforms.json",
        "sparse_pc.ply",
    ] {
        std::fs::copy(out.join(f), bin.join(f)).unwrap();
    }
    std::os::unix::fs::symlink(&images, bin.join("images")).unwrap();
    let model = ColmapModel::read(&out.join("sparse/0")).unwrap();
    model
        .write(&bin.join("sparse/0"), ColmapFormat::Binary)
        .unwrap();
    assert_eq!(ColmapModel::read(&bin.join("sparse/0")).unwrap(), model);
    let summary_bin = check_with_python(&bin, 1000);
    assert_eq!(summary_bin["points"], summary["points"]);
    assert_eq!(
        summary_bin["mean_reprojection_error_px"],
        summary["mean_reprojection_error_px"]
    );

    // import-colmap reads back what estimate wrote, points included.
    let back = dir.join("back.json");
    let printed = posediff(&[
        "import-colmap".as_ref(),
        out.join("sparse/0").as_os_str(),
        "--images".as_ref(),
        images.as_os_str(),
        "--out".as_ref(),
        back.as_os_str(),
    ]);
    let printed = String::from_utf8_lossy(&printed.stdout);
    assert!(
        printed.contains(&format!("the model has {} points", summary["points"])),
        "{printed}"
    );
    let a = read_cameras_json_partial(&out.join("cameras.json")).unwrap();
    let b = read_cameras_json_partial(&back).unwrap();
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.image, y.image);
        let (x, y) = (x.camera.unwrap(), y.camera.unwrap());
        assert!((x.intrinsics.matrix() - y.intrinsics.matrix()).norm() < 1e-9);
        assert!((x.cam_from_world.rotation - y.cam_from_world.rotation).norm() < 1e-9);
        assert!((x.cam_from_world.translation - y.cam_from_world.translation).norm() < 1e-9);
    }

    // The viewer, written by estimate and by `view --gt`, renders in Chromium.
    let gt_page = dir.join("view_gt.html");
    posediff(&[
        "view".as_ref(),
        out.as_os_str(),
        "--gt".as_ref(),
        shared_path("data/strecha_fountainP11/cameras.json").as_os_str(),
        "-o".as_ref(),
        gt_page.as_os_str(),
    ]);
    let html = std::fs::read_to_string(&gt_page).unwrap();
    assert!(
        html.contains("\"ground_truth\":[{"),
        "the ground truth is in the page"
    );
    assert!(html.contains("rotation_error_deg"));
    for (k, page) in [out.join("view.html"), gt_page].iter().enumerate() {
        let shot = dir.join(format!("shot{k}.png"));
        let (dom, console) = load_in_chromium(page, &shot, &dir.join(format!("profile{k}")));
        assert!(
            dom.contains("data-status=\"rendered\""),
            "{}: not rendered: {}",
            page.display(),
            dom.lines().find(|l| l.contains("<body")).unwrap_or("")
        );
        assert!(console.is_empty(), "console output: {console:?}");
        let drawn = drawn_fraction(&shot);
        assert!(
            drawn > 0.01,
            "{}: only {drawn} of the pixels drawn",
            page.display()
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A wide-angle copy of the fountain (OpenCV k1 = −0.12, k2 = 0.02, as issue 40's): the
/// distortion is measured, every camera comes out SIMPLE_RADIAL, pycolmap reads that model
/// with the 2-D points in the photos' pixels (its own reprojection below a pixel, equal to
/// ours), import-colmap keeps the lens, and the cameras are right; so with `--camera-model
/// OPENCV` and `OPENCV_FISHEYE`.
#[test]
fn a_wide_angle_fountain_is_calibrated_and_exported_with_its_lens() {
    let dir = posediff_fixtures::temp_dir("clients-radial");
    let set = dir.join("set");
    posediff(&[
        "variant".as_ref(),
        shared_path("data/strecha_fountainP11").as_os_str(),
        "--radial=-0.12:0.02".as_ref(),
        "--out".as_ref(),
        set.as_os_str(),
    ]);
    let out = dir.join("out");
    posediff(&[
        "estimate".as_ref(),
        set.join("images").as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--no-view".as_ref(),
        "--undistort".as_ref(),
        "--quiet".as_ref(),
    ]);
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    let distortion = &run["report"]["cameras"]["distortion"];
    assert_eq!(distortion["measured"], true, "{distortion}");
    // One SIMPLE_RADIAL k stands for k1 and k2 together: over this image (r² ≤ 0.4) the best
    // single coefficient lies between −0.12 and −0.09 (−0.099 measured).
    let k = distortion["k1"][0].as_f64().unwrap();
    assert!((-0.12..-0.09).contains(&k), "k {k}");
    let cams: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json")).unwrap()).unwrap();
    for c in cams.as_array().unwrap() {
        assert_eq!(c["model"], "SIMPLE_RADIAL", "{c}");
        assert_eq!(c["params"][3].as_f64().unwrap(), k);
    }
    // pycolmap: the model and params, and its reprojection in the photos' pixels.
    let summary = check_with_python(&out, 1000);
    assert_eq!(summary["cameras"], 1, "{summary}");
    // import-colmap keeps the lens.
    let back = dir.join("back.json");
    posediff(&[
        "import-colmap".as_ref(),
        out.join("sparse/0").as_os_str(),
        "--out".as_ref(),
        back.as_os_str(),
    ]);
    let a = read_cameras_json_partial(&out.join("cameras.json")).unwrap();
    let b = read_cameras_json_partial(&back).unwrap();
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        let (lx, ly) = (x.lens.as_ref().unwrap(), y.lens.as_ref().unwrap());
        assert_eq!(lx.model(), ly.model());
        for (p, q) in lx.params().iter().zip(ly.params()) {
            assert!(
                (p - q).abs() < 1e-9,
                "{:?} vs {:?}",
                lx.params(),
                ly.params()
            );
        }
    }
    // --undistort: a PINHOLE model whose 2-D points are the undistorted keypoints, and photos
    // resampled so that each undistorted point shows what the photo shows at its photo pixel
    // (and not what it shows at the undistorted position: the resampling goes the right way).
    let photo = ColmapModel::read(&out.join("sparse/0")).unwrap();
    let pinhole = ColmapModel::read(&out.join("undistorted/sparse/0")).unwrap();
    assert!(pinhole.cameras.iter().all(|c| c.model == "PINHOLE"));
    assert!(
        pinhole
            .recomputed_mean_error(&out)
            .unwrap()
            .is_some_and(|e| e < 1.0)
    );
    let name = &photo.images[0].name;
    let a = posediff::reconstruction::read_colour(&set.join("images").join(name)).unwrap();
    let b =
        posediff::reconstruction::read_colour(&out.join("undistorted/images").join(name)).unwrap();
    // The grey level at a COLMAP pixel; `None` outside the image (undistorted keypoints of a
    // barrel lens reach beyond the frame).
    let grey = |m: &opencv::core::Mat, xy: [f64; 2]| -> Option<f64> {
        use opencv::prelude::*;
        let (x, y) = ((xy[0] - 0.5).round() as i32, (xy[1] - 0.5).round() as i32);
        let p = m.at_2d::<opencv::core::Vec3b>(y, x).ok()?;
        Some((f64::from(p[0]) + f64::from(p[1]) + f64::from(p[2])) / 3.0)
    };
    let (mut right, mut wrong, mut n) = (0.0, 0.0, 0);
    for ((p, _), (u, _)) in photo.images[0]
        .points2d
        .iter()
        .zip(&pinhole.images[0].points2d)
    {
        if (p[0] - u[0]).hypot(p[1] - u[1]) <= 4.0 {
            continue;
        }
        if let (Some(at), Some(there), Some(here)) = (grey(&a, *p), grey(&b, *u), grey(&b, *p)) {
            right += (at - there).abs();
            wrong += (at - here).abs();
            n += 1;
        }
    }
    assert!(n > 100, "{n} keypoints the lens moves by over 4 px");
    assert!(
        right < 0.5 * wrong,
        "mean grey difference {} at the undistorted points, {} at the photo's",
        right / f64::from(n),
        wrong / f64::from(n)
    );
    // The cameras against the copy's ground truth.
    let maa = maa_30(&out.join("cameras.json"), &set.join("cameras.json"), &dir);
    assert!(maa > 0.99, "mAA(30) {maa}");
    // `--camera-model OPENCV` and `OPENCV_FISHEYE`: every camera of that model with one focal
    // (the fisheye's held at the adjusted one: K's focal is the lens's), read so by pycolmap
    // (its reprojection below a pixel), transforms.json's camera_model and coefficients the
    // lens's (`k1 k2 p1 p2`, or the fisheye's `k1 k2 k3 k4`), the cameras right.
    for model in ["OPENCV", "OPENCV_FISHEYE"] {
        let out = dir.join(model);
        posediff(&[
            "estimate".as_ref(),
            set.join("images").as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
            "--camera-model".as_ref(),
            model.as_ref(),
            "--no-view".as_ref(),
            "--quiet".as_ref(),
        ]);
        let cams: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json")).unwrap())
                .unwrap();
        let transforms: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("transforms.json")).unwrap())
                .unwrap();
        assert_eq!(transforms["camera_model"], model);
        let keys = if model == "OPENCV" {
            ["k1", "k2", "p1", "p2"]
        } else {
            ["k1", "k2", "k3", "k4"]
        };
        for c in cams.as_array().unwrap() {
            assert_eq!(c["model"], model, "{c}");
            let params: Vec<f64> = c["params"]
                .as_array()
                .unwrap()
                .iter()
                .map(|p| p.as_f64().unwrap())
                .collect();
            assert_eq!(params[0], params[1], "{c}");
            assert_eq!(params[0], c["K"][0][0].as_f64().unwrap(), "{c}");
            if model == "OPENCV" {
                assert!((-0.13..-0.11).contains(&params[4]), "k1 {c}");
            }
            // One camera: nerfstudio's intrinsics at the top, else the frame's own.
            let frame = transforms["frames"]
                .as_array()
                .unwrap()
                .iter()
                .find(|f| {
                    f["file_path"]
                        .as_str()
                        .unwrap()
                        .ends_with(c["image"].as_str().unwrap())
                })
                .filter(|f| f.get("k1").is_some())
                .unwrap_or(&transforms);
            for (key, value) in keys.iter().zip(&params[4..]) {
                assert_eq!(frame[key].as_f64(), Some(*value), "{key} {frame}");
            }
        }
        let summary = check_with_python(&out, 1000);
        assert_eq!(summary["cameras"], 1, "{summary}");
        let maa = maa_30(&out.join("cameras.json"), &set.join("cameras.json"), &dir);
        assert!(maa > 0.99, "{model}: mAA(30) {maa}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_empty_page_draws_nothing_so_the_screenshot_check_can_fail() {
    let dir = posediff_fixtures::temp_dir("clients-blank");
    let page = dir.join("view.html");
    let html = posediff::io::viewer::render(
        "blank",
        &posediff::reconstruction::Reconstruction::default(),
        &[],
        None,
    )
    .unwrap();
    std::fs::write(&page, html).unwrap();
    let shot = dir.join("shot.png");
    let (dom, console) = load_in_chromium(&page, &shot, &dir.join("profile"));
    assert!(dom.contains("data-status=\"rendered\""));
    assert!(console.is_empty(), "{console:?}");
    let drawn = drawn_fraction(&shot);
    assert!(drawn < 0.001, "{drawn}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--database D`: pycolmap 4.2.1 opens the database a run kept (its counts are run.json's)
/// and both its mappers, GLOMAP's global one and the incremental one, reconstruct the
/// fountain from it with the right rotations, with a camera per photo or one shared by all
/// (`--camera-mode single`).
#[test]
fn pycolmap_maps_the_database_we_write() {
    let dir = posediff_fixtures::temp_dir("clients-database");
    let images = shared_path("data/strecha_fountainP11/images");
    // The default (a camera per photo: the fountain has no EXIF camera) and one camera shared
    // by every photo (`--camera-mode single`, COLMAP's `ImageReader.single_camera`).
    for (mode, cameras) in [("auto", 11), ("single", 1)] {
        let out = dir.join(format!("out-{mode}"));
        let db = dir.join(format!("database-{mode}.db"));
        posediff(&[
            "estimate".as_ref(),
            images.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
            "--database".as_ref(),
            db.as_os_str(),
            "--camera-mode".as_ref(),
            mode.as_ref(),
            "--quiet".as_ref(),
        ]);
        let r = Command::new(python())
            .arg(workspace().join("scripts/check_database.py"))
            .arg(&out)
            .arg("--gt")
            .arg(shared_path("data/strecha_fountainP11/cameras.json"))
            .arg("--database")
            .arg(&db)
            .output()
            .unwrap();
        assert!(
            r.status.success(),
            "check_database.py: {}",
            String::from_utf8_lossy(&r.stderr)
        );
        let found: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
        assert_eq!(found["images"], 11);
        assert_eq!(found["cameras"], cameras, "{mode}: {found}");
        for mapper in ["global", "incremental"] {
            assert_eq!(found[mapper]["registered"], 11, "{mode}: {found}");
            assert_eq!(found[mapper]["cameras"], cameras, "{mode}: {found}");
            assert!(found[mapper]["rra_5"].as_f64().unwrap() >= 0.95, "{found}");
        }
    }
    // A snapshot database (Python's `write(formats=["database"])`) is written new: a write
    // into an existing file is refused.
    let e = posediff::io::database::write_database(
        &dir.join("database-single.db"),
        &posediff::reconstruction::Reconstruction::default(),
        &[],
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("exists"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `posediff map` on a database pycolmap 4.2.1 wrote itself (its SIFT extraction and
/// exhaustive matching, 6-column affine keypoints, CALIBRATED/UNCALIBRATED geometries): every
/// fountain image estimated with the right rotations, nothing matched again.
#[test]
fn posediff_maps_a_database_pycolmap_wrote() {
    let dir = posediff_fixtures::temp_dir("clients-map-pycolmap");
    let images = shared_path("data/strecha_fountainP11/images");
    let db = dir.join("pycolmap.db");
    let r = Command::new(python())
        .arg("-c")
        .arg(
            "import sys, pycolmap\n\
             pycolmap.extract_features(sys.argv[2], sys.argv[1])\n\
             pycolmap.match_exhaustive(sys.argv[2])\n",
        )
        .arg(&images)
        .arg(&db)
        .output()
        .unwrap();
    assert!(
        r.status.success(),
        "pycolmap: {}",
        String::from_utf8_lossy(&r.stderr)
    );
    let out = dir.join("out");
    posediff(&[
        "map".as_ref(),
        "--database".as_ref(),
        db.as_os_str(),
        "--images".as_ref(),
        images.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--no-view".as_ref(),
        "--quiet".as_ref(),
    ]);
    let run: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(
        run["report"]["pair_selection"], "database",
        "{}",
        run["report"]
    );
    let scores = dir.join("scores.json");
    posediff(&[
        "score".as_ref(),
        out.join("cameras.json").as_os_str(),
        "--gt".as_ref(),
        shared_path("data/strecha_fountainP11/cameras.json").as_os_str(),
        "--out".as_ref(),
        scores.as_os_str(),
    ]);
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(&scores).unwrap()).unwrap();
    assert_eq!(s["scores"]["registered"], 1.0, "{s}");
    assert!(s["scores"]["maa_30"].as_f64().unwrap() >= 0.95, "{s}");
    std::fs::remove_dir_all(&dir).unwrap();
}
