//! Training PoseDiffusion on CO3D-layout data (`posediff train`, `cargo xtask train`; SPEC.md
//! §7.2, `train.py`).
//!
//! Per iteration: one frame count `n ∈ [3, max_frames]`, `⌊images_per_batch / n⌋` sequences
//! (with replacement) of `n` random frames each (without replacement), the ground truth of each
//! set normalised as the official dataset does (camera 0's PyTorch3D frame, optical-axis
//! scale) and encoded; `batch_repeat` draws of `(t, ε)` per set (one `t` per set); the L1
//! ε-prediction loss; `clip_grad_norm_(1.0)`; torch's AdamW under the warm-up + cosine-restarts
//! schedule. The random numbers of iteration `k` come from a generator seeded by
//! `(seed, k)`, so a resumed run continues exactly as an uninterrupted one.
//!
//! With a frozen backbone the features of every frame are computed once (official centre crop,
//! the test-time loader) and cached: the practical mode on a CPU. Otherwise every batch is read
//! and augmented as the official dataset does ([`crate::train::augment`]: jittered square crops, colour
//! jitter per sequence) and the gradients reach the backbone.
//!
//! A checkpoint folder holds `model.safetensors` (official keys, schedule buffers included:
//! `posediff estimate --weights` and PyTorch load it), `optimizer.safetensors` (AdamW moments),
//! `trainer.json` (iteration, settings), `loss.csv` and `loss.png`.

pub mod augment;
pub mod log;

pub use log::{LogRow, read_log, write_log};

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use posediff_diffusion::checkpoint::Checkpoint;
use posediff_diffusion::train::{AdamW, Trainable, clip_grad_norm, denoising_loss, learning_rate};
use posediff_geometry::Camera;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::error::{PosediffError, Result};
use crate::estimate::estimator::normalised_encodings;
use crate::io::co3d::{frame_path, load_annotations, usable_sequences};
use crate::io::loader::{load_images, read_rgb};
use crate::train::augment::{
    AugmentConfig, SequenceColour, crop_and_resize, crop_camera, jittered_crop,
};

/// Training settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// `tiny` or `official`.
    pub preset: String,
    /// Peak learning rate.
    pub lr: f64,
    /// Learning rate at the start of the warm-up.
    pub warmup_init: f64,
    /// Warm-up iterations.
    pub warmup: u64,
    /// Cosine period (restarts) in iterations.
    pub period: u64,
    /// Largest frame count per set.
    pub max_frames: usize,
    /// Images per batch (`⌊images_per_batch / n⌋` sets).
    pub images_per_batch: usize,
    /// `(t, ε)` draws per set.
    pub batch_repeat: usize,
    /// Iterations in all.
    pub iterations: u64,
    /// Gradient-norm clip.
    pub clip: f64,
    /// Sequences with fewer frames are skipped.
    pub min_frames: usize,
    /// Seed of the sampling.
    pub seed: u64,
    /// Write a checkpoint every this many iterations (and at the end).
    pub checkpoint_every: u64,
    /// ViT blocks of a freshly initialised model (without `--init`).
    #[serde(default = "tiny_depth")]
    pub vit_blocks: usize,
    /// Denoiser trunk layers of a freshly initialised model.
    #[serde(default = "tiny_depth")]
    pub trunk_layers: usize,
}

/// Depth of the tiny network (state files written before the depth fields existed).
fn tiny_depth() -> usize {
    2
}

impl TrainConfig {
    /// The official recipe (`cfgs/default_train.yaml`): lr 1e-4, 10 % warm-up from 1e-7, cosine
    /// restarts every 50 epochs of 16384 batches, 3–50 frames, 512 images per batch, batch repeat
    /// 90, 100 epochs, sequences of ≥ 50 frames.
    pub fn official() -> Self {
        let epoch = 16_384;
        Self {
            preset: "official".into(),
            lr: 1e-4,
            warmup_init: 1e-7,
            warmup: 5 * epoch,
            period: 50 * epoch,
            max_frames: 50,
            images_per_batch: 512,
            batch_repeat: 90,
            iterations: 100 * epoch,
            clip: 1.0,
            min_frames: 50,
            seed: 0,
            checkpoint_every: epoch,
            vit_blocks: 12,
            trunk_layers: 8,
        }
    }

