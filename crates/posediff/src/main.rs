//! The `posediff` command: `posediff estimate <folder or images> --weights <ckpt> --out <dir>`.
// The command prints its summary table on stdout.
#![allow(clippy::print_stdout)]

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, bail};
use candle_core::Device;
use clap::{Parser, Subcommand, ValueEnum};
use posediff::colmap::{ColmapFormat, ColmapModel};
use posediff::export::{
    ImageCamera, NamedCamera, read_cameras_json_partial, write_cameras_json_partial,
};
use posediff::geometric::{
    GeometricConfig, KnownIntrinsics, Refinement, estimate_geometric, refine_given_cameras,
};
use posediff::loader::image_files;
use posediff::outputs::{
    ImagesMode, InputImages, OutputOptions, prepare_output_dir, write_outputs,
};
use posediff::reconstruction::Reconstruction;
use posediff::{EstimateConfig, Estimator, Progress, Silent};
use posediff_matching::Detector;
use posediff_sfm::points::PointOptions;

#[derive(Parser)]
#[command(
    name = "posediff",
    version,
    about = "Camera poses from a handful of photos (PoseDiffusion in Rust)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum Matcher {
    Sift,
    Orb,
}

/// How checkpoint-free cameras are refined.
#[derive(Clone, Copy, ValueEnum)]
enum RefineArg {
    /// Levenberg–Marquardt on the Sampson distances until the cost stops falling, then the
    /// bundle adjustment with tracks.
    Converge,
    /// With --weights: PoseDiffusion's cameras (after GGS) refined by the mapper's bundle
    /// adjustment with tracks (the paper's future work). Without: as `converge`.
    Bundle,
    /// The official five-phase GGS schedule (7000 SGD iterations) in the 224 crops.
    Official,
    /// The averaged cameras as they are.
    None,
}

/// What a benchmark scores.
#[derive(Clone, Copy, ValueEnum)]
enum BenchMethod {
    /// The ground truth itself (the ceiling check of the scoring).
    GroundTruth,
    /// Cameras without a checkpoint (two-view geometry, averaging, refinement).
    Geometric,
    /// PoseDiffusion with `--weights`.
    Posediffusion,
}

#[derive(Clone, Copy, ValueEnum)]
enum DeviceArg {
    Cpu,
    Cuda,
}

