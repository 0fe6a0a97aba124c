//! `--matcher aliked-lightglue` end to end: the released weights (fetched by `cargo xtask
//! weights` into `target/weights/`, or `$POSEDIFF_WEIGHTS_DIR`), real images, the CLI.

// Test helpers unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::ffi::OsString;
use std::path::PathBuf;
use std::process::Command;

use posediff::correspondences::{LearnedMatcher, MatcherChoice, SharedLearned, match_images};
use posediff_fixtures::{shared_path, workspace_root};
use posediff_matching::MatchConfig;

fn weights_dir() -> PathBuf {
    std::env::var_os("POSEDIFF_WEIGHTS_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("target/weights"))
}

fn apple(n: usize) -> Vec<PathBuf> {
    let dir = shared_path("data/co3d_apple_posediffusion/images");
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    files.truncate(n);
    files
}

#[test]
fn matcher_names_round_trip() {
    for m in [
        MatcherChoice::Sift,
        MatcherChoice::Orb,
        MatcherChoice::AlikedLightGlue,
        MatcherChoice::AlikedN16RotLightGlue,
        MatcherChoice::DiskLightGlue,
    ] {
        assert_eq!(m.as_str().parse::<MatcherChoice>().unwrap(), m);
    }
    let e = "superglue"
        .parse::<MatcherChoice>()
        .unwrap_err()
        .to_string();
    assert!(e.contains("aliked-lightglue"), "{e}");
}

/// Neighbouring apple frames: keypoints in the original pixels, verified matches that the
/// ground-truth epipolar geometry agrees with.
#[test]
fn learned_matches_of_neighbouring_frames_are_verified_and_in_original_pixels() {
    let learned = SharedLearned(std::sync::Arc::new(
        LearnedMatcher::load(&weights_dir()).unwrap_or_else(|e| panic!("{e}")),
    ));
    let images = apple(2);
    let (features, pairs) =
        match_images(&images, None, &MatchConfig::default(), Some(&learned)).unwrap();
    assert_eq!(features.len(), 2);
    for f in &features {
        assert_eq!(
            f.keypoints.len(),
            posediff::correspondences::LEARNED_MAX_KEYPOINTS
        );
        let (w, h) = (
            f64::from(f.image_size.width()),
            f64::from(f.image_size.height()),
        );
        assert!(
            f.keypoints
                .iter()
                .all(|k| k[0] >= -0.5 && k[1] >= -0.5 && k[0] <= w - 0.5 && k[1] <= h - 0.5)
        );
        // The keypoints spread over the image (original pixels, not the 1024 px copy).
        let max_y = f.keypoints.iter().map(|k| k[1]).fold(0.0, f64::max);
        assert!(max_y > 0.6 * h, "max y {max_y} of {h}");
    }
    let p = &pairs[0];
    assert!(p.len() >= 100, "{} verified matches", p.len());
    // Against the ground truth: the Sampson distances of the matches under the true F.
    let gt = posediff::io::export::read_cameras_json(&shared_path(
        "data/co3d_apple_posediffusion/cameras.json",
    ))
    .unwrap();
    let cam = |path: &PathBuf| {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        gt.iter()
            .find(|c| c.image.ends_with(&name))
            .map(|c| c.camera)
            .unwrap()
    };
    let (a, b) = (cam(&images[0]), cam(&images[1]));
    let f = posediff_geometry::epipolar::fundamental_from_cameras(&a, &b);
    let good = p
        .kp1
        .iter()
        .zip(&p.kp2)
        .filter(|(x, y)| {
            let (x, y) = (
                nalgebra::Point2::new(x[0], x[1]),
                nalgebra::Point2::new(y[0], y[1]),
            );
            posediff_geometry::epipolar::sampson_error(&f, &x, &y).is_ok_and(|e| e < 4.0)
        })
        .count();
    assert!(
        good as f64 >= 0.95 * p.len() as f64,
        "{good} of {} within 4 px² of the true epipolar geometry",
        p.len()
    );
}

/// `match_pairs` prepares each image once for all its pairs; the matches are the ones of each
/// pair matched alone, in the order the pairs were asked for.
#[test]
fn prepared_images_give_each_pairs_own_matches() {
    let learned = SharedLearned(std::sync::Arc::new(
        LearnedMatcher::load(&weights_dir()).unwrap_or_else(|e| panic!("{e}")),
    ));
    let images = apple(3);
    let config = MatchConfig::default();
    let asked = [(1, 2), (0, 2), (0, 1)];
    let (features, pairs) = match_images(&images, Some(&asked), &config, Some(&learned)).unwrap();
    assert_eq!(pairs.len(), asked.len());
    for (p, &(i, j)) in pairs.iter().zip(&asked) {
        assert_eq!((p.first, p.second), (i, j));
        let alone = learned
            .0
            .match_pair(&features[i], &features[j], i, j, &config)
            .unwrap();
        assert!(!alone.is_empty());
        assert_eq!(p.idx1, alone.idx1, "pair ({i}, {j})");
        assert_eq!(p.idx2, alone.idx2, "pair ({i}, {j})");
        assert_eq!(p.kp1, alone.kp1, "pair ({i}, {j})");
    }
}

/// For COLMAP's `matches` table the learned matcher keeps LightGlue's matches before
/// verification: the verified ones are among them and are what `match_pairs` gives.
#[test]
fn the_learned_matcher_keeps_its_matches_before_verification() {
    use posediff::correspondences::{Correspondences, LearnedCorrespondences, extract_all};
    let learned = SharedLearned(std::sync::Arc::new(
        LearnedMatcher::load(&weights_dir()).unwrap_or_else(|e| panic!("{e}")),
    ));
    let images = apple(3);
    let config = MatchConfig::default();
    let features = extract_all(&images, &config, Some(&learned)).unwrap();
    let matcher = LearnedCorrespondences {
        learned: &learned,
        config: &config,
    };
    let asked = [(0, 1), (1, 2)];
    let counter = posediff::correspondences::NoCounter;
    let both = matcher
        .match_pairs_with_raw(&features, &asked, (&counter, "matching"))
        .unwrap();
    let verified = matcher
        .match_pairs(&features, &asked, (&counter, "matching"))
        .unwrap();
    assert_eq!(both.len(), 2);
    for ((raw, v), alone) in both.iter().zip(&verified) {
        let raw = raw.as_ref().unwrap();
        assert_eq!(v, alone);
        assert!(!v.is_empty());
        let pairs: std::collections::HashSet<(u32, u32)> = raw
            .idx1
            .iter()
            .copied()
            .zip(raw.idx2.iter().copied())
            .collect();
        assert!(
            v.idx1
                .iter()
                .zip(&v.idx2)
                .all(|(a, b)| pairs.contains(&(*a, *b)))
        );
        assert!(raw.len() >= v.len());
    }
}

#[test]
fn missing_weights_fail_before_any_image_is_read_and_name_the_command() {
    let dir = posediff_fixtures::temp_dir("learned-no-weights");
    let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args([
            OsString::from("estimate"),
            shared_path("data/co3d_apple_posediffusion/images").into(),
            "--matcher".into(),
            "aliked-lightglue".into(),
            "--weights-dir".into(),
            dir.join("nothing-here").into(),
            "--out".into(),
            dir.join("out").into(),
        ])
        .output()
        .unwrap();
    assert!(!r.status.success());
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(err.contains("cargo xtask weights"), "{err}");
    assert!(err.contains("aliked-n16"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `posediff estimate <set> --matcher aliked-lightglue` into `<dir>/out`, which must succeed:
/// the output folder and run.json.
fn estimate_learned(set: &std::path::Path, dir: &std::path::Path) -> (PathBuf, serde_json::Value) {
    let out = dir.join("out");
    let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args([
            OsString::from("estimate"),
            set.into(),
            "--matcher".into(),
            "aliked-lightglue".into(),
            "--weights-dir".into(),
            weights_dir().into(),
            "--out".into(),
            out.clone().into(),
            "--quiet".into(),
            "--no-view".into(),
        ])
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let run =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    (out, run)
}

/// Three frames through the CLI: every camera estimated, run.json names the matcher.
#[test]
fn the_cli_estimates_with_the_learned_matcher() {
    let dir = posediff_fixtures::temp_dir("learned-cli");
    apple_with_turned(&dir, 3, &[]);
    let (out, run) = estimate_learned(&dir.join("set"), &dir);
    assert_eq!(run["matcher"], "aliked-lightglue");
    let cams: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json")).unwrap()).unwrap();
    assert_eq!(cams.len(), 3);
    assert!(cams.iter().all(|c| c["estimated"] == true), "{cams:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `aliked-n16rot-lightglue` loads the rotation-trained ALIKED (other keypoints than n16's on
/// the same image) and still gives verified matches between neighbouring apple frames.
#[test]
fn the_n16rot_choice_runs_its_own_network() {
    let dir = weights_dir();
    let aliked = MatcherChoice::AlikedN16RotLightGlue
        .extractor_weights()
        .unwrap();
    assert_eq!(aliked, posediff_learned::WeightSet::AlikedN16Rot);
    let rot = SharedLearned(std::sync::Arc::new(
        LearnedMatcher::load_with(&dir, aliked).unwrap_or_else(|e| panic!("{e}")),
    ));
    let n16 = LearnedMatcher::load(&dir).unwrap();
    let images = apple(2);
    let a = n16.extract(&images[0]).unwrap();
    let b = rot.0.extract(&images[0]).unwrap();
    assert_eq!(a.keypoints.len(), b.keypoints.len());
    assert_ne!(a.keypoints, b.keypoints, "n16rot gave n16's keypoints");
    let (_, pairs) = match_images(&images, None, &MatchConfig::default(), Some(&rot)).unwrap();
    assert!(pairs[0].len() >= 100, "{} verified matches", pairs[0].len());
}

/// `disk-lightglue` runs DISK with the LightGlue trained on it: up to 2048 keypoints inside the
/// original image, and verified matches between neighbouring apple frames.
#[test]
fn the_disk_choice_runs_disk_with_its_own_lightglue() {
    let extractor = MatcherChoice::DiskLightGlue.extractor_weights().unwrap();
    assert_eq!(extractor, posediff_learned::WeightSet::Disk);
    let (file, lightglue) =
        posediff::correspondences::learned_weight_files(&weights_dir(), extractor)
            .unwrap_or_else(|e| panic!("{e}"));
    assert!(
        file.to_string_lossy().contains("disk-depth-save"),
        "{file:?}"
    );
    assert!(
        lightglue.to_string_lossy().contains("disk_lightglue"),
        "{lightglue:?}"
    );
    let disk = SharedLearned(std::sync::Arc::new(
        LearnedMatcher::load_with(&weights_dir(), extractor).unwrap_or_else(|e| panic!("{e}")),
    ));
    let images = apple(2);
    let (features, pairs) =
        match_images(&images, None, &MatchConfig::default(), Some(&disk)).unwrap();
    for f in &features {
        assert!(
            f.keypoints.len() > 500 && f.keypoints.len() <= 2048,
            "{}",
            f.keypoints.len()
        );
        let (w, h) = (
            f64::from(f.image_size.width()),
            f64::from(f.image_size.height()),
        );
        assert!(
            f.keypoints
                .iter()
                .all(|k| k[0] >= -0.5 && k[1] >= -0.5 && k[0] < w && k[1] < h)
        );
    }
    assert!(pairs[0].len() >= 100, "{} verified matches", pairs[0].len());
}

/// `auto` with a learned matcher: every pair up to `LEARNED_EXHAUSTIVE_UP_TO` images, above
/// it the first pass and the second; an explicit selection is kept as given.
#[test]
fn the_learned_auto_plan_is_exhaustive_for_small_sets_then_two_passes() {
    use posediff::estimate::geometric::{
        Densify, GeometricConfig, LEARNED_EXHAUSTIVE_UP_TO, LEARNED_FIRST_PASS,
    };
    use posediff_matching::PairSelection;
    let config = GeometricConfig {
        learned: Some(SharedLearned(std::sync::Arc::new(
            LearnedMatcher::load(&weights_dir()).unwrap_or_else(|e| panic!("{e}")),
        ))),
        ..GeometricConfig::default()
    };
    let exhaustive = PairSelection::Rules(vec![posediff_matching::PairRule::Exhaustive]);
    let small = config.plan(LEARNED_EXHAUSTIVE_UP_TO);
    assert_eq!(small, (exhaustive.clone(), None));
    assert_eq!(
        PairSelection::Auto.rules(LEARNED_EXHAUSTIVE_UP_TO),
        vec![posediff_matching::PairRule::Exhaustive]
    );
    let (selection, densify) = config.plan(LEARNED_EXHAUSTIVE_UP_TO + 1);
    assert_eq!(selection, PairSelection::Rules(LEARNED_FIRST_PASS.to_vec()));
    assert_eq!(densify, Some(Densify::default()));
    let mut explicit = config.clone();
    explicit.options.pairs.selection = "exhaustive".parse().unwrap();
    assert_eq!(explicit.plan(100), (exhaustive.clone(), None));
    // The thresholds are the options tree's: a larger exhaustive bound, a forced second pass.
    let mut wider = config.clone();
    wider.options.pairs.learned_exhaustive_up_to = 100;
    wider.options.densify.when = posediff::estimate::options::DensifyWhen::Always;
    assert_eq!(wider.plan(100), (exhaustive, Some(Densify::default())));
}

/// The stages a run reports, as (name, total, steps counted).
#[derive(Default)]
struct Record {
    stages: std::sync::Mutex<Vec<(String, u64, usize)>>,
}

impl posediff::correspondences::StepCounter for Record {
    fn stage(&self, name: &str, total: u64) {
        self.stages
            .lock()
            .unwrap()
            .push((name.to_owned(), total, 0));
    }
    fn step(&self) {
        if let Some(last) = self.stages.lock().unwrap().last_mut() {
            last.2 += 1;
        }
    }
}

/// What the CLI's progress bars see: each stage of the geometric path in order, the learned
/// matcher's images and pairs counted one step each (from whichever thread did them).
#[test]
fn the_geometric_stages_count_images_and_pairs() {
    use posediff::estimate::geometric::{GeometricConfig, estimate_geometric_counted};
    let config = GeometricConfig {
        learned: Some(SharedLearned(std::sync::Arc::new(
            LearnedMatcher::load(&weights_dir()).unwrap_or_else(|e| panic!("{e}")),
        ))),
        ..GeometricConfig::default()
    };
    let record = Record::default();
    let estimate = estimate_geometric_counted(&apple(3), &config, &record).unwrap();
    assert!(estimate.cameras.iter().filter(|c| c.is_some()).count() >= 2);
    let stages = record.stages.into_inner().unwrap();
    assert_eq!(
        stages,
        vec![
            ("features".to_owned(), 3, 3),
            ("matching".to_owned(), 3, 3),
            ("mapping".to_owned(), 0, 0),
        ]
    );
}

/// `image` turned by 180°, written losslessly into `dir`.
fn write_turned(image: &std::path::Path, dir: &std::path::Path) -> PathBuf {
    use opencv::core::{Mat, ROTATE_180, Vector, rotate};
    use opencv::imgcodecs::{IMREAD_COLOR, imread, imwrite};
    let img = imread(image.to_str().unwrap(), IMREAD_COLOR).unwrap();
    let mut turned = Mat::default();
    rotate(&img, &mut turned, ROTATE_180).unwrap();
    let stem = image.file_stem().unwrap().to_str().unwrap();
    let out = dir.join(format!("{stem}_turned.png"));
    assert!(imwrite(out.to_str().unwrap(), &turned, &Vector::new()).unwrap());
    out
}

/// An image turned by 180° and extracted turned back is the upright image's extraction: the
/// same descriptors, the keypoints at `(w − 1 − x, h − 1 − y)` of the upright ones (a sign or an
/// off-by-one in the mapping fails). Matched with LightGlue seeing the turned positions, it
/// gives the upright pair's matches; matched as it lies, far fewer.
#[test]
fn a_turned_image_is_matched_as_the_upright_one() {
    let learned = LearnedMatcher::load(&weights_dir()).unwrap_or_else(|e| panic!("{e}"));
    let dir = posediff_fixtures::temp_dir("learned-turned");
    let images = apple(2);
    let turned_path = write_turned(&images[1], &dir);
    let a = learned.extract(&images[0]).unwrap();
    let b = learned.extract(&images[1]).unwrap();
    let turned = learned.extract_turned(&turned_path, true).unwrap();
    assert_eq!(turned.image_size, b.image_size);
    let (w, h) = (
        f64::from(b.image_size.width()),
        f64::from(b.image_size.height()),
    );
    assert_eq!(turned.keypoints.len(), b.keypoints.len());
    for (t, u) in turned.keypoints.iter().zip(&b.keypoints) {
        assert!(
            (t[0] - (w - 1.0 - u[0])).abs() < 1e-9 && (t[1] - (h - 1.0 - u[1])).abs() < 1e-9,
            "{t:?} against {u:?}"
        );
    }
    assert_eq!(turned.descriptors, b.descriptors);

    let config = MatchConfig::default();
    let upright = learned.match_pair(&a, &b, 0, 1, &config).unwrap();
    let pa = learned.prepare(&a).unwrap();
    assert!(turned.half_turned && !b.half_turned);
    let pt = learned.prepare(&turned).unwrap();
    let matched = learned
        .match_prepared((&a, &pa), (&turned, &pt), 0, 1, &config)
        .unwrap();
    assert!(upright.len() >= 100, "{} upright matches", upright.len());
    // The verification runs on other coordinates: the same matches up to RANSAC's borderline
    // points.
    let same = matched
        .idx2
        .iter()
        .zip(&matched.idx1)
        .filter(|m| upright.idx2.iter().zip(&upright.idx1).any(|u| u == *m))
        .count();
    assert!(
        same as f64 >= 0.95 * upright.len() as f64,
        "{same} of {} upright matches found turned ({} in all)",
        upright.len(),
        matched.len()
    );
    // As it lies (LightGlue seeing the positions upside down to the descriptors' patches):
    let as_is = learned.extract(&turned_path).unwrap();
    let wrong_way = learned.match_pair(&a, &as_is, 0, 1, &config).unwrap();
    assert!(
        2 * wrong_way.len() < upright.len(),
        "{} matches of the turned image as it lies, {} upright",
        wrong_way.len(),
        upright.len()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Rotation matrix of a cameras.json record.
fn rotation_of(c: &serde_json::Value) -> nalgebra::Matrix3<f64> {
    nalgebra::Matrix3::from_fn(|r, k| c["R"][r][k].as_f64().unwrap())
}

/// The first `n` apple frames copied into `<dir>/set`, the frames `turned` written upside down.
fn apple_with_turned(dir: &std::path::Path, n: usize, turned: &[usize]) -> Vec<PathBuf> {
    let set = dir.join("set");
    std::fs::create_dir_all(&set).unwrap();
    apple(n)
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if turned.contains(&i) {
                write_turned(p, &set)
            } else {
                let to = set.join(p.file_name().unwrap());
                std::fs::copy(p, &to).unwrap();
                to
            }
        })
        .collect()
}

/// Each estimated rotation relative to the first frame's is the ground truth's within 5°, with
/// the frames `turned` turned by 180° about the optical axis (`R ↦ diag(−1, −1, 1) R`).
fn assert_rotations_with_turned(rotations: &[nalgebra::Matrix3<f64>], turned: &[usize]) {
    let frames = apple(rotations.len());
    let gt: Vec<serde_json::Value> = serde_json::from_str(
        &std::fs::read_to_string(shared_path("data/co3d_apple_posediffusion/cameras.json"))
            .unwrap(),
    )
    .unwrap();
    let turn = nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(-1.0, -1.0, 1.0));
    let as_given = |i: usize| {
        let name = frames[i].file_name().unwrap().to_str().unwrap();
        let r = gt
            .iter()
            .find(|c| c["image"].as_str().unwrap().ends_with(name))
            .map(rotation_of)
            .unwrap();
        if turned.contains(&i) { turn * r } else { r }
    };
    for i in 1..rotations.len() {
        let truth = as_given(i) * as_given(0).transpose();
        let estimate = rotations[i] * rotations[0].transpose();
        let error = nalgebra::Rotation3::from_matrix(&(estimate * truth.transpose())).angle();
        assert!(
            error.to_degrees() < 5.0,
            "frame {i}: relative rotation off by {:.2}°",
            error.to_degrees()
        );
    }
}

/// Four apple frames through the CLI, the last one upside down: ALIKED is not invariant to
/// in-plane rotation, so it matches the others poorly as it lies; run.json names it in
/// `turned_images`, all four cameras are estimated, and cameras.json holds its camera for the
/// image as given (the ground truth's turned by 180°).
#[test]
fn the_cli_maps_an_image_turned_upside_down() {
    let dir = posediff_fixtures::temp_dir("learned-cli-turned");
    apple_with_turned(&dir, 4, &[3]);
    let (out, run) = estimate_learned(&dir.join("set"), &dir);
    assert_eq!(run["report"]["turned_images"], serde_json::json!([3]));
    let cams: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json")).unwrap()).unwrap();
    assert!(cams.iter().all(|c| c["estimated"] == true), "{cams:?}");
    let rotations: Vec<_> = cams.iter().map(rotation_of).collect();
    assert_rotations_with_turned(&rotations, &[3]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Six apple frames, the last three upside down: the strong pairs form one group of each
/// orientation, and the orientation check turns the second group before the first map (its
/// stages come before any "mapping", and no image is retried after it); all six cameras are
/// estimated and right.
#[test]
fn the_orientation_check_turns_a_group_before_the_map() {
    use posediff::estimate::geometric::{GeometricConfig, estimate_geometric_counted};
    let dir = posediff_fixtures::temp_dir("learned-turned-group");
    let images = apple_with_turned(&dir, 6, &[3, 4, 5]);
    let config = GeometricConfig {
        learned: Some(SharedLearned(std::sync::Arc::new(
            LearnedMatcher::load(&weights_dir()).unwrap_or_else(|e| panic!("{e}")),
        ))),
        ..GeometricConfig::default()
    };
    let record = Record::default();
    let estimate = estimate_geometric_counted(&images, &config, &record).unwrap();
    assert_eq!(estimate.report.turned_images, vec![3, 4, 5]);
    let stages: Vec<String> = record
        .stages
        .into_inner()
        .unwrap()
        .into_iter()
        .map(|s| s.0)
        .collect();
    let first_map = stages.iter().position(|s| s == "mapping").unwrap();
    let check = stages.iter().position(|s| s == "orientation check");
    assert!(
        check.is_some_and(|c| c < first_map)
            && stages[..first_map].contains(&"turned pairs".to_owned())
            && !stages[first_map..].contains(&"turned images".to_owned()),
        "{stages:?}"
    );
    let rotations: Vec<_> = estimate
        .cameras
        .iter()
        .map(|c| c.as_ref().unwrap().cam_from_world.rotation)
        .collect();
    assert_rotations_with_turned(&rotations, &[3, 4, 5]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// LightGlue's products are F32 unless `learned.precision` asks for the tiles' "high"
/// (`--set`, a config file, Python's `options`), and the tree's keypoints reach the extractor;
/// a value that is not a precision is refused.
#[test]
fn the_learned_precision_is_an_option_and_f32_by_default() {
    use posediff::estimate::run::RunOptions;
    use posediff_diffusion::MatmulPrecision;
    let mut options = RunOptions {
        matcher: MatcherChoice::AlikedLightGlue,
        weights_dir: Some(weights_dir()),
        ..RunOptions::default()
    };
    let loaded = options.load_learned().unwrap().expect("a learned matcher");
    assert_eq!(loaded.0.precision(), MatmulPrecision::Highest);
    options.pipeline = options
        .pipeline
        .with_field("learned.precision", "high")
        .unwrap();
    options.pipeline = options
        .pipeline
        .with_field("learned.max_keypoints", "1024")
        .unwrap();
    let loaded = options.load_learned().unwrap().expect("a learned matcher");
    assert_eq!(loaded.0.precision(), MatmulPrecision::High);
    assert_eq!(loaded.0.aliked_config.max_keypoints, 1024);
    assert_eq!(loaded.0.image_side, 1024);
    let wrong = options.pipeline.with_field("learned.precision", "bf16");
    let message = wrong.unwrap_err().to_string();
    assert!(message.contains("learned.precision"), "{message}");
}

/// A database made by the learned matcher records its `learned.*` settings: the same run
/// reads its features back, and one with other keypoints or precision is refused by name
/// before any work instead of mixing features.
#[test]
fn a_learned_database_refuses_other_learned_settings() {
    let dir = posediff_fixtures::temp_dir("learned-database-settings");
    let images = dir.join("images");
    std::fs::create_dir_all(&images).unwrap();
    for img in &apple(3) {
        std::fs::copy(img, images.join(img.file_name().unwrap())).unwrap();
    }
    let db = dir.join("learned.db");
    let run = |out: &str, extra: &[&str]| {
        let mut args: Vec<OsString> = [
            "estimate".into(),
            images.clone().into_os_string(),
            "--matcher".into(),
            "aliked-lightglue".into(),
            "--weights-dir".into(),
            weights_dir().into_os_string(),
            "--database".into(),
            db.clone().into_os_string(),
            "--out".into(),
            dir.join(out).into_os_string(),
            "--quiet".into(),
            "--no-view".into(),
        ]
        .into();
        args.extend(extra.iter().map(OsString::from));
        Command::new(env!("CARGO_BIN_EXE_posediff"))
            .args(&args)
            .output()
            .unwrap()
    };
    let first = run("first", &[]);
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let again = run("again", &[]);
    assert!(
        again.status.success(),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    for setting in ["learned.max_keypoints=1024", "learned.precision=high"] {
        let other = run("other", &["--set", setting]);
        let e = String::from_utf8_lossy(&other.stderr);
        assert!(!other.status.success(), "{setting}: accepted");
        assert!(
            e.contains("holds features made with settings"),
            "{setting}: {e}"
        );
        assert!(!dir.join("other").join("cameras.json").exists());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
