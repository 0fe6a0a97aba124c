//! `posediff device-check`: is the network right and how fast is it on this device? The F32
//! parity checks against the official outputs of `../shared/reference/{tiny,full}` (backbone,
//! denoiser, the reverse diffusion teacher-forced step by step), then timings of the
//! backbone, one denoiser step, the 100-step sampling and the training iteration of the tiny
//! and official presets. Writes `report.json` and `report.md`; fails after writing them when a
//! parity check fails. `scripts/device_check.sh` runs it on a GPU machine (`--device cuda`)
//! and, in the tests, on the CPU.
//!
//! The tolerances are those of the CPU's F32 parity tests (`posediff-diffusion/tests/
//! parity_f32.rs`, `parity_model.rs`): float32 rounding of the network, about 1e-6 relative per
//! single pass (`full/README.md`), summed in another order on the GPU but not less precise.
//! The features are LayerNorm outputs up to about 5: 1e-5 absolute; a denoiser output
//! 1e-6 × max(1, |ε̂|max); a teacher-forced step x_(t−1) 1e-5 absolute. cuBLAS's reduced
//! precision (TF32) is switched off for these checks: it keeps 10 mantissa bits, not 23.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use candle_core::{DType, Device, IndexOp, Tensor};
use posediff::train::TrainConfig;
use posediff_diffusion::PoseDiffusionModel;
use posediff_diffusion::checkpoint::Checkpoint;
use posediff_diffusion::sampler::{SeededNoise, denoise_step, sample};
use posediff_diffusion::train::{AdamW, Trainable, clip_grad_norm, denoising_loss};
use rand::{Rng, SeedableRng};

use super::DeviceArg;