#[derive(Subcommand)]
enum Command {
    /// Estimate the cameras of a folder of images (or a list of image files).
    Estimate(EstimateArgs),
    /// Score a method on the real sets of `--data` over `--subsets` (JSON + Markdown report).
    BenchReal {
        /// Folder of sets in the cameras.json layout.
        #[arg(long)]
        data: PathBuf,
        /// subsets.json.
        #[arg(long)]
        subsets: PathBuf,
        /// Checkpoint for PoseDiffusion.
        #[arg(long)]
        weights: Option<PathBuf>,
        /// What to score (default: posediffusion with --weights, else geometric).
        #[arg(long, value_enum)]
        method: Option<BenchMethod>,
        /// Report path (JSON; the Markdown table is written beside it).
        #[arg(long)]
        out: PathBuf,
    },
    /// The official CO3Dv2 test protocol (JSON + Markdown report).
    BenchCo3d {
        /// CO3D root (image file paths of the annotations are relative to it).
        #[arg(long)]
        co3d_dir: PathBuf,
        /// Folder of `{category}_test.jgz`.
        #[arg(long)]
        annotation_dir: PathBuf,
        /// `seen`, `unseen` or a comma-separated list.
        #[arg(long, default_value = "seen")]
        categories: String,
        /// Frames drawn per sequence.
        #[arg(long, default_value_t = 10)]
        num_frames: usize,
        /// Minimum frames of a usable sequence (official 50).
        #[arg(long, default_value_t = 50)]
        min_frames: usize,
        /// numpy seed (official 0).
        #[arg(long, default_value_t = 0)]
        seed: u32,
        /// Checkpoint for PoseDiffusion.
        #[arg(long)]
        weights: Option<PathBuf>,
        /// What to score (default: posediffusion with --weights, else geometric).
        #[arg(long, value_enum)]
        method: Option<BenchMethod>,
        /// Skip GGS.
        #[arg(long)]
        no_ggs: bool,
        /// Report path (JSON; the Markdown table is written beside it).
        #[arg(long)]
        out: PathBuf,
    },
    /// Train on CO3D-layout data (e.g. `cargo xtask synth` output): the official recipe with a
    /// frozen backbone whose features are computed once.
    Train {
        /// CO3D root (image paths of the annotations are relative to it).
        #[arg(long)]
        co3d_dir: PathBuf,
        /// Folder of `{category}_{split}.jgz`.
        #[arg(long)]
        annotation_dir: PathBuf,
        /// Comma-separated categories.
        #[arg(long)]
        categories: String,
        /// Checkpoint folder (model.safetensors, optimizer.safetensors, trainer.json, loss.csv,
        /// loss.png).
        #[arg(long)]
        out: PathBuf,
        /// Settings: `tiny` (a CPU-sized run) or `official` (cfgs/default_train.yaml).
        #[arg(long, default_value = "tiny")]
        config: String,
        /// Initial weights in the official layout (e.g. the official checkpoint to fine-tune, or
        /// ../shared/reference/tiny/model_tiny.safetensors); without it a fresh model of the
        /// preset's depths (PyTorch's default initialisation; DINO's for the ViT, so a frozen
        /// fresh backbone gives random features: fine-tune from pretrained weights instead).
        #[arg(long)]
        init: Option<PathBuf>,
        /// Keep the backbone fixed and cache its features (no augmentation; the practical mode
        /// on a CPU). Without it every batch is read, augmented as the official dataset does
        /// and the backbone is trained too.
        #[arg(long)]
        freeze_backbone: bool,
        /// Continue the run saved in --out.
        #[arg(long)]
        resume: bool,
        /// Override the iteration count of the preset.
        #[arg(long)]
        iterations: Option<u64>,
        /// Stop after this many iterations of this invocation (the schedule still spans
        /// --iterations; --resume continues).
        #[arg(long)]
        stop_after: Option<u64>,
        /// Annotation split.
        #[arg(long, default_value = "train")]
        split: String,
        /// Where the network runs.
        #[arg(long, value_enum, default_value = "cpu")]
        device: DeviceArg,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Convert a COLMAP model (text or binary) to cameras.json, e.g. for
    /// `estimate --init`: with --images, one entry per image of that folder in its order
    /// (images COLMAP did not register are marked not estimated).
    ImportColmap {
        /// Folder of the COLMAP model (e.g. sparse/0).
        model: PathBuf,
        /// The image folder the model belongs to.
        #[arg(long)]
        images: Option<PathBuf>,
        /// Output cameras.json.
        #[arg(long)]
        out: PathBuf,
    },
    /// Score cameras against a ground truth with the official test.py metrics (every pair,
    /// images not estimated failed in all their pairs).
    Score {
        /// A cameras.json (images not estimated allowed).
        cameras: PathBuf,
        /// Ground-truth cameras.json (matched by image name, any order).
        #[arg(long)]
        gt: PathBuf,
        /// Also write the scores as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Write view.html (cameras with thumbnails, points, the aligned ground truth) for an
    /// output folder of `estimate`.
    View {
        /// The output folder (its sparse/0 and images/ are read).
        dir: PathBuf,
        /// Ground-truth cameras.json (matched by image name), drawn aligned, with errors.
        #[arg(long)]
        gt: Option<PathBuf>,
        /// The page to write (default: <dir>/view.html).
        #[arg(short = 'o', long = "out")]
        out: Option<PathBuf>,
    },
    /// Plot cameras (frusta from above and from the side), optionally against the ground truth.
    Plot {
        /// A cameras.json.
        cameras: PathBuf,
        /// Ground-truth cameras.json (matched by image name, any order).
        #[arg(long)]
        gt: Option<PathBuf>,
        /// Output PNG.
        #[arg(short = 'o', long = "out")]
        out: PathBuf,
    },
}

/// Progress bars on stderr (drawn only on a terminal).
#[derive(Default)]
struct Bars {
    bar: Option<indicatif::ProgressBar>,
}

impl Progress for Bars {
    fn start(&mut self, stage: &str, total: u64) {
        let bar = if total > 0 {
            let b = indicatif::ProgressBar::new(total);
            if let Ok(style) = indicatif::ProgressStyle::with_template(
                "{msg:>10} [{bar:40}] {pos}/{len} {elapsed}",
            ) {
                b.set_style(style.progress_chars("=> "));
            }
            b
        } else {
            let b = indicatif::ProgressBar::new_spinner();
            b.enable_steady_tick(std::time::Duration::from_millis(120));
            b
        };
        bar.set_message(stage.to_owned());
        self.bar = Some(bar);
    }

    fn advance(&mut self) {
        if let Some(b) = &self.bar {
            b.inc(1);
        }
    }

    fn finish(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
    }
}

fn main() -> ExitCode {
    // Logs go to stderr; `RUST_LOG=info` shows the stages, warnings are on by default.
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    let args = match cli.command {
        Command::Estimate(args) => args,
        Command::Plot { cameras, gt, out } => return plot(&cameras, gt.as_deref(), &out),
        Command::View { dir, gt, out } => return view(&dir, gt.as_deref(), out.as_deref()),
        Command::Score { cameras, gt, out } => return score(&cameras, &gt, out.as_deref()),
        Command::Train {
            co3d_dir,
            annotation_dir,
            categories,
            out,
            config,
            init,
            freeze_backbone,
            resume,
            iterations,
            stop_after,
            split,
            device,
            quiet,
        } => {
            let mut cfg = match config.as_str() {
                "tiny" => posediff::train::TrainConfig::tiny(),
                "official" => posediff::train::TrainConfig::official(),
                other => bail!("unknown --config {other:?} (tiny or official)"),
            };
            if let Some(k) = iterations {
                cfg.iterations = k;
                cfg.period = cfg.period.min(k.max(1));
            }
            let device = match device {
                DeviceArg::Cpu => Device::Cpu,
                DeviceArg::Cuda => Device::new_cuda(0)
                    .context("--device cuda needs a CUDA build (feature `cuda`) and a GPU")?,
            };
            let mut trainer = posediff::train::Trainer::open(
                init.as_deref(),
                &out,
                cfg,
                freeze_backbone,
                resume,
                &device,
            )?;
            if let (true, Some(k)) = (resume, iterations) {
                // A resumed run keeps its schedule; only its length changes.
                trainer.state.config.iterations = k;
            }
            let list: Vec<String> = categories
                .split(',')
                .map(|c| c.trim().to_owned())
                .filter(|c| !c.is_empty())
                .collect();
            let bar = if quiet {
                indicatif::ProgressBar::hidden()
            } else {
                indicatif::ProgressBar::new(0)
            };
            if let Ok(style) = indicatif::ProgressStyle::with_template(
                "{msg:>12} [{bar:40}] {pos}/{len} {elapsed}",
            ) {
                bar.set_style(style.progress_chars("=> "));
            }
            bar.set_message("features");
            let data = posediff::train::load_training_data(
                &co3d_dir,
                &annotation_dir,
                &list,
                &split,
                trainer.state.config.min_frames,
                trainer
                    .state
                    .freeze_backbone
                    .then_some(&trainer.trainable.model),
                &device,
                |done, total| {
                    bar.set_length(total as u64);
                    bar.set_position(done as u64);
                },
            )?;
            bar.set_length(trainer.state.config.iterations);
            bar.set_position(trainer.state.iteration);
            bar.set_message("training");
            trainer.run(&data, stop_after, |row, images_per_s| {
                bar.set_position(row.iteration + 1);
                bar.set_message(format!(
                    "loss {:.4} lr {:.1e} {:.0} img/s",
                    row.loss, row.lr, images_per_s
                ));
            })?;
            bar.finish_and_clear();
            if !quiet {
                println!(
                    "{} sequences; iteration {} of {}; checkpoint in {}",
                    data.len(),
                    trainer.state.iteration,
                    trainer.state.config.iterations,
                    out.display()
                );
            }
            return Ok(());
        }
        Command::ImportColmap { model, images, out } => {
            let entries = match images {
                Some(dir) => {
                    posediff::export::colmap_for_images(&model, &image_files(&dir)?, &dir)?
                }
                None => {
                    let mut cams = posediff::export::read_colmap_cameras(&model)?;
                    cams.sort_by(|a, b| a.image.cmp(&b.image));
                    cams.into_iter()
                        .map(|c| ImageCamera {
                            image: c.image,
                            size: c.camera.image_size,
                            camera: Some(c.camera),
                        })
                        .collect()
                }
            };
            write_cameras_json_partial(&out, &entries)?;
            let points = ColmapModel::read(&model)?.points.len();
            println!(
                "wrote {} ({} of {} images registered; the model has {points} points)",
                out.display(),
                entries.iter().filter(|e| e.camera.is_some()).count(),
                entries.len()
            );
            return Ok(());
        }
        Command::BenchReal {
            data,
            subsets,
            weights,
            method,
            out,
        } => {
            let method = bench_method(method, weights.as_deref(), false)?;
            let rows = posediff::bench::bench_real(&data, &subsets, method.as_ref())?;
            let md = posediff::bench::real_markdown(&method.name(), &rows);
            return write_report(
                &out,
                serde_json::json!({"command": command_line(), "method": method.name(), "rows": rows}),
                &md,
            );
        }
        Command::BenchCo3d {
            co3d_dir,
            annotation_dir,
            categories,
            num_frames,
            min_frames,
            seed,
            weights,
            method,
            no_ggs,
            out,
        } => {
            let list: Vec<String> = match categories.as_str() {
                "seen" => posediff::co3d::SEEN_CATEGORIES
                    .iter()
                    .map(|c| c.to_string())
                    .collect(),
                "unseen" => posediff::co3d::UNSEEN_CATEGORIES
                    .iter()
                    .map(|c| c.to_string())
                    .collect(),
                other => other
                    .split(',')
                    .map(|c| c.trim().to_owned())
                    .filter(|c| !c.is_empty())
                    .collect(),
            };
            let method = bench_method(method, weights.as_deref(), no_ggs)?;
            let report = posediff::bench::bench_co3d(
                &co3d_dir,
                &annotation_dir,
                &list,
                min_frames,
                num_frames,
                seed,
                method.as_ref(),
            )?;
            let md = posediff::bench::co3d_markdown(&method.name(), &report);
            return write_report(
                &out,
                serde_json::json!({"command": command_line(), "method": method.name(), "report": report}),
                &md,
            );
        }
    };
    estimate(args)
}

/// The arguments of `posediff estimate`.
#[derive(clap::Args)]
struct EstimateArgs {
    /// A folder (its .png/.jpg/.jpeg files, sorted) or image files (in the order given).
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Official PoseDiffusion checkpoint (.pth or safetensors). Without it the cameras come
    /// from the images' geometry alone (matching, averaging, refinement).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Start from an estimate: `geometric` (the checkpoint-free cameras) or a cameras.json.
    /// With --weights the reverse diffusion starts at --start-step from the noised estimate;
    /// without, a cameras.json is refined on the matches.
    #[arg(long)]
    init: Option<String>,
    /// With --weights and --init: the diffusion step the estimate is noised to (0-99; larger
    /// trusts it less).
    #[arg(long, default_value_t = 30)]
    start_step: usize,
    /// Known focal length in pixels for every image (principal points at the centres); the
    /// focal is not estimated.
    #[arg(long, conflicts_with = "intrinsics")]
    focal_px: Option<f64>,
    /// Known intrinsics: a cameras.json whose "K" per image is used (same images, same
    /// order; R and t are ignored).
    #[arg(long)]
    intrinsics: Option<PathBuf>,
    /// Refinement of the checkpoint-free cameras: to convergence (Levenberg–Marquardt on
    /// the Sampson distances), the official GGS schedule, or none.
    #[arg(long, value_enum, default_value = "converge")]
    refine: RefineArg,
    /// Which image pairs are matched by the checkpoint-free path: `auto` (every pair up to
    /// 60 images, `sequential:10,retrieval:20` above), `exhaustive`, `sequential:K` (each
    /// image with the next K), `retrieval:K` (its K most similar by a bag of visual words), or
    /// a union such as `sequential:10,retrieval:20`.
    #[arg(long, default_value = "auto")]
    pairs: posediff_matching::PairSelection,
    /// Output folder (created).
    #[arg(long)]
    out: PathBuf,
    /// Seed of the sampler.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Samples per image set (spread reported in run.json).
    #[arg(long, default_value_t = 1)]
    samples: usize,
    /// Skip geometry-guided sampling (and matching).
    #[arg(long)]
    no_ggs: bool,
    /// Keypoint detector for GGS matches.
    #[arg(long, value_enum, default_value = "sift")]
    matcher: Matcher,
    /// Where the network runs.
    #[arg(long, value_enum, default_value = "cpu")]
    device: DeviceArg,
    /// Print nothing but errors.
    #[arg(long)]
    quiet: bool,
    /// Files of the COLMAP model in out/sparse/0.
    #[arg(long, value_enum, default_value = "text")]
    colmap_format: ColmapFormatArg,
    /// How the images are made reachable as out/images (for the COLMAP model and
    /// transforms.json): a link to the folder (or one per file), copies, or nothing
    /// (transforms.json then names the images by absolute path).
    #[arg(long, value_enum, default_value = "link")]
    images: ImagesArg,
    /// Do not write view.html.
    #[arg(long)]
    no_view: bool,
    /// Go on without images that are corrupt, truncated or unreadable (listed in run.json)
    /// instead of stopping.
    #[arg(long)]
    skip_bad_images: bool,
}

#[derive(Clone, Copy, ValueEnum)]
enum ColmapFormatArg {
    Text,
    Binary,
}

#[derive(Clone, Copy, ValueEnum)]
enum ImagesArg {
    Link,
    Copy,
    None,
}

impl EstimateArgs {
    fn output_options(&self) -> OutputOptions {
        OutputOptions {
            colmap_format: match self.colmap_format {
                ColmapFormatArg::Text => ColmapFormat::Text,
                ColmapFormatArg::Binary => ColmapFormat::Binary,
            },
            images: match self.images {
                ImagesArg::Link => ImagesMode::Link,
                ImagesArg::Copy => ImagesMode::Copy,
                ImagesArg::None => ImagesMode::None,
            },
            view: !self.no_view,
        }
    }
}

/// Where the initial cameras come from.
enum InitSource {
    Geometric,
    /// Per image, matched by name (`None`: no camera given).
    File(Vec<Option<posediff_geometry::Camera>>),
}

fn estimate(args: EstimateArgs) -> anyhow::Result<()> {
    // Every cheap check first: options, paths, files that name the images, the output folder,
    // the images' headers, the checkpoint's keys and shapes; only then features and matching.
    if args.samples == 0 {
        bail!("--samples must be at least 1");
    }
    if let Some(f) = args.focal_px
        && !(f.is_finite() && f > 0.0)
    {
        bail!("--focal-px must be a positive, finite number of pixels, got {f}");
    }
    if args.start_step > 99 {
        bail!(
            "--start-step must be 0-99 (a step of the 100-step schedule), got {}",
            args.start_step
        );
    }
    if args.start_step != 30 && args.init.is_none() {
        bail!(
            "--start-step needs --init (it is where the diffusion starts from the initial cameras)"
        );
    }
    for path in &args.inputs {
        if !path.exists() {
            bail!("no such file or directory: {}", path.display());
        }
    }
    if let Some(w) = &args.weights
        && !w.is_file()
    {
        bail!("--weights: no such file: {}", w.display());
    }
    let folder_given = matches!(args.inputs.as_slice(), [one] if one.is_dir());
    let (listed, root) = match args.inputs.as_slice() {
        [one] if one.is_dir() => (image_files(one)?, Some(one.clone())),
        files => {
            if let Some(dir) = files.iter().find(|f| f.is_dir()) {
                bail!(
                    "{} is a folder: give one folder, or image files",
                    dir.display()
                );
            }
            (
                files.to_vec(),
                files
                    .first()
                    .and_then(|f| f.parent())
                    .map(Path::to_path_buf),
            )
        }
    };
    let (images, bad_images) = posediff::loader::check_images(&listed);
    if !bad_images.is_empty() {
        let list: Vec<String> = bad_images
            .iter()
            .map(|(p, why)| format!("{}: {why}", p.display()))
            .collect();
        if !args.skip_bad_images {
            bail!(
                "{} unusable image(s) (give --skip-bad-images to go on without them):\n  {}",
                list.len(),
                list.join("\n  ")
            );
        }
        for l in &list {
            log::warn!("skipped {l}");
        }
    }
    if images.len() < 2 {
        bail!(
            "need at least 2 images, got {}{}",
            images.len(),
            if bad_images.is_empty() {
                String::new()
            } else {
                format!(" after skipping {} unusable", bad_images.len())
            }
        );
    }
    let skipped: Vec<serde_json::Value> = bad_images
        .iter()
        .map(|(p, why)| serde_json::json!({"image": p, "reason": why}))
        .collect();
    let inputs = InputImages {
        files: images.clone(),
        folder: root.clone(),
        folder_given,
    };
    let names: Vec<String> = images
        .iter()
        .map(|p| posediff::pipeline::relative_name(p, root.as_deref()))
        .collect();
    let mut seen = std::collections::HashMap::new();
    for (k, n) in names.iter().enumerate() {
        if let Some(first) = seen.insert(n.as_str(), k) {
            bail!(
                "{} and {} have the same name {n:?}: the outputs name images by it; give each image once, with distinct file names",
                images[first].display(),
                images[k].display()
            );
        }
    }
    let known = match (args.focal_px, &args.intrinsics) {
        (Some(f), _) => KnownIntrinsics::FocalPx(f),
        (None, Some(path)) => {
            let given = read_per_image(path, &names, "--intrinsics")?
                .complete("--intrinsics", path)
                .map_err(anyhow::Error::msg)?;
            KnownIntrinsics::PerImage(
                given
                    .iter()
                    .map(|g| {
                        g.camera
                            .map(|c| c.intrinsics)
                            .with_context(|| format!("{}: no K for {}", path.display(), g.image))
                    })
                    .collect::<anyhow::Result<Vec<_>>>()?,
            )
        }
        (None, None) => KnownIntrinsics::Unknown,
    };
    let mut init_warnings = Vec::new();
    let init = match args.init.as_deref() {
        None => None,
        Some("geometric") => Some(InitSource::Geometric),
        Some(path) => {
            let path = PathBuf::from(path);
            let matched = read_per_image(&path, &names, "--init")?;
            if matched.matched() == 0 {
                bail!("{}", matched.mismatch("--init", &path));
            }
            if !matched.images_without_record.is_empty()
                || !matched.records_without_image.is_empty()
            {
                init_warnings.push(format!(
                    "{} (images without an initial camera start uninitialised)",
                    matched.mismatch("--init", &path)
                ));
            }
            let cams: Vec<Option<posediff_geometry::Camera>> = matched
                .per_image
                .into_iter()
                .map(|r| r.and_then(|r| r.camera))
                .collect();
            if cams.iter().all(Option::is_none) {
                bail!(
                    "--init {}: none of its cameras is estimated",
                    path.display()
                );
            }
            Some(InitSource::File(cams))
        }
    };
    let device_name = match args.device {
        DeviceArg::Cpu => "cpu",
        DeviceArg::Cuda => "cuda",
    };
    let device = match (args.device, &args.weights) {
        (DeviceArg::Cuda, Some(_)) => Device::new_cuda(0)
            .context("--device cuda needs a CUDA build (feature `cuda`) and a GPU")?,
        (DeviceArg::Cuda, None) => bail!("--device cuda runs the network: it needs --weights"),
        (DeviceArg::Cpu, _) => Device::Cpu,
    };
    let output_options = args.output_options();
    prepare_output_dir(&args.out, &inputs, output_options.images)?;
    let mut geometric = GeometricConfig {
        intrinsics: known.clone(),
        pairs: args.pairs.clone(),
        refinement: match args.refine {
            RefineArg::Converge | RefineArg::Bundle => {
                Refinement::Converge(posediff_sfm::sampson_refine::SampsonRefineOptions::default())
            }
            RefineArg::Official => Refinement::Official(posediff_guidance::GgsConfig::default()),
            RefineArg::None => Refinement::None,
        },
        ..GeometricConfig::default()
    };
    geometric.matching.features.detector = detector(args.matcher);
    let mut bars = Bars::default();
    let quiet = args.quiet;
    let progress: &mut dyn Progress = if quiet { &mut Silent } else { &mut bars };
    let Some(weights) = args.weights.clone() else {
        // Checkpoint-free.
        progress.start("geometry", 0);
        let result = match &init {
            Some(InitSource::File(cams)) => refine_given_cameras(&images, cams, &geometric),
            _ => estimate_geometric(&images, &geometric),
        };
        progress.finish();
        let result = result?;
        let mut warnings = init_warnings;
        warnings.extend(result.warnings.iter().cloned());
        for w in &warnings {
            log::warn!("{w}");
        }
        let entries: Vec<ImageCamera> = names
            .iter()
            .zip(&result.cameras)
            .zip(&result.sizes)
            .map(|((name, camera), size)| ImageCamera {
                image: name.clone(),
                size: *size,
                camera: *camera,
            })
            .collect();
        let run = serde_json::json!({
            "posediff": env!("CARGO_PKG_VERSION"),
            "method": "geometric (no checkpoint)",
            "images": images,
            "init": args.init,
            "refine": format!("{:?}", geometric.refinement),
            "report": result.report,
            "matches_per_pair": result.pairs.iter().map(|p| serde_json::json!({"first": p.first, "second": p.second, "matches": p.len()})).collect::<Vec<_>>(),
            "skipped_images": skipped,
            "warnings": warnings,
        });
        return finish(
            &args.out,
            entries,
            &result.pairs,
            &inputs,
            run,
            &output_options,
            quiet,
        );
    };
    let mut config = EstimateConfig {
        seed: args.seed,
        samples: args.samples,
        ggs: !args.no_ggs,
        intrinsics: known.clone(),
        ..EstimateConfig::default()
    };
    config.matching.features.detector = detector(args.matcher);
    let load_start = std::time::Instant::now();
    let estimator = Estimator::load(&weights, device, config.clone())
        .with_context(|| format!("loading weights {}", weights.display()))?;
    let load_weights = load_start.elapsed().as_secs_f64();
    let init_cameras: Option<Vec<posediff_geometry::Camera>> = match &init {
        None => None,
        Some(source) => {
            let given = match source {
                InitSource::Geometric => {
                    progress.start("geometry", 0);
                    let g = estimate_geometric(&images, &geometric);
                    progress.finish();
                    let g = g?;
                    init_warnings.extend(g.warnings);
                    g.cameras
                }
                InitSource::File(cams) => cams.clone(),
            };
            let Some(fallback) = given.iter().flatten().next().copied() else {
                bail!("the initial estimate has no camera");
            };
            let missing: Vec<&str> = names
                .iter()
                .zip(&given)
                .filter(|(_, c)| c.is_none())
                .map(|(n, _)| n.as_str())
                .collect();
            if !missing.is_empty() {
                init_warnings.push(format!(
                    "no initial camera for {}: the diffusion starts them at the first estimated camera",
                    missing.join(", ")
                ));
            }
            Some(
                given
                    .iter()
                    .zip(&images)
                    .map(|(c, _)| c.unwrap_or(fallback))
                    .collect(),
            )
        }
    };
    let estimate = estimator.estimate_from(
        &images,
        root.as_deref(),
        init_cameras.as_deref().map(|c| (c, args.start_step)),
        progress,
    )?;
    let mut first = estimate.samples[0].clone();
    let mut bundle_report = None;
    if matches!(args.refine, RefineArg::Bundle) {
        if estimate.pairs.iter().all(|p| p.is_empty()) {
            bail!(
                "--refine bundle needs verified matches (none were found, or --no-ggs was given)"
            );
        }
        let mut cams: Vec<posediff_geometry::Camera> = first.iter().map(|c| c.camera).collect();
        let report = posediff::geometric::bundle_refine_cameras(
            &mut cams,
            &estimate.pairs,
            !matches!(known, KnownIntrinsics::Unknown),
        )?;
        for (named, c) in first.iter_mut().zip(cams) {
            named.camera = c;
        }
        bundle_report = Some(report);
    }
    let entries: Vec<ImageCamera> = first
        .iter()
        .map(|c| ImageCamera {
            image: c.image.clone(),
            size: c.camera.image_size,
            camera: Some(c.camera),
        })
        .collect();
    let mut warnings = init_warnings;
    warnings.extend(estimate.warnings.iter().cloned());
    for w in &warnings {
        log::warn!("{w}");
    }
    let run = serde_json::json!({
        "posediff": env!("CARGO_PKG_VERSION"),
        "method": "posediffusion",
        "weights": weights,
        "images": images,
        "init": args.init,
        "start_step": init_cameras.as_ref().map(|_| args.start_step),
        "seed": args.seed,
        "samples": args.samples,
        "ggs": !args.no_ggs,
        "bundle": bundle_report,
        "device": device_name,
        "seconds": {"load_weights": load_weights, "load_images": estimate.times.load, "matching": estimate.times.matching,
                    "features": estimate.times.features, "sampling": estimate.times.sampling, "ggs": estimate.times.ggs},
        "matches_per_pair": estimate.matches_per_pair.iter().map(|(a, b, n)| serde_json::json!({"first": a, "second": b, "matches": n})).collect::<Vec<_>>(),
        "skipped_images": skipped,
        "sample_spread": first.iter().zip(estimate.spread()?).map(|(c, s)| serde_json::json!({
            "image": c.image, "rotation_deg_max": s.rotation_deg_max, "center_distance_max": s.center_distance_max,
        })).collect::<Vec<_>>(),
        "warnings": warnings,
    });
    if estimate.pairs.iter().all(|p| p.is_empty()) {
        log::warn!("no verified matches (--no-ggs skips matching): the COLMAP model has no points");
    }
    finish(
        &args.out,
        entries,
        &estimate.pairs,
        &inputs,
        run,
        &output_options,
        quiet,
    )
}

/// A cameras.json's entries matched to the images by name.
fn read_per_image(
    path: &Path,
    names: &[String],
    what: &str,
) -> anyhow::Result<posediff::records::Matched<ImageCamera>> {
    let given = read_cameras_json_partial(path)
        .with_context(|| format!("reading {what} {}", path.display()))?;
    posediff::records::match_by_name(
        names,
        given.into_iter().map(|g| (g.image.clone(), g)).collect(),
    )
    .map_err(|e| anyhow::anyhow!("{what} {}: {e}", path.display()))
}

fn detector(m: Matcher) -> Detector {
    match m {
        Matcher::Sift => Detector::Sift,
        Matcher::Orb => Detector::Orb,
    }
}

/// Triangulates the points with the final cameras, writes every output (see
/// `posediff::outputs`) and prints the cameras.
fn finish(
    out: &Path,
    entries: Vec<ImageCamera>,
    pairs: &[posediff_geometry::PairMatches],
    inputs: &InputImages,
    mut run: serde_json::Value,
    options: &OutputOptions,
    quiet: bool,
) -> anyhow::Result<()> {
    let (recon, points) = Reconstruction::triangulate(
        entries,
        Some(&inputs.files),
        pairs,
        &PointOptions::default(),
    )?;
    if let Some(map) = run.as_object_mut() {
        map.insert(
            "points".into(),
            serde_json::json!({
                "tracks": points.tracks.tracks,
                "inconsistent_tracks": points.tracks.inconsistent,
                "points": points.points,
                "observations": points.observations,
                "dropped_observations": points.dropped_observations,
                "tracks_without_two_estimated_images": points.unseen,
                "rejected_tracks": points.rejected,
                "mean_reprojection_error_px": points.mean_error_px,
                "max_reprojection_px": PointOptions::default().max_reprojection_px,
                "min_triangulation_angle_deg": PointOptions::default().min_angle_deg,
            }),
        );
    }
    let written = write_outputs(out, &recon, inputs, &run, options)?;
    if !quiet {
        println!(
            "{:<32} {:>9} {:>9} {:>28}",
            "image", "fx px", "fy px", "centre (world)"
        );
        for e in &recon.images {
            match &e.camera.camera {
                Some(c) => {
                    let k = &c.intrinsics;
                    let p = c.center();
                    println!(
                        "{:<32} {:>9.1} {:>9.1} {:>9.3} {:>9.3} {:>9.3}",
                        e.camera.image,
                        k.fx(),
                        k.fy(),
                        p.x,
                        p.y,
                        p.z
                    );
                }
                None => println!("{:<32} not estimated", e.camera.image),
            }
        }
        println!(
            "{} points (mean reprojection error {:.3} px, mean track length {:.1})",
            written.points,
            written.mean_reprojection_error_px.unwrap_or(0.0),
            written.mean_track_length
        );
        println!("wrote {} to {}", written.files.join(", "), out.display());
    }
    Ok(())
}

/// `posediff view`: view.html from an output folder's COLMAP model and images.
fn view(dir: &Path, gt: Option<&Path>, out: Option<&Path>) -> anyhow::Result<()> {
    let model_dir = dir.join("sparse").join("0");
    let model = ColmapModel::read(&model_dir)
        .with_context(|| format!("{} is not a posediff output folder", dir.display()))?;
    let recon = model.to_reconstruction(&model_dir)?;
    let files: Vec<PathBuf> = recon
        .images
        .iter()
        .map(|i| dir.join("images").join(&i.camera.image))
        .collect();
    let thumbs: Vec<Option<Vec<u8>>> = if files.iter().all(|f| f.is_file()) {
        posediff::outputs::thumbnails(&recon, &files)?
    } else {
        log::warn!(
            "{}/images does not hold the images: no thumbnails",
            dir.display()
        );
        vec![None; recon.images.len()]
    };
    let truth = match gt {
        None => None,
        Some(path) => {
            let given = read_cameras_json_partial(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let by_name = |name: &str| {
                given.iter().find(|g| g.image == name).or_else(|| {
                    let file = Path::new(name).file_name();
                    given
                        .iter()
                        .find(|g| Path::new(&g.image).file_name() == file)
                })
            };
            Some(
                recon
                    .images
                    .iter()
                    .map(|i| by_name(&i.camera.image).and_then(|g| g.camera))
                    .collect::<Vec<_>>(),
            )
        }
    };
    let title = posediff::outputs::set_title(Some(&dir.join("images")));
    let html = posediff::viewer::render(&title, &recon, &thumbs, truth.as_deref())?;
    let path = out.map_or_else(|| dir.join("view.html"), Path::to_path_buf);
    std::fs::write(&path, html).with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}

/// The ground truth's cameras for the entries of `cameras`, matched by name: every entry
/// must have one and every ground-truth camera an entry.
fn truth_for(
    cameras: &Path,
    est: &[ImageCamera],
    gt: &Path,
) -> anyhow::Result<Vec<posediff_geometry::Camera>> {
    let truth = posediff::export::read_cameras_json(gt)
        .with_context(|| format!("reading {}", gt.display()))?;
    let names: Vec<String> = est.iter().map(|e| e.image.clone()).collect();
    posediff::records::match_by_name(
        &names,
        truth
            .into_iter()
            .map(|c| (c.image.clone(), c.camera))
            .collect(),
    )
    .map_err(|e| anyhow::anyhow!("--gt {}: {e}", gt.display()))?
    .complete(&format!("--gt (for {})", cameras.display()), gt)
    .map_err(anyhow::Error::msg)
}

fn score(cameras: &Path, gt: &Path, out: Option<&Path>) -> anyhow::Result<()> {
    let est = read_cameras_json_partial(cameras)
        .with_context(|| format!("reading {}", cameras.display()))?;
    let gt_cams = truth_for(cameras, &est, gt)?;
    let pred: Vec<_> = est
        .iter()
        .map(|e| e.camera.map(|c| c.cam_from_world))
        .collect();
    let (s, cc) = posediff::bench::score_set(&gt_cams, &pred)?;
    println!(
        "{} cameras ({} estimated): RRA@15 {:.3}  RTA@15 {:.3}  mAA(30) {:.3}  CC@0.1 {:.3}",
        est.len(),
        pred.iter().filter(|p| p.is_some()).count(),
        s.rra[1],
        s.rta[1],
        s.maa_30,
        cc
    );
    if let Some(out) = out {
        let json = serde_json::json!({"cameras": cameras, "gt": gt, "scores": s, "cc_10": cc});
        std::fs::write(out, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}

fn plot(cameras: &Path, gt: Option<&Path>, out: &Path) -> anyhow::Result<()> {
    let (est, truth) = plot_inputs(cameras, gt)?;
    let errors = posediff::plot::plot_cameras(out, &est, truth.as_deref())?;
    for e in &errors {
        println!(
            "{:<32} {:>8.2} deg {:>8.4} centre",
            e.image, e.rotation_deg, e.center_rel
        );
    }
    println!("wrote {}", out.display());
    Ok(())
}

/// The estimated cameras and, when given, the ground truth of the same images (images not
/// estimated are left out of both).
fn plot_inputs(
    cameras: &Path,
    gt: Option<&Path>,
) -> anyhow::Result<(Vec<NamedCamera>, Option<Vec<NamedCamera>>)> {
    let est = read_cameras_json_partial(cameras)
        .with_context(|| format!("reading {}", cameras.display()))?;
    let truth = gt.map(|g| truth_for(cameras, &est, g)).transpose()?;
    let keep: Vec<bool> = est.iter().map(|e| e.camera.is_some()).collect();
    if keep.iter().filter(|k| **k).count() < 2 {
        bail!("{} has fewer than two estimated cameras", cameras.display());
    }
    let est_named = ImageCamera::estimated(&est);
    let truth = truth.map(|t| {
        t.into_iter()
            .zip(&est)
            .filter(|(_, e)| e.camera.is_some())
            .map(|(camera, e)| NamedCamera {
                image: e.image.clone(),
                camera,
            })
            .collect()
    });
    Ok((est_named, truth))
}

fn command_line() -> String {
    std::env::args().collect::<Vec<_>>().join(" ")
}

fn bench_method(
    method: Option<BenchMethod>,
    weights: Option<&Path>,
    no_ggs: bool,
) -> anyhow::Result<Box<dyn posediff::bench::Method>> {
    let method = method.unwrap_or(if weights.is_some() {
        BenchMethod::Posediffusion
    } else {
        BenchMethod::Geometric
    });
    Ok(match (method, weights) {
        (BenchMethod::GroundTruth, _) => Box::new(posediff::bench::GroundTruth),
        (BenchMethod::Geometric, _) => Box::new(posediff::bench::Geometric::default()),
        (BenchMethod::Posediffusion, None) => bail!("--method posediffusion needs --weights"),
        (BenchMethod::Posediffusion, Some(w)) => {
            let config = EstimateConfig {
                ggs: !no_ggs,
                ..EstimateConfig::default()
            };
            let estimator = Estimator::load(w, Device::Cpu, config)
                .with_context(|| format!("loading weights {}", w.display()))?;
            Box::new(posediff::bench::Posediffusion {
                estimator,
                label: format!(
                    "posediff ({}{})",
                    w.display(),
                    if no_ggs { ", no GGS" } else { "" }
                ),
            })
        }
    })
}

fn write_report(out: &Path, json: serde_json::Value, md: &str) -> anyhow::Result<()> {
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(out, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", out.display()))?;
    std::fs::write(out.with_extension("md"), md)
        .with_context(|| format!("writing {}", out.with_extension("md").display()))?;
    println!("{md}");
    Ok(())
}