    /// A CPU-sized run: lr 5e-4 after 100 warm-up iterations, one cosine period, 3–10 frames,
    /// 40 images per batch, batch repeat 4, sequences of ≥ 10 frames; fresh models have the tiny
    /// fixture's depths (2 ViT blocks, 2 trunk layers).
    pub fn tiny() -> Self {
        Self {
            preset: "tiny".into(),
            lr: 5e-4,
            warmup_init: 1e-6,
            warmup: 100,
            period: 2_000,
            max_frames: 10,
            images_per_batch: 40,
            batch_repeat: 4,
            iterations: 2_000,
            clip: 1.0,
            min_frames: 10,
            seed: 0,
            checkpoint_every: 500,
            vit_blocks: 2,
            trunk_layers: 2,
        }
    }
}

/// One training sequence: its frames' cameras and, with a frozen backbone, cached features.
#[derive(Debug, Clone)]
pub struct TrainSequence {
    /// Sequence name.
    pub name: String,
    /// Camera of each frame's official (unjittered) 224 crop.
    pub cameras: Vec<Camera>,
    /// Features `(F, 384)` of those crops (frozen backbone), else `None`.
    pub features: Option<Tensor>,
    /// Each frame's image file and camera of the whole image (for the jittered crops).
    pub frames: Vec<(PathBuf, Camera)>,
}

/// An annotation split: `{category}_{split}.jgz`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Split {
    /// `{category}_train.jgz`.
    Train,
    /// `{category}_test.jgz`.
    Test,
}

impl Split {
    /// Its name in the file names.
    pub fn name(self) -> &'static str {
        match self {
            Self::Train => "train",
            Self::Test => "test",
        }
    }
}

/// Where the training data is and which of it is used.
#[derive(Debug, Clone, Copy)]
pub struct TrainData<'a> {
    /// CO3D root (the annotations' image paths are relative to it).
    pub co3d_dir: &'a Path,
    /// Folder of `{category}_{split}.jgz`.
    pub annotation_dir: &'a Path,
    /// Categories.
    pub categories: &'a [String],
    /// Split.
    pub split: Split,
    /// Sequences with fewer frames are left out.
    pub min_frames: usize,
}

/// What a run feeds the model: each frame's features computed once by a frozen backbone, or
/// the frames themselves, read and augmented per batch.
#[derive(Debug, Clone, Copy)]
pub enum FrameInput<'m> {
    /// Features cached with this model's backbone.
    CachedFeatures(&'m posediff_diffusion::PoseDiffusionModel),
    /// Frames read per batch (only their sizes and cameras now).
    Augmented,
}

/// Reads the annotations of `data`; with [`FrameInput::CachedFeatures`] also computes every
/// usable frame's features with the model's backbone, 16 images at a time.
///
/// # Errors
/// Unreadable annotations or images, no usable sequence, model errors.
pub fn load_training_data(
    data: &TrainData<'_>,
    input: FrameInput<'_>,
    device: &Device,
    mut progress: impl FnMut(usize, usize),
) -> Result<Vec<TrainSequence>> {
    let TrainData {
        co3d_dir,
        annotation_dir,
        categories,
        split,
        min_frames,
    } = *data;
    let split = split.name();
    let mut all = Vec::new();
    for category in categories {
        let sequences = load_annotations(&annotation_dir.join(format!("{category}_{split}.jgz")))?;
        all.extend(
            usable_sequences(&sequences, min_frames)
                .into_iter()
                .cloned(),
        );
    }
    if all.is_empty() {
        return Err(PosediffError::InvalidArgument(format!(
            "no {split} sequence with at least {min_frames} frames in {}",
            annotation_dir.display()
        )));
    }
    let total = all.len();
    let mut out = Vec::with_capacity(total);
    for (k, seq) in all.iter().enumerate() {
        let paths: Vec<PathBuf> = seq.frames.iter().map(|f| frame_path(co3d_dir, f)).collect();
        let mut chunks = Vec::new();
        let mut cameras = Vec::new();
        let mut frames = Vec::new();
        for (chunk_paths, chunk_frames) in paths.chunks(16).zip(seq.frames.chunks(16)) {
            let FrameInput::CachedFeatures(model) = input else {
                // Batches are read and augmented later: only the sizes are needed now.
                for (path, f) in chunk_paths.iter().zip(chunk_frames) {
                    let (size, _) = read_rgb(path)?;
                    cameras.push(f.crop_camera(size)?);
                    frames.push((path.clone(), f.pytorch3d().to_opencv(size)?));
                }
                continue;
            };
            let loaded = load_images(chunk_paths)?;
            for ((l, f), path) in loaded.iter().zip(chunk_frames).zip(chunk_paths) {
                cameras.push(f.crop_camera(l.size)?);
                frames.push((path.clone(), f.pytorch3d().to_opencv(l.size)?));
            }
            {
                let pixels: Vec<f32> = loaded
                    .iter()
                    .flat_map(|l| l.pixels.iter().copied())
                    .collect();
                let side = posediff_geometry::MODEL_INPUT_SIDE as usize;
                let images = Tensor::from_vec(pixels, (1, loaded.len(), 3, side, side), device)?;
                chunks.push(model.image_features(&images)?.squeeze(0)?.detach());
            }
        }
        out.push(TrainSequence {
            name: seq.name.clone(),
            cameras,
            features: if chunks.is_empty() {
                None
            } else {
                Some(Tensor::cat(&chunks, 0)?)
            },
            frames,
        });
        progress(k + 1, total);
    }
    Ok(out)
}