/// Check the network on a device against the official outputs and time it (report.json,
/// report.md).
#[derive(clap::Args)]
pub struct Args {
    /// The parity fixtures: the folder holding `full/` (`../shared/reference`).
    #[arg(long)]
    reference: PathBuf,
    /// The tiny fixtures' model, when not `tiny/model_tiny.safetensors` of `--reference` (the
    /// repository's `fixtures/torch/model_tiny_module_prefix.pth` holds the same values).
    #[arg(long)]
    tiny_model: Option<PathBuf>,
    /// Where the network runs.
    #[arg(long, value_enum, default_value = "cpu")]
    device: DeviceArg,
    /// Output folder (report.json, report.md).
    #[arg(long)]
    out: PathBuf,
    /// Frame counts timed (backbone, denoiser step, 100-step sampling).
    #[arg(long, value_delimiter = ',', default_value = "1,10,20,100")]
    frames: Vec<usize>,
    /// Timed runs per measurement (the best is reported).
    #[arg(long, default_value_t = 5)]
    repeats: usize,
    /// Timed training iterations per preset (after one warm-up iteration).
    #[arg(long, default_value_t = 5)]
    train_iterations: usize,
    /// Also write the timed official-size model here (for `posediff estimate --weights`).
    #[arg(long)]
    save_model: Option<PathBuf>,
    /// Also run the timed network in BF16 and F16: their difference from F32 on the fixture
    /// images and their speed at 20 frames (informational, no bound).
    #[arg(long)]
    half: bool,
    /// Skip the official preset's training iteration (900 sequences of 50 frames; always
    /// skipped on the CPU, where its backward pass needs more than 24 GB).
    #[arg(long)]
    skip_official_training: bool,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        if self.frames.is_empty() || self.frames.contains(&0) || self.repeats == 0 {
            bail!("--frames needs positive frame counts and --repeats at least 1");
        }
        // The fixture sets: tiny (17 MB, travels to a GPU machine) always, full when present.
        let mut tiny = FixtureSet::tiny(&self.reference);
        if let Some(model) = &self.tiny_model {
            tiny.model.clone_from(model);
        }
        let sets: Vec<FixtureSet> = [tiny, FixtureSet::full(&self.reference)]
            .into_iter()
            .filter(|s| s.required || s.model.is_file())
            .collect();
        for set in &sets {
            for f in [&set.model, &set.denoiser_io, &set.sampling_io] {
                if !f.is_file() {
                    bail!(
                        "{}: missing (--reference is the folder of the parity fixtures, \
                         ../shared/reference, holding tiny/ and optionally full/; --tiny-model \
                         for the tiny model elsewhere)",
                        f.display()
                    );
                }
            }
        }
        // The output folder before minutes of work, not after.
        std::fs::create_dir_all(&self.out)
            .with_context(|| format!("creating {}", self.out.display()))?;
        let device = self.device.device()?;
        // Full float32 products for the parity checks and the timings alike.
        candle_core::cuda::set_gemm_reduced_precision_f32(false);
        let mut checks = Vec::new();
        for set in &sets {
            let model = PoseDiffusionModel::load(&set.model, DType::F32, &device)
                .with_context(|| format!("loading {}", set.model.display()))?;
            checks.extend(parity(set, &model, &device)?);
        }
        for c in &checks {
            eprintln!(
                "{:<48} worst {:.3e} (bound {:.1e}) {}",
                c.name,
                c.worst,
                c.bound,
                if c.pass() { "ok" } else { "FAILED" }
            );
        }
        // The timed network: the official size, the random-weight checkpoint of the fixtures
        // when present, else freshly initialised (timings do not depend on the values).
        let full = FixtureSet::full(&self.reference);
        let load_start = Instant::now();
        let (checkpoint, timed_model) = if full.model.is_file() {
            (
                Checkpoint::load(&full.model, &device)?,
                full.model.display().to_string(),
            )
        } else {
            let depths = posediff_diffusion::checkpoint::ModelDepths::OFFICIAL;
            (
                posediff_diffusion::train::initial_checkpoint(depths, 0, &device)?,
                "official size, initialised with seed 0".to_owned(),
            )
        };
        let model = PoseDiffusionModel::from_checkpoint(&checkpoint, DType::F32, &device)?;
        device.synchronize()?;
        let load_s = load_start.elapsed().as_secs_f64();
        if let Some(path) = &self.save_model {
            checkpoint
                .save_safetensors(path)
                .with_context(|| format!("writing {}", path.display()))?;
        }
        let timings = network_timings(&model, &device, &self.frames, self.repeats)?;
        let half = if self.half {
            half_precision(&checkpoint, &model, &sets[0], &device, self.repeats)?
        } else {
            Vec::new()
        };
        drop(model);
        let tiny = Checkpoint::load(&sets[0].model, &device)?;
        let mut training = vec![train_rate(
            &tiny,
            &TrainConfig::tiny(),
            &device,
            self.train_iterations,
        )?];
        if self.skip_official_training {
            training.push(TrainingRow::Skipped {
                preset: "official".into(),
                skipped: "--skip-official-training".into(),
            });
        } else if device.is_cpu() {
            // 900 sequences of 50 frames with their backward pass: killed at 24 GB here.
            training.push(TrainingRow::Skipped {
                preset: "official".into(),
                skipped: "a GPU's: on the CPU its backward pass needs more than 24 GB".into(),
            });
        } else {
            // Its size is the device's limit (out of memory, say): reported, not fatal, so the
            // parity and network figures above still reach the report.
            let official = train_rate(
                &checkpoint,
                &TrainConfig::official(),
                &device,
                self.train_iterations,
            )
            .unwrap_or_else(|e| TrainingRow::Failed {
                preset: "official".into(),
                error: first_line(&e),
            });
            training.push(official);
        }
        let report = DeviceReport {
            device: self.device.name(),
            device_name: device_name(&device),
            threads: candle_core::utils::get_num_threads(),
            timed_model,
            model_load_s: load_s,
            parity: checks.iter().map(Check::record).collect(),
            parity_passed: checks.iter().all(Check::pass),
            network: timings,
            half_precision: half,
            training,
        };
        let json_path = self.out.join("report.json");
        std::fs::write(&json_path, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", json_path.display()))?;
        let md = markdown(&report);
        let md_path = self.out.join("report.md");
        std::fs::write(&md_path, &md).with_context(|| format!("writing {}", md_path.display()))?;
        eprintln!("{md}");
        let failed: Vec<&str> = checks
            .iter()
            .filter(|c| !c.pass())
            .map(|c| c.name.as_str())
            .collect();
        if !failed.is_empty() {
            bail!(
                "parity failed on {}: {} (report in {})",
                self.device.name(),
                failed.join(", "),
                self.out.display()
            );
        }
        Ok(())
    }
}

