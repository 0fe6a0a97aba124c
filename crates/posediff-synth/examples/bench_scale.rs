//! `cargo xtask bench-scale`: how the checkpoint-free mapper grows with the number of frames.
//!
//! For each camera path (orbit, forward) and each N, a synthetic 640×480 sequence with exact
//! cameras is rendered (`posediff-synth`), then a fresh process runs the pipeline stage by
//! stage — extraction, pair selection, matching, then the mapper (two-view geometry, averaging,
//! refinement, bundle adjustment) — recording wall time and the peak resident set after each
//! stage, and scores the cameras against the ground truth (RRA@5, RTA@5, mAA(30), registered
//! fraction). The report (JSON + Markdown) fits the growth exponent of each stage between
//! successive sizes and over N ≥ 100.
//!
//! With `--against-colmap`, COLMAP 4.2's global mapper (pycolmap 4.2.1 through
//! `../shared/tools/pycolmap_run.py`: SIFT, sequential matching with `--colmap-overlap` (15)
//! neighbours, a comparable number of pairs to posediff's `auto`) runs on the same frames in the
//! same run, under `/usr/bin/time` for its peak resident set, and is scored the same way: the
//! report gets both columns and the speed-up.
//!
//! ```sh
//! cargo xtask bench-scale --sizes 20,50,100 --paths orbit,forward --out target/bench-scale
//! cargo xtask bench-scale --sizes 300 --paths orbit --against-colmap \
//!     --python target/client-venv/bin/python --out target/bench-scale-colmap
//! ```
#![allow(clippy::print_stdout)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use posediff::estimate::geometric::{GeometricConfig, estimate_from_matches};
use posediff_matching::{PairSelection, extract_all, match_pairs, select_pairs};
use posediff_synth::scene::PathKind;
use posediff_synth::{DatasetSpec, LensSpec, parse_size, write_dataset};
use serde_json::{Value, json};

/// The peak resident set of this process so far, MB (Linux `VmHWM`).
fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// CPU seconds (user + system) this process has used so far (Linux `/proc/self/stat`): the
/// measure that other work on the host does not inflate, written beside the wall time.
fn cpu_seconds() -> f64 {
    let ticks = Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| {
            String::from_utf8_lossy(&o.stdout)
                .trim()
                .parse::<f64>()
                .ok()
        })
        .unwrap_or(f64::NAN);
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            // Fields after the command name (which may hold spaces) start at the state, field 3;
            // utime and stime are fields 14 and 15.
            let rest = &s[s.rfind(')')? + 2..];
            let f: Vec<&str> = rest.split_whitespace().collect();
            Some(f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?)
        })
        .map_or(f64::NAN, |t| t / ticks)
}