/// The generator of iteration `it`.
fn iteration_rng(seed: u64, it: u64) -> StdRng {
    StdRng::seed_from_u64(seed ^ (it + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

/// The sets of one batch: per set the sequence and its frame indices.
fn sample_sets<'d>(
    data: &'d [TrainSequence],
    config: &TrainConfig,
    rng: &mut StdRng,
) -> Result<Vec<(&'d TrainSequence, Vec<usize>)>> {
    let longest = data.iter().map(|s| s.cameras.len()).max().unwrap_or(0);
    let top = config.max_frames.min(longest);
    if top < 3 {
        return Err(PosediffError::InvalidArgument(
            "training needs sequences of at least 3 frames".into(),
        ));
    }
    let n = rng.random_range(3..=top);
    let eligible: Vec<&TrainSequence> = data.iter().filter(|s| s.cameras.len() >= n).collect();
    let sets = (config.images_per_batch / n).max(1);
    Ok((0..sets)
        .map(|_| {
            let seq = eligible[rng.random_range(0..eligible.len())];
            (
                seq,
                rand::seq::index::sample(rng, seq.cameras.len(), n).into_vec(),
            )
        })
        .collect())
}

/// Cached features `(B, n, 384)` and normalised encodings `(B, n, 9)` of the sets.
fn cached_batch(
    sets: &[(&TrainSequence, Vec<usize>)],
    device: &Device,
) -> Result<(Tensor, Tensor)> {
    let n = sets.first().map_or(0, |s| s.1.len());
    let (mut z, mut x0) = (Vec::with_capacity(sets.len()), Vec::new());
    for (seq, ids) in sets {
        let cams: Vec<Camera> = ids.iter().map(|&i| seq.cameras[i]).collect();
        x0.extend(normalised_encodings(&cams)?);
        let features = seq.features.as_ref().ok_or_else(|| {
            PosediffError::InvalidArgument("no cached features: the backbone is not frozen".into())
        })?;
        let index = Tensor::from_vec(
            ids.iter().map(|&i| i as u32).collect::<Vec<u32>>(),
            ids.len(),
            device,
        )?;
        z.push(features.index_select(&index, 0)?);
    }
    Ok((
        Tensor::stack(&z, 0)?,
        Tensor::from_vec(x0, (sets.len(), n, 9), device)?,
    ))
}

/// Augmented images `(B, n, 3, 224, 224)` (jittered crops, per-sequence colour jitter) and the
/// normalised encodings `(B, n, 9)` of their crop cameras.
fn image_batch(
    sets: &[(&TrainSequence, Vec<usize>)],
    rng: &mut StdRng,
    device: &Device,
) -> Result<(Tensor, Tensor)> {
    let config = AugmentConfig::default();
    let side = posediff_geometry::MODEL_INPUT_SIDE;
    let n = sets.first().map_or(0, |s| s.1.len());
    let (mut pixels, mut x0) = (Vec::new(), Vec::new());
    for (seq, ids) in sets {
        let colour = SequenceColour::draw(&config, rng);
        let mut cams = Vec::with_capacity(ids.len());
        for &i in ids {
            let (path, camera) = &seq.frames[i];
            let (size, rgb) = read_rgb(path)?;
            let crop = jittered_crop(size, &config, rng);
            let mut chw = crop_and_resize(&rgb, size, &crop, side);
            colour.apply(&mut chw);
            pixels.extend(chw);
            cams.push(crop_camera(camera, &crop, side)?);
        }
        x0.extend(normalised_encodings(&cams)?);
    }
    let s = side as usize;
    Ok((
        Tensor::from_vec(pixels, (sets.len(), n, 3, s, s), device)?,
        Tensor::from_vec(x0, (sets.len(), n, 9), device)?,
    ))
}

/// What `trainer.json` holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrainerState {
    /// Iterations done.
    pub iteration: u64,
    /// Settings.
    pub config: TrainConfig,
    /// The checkpoint the run started from (`None`: freshly initialised).
    pub init: Option<PathBuf>,
    /// Which parameters are trained.
    pub mode: TrainMode,
}

/// Which parameters a run trains.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrainMode {
    /// The denoiser only; the backbone's features are computed once per frame (no
    /// augmentation: the practical mode on a CPU).
    FrozenBackbone,
    /// Every parameter; batches are read and augmented as the official dataset does.
    Full,
}