/// One set of parity fixtures: a random-weight model and the official outputs it gave.
struct FixtureSet {
    name: &'static str,
    model: PathBuf,
    denoiser_io: PathBuf,
    sampling_io: PathBuf,
    required: bool,
}

impl FixtureSet {
    fn tiny(reference: &Path) -> Self {
        let dir = reference.join("tiny");
        Self {
            name: "tiny",
            model: dir.join("model_tiny.safetensors"),
            denoiser_io: dir.join("denoiser_io_tiny.safetensors"),
            sampling_io: dir.join("sampling_io_tiny.safetensors"),
            required: true,
        }
    }

    fn full(reference: &Path) -> Self {
        let dir = reference.join("full");
        Self {
            name: "full",
            model: dir.join("model_random.safetensors"),
            denoiser_io: dir.join("denoiser_io.safetensors"),
            sampling_io: dir.join("sampling_io.safetensors"),
            required: false,
        }
    }
}

/// What the device calls itself (the CPU, or the GPU's index).
fn device_name(device: &Device) -> String {
    match device {
        Device::Cpu => std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("model name"))
                    .and_then(|l| l.split(':').nth(1))
                    .map(|n| n.trim().to_owned())
            })
            .unwrap_or_else(|| "cpu".to_owned()),
        Device::Cuda(_) => "cuda:0".to_owned(),
        Device::Metal(_) => "metal".to_owned(),
    }
}

/// One parity check: the worst absolute difference against its bound.
struct Check {
    name: String,
    worst: f64,
    bound: f64,
}

impl Check {
    fn pass(&self) -> bool {
        self.worst.is_finite() && self.worst <= self.bound
    }

    fn record(&self) -> CheckRecord {
        CheckRecord {
            check: self.name.clone(),
            worst_abs: self.worst,
            bound: self.bound,
            pass: self.pass(),
        }
    }
}

/// The values of `t` in f64 on the host.
fn host(t: &Tensor) -> anyhow::Result<Vec<f64>> {
    Ok(t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?)
}

/// Largest `|a − b|` (infinite on a shape mismatch or a non-finite value).
fn worst(ours: &Tensor, expected: &Tensor) -> anyhow::Result<f64> {
    let (a, b) = (host(ours)?, host(expected)?);
    if a.len() != b.len() {
        return Ok(f64::INFINITY);
    }
    Ok(a.iter().zip(&b).fold(0.0, |w, (x, y)| {
        let d = (x - y).abs();
        if d.is_finite() {
            w.max(d)
        } else {
            f64::INFINITY
        }
    }))
}

/// `max(1, max |t|)`.
fn scale(t: &Tensor) -> anyhow::Result<f64> {
    Ok(host(t)?.iter().fold(1.0f64, |a, v| a.max(v.abs())))
}

