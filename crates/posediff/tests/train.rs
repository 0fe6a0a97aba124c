//! Training on synthetic data: a resumed run continues with exactly the loss curve of an
//! uninterrupted one, and the checkpoint it writes loads in `posediff estimate`.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use candle_core::Device;
use posediff::train::{
    FrameInput, LogRow, Split, Start, TrainConfig, TrainData, TrainMode, Trainer,
    load_training_data, read_log,
};
use posediff::{EstimateConfig, EstimateInput, Estimator, Silent};
use posediff_geometry::ImageSize;
use posediff_synth::{DatasetSpec, LensSpec, write_dataset};

fn tiny_model() -> PathBuf {
    posediff_fixtures::shared_path("reference/tiny/model_tiny.safetensors")
}

/// The largest change of parameter `key` between two checkpoints.
fn max_change(
    before: &posediff_diffusion::checkpoint::Checkpoint,
    after: &posediff_diffusion::checkpoint::Checkpoint,
    key: &str,
) -> f32 {
    (before.tensor_map()[key]
        .to_dtype(candle_core::DType::F32)
        .unwrap()
        - &after.tensor_map()[key])
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

/// The synthetic category's training split of `dir` (the dataset's root and annotations).
fn train_data<'a>(dir: &'a Path, categories: &'a [String]) -> TrainData<'a> {
    TrainData {
        co3d_dir: dir,
        annotation_dir: dir,
        categories,
        split: Split::Train,
        min_frames: 5,
    }
}

fn config() -> TrainConfig {
    TrainConfig {
        iterations: 4,
        period: 4,
        warmup: 1,
        images_per_batch: 12,
        batch_repeat: 2,
        max_frames: 5,
        min_frames: 5,
        checkpoint_every: 100,
        ..TrainConfig::tiny()
    }
}

/// Runs `config()` in `out`, `split` iterations first and the rest after a resume (or all at
/// once with `None`); returns the log.
fn run(data_dir: &Path, out: &Path, split: Option<u64>) -> Vec<LogRow> {
    let device = Device::Cpu;
    let start = Start::New {
        init: Some(tiny_model()),
        config: config(),
        mode: TrainMode::FrozenBackbone,
    };
    let mut trainer = Trainer::open(out, start, &device).unwrap();
    let categories = ["synthetic".to_owned()];
    let data = load_training_data(
        &train_data(data_dir, &categories),
        trainer.frame_input(),
        &device,
        |_, _| {},
    )
    .unwrap();
    trainer.run(&data, split, |_, _| {}).unwrap();
    if let Some(done) = split {
        drop(trainer);
        let mut resumed = Trainer::open(out, Start::Resume, &device).unwrap();
        assert_eq!(resumed.state.iteration, done);
        assert_eq!(resumed.state.mode, TrainMode::FrozenBackbone);
        resumed.run(&data, None, |_, _| {}).unwrap();
        return resumed.log.clone();
    }
    trainer.log.clone()
}

#[test]
fn a_resumed_run_repeats_the_uninterrupted_loss_curve_and_its_checkpoint_loads() {
    let data = posediff_fixtures::temp_dir("train-data");
    write_dataset(
        &data,
        &DatasetSpec {
            sequences: 3,
            frames: 6,
            seed: 9,
            sizes: vec![ImageSize::new(160, 120).unwrap()],
            test_every: 0,
            path: None,
            lens: LensSpec::default(),
        },
    )
    .unwrap();
    let (a, b) = (
        posediff_fixtures::temp_dir("train-a"),
        posediff_fixtures::temp_dir("train-b"),
    );
    let straight = run(&data, &a, None);
    let resumed = run(&data, &b, Some(2));
    assert_eq!(straight.len(), 4);
    assert_eq!(resumed.len(), 4);
    for (x, y) in straight.iter().zip(&resumed) {
        assert_eq!(x.iteration, y.iteration);
        assert_eq!(x.images, y.images);
        assert!(
            (x.loss - y.loss).abs() <= 1e-6 * x.loss.abs(),
            "{x:?} vs {y:?}"
        );
        assert_eq!(x.lr, y.lr);
    }
    // The files say the same.
    assert_eq!(read_log(&b.join("loss.csv")).unwrap().len(), 4);
    assert!(b.join("loss.png").is_file());

    // The trained checkpoint is in the official layout: the estimator loads and runs it.
    let estimator = Estimator::load(
        &b.join("model.safetensors"),
        Device::Cpu,
        EstimateConfig {
            ggs: false,
            ..EstimateConfig::default()
        },
    )
    .unwrap();
    let dir = data.join("synthetic/synthetic_0000/images");
    let images: Vec<PathBuf> = (0..3)
        .map(|i| dir.join(format!("frame{i:06}.png")))
        .collect();
    let e = estimator
        .estimate(EstimateInput::new(&images), &mut Silent)
        .unwrap();
    assert_eq!(e.samples[0].len(), 3);
    // Training moved the denoiser: the saved weights differ from the initial ones.
    let before =
        posediff_diffusion::checkpoint::Checkpoint::load(&tiny_model(), &Device::Cpu).unwrap();
    let after = posediff_diffusion::checkpoint::Checkpoint::load(
        &b.join("model.safetensors"),
        &Device::Cpu,
    )
    .unwrap();
    let key = "diffuser.model._last.3.bias";
    let d = max_change(&before, &after, key);
    assert!(d > 0.0);
    // ... while the frozen backbone did not move.
    let key = "image_feature_extractor._net.cls_token";
    let d = max_change(&before, &after, key);
    assert_eq!(d, 0.0);
}

#[test]
fn a_fresh_unfrozen_run_trains_the_backbone_on_augmented_batches() {
    let data = posediff_fixtures::temp_dir("train-data-unfrozen");
    write_dataset(
        &data,
        &DatasetSpec {
            sequences: 2,
            frames: 5,
            seed: 4,
            sizes: vec![ImageSize::new(160, 120).unwrap()],
            test_every: 0,
            path: None,
            lens: LensSpec::default(),
        },
    )
    .unwrap();
    let out = posediff_fixtures::temp_dir("train-unfrozen");
    let device = Device::Cpu;
    let cfg = TrainConfig {
        iterations: 2,
        images_per_batch: 6,
        max_frames: 3,
        batch_repeat: 1,
        ..config()
    };
    let start = Start::New {
        init: None,
        config: cfg,
        mode: TrainMode::Full,
    };
    let mut trainer = Trainer::open(&out, start, &device).unwrap();
    assert!(matches!(trainer.frame_input(), FrameInput::Augmented));
    let categories = ["synthetic".to_owned()];
    let seqs = load_training_data(
        &train_data(&data, &categories),
        trainer.frame_input(),
        &device,
        |_, _| {},
    )
    .unwrap();
    assert!(seqs.iter().all(|s| s.features.is_none()));
    trainer.run(&seqs, None, |_, _| {}).unwrap();
    assert_eq!(trainer.log.len(), 2);
    assert!(
        trainer
            .log
            .iter()
            .all(|r| r.loss.is_finite() && r.grad_norm > 0.0)
    );
    // A fresh model (no --init) of the tiny depths, the same seed as the run's.
    let before = posediff_diffusion::train::initial_checkpoint(
        posediff_diffusion::checkpoint::ModelDepths {
            vit_blocks: 2,
            trunk_layers: 2,
        },
        TrainConfig::tiny().seed,
        &device,
    )
    .unwrap();
    let after =
        posediff_diffusion::checkpoint::Checkpoint::load(&out.join("model.safetensors"), &device)
            .unwrap();
    let key = "image_feature_extractor._net.cls_token";
    let d = max_change(&before, &after, key);
    assert!(d > 0.0, "the backbone moved");
}