/// How [`Trainer::open`] starts a run.
#[derive(Debug, Clone)]
pub enum Start {
    /// A new run from `init` (official layout; `None`: a fresh model of the preset's depths,
    /// PyTorch's and DINO's default initialisation).
    New {
        /// Initial weights.
        init: Option<PathBuf>,
        /// Settings.
        config: TrainConfig,
        /// What is trained.
        mode: TrainMode,
    },
    /// The run saved in the output folder, continued exactly (its settings and mode).
    Resume,
}

/// A training run: the model, its optimizer and where it saves.
pub struct Trainer {
    /// Model variables.
    pub trainable: Trainable,
    /// Optimizer over the trained variables.
    pub optimizer: AdamW,
    /// Settings and progress.
    pub state: TrainerState,
    /// The loss log so far.
    pub log: Vec<LogRow>,
    /// Schedule buffers of the initial checkpoint (saved with the model).
    buffers: HashMap<String, Tensor>,
    out: PathBuf,
    device: Device,
}

impl std::fmt::Debug for Trainer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Trainer")
            .field("iteration", &self.state.iteration)
            .field("out", &self.out)
            .finish()
    }
}

fn io_err(path: &Path, source: std::io::Error) -> PosediffError {
    PosediffError::Write {
        path: path.to_owned(),
        source,
    }
}

impl Trainer {
    /// A run writing to `out`: new, or the one saved there continued.
    ///
    /// # Errors
    /// Unreadable checkpoints or state.
    pub fn open(out: &Path, start: Start, device: &Device) -> Result<Self> {
        let state_path = out.join("trainer.json");
        let resume = matches!(start, Start::Resume);
        let (weights, state, log) = if let Start::New { init, config, mode } = start {
            let state = TrainerState {
                iteration: 0,
                config,
                init: init.clone(),
                mode,
            };
            (init, state, Vec::new())
        } else {
            let text = crate::error::read_text(&state_path)?;
            let state: TrainerState =
                serde_json::from_str(&text).map_err(|e| PosediffError::invalid(&state_path, e))?;
            let log = read_log(&out.join("loss.csv"))?
                .into_iter()
                .filter(|r| r.iteration < state.iteration)
                .collect();
            (Some(out.join("model.safetensors")), state, log)
        };
        let checkpoint = match &weights {
            Some(w) => Checkpoint::load(w, device)?,
            None => posediff_diffusion::train::initial_checkpoint(
                posediff_diffusion::checkpoint::ModelDepths {
                    vit_blocks: state.config.vit_blocks,
                    trunk_layers: state.config.trunk_layers,
                },
                state.config.seed,
                device,
            )?,
        };
        let buffers = checkpoint
            .tensor_map()
            .iter()
            .filter(|(k, _)| !posediff_diffusion::train::is_parameter(k))
            .map(|(k, t)| (k.clone(), t.clone()))
            .collect();
        let trainable = Trainable::from_checkpoint(&checkpoint, device)?;
        let trained: Vec<_> = trainable
            .named_variables()
            .into_iter()
            .filter(|(k, _)| state.mode == TrainMode::Full || k.starts_with("diffuser."))
            .collect();
        let mut optimizer = AdamW::new(trained)?;
        if resume {
            let path = out.join("optimizer.safetensors");
            let tensors = candle_core::safetensors::load(&path, device)?;
            optimizer.load_state(&tensors, state.iteration)?;
        }
        Ok(Self {
            trainable,
            optimizer,
            state,
            log,
            buffers,
            out: out.to_owned(),
            device: device.clone(),
        })
    }