/// The checks of `tests/parity_f32.rs` and the teacher-forced sampling of `parity_model.rs`,
/// on `device` in F32.
fn parity(
    set: &FixtureSet,
    model: &PoseDiffusionModel,
    device: &Device,
) -> anyhow::Result<Vec<Check>> {
    let load = |path: &Path| -> anyhow::Result<std::collections::HashMap<String, Tensor>> {
        candle_core::safetensors::load(path, device)
            .with_context(|| format!("reading {}", path.display()))
    };
    let get = |map: &std::collections::HashMap<String, Tensor>, name: &str, file: &str| {
        map.get(name)
            .with_context(|| format!("{file} has no tensor {name:?}"))
            .and_then(|t| Ok(t.to_dtype(DType::F32)?))
    };
    let io = load(&set.denoiser_io)?;
    let file = set.denoiser_io.display().to_string();
    let file = file.as_str();
    let mut checks = Vec::new();
    let z = model.image_features(&get(&io, "images", file)?.unsqueeze(0)?)?;
    checks.push(Check {
        name: format!("{}: backbone features z (5 images, 3 scales)", set.name),
        worst: worst(&z, &get(&io, "z", file)?)?,
        bound: 1e-5,
    });
    let (x, z) = (get(&io, "x_t", file)?, get(&io, "z", file)?);
    for t in [0usize, 37, 99] {
        let expected = get(&io, &format!("out_t{t}"), file)?;
        let out = model.denoiser.forward(&x, &[t], &z)?;
        checks.push(Check {
            name: format!("{}: denoiser step t = {t}", set.name),
            worst: worst(&out, &expected)?,
            bound: 1e-6 * scale(&expected)?,
        });
    }
    let file = set.sampling_io.display().to_string();
    let file = file.as_str();
    let io = load(&set.sampling_io)?;
    let (z, process, noise, pred) = (
        get(&io, "z", file)?,
        get(&io, "pose_process", file)?,
        get(&io, "step_noise", file)?,
        get(&io, "pred_noise", file)?,
    );
    let s = &model.schedule;
    let (mut worst_eps, mut bound_eps, mut worst_x) = (0.0f64, 1e-6, 0.0f64);
    for k in 0..s.len() {
        let t = s.len() - 1 - k;
        let step = denoise_step(&model.denoiser, s, &process.i(k)?, t, &z)?;
        let expected = pred.i(k)?;
        let bound = 1e-6 * scale(&expected)?;
        let w = worst(&step.pred_noise, &expected)?;
        // The ratio to its own bound decides the worst step.
        if w.is_nan() || w / bound > worst_eps / bound_eps {
            (worst_eps, bound_eps) = (w, bound);
        }
        let next = if t > 0 {
            let sigma = (0.5 * s.posterior_log_variance_clipped[t]).exp();
            (&step.model_mean + (noise.i(k)? * sigma)?)?
        } else {
            step.model_mean
        };
        worst_x = worst_x.max(worst(&next, &process.i(k + 1)?)?);
    }
    checks.push(Check {
        name: format!("{}: sampling, teacher-forced ε̂ (worst step)", set.name),
        worst: worst_eps,
        bound: bound_eps,
    });
    checks.push(Check {
        name: format!("{}: sampling, teacher-forced x_(t−1)", set.name),
        worst: worst_x,
        bound: 1e-5,
    });
    Ok(checks)
}

/// The fastest of `repeats` runs of `f`, seconds (the device synchronised before the clock
/// stops).
fn best_of(
    repeats: usize,
    device: &Device,
    mut f: impl FnMut() -> anyhow::Result<()>,
) -> anyhow::Result<f64> {
    let mut best = f64::INFINITY;
    for _ in 0..repeats {
        device.synchronize()?;
        let start = Instant::now();
        f()?;
        device.synchronize()?;
        best = best.min(start.elapsed().as_secs_f64());
    }
    Ok(best)
}

/// Per frame count: the features of N images (three scales), one denoiser step and the
/// 100-step sampling (no GGS), as `posediff estimate` runs them; each after a warm-up.
fn network_timings(
    model: &PoseDiffusionModel,
    device: &Device,
    frames: &[usize],
    repeats: usize,
) -> anyhow::Result<Vec<NetworkRow>> {
    let mut rows = Vec::new();
    for &n in frames {
        let images = Tensor::rand(0f32, 1f32, (1, n, 3, 224, 224), device)?;
        let mut z = model.image_features(&images)?; // warm-up (kernel JIT, cuBLAS plans)
        let features = best_of(repeats, device, || {
            z = model.image_features(&images)?;
            Ok(())
        })?;
        let x = Tensor::randn(0f32, 1f32, (1, n, 9), device)?;
        model.denoiser.forward(&x, &[50], &z)?;
        let step = best_of(repeats.max(10), device, || {
            model.denoiser.forward(&x, &[50], &z)?;
            Ok(())
        })?;
        let mut noise = SeededNoise::new(0);
        let sampling = best_of(repeats.min(3), device, || {
            sample(&model.denoiser, &model.schedule, &z, &mut noise, None, None)?;
            Ok(())
        })?;
        eprintln!(
            "{n} frames: features {features:.4} s, denoiser step {step:.5} s, 100 steps {sampling:.4} s"
        );
        rows.push(NetworkRow {
            frames: n,
            features_s: features,
            denoiser_step_s: step,
            sampling_100_s: sampling,
            features_plus_sampling_s: features + sampling,
        });
    }
    Ok(rows)
}

