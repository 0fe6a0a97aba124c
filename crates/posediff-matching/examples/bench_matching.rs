//! Match-quality report on real image sets with ground-truth cameras:
//!
//! ```text
//! cargo xtask bench-matching --data ../shared/data --out target/bench-matching.json
//! ```
//!
//! For every set (all pairs) and detector: matches per pair after mutual nearest neighbours,
//! the ratio test and MAGSAC verification, and the fraction whose Sampson distance to the
//! ground-truth fundamental matrix (from `cameras.json`) is below 1 and 4 px²; time for
//! extraction + matching. Writes JSON to `--out` and a Markdown table beside it (`.md`).
#![allow(clippy::print_stdout)]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use posediff_geometry::camera_json::CameraRecord;
use posediff_geometry::{Camera, fundamental_from_cameras, sampson_error};
use posediff_matching::{Detector, MatchConfig, match_images};
use serde_json::json;

const SETS: [&str; 3] = [
    "co3d_apple_posediffusion",
    "middlebury_templeSR",
    "strecha_fountainP11",
];

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let get = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let (Some(data), Some(out)) = (get("--data"), get("--out")) else {
        bail!("usage: bench_matching --data <shared/data> --out <report.json>");
    };
    let data = PathBuf::from(data);
    let out = PathBuf::from(out);
    let mut rows = Vec::new();
    let mut md = String::from(
        "| set | detector | images | pairs | pairs ≥ 10 matches | matches | ≤ 1 px² | ≤ 4 px² | seconds |\n|---|---|---:|---:|---:|---:|---:|---:|---:|\n",
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
        for (name, detector) in [("sift", Detector::Sift), ("orb", Detector::Orb)] {
            let mut config = MatchConfig::default();
            config.features.detector = detector;
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
            let (_, pairs) = match_images(&images, None, &config)?;
            let seconds = start.elapsed().as_secs_f64();
            let (mut total, mut within1, mut within4, mut good_pairs) =
                (0usize, 0usize, 0usize, 0usize);
            let mut per_pair = Vec::new();
            for p in &pairs {
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
                good_pairs += usize::from(errs.len() >= 10);
                per_pair.push(json!({"first": p.first, "second": p.second, "matches": errs.len(), "within_1px2": w1, "within_4px2": w4}));
            }
            let frac = |k: usize| {
                if total > 0 {
                    k as f64 / total as f64
                } else {
                    0.0
                }
            };
            println!(
                "{set:26} {name:4}: {} pairs, {good_pairs} with >= 10 matches, {total} matches, {:.3} <= 1 px², {:.3} <= 4 px², {seconds:.2} s",
                pairs.len(),
                frac(within1),
                frac(within4)
            );
            md.push_str(&format!(
                "| {set} | {name} | {} | {} | {good_pairs} | {total} | {:.3} | {:.3} | {seconds:.2} |\n",
                images.len(),
                pairs.len(),
                frac(within1),
                frac(within4)
            ));
            rows.push(json!({
                "set": set, "detector": name, "images": images.len(), "pairs": pairs.len(),
                "pairs_with_10_matches": good_pairs, "matches_total": total,
                "frac_within_1px2": frac(within1), "frac_within_4px2": frac(within4), "seconds": seconds,
                "config": {"max_keypoints": config.features.max_keypoints, "max_image_side": config.features.max_image_side,
                           "ratio": config.ratio, "verification_threshold_px": config.verification.map(|v| v.threshold_px)},
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
        .find(|r| r["set"] == SETS[0] && r["detector"] == "sift")
        .and_then(|r| r["seconds"].as_f64());
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