    /// What [`load_training_data`] should give this run.
    pub fn frame_input(&self) -> FrameInput<'_> {
        match self.state.mode {
            TrainMode::FrozenBackbone => FrameInput::CachedFeatures(&self.trainable.model),
            TrainMode::Full => FrameInput::Augmented,
        }
    }

    /// Runs iterations until `config.iterations` (or `stop_after` more), saving checkpoints;
    /// `on_step` sees every logged row.
    ///
    /// # Errors
    /// Tensor and I/O errors.
    pub fn run(
        &mut self,
        data: &[TrainSequence],
        stop_after: Option<u64>,
        mut on_step: impl FnMut(&LogRow, f64),
    ) -> Result<()> {
        let config = self.state.config.clone();
        let device = self.device.clone();
        let end = stop_after.map_or(config.iterations, |k| {
            (self.state.iteration + k).min(config.iterations)
        });
        let steps = self.trainable.model.schedule.len();
        while self.state.iteration < end {
            let it = self.state.iteration;
            let start = Instant::now();
            let mut rng = iteration_rng(config.seed, it);
            let sets = sample_sets(data, &config, &mut rng)?;
            let (z, x0) = if self.state.mode == TrainMode::FrozenBackbone {
                cached_batch(&sets, &device)?
            } else {
                let (images, x0) = image_batch(&sets, &mut rng, &device)?;
                (self.trainable.model.image_features(&images)?, x0)
            };
            let (sets, n, _) = x0.dims3()?;
            let r = config.batch_repeat.max(1);
            let z = z.repeat((r, 1, 1))?;
            let x0 = x0.repeat((r, 1, 1))?;
            let t: Vec<usize> = (0..sets * r).map(|_| rng.random_range(0..steps)).collect();
            let noise: Vec<f32> = (0..sets * r * n * 9)
                .map(|_| StandardNormal.sample(&mut rng))
                .collect();
            let noise = Tensor::from_vec(noise, (sets * r, n, 9), &device)?;
            let model = &self.trainable.model;
            let (_, _, loss) =
                denoising_loss(&model.denoiser, &model.schedule, &z, &x0, &t, &noise)?;
            let mut grads = loss.backward()?;
            let (grad_norm, _) = clip_grad_norm(&mut grads, &self.optimizer.vars(), config.clip)?;
            let lr = learning_rate(
                it,
                config.lr,
                config.warmup_init,
                config.warmup,
                config.period,
            );
            self.optimizer.step(&grads, lr)?;
            let row = LogRow {
                iteration: it,
                loss: f64::from(loss.to_dtype(DType::F32)?.to_scalar::<f32>()?),
                lr,
                grad_norm,
                images: sets * n,
            };
            self.log.push(row);
            self.state.iteration += 1;
            let seconds = start.elapsed().as_secs_f64();
            on_step(&row, (sets * n * r) as f64 / seconds.max(1e-9));
            if self
                .state
                .iteration
                .is_multiple_of(config.checkpoint_every.max(1))
                && self.state.iteration < end
            {
                self.save()?;
            }
        }
        // At the end, also when nothing was left to do: the files (and the plot) are current.
        self.save()?;
        Ok(())
    }

    /// Writes the checkpoint folder.
    ///
    /// # Errors
    /// I/O errors; a model that no longer validates.
    pub fn save(&self) -> Result<()> {
        std::fs::create_dir_all(&self.out).map_err(|e| io_err(&self.out, e))?;
        let mut tensors: Vec<(String, Tensor)> = self
            .trainable
            .named_variables()
            .into_iter()
            .map(|(k, v)| (k, v.as_tensor().clone()))
            .collect();
        tensors.extend(self.buffers.iter().map(|(k, t)| (k.clone(), t.clone())));
        Checkpoint::from_tensors(tensors)?.save_safetensors(&self.out.join("model.safetensors"))?;
        let state: HashMap<String, Tensor> = self.optimizer.state_tensors().into_iter().collect();
        candle_core::safetensors::save(&state, self.out.join("optimizer.safetensors"))?;
        let json = serde_json::to_string_pretty(&self.state)?;
        std::fs::write(self.out.join("trainer.json"), json)
            .map_err(|e| io_err(&self.out.join("trainer.json"), e))?;
        write_log(&self.out.join("loss.csv"), &self.log)?;
        log::plot_loss(&self.out.join("loss.png"), &self.log)?;
        Ok(())
    }
}