/// The timed network in BF16 and F16 against itself in F32: the largest difference of the
/// features of the fixture images and of one denoiser step (t = 37), relative to the largest
/// F32 value, and the features + 100-step sampling at 20 frames.
fn half_precision(
    checkpoint: &Checkpoint,
    f32_model: &PoseDiffusionModel,
    set: &FixtureSet,
    device: &Device,
    repeats: usize,
) -> anyhow::Result<Vec<HalfRow>> {
    let io = candle_core::safetensors::load(&set.denoiser_io, device)
        .with_context(|| format!("reading {}", set.denoiser_io.display()))?;
    let get = |name: &str| {
        io.get(name)
            .with_context(|| format!("{} has no tensor {name:?}", set.denoiser_io.display()))
            .and_then(|t| Ok(t.to_dtype(DType::F32)?))
    };
    let images = get("images")?.unsqueeze(0)?;
    let x = get("x_t")?;
    let z32 = f32_model.image_features(&images)?;
    let out32 = f32_model.denoiser.forward(&x, &[37], &z32)?;
    let relative = |ours: &Tensor, reference: &Tensor| -> anyhow::Result<f64> {
        let ours = ours.to_dtype(DType::F32)?;
        Ok(worst(&ours, reference)? / scale(reference)?)
    };
    let one = |dtype: DType| -> anyhow::Result<HalfRow> {
        let model = PoseDiffusionModel::from_checkpoint(checkpoint, dtype, device)?;
        let z = model.image_features(&images.to_dtype(dtype)?)?;
        let out = model
            .denoiser
            .forward(&x.to_dtype(dtype)?, &[37], &z32.to_dtype(dtype)?)?;
        let n = 20;
        let frames = Tensor::rand(0f32, 1f32, (1, n, 3, 224, 224), device)?.to_dtype(dtype)?;
        let mut zn = model.image_features(&frames)?;
        let features = best_of(repeats, device, || {
            zn = model.image_features(&frames)?;
            Ok(())
        })?;
        let mut noise = SeededNoise::new(0);
        let sampling = best_of(repeats.min(3), device, || {
            sample(
                &model.denoiser,
                &model.schedule,
                &zn,
                &mut noise,
                None,
                None,
            )?;
            Ok(())
        })?;
        Ok(HalfRow::Measured {
            dtype: format!("{dtype:?}"),
            features_rel_diff: relative(&z, &z32)?,
            denoiser_rel_diff: relative(&out, &out32)?,
            features_20_s: features,
            sampling_100_20_s: sampling,
        })
    };
    // Informational: a dtype the device cannot run (candle has no BF16 product on the CPU)
    // is reported as such, not fatal.
    let rows = [DType::BF16, DType::F16]
        .into_iter()
        .map(|dtype| {
            let row = one(dtype).unwrap_or_else(|e| HalfRow::Failed {
                dtype: format!("{dtype:?}"),
                error: first_line(&e),
            });
            eprintln!("{row:?}");
            row
        })
        .collect();
    Ok(rows)
}

/// An error's message without candle's backtrace lines.
fn first_line(e: &anyhow::Error) -> String {
    let text = format!("{e:#}");
    text.lines().next().unwrap_or_default().trim().to_owned()
}

