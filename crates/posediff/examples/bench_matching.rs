//! Match-quality report on real image sets with ground-truth cameras:
//!
//! ```text
//! cargo xtask bench-matching --data ../shared/data --out target/bench-matching.json
//!     [--matchers sift,orb,aliked-lightglue] [--weights-dir target/weights]
//!     [--ratio R] [--threshold PX] [--min-inliers K]
//! ```
//!
//! For every set (all pairs) and matcher (`sift` and `orb` by default; the learned ones of
//! `posediff estimate --matcher` with `--weights-dir`): the pairs kept by the verification (at
//! least `--min-inliers` MAGSAC inliers, 20 by default), the fraction of their matches within 1
//! and 4 px² (Sampson) of the ground-truth epipolar geometry, the kept pairs that are *good*
//! (at least 80 % of their matches within 4 px²) and *wrong* (the rest), the good pairs by the
//! ground-truth rotation angle between the two cameras (0–30°, 30–60°, 60–90°, beyond 90°: good
//! pairs / all pairs in that range), and seconds per image (extraction) and per pair
//! (matching and verification). Writes JSON to `--out` and a Markdown table beside it (`.md`).
#![allow(clippy::print_stdout)]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use posediff::correspondences::{
    LearnedMatcher, MatcherChoice, SharedLearned, extract_all, match_pairs,
};
use posediff_geometry::camera_json::CameraRecord;
use posediff_geometry::epipolar::rotation_angle_between_deg;
use posediff_geometry::{Camera, fundamental_from_cameras, sampson_error};
use posediff_matching::MatchConfig;
use serde_json::json;

const SETS: [&str; 3] = [
    "co3d_apple_posediffusion",
    "middlebury_templeSR",
    "strecha_fountainP11",
];

/// A kept pair is good when at least this fraction of its matches is within 4 px².
const GOOD_FRACTION: f64 = 0.8;

/// Upper ends of the ground-truth angle ranges, degrees (the last is open).
const ANGLE_BINS: [f64; 3] = [30.0, 60.0, 90.0];