/// One case, in this process: `--case IMAGES GT OUT.json PAIRS`.
fn run_case(images_dir: &Path, gt: &Path, out: &Path, pairs: &str) -> Result<()> {
    let images = posediff::io::loader::image_files(images_dir)?;
    let n = images.len();
    let mut config = GeometricConfig::default();
    config.options.pairs.selection = pairs.parse::<PairSelection>().map_err(anyhow::Error::msg)?;
    let mut stages = Vec::new();
    let total = Instant::now();
    let clock = Instant::now();
    let features = extract_all(&images, &config.options.matching)?;
    stages.push(("extraction", clock.elapsed().as_secs_f64(), peak_rss_mb()));
    let clock = Instant::now();
    let pair_list = select_pairs(n, &config.options.pairs.selection, Some(&features))?;
    stages.push((
        "pair selection",
        clock.elapsed().as_secs_f64(),
        peak_rss_mb(),
    ));
    let clock = Instant::now();
    let matches = match_pairs(&features, &pair_list, &config.options.matching)?;
    let sizes: Vec<_> = features.iter().map(|f| f.image_size).collect();
    drop(features);
    stages.push(("matching", clock.elapsed().as_secs_f64(), peak_rss_mb()));
    let verified = matches.iter().filter(|p| !p.is_empty()).count();
    let estimate = estimate_from_matches(&sizes, matches, &config)?;
    let rss = peak_rss_mb();
    let t = &estimate.report.times;
    let bundle = estimate.report.bundle();
    stages.push(("two-view", t.two_view, rss));
    stages.push(("averaging", t.averaging, rss));
    stages.push((
        "sampson refinement",
        (t.initialisation - t.two_view - t.averaging).max(0.0),
        rss,
    ));
    stages.push(("bridge resection", t.resection, rss));
    stages.push(("bundle adjustment", t.refinement - t.resection, rss));
    let seconds = total.elapsed().as_secs_f64();
    let truth = posediff::io::export::read_cameras_json(gt)?;
    let gt_cams: Vec<_> = truth.iter().map(|c| c.camera).collect();
    let pred: Vec<_> = estimate
        .cameras
        .iter()
        .map(|c| c.map(|c| c.cam_from_world))
        .collect();
    let (scores, cc) = posediff::bench::score_set(&gt_cams, &pred)?;
    let registered = pred.iter().filter(|p| p.is_some()).count() as f64 / n as f64;
    let report = json!({
        "frames": n,
        "pairs": pairs,
        "pairs_matched": pair_list.len(),
        "pairs_verified": verified,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds(),
        "peak_rss_mb": peak_rss_mb(),
        "stages": stages.iter().map(|(s, t, r)| json!({"stage": s, "seconds": t, "peak_rss_mb_after": r})).collect::<Vec<_>>(),
        "rra_5": scores.rra[0],
        "rta_5": scores.rta[0],
        "maa_30": scores.maa_30,
        "cc_10": cc,
        "registered": registered,
        "bundle_points": bundle.map_or(0, |b| b.points),
        "bundle_observations": bundle.map_or(0, |b| b.observations),
        "bundle_iterations": bundle.map_or(0, |b| b.iterations),
        "sampson_iterations": estimate.report.sampson().map_or(0, |s| s.iterations),
        "focal_factor": estimate.report.focal_factor,
    });
    std::fs::write(out, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", out.display()))?;
    Ok(())
}

/// How to run COLMAP 4.2 beside posediff (`--against-colmap`).
struct Colmap {
    python: PathBuf,
    script: PathBuf,
    overlap: usize,
}

/// COLMAP 4.2's global mapper on `images` into `out`, scored against `gt`: wall seconds (its
/// own, features and matching included), peak RSS, the accuracy figures. A failed run is a
/// report with `"error"`, not an abort, so posediff's column still lands.
fn run_colmap(colmap: &Colmap, images: &Path, gt: &Path, out: &Path) -> Value {
    let rss_file = out.with_extension("rss");
    let _ = std::fs::create_dir_all(out.parent().unwrap_or(Path::new(".")));
    let clock = Instant::now();
    let output = Command::new("/usr/bin/time")
        .args(["-f", "%M %U %S", "-o"])
        .arg(&rss_file)
        .arg(&colmap.python)
        .arg(&colmap.script)
        .arg(images)
        .arg(out)
        .args(["--mappers", "global", "--threads", "2", "--matching"])
        .arg(format!("sequential:{}", colmap.overlap))
        .output();
    let wall = clock.elapsed().as_secs_f64();
    let output = match output {
        Ok(o) => o,
        Err(e) => {
            return json!({"error": format!("running /usr/bin/time {}: {e}", colmap.python.display())});
        }
    };
    if !output.status.success() {
        let stderr = String::from_utf8_lossy(&output.stderr);
        return json!({"error": format!("pycolmap_run.py failed ({}): {}", output.status, stderr.lines().last().unwrap_or(""))});
    }
    let lines: Vec<Value> = String::from_utf8_lossy(&output.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    let seconds_of = |key: &str, name: &str| {
        lines
            .iter()
            .find(|v| v[key] == json!(name))
            .and_then(|v| v["seconds"].as_f64())
    };
    // `/usr/bin/time -f "%M %U %S"`: peak kB, user and system seconds (its last line).
    let time_fields: Vec<f64> = std::fs::read_to_string(&rss_file)
        .ok()
        .and_then(|s| {
            s.lines()
                .last()?
                .split_whitespace()
                .map(|x| x.parse::<f64>().ok())
                .collect()
        })
        .unwrap_or_default();
    let peak_rss_mb = time_fields.first().map_or(f64::NAN, |kb| kb / 1024.0);
    let cpu_seconds = match time_fields[..] {
        [_, user, system] => user + system,
        _ => f64::NAN,
    };
    match posediff::bench::score_cameras_files(&out.join("global/cameras.json"), gt) {
        Ok(s) => json!({
            "mapper": "COLMAP 4.2 global (pycolmap 4.2.1)",
            "matching": format!("sequential:{}", colmap.overlap),
            "seconds": seconds_of("mapper", "global").unwrap_or(wall),
            "features_matching_seconds": seconds_of("stage", "features+matching"),
            "cpu_seconds": cpu_seconds,
            "peak_rss_mb": peak_rss_mb,
            "rra_5": s.scores.rra[0],
            "rta_5": s.scores.rta[0],
            "maa_30": s.scores.maa_30,
            "registered": s.scores.registered,
        }),
        Err(e) => json!({"error": format!("scoring COLMAP's cameras: {e}")}),
    }
}

fn arg(args: &[String], flag: &str, default: &str) -> String {
    args.windows(2)
        .find(|w| w[0] == flag)
        .map_or_else(|| default.to_owned(), |w| w[1].clone())
}

/// Least-squares slope of log(y) against log(x).
fn exponent(points: &[(f64, f64)]) -> Option<f64> {
    let p: Vec<(f64, f64)> = points
        .iter()
        .filter(|(x, y)| *x > 0.0 && *y > 1e-3)
        .map(|(x, y)| (x.ln(), y.ln()))
        .collect();
    if p.len() < 2 {
        return None;
    }
    let n = p.len() as f64;
    let (mx, my) = (
        p.iter().map(|q| q.0).sum::<f64>() / n,
        p.iter().map(|q| q.1).sum::<f64>() / n,
    );
    let sxx: f64 = p.iter().map(|q| (q.0 - mx).powi(2)).sum();
    let sxy: f64 = p.iter().map(|q| (q.0 - mx) * (q.1 - my)).sum();
    (sxx > 0.0).then(|| sxy / sxx)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("--case") {
        let [_, images, gt, out, pairs] = args.as_slice() else {
            bail!("usage: bench_scale --case IMAGES GT OUT.json PAIRS");
        };
        return run_case(Path::new(images), Path::new(gt), Path::new(out), pairs);
    }
    let sizes: Vec<usize> = arg(&args, "--sizes", "20,50,100")
        .split(',')
        .map(|s| s.trim().parse().context("--sizes: whole numbers"))
        .collect::<Result<_>>()?;
    let paths: Vec<String> = arg(&args, "--paths", "orbit,forward")
        .split(',')
        .map(str::to_owned)
        .collect();
    let out = PathBuf::from(arg(&args, "--out", "target/bench-scale"));
    let pairs = arg(&args, "--pairs", "auto");
    let seed: u64 = arg(&args, "--seed", "3").parse().context("--seed")?;
    let colmap = if args.iter().any(|a| a == "--against-colmap") {
        let python = PathBuf::from(arg(&args, "--python", "python3"));
        let script = PathBuf::from(arg(
            &args,
            "--colmap-script",
            "../shared/tools/pycolmap_run.py",
        ));
        if !script.is_file() {
            bail!(
                "--against-colmap: {} is not a file (pass --colmap-script)",
                script.display()
            );
        }
        let check = Command::new(&python)
            .args(["-c", "import pycolmap; print(pycolmap.__version__)"])
            .output()
            .with_context(|| format!("--python {}", python.display()))?;
        if !check.status.success() {
            bail!(
                "--against-colmap: {} cannot import pycolmap (install scripts/requirements-clients.txt or pass --python)",
                python.display()
            );
        }
        Some(Colmap {
            python,
            script,
            overlap: arg(&args, "--colmap-overlap", "15")
                .parse()
                .context("--colmap-overlap: a whole number")?,
        })
    } else {
        None
    };
    std::fs::create_dir_all(&out)?;
    let exe = std::env::current_exe()?;
    let mut cases: Vec<Value> = Vec::new();
    for path in &paths {
        let kind = match path.as_str() {
            "orbit" => PathKind::Orbit,
            "forward" => PathKind::Forward,
            other => bail!("--paths: unknown path `{other}` (orbit, forward)"),
        };
        for &n in &sizes {
            let scene_dir = out.join(format!("scenes/{path}_{n}"));
            let seq = scene_dir.join("synthetic/synthetic_0000");
            if !seq.join("cameras.json").is_file() {
                let clock = Instant::now();
                write_dataset(
                    &scene_dir,
                    &DatasetSpec {
                        sequences: 1,
                        frames: n,
                        seed,
                        sizes: vec![parse_size("640x480")?],
                        test_every: 0,
                        path: Some(kind),
                        lens: LensSpec::default(),
                    },
                )?;
                eprintln!(
                    "rendered {path} N={n} in {:.1} s",
                    clock.elapsed().as_secs_f64()
                );
            }
            let case = out.join(format!("{path}_{n}.json"));
            eprintln!("running {path} N={n} ...");
            let status = Command::new(&exe)
                .args(["--case"])
                .arg(seq.join("images"))
                .arg(seq.join("cameras.json"))
                .arg(&case)
                .arg(&pairs)
                .status()?;
            if !status.success() {
                bail!("{path} N={n} failed: {status}");
            }
            let mut v: Value = serde_json::from_str(&std::fs::read_to_string(&case)?)?;
            v["path"] = json!(path);
            eprintln!(
                "{path} N={n}: {:.1} s, peak {:.0} MB, RRA@5 {:.3}, RTA@5 {:.3}, mAA(30) {:.3}, registered {:.3}",
                v["seconds"].as_f64().unwrap_or(f64::NAN),
                v["peak_rss_mb"].as_f64().unwrap_or(f64::NAN),
                v["rra_5"].as_f64().unwrap_or(f64::NAN),
                v["rta_5"].as_f64().unwrap_or(f64::NAN),
                v["maa_30"].as_f64().unwrap_or(f64::NAN),
                v["registered"].as_f64().unwrap_or(f64::NAN),
            );
            if let Some(colmap) = &colmap {
                eprintln!("running COLMAP 4.2's global mapper on {path} N={n} ...");
                let c = run_colmap(
                    colmap,
                    &seq.join("images"),
                    &seq.join("cameras.json"),
                    &out.join(format!("colmap/{path}_{n}")),
                );
                eprintln!("{path} N={n} COLMAP: {c}");
                v["colmap"] = c;
            }
            cases.push(v);
        }
    }
    // Growth exponents per path and stage.
    let stage_names: Vec<String> = cases
        .first()
        .and_then(|c| c["stages"].as_array())
        .map(|s| {
            s.iter()
                .filter_map(|x| x["stage"].as_str().map(str::to_owned))
                .collect()
        })
        .unwrap_or_default();
    let mut exponents = serde_json::Map::new();
    for path in &paths {
        let of_path: Vec<&Value> = cases.iter().filter(|c| c["path"] == json!(path)).collect();
        let mut per_stage = serde_json::Map::new();
        for (k, stage) in stage_names.iter().enumerate() {
            let points: Vec<(f64, f64)> = of_path
                .iter()
                .filter_map(|c| Some((c["frames"].as_f64()?, c["stages"][k]["seconds"].as_f64()?)))
                .collect();
            let large: Vec<(f64, f64)> = points.iter().copied().filter(|p| p.0 >= 100.0).collect();
            per_stage.insert(
                stage.clone(),
                json!({"all": exponent(&points), "n_ge_100": exponent(&large)}),
            );
        }
        exponents.insert(path.clone(), Value::Object(per_stage));
    }
    let report = json!({"pairs": pairs, "seed": seed, "cases": cases, "exponents": exponents});
    std::fs::write(
        out.join("report.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    let mut md = String::from(
        "| path | N | pairs | total s | peak RSS MB | RRA@5 | RTA@5 | mAA(30) | registered | points |",
    );
    md.push_str(&format!(
        " {} |\n",
        stage_names
            .iter()
            .map(|s| format!("{s} s"))
            .collect::<Vec<_>>()
            .join(" | ")
    ));
    md.push_str(&format!("|{}\n", "---|".repeat(10 + stage_names.len())));
    for c in &cases {
        let f = |k: &str| c[k].as_f64().unwrap_or(f64::NAN);
        md.push_str(&format!(
            "| {} | {} | {} | {:.1} | {:.0} | {:.3} | {:.3} | {:.3} | {:.3} | {} |",
            c["path"].as_str().unwrap_or(""),
            c["frames"],
            c["pairs_matched"],
            f("seconds"),
            f("peak_rss_mb"),
            f("rra_5"),
            f("rta_5"),
            f("maa_30"),
            f("registered"),
            c["bundle_points"],
        ));
        for k in 0..stage_names.len() {
            md.push_str(&format!(
                " {:.2} |",
                c["stages"][k]["seconds"].as_f64().unwrap_or(f64::NAN)
            ));
        }
        md.push('\n');
    }
    md.push_str("\nGrowth exponent of each stage's time in N (least squares on log-log; all sizes / N ≥ 100):\n\n| path | stage | all | N ≥ 100 |\n|---|---|---|---|\n");
    for (path, per_stage) in &exponents {
        if let Some(m) = per_stage.as_object() {
            for (stage, e) in m {
                let fmt = |v: &Value| v.as_f64().map_or("–".to_owned(), |x| format!("{x:.2}"));
                md.push_str(&format!(
                    "| {path} | {stage} | {} | {} |\n",
                    fmt(&e["all"]),
                    fmt(&e["n_ge_100"])
                ));
            }
        }
    }
    if colmap.is_some() {
        md.push_str("\nAgainst COLMAP 4.2's global mapper (pycolmap 4.2.1, SIFT, sequential matching) on the same frames, in the same run:\n\n| path | N | posediff s | COLMAP s | speed-up | CPU s, posediff / COLMAP (whole process) | posediff / COLMAP peak RSS MB | posediff / COLMAP mAA(30) | RRA@5 | RTA@5 | registered |\n|---|---|---|---|---|---|---|---|---|---|---|\n");
        for c in &cases {
            let ours = |k: &str| c[k].as_f64().unwrap_or(f64::NAN);
            let theirs = |k: &str| c["colmap"][k].as_f64().unwrap_or(f64::NAN);
            if let Some(e) = c["colmap"]["error"].as_str() {
                md.push_str(&format!(
                    "| {} | {} | {:.1} | failed: {e} | | | | | | | |\n",
                    c["path"].as_str().unwrap_or(""),
                    c["frames"],
                    ours("seconds")
                ));
                continue;
            }
            md.push_str(&format!(
                "| {} | {} | {:.1} | {:.1} | {:.2}× | {:.0} / {:.0} | {:.0} / {:.0} | {:.3} / {:.3} | {:.3} / {:.3} | {:.3} / {:.3} | {:.3} / {:.3} |\n",
                c["path"].as_str().unwrap_or(""),
                c["frames"],
                ours("seconds"),
                theirs("seconds"),
                theirs("seconds") / ours("seconds"),
                ours("cpu_seconds"),
                theirs("cpu_seconds"),
                ours("peak_rss_mb"),
                theirs("peak_rss_mb"),
                ours("maa_30"),
                theirs("maa_30"),
                ours("rra_5"),
                theirs("rra_5"),
                ours("rta_5"),
                theirs("rta_5"),
                ours("registered"),
                theirs("registered"),
            ));
        }
    }
    std::fs::write(out.join("report.md"), &md)?;
    println!("{md}");
    println!("wrote {} and report.md", out.join("report.json").display());
    Ok(())
}