/// Training iterations per second of `preset` with a frozen backbone (features cached, as
/// `posediff train --freeze-backbone` runs): the preset's batch (⌊images / max_frames⌋ sets of
/// `max_frames` frames, each repeated `batch_repeat` times with its own step and noise) on
/// random features and encodings, the denoising loss, backward, gradient clipping and AdamW.
fn train_rate(
    checkpoint: &Checkpoint,
    preset: &TrainConfig,
    device: &Device,
    iterations: usize,
) -> anyhow::Result<TrainingRow> {
    let trainable = Trainable::from_checkpoint(checkpoint, device)?;
    let trained: Vec<_> = trainable
        .named_variables()
        .into_iter()
        .filter(|(k, _)| k.starts_with("diffuser."))
        .collect();
    let mut optimizer = AdamW::new(trained)?;
    let n = preset.max_frames;
    let sets = (preset.images_per_batch / n).max(1);
    let r = preset.batch_repeat.max(1);
    let b = sets * r;
    let z = Tensor::randn(0f32, 1f32, (sets, n, 384), device)?.repeat((r, 1, 1))?;
    let x0 = Tensor::randn(0f32, 1f32, (sets, n, 9), device)?.repeat((r, 1, 1))?;
    let model = &trainable.model;
    let steps = model.schedule.len();
    let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    let mut seconds = Vec::new();
    let mut last_loss = f64::NAN;
    for i in 0..=iterations {
        device.synchronize()?;
        let start = Instant::now();
        let t: Vec<usize> = (0..b).map(|_| rng.random_range(0..steps)).collect();
        let noise = Tensor::randn(0f32, 1f32, (b, n, 9), device)?;
        let (_, _, loss) = denoising_loss(&model.denoiser, &model.schedule, &z, &x0, &t, &noise)?;
        let mut grads = loss.backward()?;
        clip_grad_norm(&mut grads, &optimizer.vars(), preset.clip)?;
        optimizer.step(&grads, preset.lr)?;
        last_loss = f64::from(loss.to_scalar::<f32>()?);
        device.synchronize()?;
        if i > 0 {
            seconds.push(start.elapsed().as_secs_f64());
        }
    }
    if !last_loss.is_finite() {
        bail!("{} training: the loss is not finite", preset.preset);
    }
    let mean = seconds.iter().sum::<f64>() / seconds.len().max(1) as f64;
    eprintln!(
        "training, {} preset: {mean:.3} s per iteration ({sets} sets × {n} frames × {r} repeats)",
        preset.preset
    );
    Ok(TrainingRow::Measured {
        preset: preset.preset.to_string(),
        depths: format!("{:?}", checkpoint.depths()),
        sets,
        frames: n,
        batch_repeat: r,
        iterations_timed: seconds.len(),
        seconds_per_iteration: mean,
        iterations_per_s: 1.0 / mean,
        loss: last_loss,
    })
}

/// report.json: one typed record.
#[derive(Debug, serde::Serialize)]
struct DeviceReport {
    /// `cpu` or `cuda`.
    device: &'static str,
    /// The CPU's model name or the GPU.
    device_name: String,
    /// candle's threads.
    threads: usize,
    /// The checkpoint the timings ran.
    timed_model: String,
    /// Seconds to load it.
    model_load_s: f64,
    /// Each parity check.
    parity: Vec<CheckRecord>,
    /// All within their bounds.
    parity_passed: bool,
    /// Timings per frame count.
    network: Vec<NetworkRow>,
    /// BF16 and F16 against F32 (`--half`).
    half_precision: Vec<HalfRow>,
    /// Training iterations per preset.
    training: Vec<TrainingRow>,
}

/// One parity check in report.json.
#[derive(Debug, serde::Serialize)]
struct CheckRecord {
    check: String,
    worst_abs: f64,
    bound: f64,
    pass: bool,
}

