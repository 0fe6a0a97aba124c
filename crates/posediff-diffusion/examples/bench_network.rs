//! The network's stages timed as the pipeline runs them (`cargo xtask bench-network`): the
//! features of N images (three scales, one batch, as `posediff estimate` does), one denoiser
//! step, and the 100-step reverse diffusion (no GGS), at each N of `--frames`; with
//! `--pytorch P.json` (written by `scripts/network_torch.py` in the same run) the ratio table.
//! Writes `OUT/report.json` and `OUT/report.md`.
//!
//! `cargo run --release -p posediff-diffusion --example bench_network -- --reference
//! ../shared/reference/full --frames 10,20,100 --out target/bench-network [--pytorch P.json]`

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::{DType, Device, Tensor};
use posediff_diffusion::PoseDiffusionModel;
use posediff_diffusion::sampler::{SeededNoise, sample};
use serde_json::{Value, json};

/// The `posediff` binary's allocator (glibc's returns the layers' large buffers to the kernel
/// after each op: page faults on every allocation).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

struct Args {
    reference: PathBuf,
    frames: Vec<usize>,
    repeats: usize,
    out: PathBuf,
    pytorch: Option<PathBuf>,
}

fn args() -> Result<Args> {
    let mut a = Args {
        reference: PathBuf::from("../shared/reference/full"),
        frames: vec![10, 20, 100],
        repeats: 3,
        out: PathBuf::from("target/bench-network"),
        pytorch: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--reference" => a.reference = value()?.into(),
            "--frames" => {
                a.frames = value()?
                    .split(',')
                    .map(|s| s.parse().with_context(|| format!("--frames: {s:?}")))
                    .collect::<Result<_>>()?;
            }
            "--repeats" => a.repeats = value()?.parse()?,
            "--out" => a.out = value()?.into(),
            "--pytorch" => a.pytorch = Some(value()?.into()),
            _ => bail!("unknown argument {flag:?}"),
        }
    }
    if a.repeats == 0 || a.frames.is_empty() {
        bail!("--repeats and --frames must not be empty");
    }
    Ok(a)
}

/// The peak resident set of this process so far, MB (Linux `VmHWM`).
fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// The fastest of `repeats` runs of `f`, seconds, and all of them.
fn best_of(repeats: usize, mut f: impl FnMut() -> Result<()>) -> Result<(f64, Vec<f64>)> {
    let mut all = Vec::with_capacity(repeats);
    for _ in 0..repeats {
        let start = Instant::now();
        f()?;
        all.push(start.elapsed().as_secs_f64());
    }
    let best = all.iter().copied().fold(f64::INFINITY, f64::min);
    Ok((best, all))
}

fn main() -> Result<()> {
    let a = args()?;
    let path = a.reference.join("model_random.safetensors");
    let model = PoseDiffusionModel::load(&path, DType::F32, &Device::Cpu)
        .with_context(|| format!("{}", path.display()))?;
    let mut rows = Vec::new();
    for &n in &a.frames {
        let images = Tensor::rand(0f32, 1f32, (1, n, 3, 224, 224), &Device::Cpu)?;
        model.image_features(&images.narrow(1, 0, n.min(2))?)?; // warm-up
        let mut z = None;
        let (features, features_runs) = best_of(a.repeats, || {
            z = Some(model.image_features(&images)?);
            Ok(())
        })?;
        let z = z.context("no features")?;
        let x = Tensor::randn(0f32, 1f32, (1, n, 9), &Device::Cpu)?;
        let (step, _) = best_of(10, || {
            model.denoiser.forward(&x, &[50], &z)?;
            Ok(())
        })?;
        let mut noise = SeededNoise::new(0);
        let (sampling, sampling_runs) = best_of(a.repeats, || {
            sample(&model.denoiser, &model.schedule, &z, &mut noise, None, None)?;
            Ok(())
        })?;
        eprintln!("posediff {n} frames: features {features:.3} s, 100 steps {sampling:.3} s");
        rows.push(json!({
            "frames": n,
            "features_s": features,
            "features_runs_s": features_runs,
            "denoiser_step_s": step,
            "sampling_100_s": sampling,
            "sampling_runs_s": sampling_runs,
            "peak_rss_mb": peak_rss_mb(),
        }));
    }
    let pytorch: Option<Value> = match &a.pytorch {
        Some(p) => Some(
            serde_json::from_str(
                &std::fs::read_to_string(p).with_context(|| format!("{}", p.display()))?,
            )
            .with_context(|| format!("{}", p.display()))?,
        ),
        None => None,
    };
    let report = json!({
        "threads": candle_core::utils::get_num_threads(),
        "posediff": rows,
        "pytorch": pytorch,
    });
    std::fs::create_dir_all(&a.out)?;
    std::fs::write(
        a.out.join("report.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    let md = markdown(&rows, pytorch.as_ref());
    std::fs::write(a.out.join("report.md"), &md)?;
    eprintln!("{md}");
    Ok(())
}

/// The table: per N and stage, PyTorch's and our best time and their ratio (PyTorch / ours:
/// above 1 when we are faster).
fn markdown(rows: &[Value], pytorch: Option<&Value>) -> String {
    let mut md = String::from(
        "| frames | stage | PyTorch (s) | posediff (s) | PyTorch / posediff |\n|---:|---|---:|---:|---:|\n",
    );
    for row in rows {
        let n = row["frames"].as_u64().unwrap_or(0);
        let theirs = pytorch.and_then(|p| {
            p["rows"]
                .as_array()?
                .iter()
                .find(|r| r["frames"].as_u64() == Some(n))
        });
        for (key, label) in [
            ("features_s", "features, 3 scales"),
            ("denoiser_step_s", "one denoiser step"),
            ("sampling_100_s", "100 denoiser steps (sampling)"),
        ] {
            let ours = row[key].as_f64().unwrap_or(f64::NAN);
            let (t, ratio) = match theirs.and_then(|r| r[key].as_f64()) {
                Some(t) => (format!("{t:.3}"), format!("{:.2}x", t / ours)),
                None => ("–".to_owned(), "–".to_owned()),
            };
            let _ = writeln!(md, "| {n} | {label} | {t} | {ours:.3} | {ratio} |");
        }
    }
    if let Some(p) = pytorch {
        let _ = writeln!(
            md,
            "\nPyTorch {} with {} threads; its check against the official outputs: {}",
            p["torch"].as_str().unwrap_or("?"),
            p["threads"],
            p["checks"]
        );
    }
    md
}