fn angle_bin(angle: f64) -> usize {
    ANGLE_BINS
        .iter()
        .position(|&hi| angle < hi)
        .unwrap_or(ANGLE_BINS.len())
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let get = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let (Some(data), Some(out)) = (get("--data"), get("--out")) else {
        bail!(
            "usage: bench_matching --data <shared/data> --out <report.json> \
             [--matchers sift,orb,aliked-lightglue] [--weights-dir D]"
        );
    };
    let matchers: Vec<MatcherChoice> = get("--matchers")
        .unwrap_or_else(|| "sift,orb".into())
        .split(',')
        .map(|m| m.trim().parse().context("--matchers"))
        .collect::<anyhow::Result<_>>()?;
    let weights_dir = get("--weights-dir")
        .map(PathBuf::from)
        .unwrap_or_else(posediff_learned::weights::default_dir);
    // Every learned matcher's weights are checked (and loaded) before any image is read.
    let mut learned = Vec::new();
    for m in &matchers {
        learned.push(match m.extractor_weights() {
            Some(set) => Some(SharedLearned(std::sync::Arc::new(
                LearnedMatcher::load_with(&weights_dir, set)?,
            ))),
            None => None,
        });
    }
    let data = PathBuf::from(data);
    let out = PathBuf::from(out);
    let mut rows = Vec::new();
    let mut md = String::from(
        "| set | matcher | images | pairs | kept (≥ min inliers) | good | wrong | good by angle 0-30 / 30-60 / 60-90 / >90° | matches | ≤ 1 px² | ≤ 4 px² | s / image | s / pair |\n\
         |---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|\n",
    );
    for set in SETS {
        let dir = data.join(set);
        let text = std::fs::read_to_string(dir.join("cameras.json"))
            .with_context(|| format!("{set}/cameras.json"))?;
        let records: Vec<CameraRecord> = serde_json::from_str(&text)?;
        let cameras: Vec<Camera> = records
            .iter()
            .map(CameraRecord::to_camera)
            .collect::<Result<_, _>>()?;
        let images: Vec<PathBuf> = records.iter().map(|r| dir.join(&r.image)).collect();
        let all_pairs = posediff_matching::exhaustive_pairs(images.len());
        let angles: Vec<f64> = all_pairs
            .iter()
            .map(|&(i, j)| {
                rotation_angle_between_deg(
                    &cameras[i].cam_from_world.rotation,
                    &cameras[j].cam_from_world.rotation,
                )
            })
            .collect();
        let mut in_bin = [0usize; 4];
        for &a in &angles {
            in_bin[angle_bin(a)] += 1;
        }
        for (matcher, learned) in matchers.iter().zip(&learned) {
            let name = matcher.as_str();
            let mut config = MatchConfig::default();
            config.features.detector = matcher.detector();
            if let Some(r) = get("--ratio") {
                config.ratio = Some(r.parse()?);
            }
            if let (Some(t), Some(v)) = (get("--threshold"), config.verification.as_mut()) {
                v.threshold_px = t.parse()?;
            }
            if let Some(k) = get("--min-inliers") {
                config.min_verified = k.parse()?;
            }
            eprintln!("{set} {name} ...");
            let start = Instant::now();
            let features = extract_all(&images, &config, learned.as_ref())?;
            let extraction = start.elapsed().as_secs_f64();
            let start = Instant::now();
            let pairs = match_pairs(&features, &all_pairs, &config, learned.as_ref())?;
            let matching = start.elapsed().as_secs_f64();
            let (mut total, mut within1, mut within4) = (0usize, 0usize, 0usize);
            let (mut kept, mut good, mut good_by_bin) = (0usize, 0usize, [0usize; 4]);
            let mut per_pair = Vec::new();
            for (p, &angle) in pairs.iter().zip(&angles) {
                let f = fundamental_from_cameras(&cameras[p.first], &cameras[p.second]);
                let errs: Vec<f64> = p
                    .kp1
                    .iter()
                    .zip(&p.kp2)
                    .map(|(a, b)| {
                        sampson_error(
                            &f,
                            &nalgebra::Point2::new(a[0], a[1]),
                            &nalgebra::Point2::new(b[0], b[1]),
                        )
                        .unwrap_or(f64::INFINITY)
                    })
                    .collect();
                let w1 = errs.iter().filter(|e| **e < 1.0).count();
                let w4 = errs.iter().filter(|e| **e < 4.0).count();
                total += errs.len();
                within1 += w1;
                within4 += w4;
                let is_good = !errs.is_empty() && w4 as f64 >= GOOD_FRACTION * errs.len() as f64;
                if !errs.is_empty() {
                    kept += 1;
                    if is_good {
                        good += 1;
                        good_by_bin[angle_bin(angle)] += 1;
                    }
                }
                per_pair.push(
                    json!({"first": p.first, "second": p.second, "gt_angle_deg": angle,
                    "matches": errs.len(), "within_1px2": w1, "within_4px2": w4, "good": is_good}),
                );
            }
            let frac = |k: usize| {
                if total > 0 {
                    k as f64 / total as f64
                } else {
                    0.0
                }
            };
            let per_image = extraction / images.len() as f64;
            let per_pair_s = matching / all_pairs.len().max(1) as f64;
            let by_angle = (0..4)
                .map(|b| format!("{}/{}", good_by_bin[b], in_bin[b]))
                .collect::<Vec<_>>()
                .join(", ");
            let wrong = kept - good;
            println!(
                "{set:26} {name:24}: {kept} kept, {good} good, {wrong} wrong ({by_angle}), {total} matches, {:.3} <= 4 px², {per_image:.3} s/image, {per_pair_s:.3} s/pair",
                frac(within4)
            );
            md.push_str(&format!(
                "| {set} | {name} | {} | {} | {kept} | {good} | {wrong} | {by_angle} | {total} | {:.3} | {:.3} | {per_image:.3} | {per_pair_s:.3} |\n",
                images.len(),
                all_pairs.len(),
                frac(within1),
                frac(within4)
            ));
            rows.push(json!({
                "set": set, "matcher": name, "images": images.len(), "pairs": all_pairs.len(),
                "pairs_kept": kept, "pairs_good": good, "pairs_wrong": wrong,
                "good_by_angle": {"bins_deg": [0, 30, 60, 90], "good": good_by_bin, "pairs": in_bin},
                "matches_total": total,
                "frac_within_1px2": frac(within1), "frac_within_4px2": frac(within4),
                "seconds_extraction": extraction, "seconds_matching": matching,
                "seconds_per_image": per_image, "seconds_per_pair": per_pair_s,
                "config": {"max_keypoints": config.features.max_keypoints, "max_image_side": config.features.max_image_side,
                           "ratio": config.ratio, "verification_threshold_px": config.verification.map(|v| v.threshold_px),
                           "min_inliers": config.min_verified},
                "per_pair": per_pair,
            }));
        }
    }
    // OpenCV-python SIFT + BFMatcher on the apple frames, in the same run, for the speed ratio.
    let apple_images = data.join(SETS[0]).join("images");
    let baseline = std::process::Command::new("python3")
        .arg("scripts/opencv_python_matching_baseline.py")
        .arg(&apple_images)
        .output()
        .ok()
        .filter(|o| o.status.success())
        .and_then(|o| serde_json::from_slice::<serde_json::Value>(&o.stdout).ok());
    let ours = rows
        .iter()
        .find(|r| r["set"] == SETS[0] && r["matcher"] == "sift")
        .and_then(|r| Some(r["seconds_extraction"].as_f64()? + r["seconds_matching"].as_f64()?));
    let ratio = match (&baseline, ours) {
        (Some(b), Some(o)) => b["seconds"].as_f64().map(|b| b / o),
        _ => None,
    };
    match (&baseline, ratio) {
        (Some(b), Some(r)) => {
            let line = format!(
                "\nOpenCV-python {} SIFT + BFMatcher (cross-check), {} apple frames, all pairs: {:.2} s; posediff SIFT + mutual NN + ratio + MAGSAC: {:.2} s ({r:.2}x faster)\n",
                b["opencv"], b["images"], b["seconds"].as_f64().unwrap_or(f64::NAN), ours.unwrap_or(f64::NAN)
            );
            md.push_str(&line);
        }
        _ => md.push_str("\nOpenCV-python baseline not run (needs python3 with opencv-python-headless; run from the workspace root).\n"),
    }
    let report = json!({
        "command": std::env::args().collect::<Vec<_>>().join(" "),
        "results": rows,
        "opencv_python_baseline_apple": baseline,
        "speedup_vs_opencv_python_apple_sift": ratio,
    });
    std::fs::write(&out, serde_json::to_string_pretty(&report)?)?;
    std::fs::write(out.with_extension("md"), &md)?;
    println!("\n{md}");
    Ok(())
}