/// The network's timings at one frame count (best of the runs, seconds).
#[derive(Debug, serde::Serialize)]
struct NetworkRow {
    frames: usize,
    features_s: f64,
    denoiser_step_s: f64,
    sampling_100_s: f64,
    features_plus_sampling_s: f64,
}

/// One half-precision dtype against F32, or why it did not run.
#[derive(Debug, serde::Serialize)]
#[serde(untagged)]
enum HalfRow {
    Measured {
        dtype: String,
        features_rel_diff: f64,
        denoiser_rel_diff: f64,
        features_20_s: f64,
        sampling_100_20_s: f64,
    },
    Failed {
        dtype: String,
        error: String,
    },
}

/// One training preset's iteration rate, or why it did not run.
#[derive(Debug, serde::Serialize)]
#[serde(untagged)]
enum TrainingRow {
    Measured {
        preset: String,
        depths: String,
        sets: usize,
        frames: usize,
        batch_repeat: usize,
        iterations_timed: usize,
        seconds_per_iteration: f64,
        iterations_per_s: f64,
        loss: f64,
    },
    Skipped {
        preset: String,
        skipped: String,
    },
    Failed {
        preset: String,
        error: String,
    },
}

/// The Markdown report.
fn markdown(r: &DeviceReport) -> String {
    let mut md = format!(
        "# posediff device-check: {} ({})\n\nTimed model: {} (loaded in {:.2} s).\n\n## F32 parity against the official outputs\n\n| check | worst abs | bound | |\n|---|---:|---:|---|\n",
        r.device, r.device_name, r.timed_model, r.model_load_s,
    );
    for c in &r.parity {
        let _ = writeln!(
            md,
            "| {} | {:.2e} | {:.1e} | {} |",
            c.check,
            c.worst_abs,
            c.bound,
            if c.pass { "ok" } else { "**failed**" }
        );
    }
    md.push_str("\n## Network (best of the runs, seconds)\n\n| frames | features, 3 scales | one denoiser step | 100-step sampling | features + sampling |\n|---:|---:|---:|---:|---:|\n");
    for row in &r.network {
        let _ = writeln!(
            md,
            "| {} | {:.4} | {:.5} | {:.4} | {:.4} |",
            row.frames,
            row.features_s,
            row.denoiser_step_s,
            row.sampling_100_s,
            row.features_plus_sampling_s
        );
    }
    if !r.half_precision.is_empty() {
        md.push_str("\n## Half precision against F32 (the timed network; differences relative to the largest F32 value)\n\n| dtype | features | denoiser step | features, 20 frames (s) | 100-step sampling, 20 frames (s) |\n|---|---:|---:|---:|---:|\n");
        for row in &r.half_precision {
            let _ = match row {
                HalfRow::Failed { dtype, error } => {
                    writeln!(md, "| {dtype} | not run: {error} | | | |")
                }
                HalfRow::Measured {
                    dtype,
                    features_rel_diff,
                    denoiser_rel_diff,
                    features_20_s,
                    sampling_100_20_s,
                } => writeln!(
                    md,
                    "| {dtype} | {features_rel_diff:.2e} | {denoiser_rel_diff:.2e} | {features_20_s:.4} | {sampling_100_20_s:.4} |"
                ),
            };
        }
    }
    md.push_str("\n## Training iteration (frozen backbone)\n\n| preset | batch | s / iteration | iterations / s |\n|---|---|---:|---:|\n");
    for row in &r.training {
        let _ = match row {
            TrainingRow::Failed { preset, error } => {
                writeln!(md, "| {preset} | failed: {error} | – | – |")
            }
            TrainingRow::Skipped { preset, skipped } => {
                writeln!(md, "| {preset} | skipped ({skipped}) | – | – |")
            }
            TrainingRow::Measured {
                preset,
                sets,
                frames,
                batch_repeat,
                seconds_per_iteration,
                iterations_per_s,
                ..
            } => writeln!(
                md,
                "| {preset} | {sets} sets × {frames} frames × {batch_repeat} repeats | {seconds_per_iteration:.3} | {iterations_per_s:.2} |"
            ),
        };
    }
    md
}
