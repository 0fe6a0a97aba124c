//! `posediff estimate`: cameras (and points) for a folder of images or a list of files.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use candle_core::Device;
use clap::ValueEnum;
use posediff::estimate::options::PipelineOptions;
use posediff::estimate::run::{
    DEFAULT_START_STEP, InitSource, Inputs, IntrinsicsSource, Network, RefineMode, RunOptions,
    load_estimator, run,
};
use posediff::estimate::run_report::Resources;
use posediff::io::colmap::ColmapFormat;
use posediff::io::outputs::{
    FRAMES, ImagesMode, OutputOptions, Written, prepare_output_dir, thumbnail_side,
};
use posediff::io::video::{check_masks, extract_keyframes, is_video, probe};
use posediff::reconstruction::Reconstruction;
use posediff::{Progress, Silent};

use super::{Bars, DeviceArg, Matcher};

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

/// The arguments of `posediff estimate`.
#[derive(clap::Args)]
pub struct Args {
    /// A folder (its .png/.jpg/.jpeg files, sorted), image files (in the order given), or
    /// videos (.mp4, .mov, .mkv, .avi, …): each decoded once, its keyframes chosen (sharp,
    /// overlapping, not near duplicates) and written to out/images as
    /// `<video>_f<frame>_t<seconds>s.jpg`, one camera per video.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Video input: frames looked at per second of video (default: every frame). (Sets the
    /// options tree's `video.fps`.)
    #[arg(long)]
    fps: Option<f64>,
    /// Video input: at most this many keyframes per video, thinned evenly. (Sets the options
    /// tree's `video.max_frames`.)
    #[arg(long)]
    max_frames: Option<usize>,
    /// Official PoseDiffusion checkpoint (.pth or safetensors). Without it the cameras come
    /// from the images' geometry alone (matching, averaging, refinement).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Start from an estimate: `geometric` (the checkpoint-free cameras) or a cameras.json.
    /// With --weights the reverse diffusion starts at --start-step from the noised estimate;
    /// without, a cameras.json is refined on the matches.
    #[arg(long)]
    init: Option<InitSource>,
    /// With --weights and --init: the diffusion step the estimate is noised to (0-99; larger
    /// trusts it less).
    #[arg(long, default_value_t = DEFAULT_START_STEP)]
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
    /// 60 images, `sequential:10,retrieval:20` above; with a learned matcher every pair up to
    /// 12 images, above `sequential:3,retrieval:3` and then a second pass on the first map's
    /// cameras: each image with up to 5 unmatched images within 45°), `exhaustive`,
    /// `sequential:K` (each image with the next K), `retrieval:K` (its K most similar by a bag
    /// of visual words), or a union such as `sequential:10,retrieval:20`.
    /// (Sets the options tree's `pairs.selection`; default `auto`.)
    #[arg(long)]
    pairs: Option<posediff_matching::PairSelection>,
    /// Which photos share a camera (checkpoint-free path, unknown intrinsics): `auto` (with
    /// EXIF, a camera per EXIF make, model, focal length and image size, its focal prior from
    /// the EXIF as COLMAP reads it; without, a focal per image calibrated from the view graph,
    /// and images whose focals agree within `mapper.calibration.group_tolerance` share one
    /// camera), `single` (one focal for all), `per-folder` or `per-image` (COLMAP's default).
    /// (Sets the options tree's `cameras.mode`; default `auto`.)
    #[arg(long, value_name = "MODE")]
    camera_mode: Option<posediff_pipeline::options::CameraMode>,
    /// The lens model, as COLMAP names it (checkpoint-free path, unknown intrinsics):
    /// `SIMPLE_RADIAL` (the default: a radial coefficient per camera where the data show one),
    /// `RADIAL` (two coefficients, for a wide-angle lens), `OPENCV` (two radial and two
    /// tangential coefficients, one focal), `OPENCV_FISHEYE` (four coefficients of the angle),
    /// `SIMPLE_PINHOLE` or `PINHOLE` (no distortion). (Sets the options tree's `cameras.distortion` and
    /// `cameras.lens_refinement`.)
    #[arg(long, value_name = "MODEL")]
    camera_model: Option<String>,
    /// The pipeline's options from a TOML (`.toml`) or JSON file: any subset of the tree
    /// run.json's `options` shows (e.g. `[orientation]` / `strong_pair = 100`). Applied before
    /// `--pairs` and `--set`.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// One option of the tree, `key.path=value` (e.g. `orientation.strong_pair=100`,
    /// `densify.when=always`, `mapper.bundle=null`); repeatable, applied last, in order.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
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
    /// Keypoints and matches of both paths (GGS and the checkpoint-free mapper).
    #[arg(long, value_enum, default_value = "sift")]
    matcher: Matcher,
    /// Folder of the learned matcher's weights (default: $POSEDIFF_WEIGHTS_DIR, else
    /// ~/.cache/posediff/weights).
    #[arg(long)]
    weights_dir: Option<PathBuf>,
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
    /// Also write out/undistorted/ where a lens distortion was estimated: the photos resampled
    /// onto their pinhole cameras and a PINHOLE COLMAP model (as COLMAP's image undistorter,
    /// for 3DGS and gsplat).
    #[arg(long)]
    undistort: bool,
    /// COLMAP 4.2's database.db at this path (created if absent): features and verified
    /// matches are read from it first and written to it as they are made, so that a run that
    /// stops resumes where it was; COLMAP's and GLOMAP's mappers (and pycolmap) map it as it
    /// is. `posediff features` and `posediff match` fill it in steps.
    #[arg(long, value_name = "FILE")]
    database: Option<PathBuf>,
    /// Databases of the same matcher and settings (e.g. `posediff features|match --shard`
    /// workers') whose features and pairs `--database` lacks: imported first, so only what
    /// none of them did is done (repeatable; needs --database).
    #[arg(long = "from", value_name = "DB")]
    import_from: Vec<PathBuf>,
    /// Go on without images that are corrupt, truncated or unreadable (listed in run.json)
    /// instead of stopping.
    #[arg(long)]
    skip_bad_images: bool,
    /// A folder of masks named as COLMAP's (`<image name>.png`, zero = ignore): keypoints on
    /// masked pixels are dropped before matching; an image without a mask is used whole.
    #[arg(long)]
    masks: Option<PathBuf>,
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

impl Args {
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
            undistort: self.undistort,
            ..OutputOptions::default()
        }
    }
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        let start = Instant::now();
        // Every cheap check first: options, paths, files that name the images, the output
        // folder, the images' headers, the checkpoint's keys and shapes; only then features and
        // matching.
        let mut options = self.run_options()?;
        options.check()?;
        if self.start_step != DEFAULT_START_STEP && self.init.is_none() {
            bail!(
                "--start-step needs --init (it is where the diffusion starts from the initial cameras)"
            );
        }
        if let Some(w) = &self.weights
            && !w.is_file()
        {
            bail!("--weights: no such file: {}", w.display());
        }
        let videos: Vec<&PathBuf> = self.inputs.iter().filter(|p| is_video(p)).collect();
        if !videos.is_empty() {
            if videos.len() != self.inputs.len() {
                bail!("give videos or images, not both (each video's keyframes become the images)");
            }
            return self.run_video(options, start);
        }
        let inputs = Inputs::resolve(&self.inputs, self.skip_bad_images)?;
        options.thumbnail_side = (!self.no_view).then(|| thumbnail_side(inputs.names.len()));
        if matches!(self.device, DeviceArg::Cuda) && self.weights.is_none() {
            bail!("--device cuda runs the network: it needs --weights");
        }
        let device = if self.weights.is_some() {
            self.device.device()?
        } else {
            Device::Cpu
        };
        let output_options = self.output_options();
        prepare_output_dir(&self.out, &inputs.images, output_options.images)?;
        let loaded = match &self.weights {
            Some(w) => Some(
                load_estimator(w, device)
                    .with_context(|| format!("loading weights {}", w.display()))?,
            ),
            None => None,
        };
        let network = match (&loaded, &self.weights) {
            (Some((estimator, seconds)), Some(weights)) => Some(Network {
                estimator,
                weights,
                device: self.device.name(),
                load_seconds: *seconds,
            }),
            _ => None,
        };
        let mut bars = Bars::default();
        let progress: &mut dyn Progress = if self.quiet { &mut Silent } else { &mut bars };
        let mut result = run(&inputs, &options, network, progress)?;
        result.report.resources = Some(Resources::since(start));
        let written = result.write(&self.out, &output_options)?;
        if !self.quiet {
            print_cameras(&result.reconstruction, &written, &self.out);
        }
        Ok(())
    }

    /// Videos: each probed, the masks checked and the output folder prepared before any
    /// decoding; then one decoding pass per video writing its keyframes into
    /// `out/.posediff-frames`, the run on them, and the keyframes moved into `out/images` with
    /// the results.
    fn run_video(self, mut options: RunOptions, start: Instant) -> anyhow::Result<()> {
        if self.weights.is_some() {
            bail!(
                "video input runs the checkpoint-free path: extract keyframes with a first run, \
                 then give out/images to --weights"
            );
        }
        if matches!(self.images, ImagesArg::None) {
            bail!(
                "--images none: a video's keyframes are written to out/images (they are the images the outputs name)"
            );
        }
        let infos = probe(&self.inputs)?;
        if let Some(dir) = &self.masks {
            check_masks(dir, &infos)?;
        }
        let mut output_options = self.output_options();
        output_options.images = ImagesMode::Move;
        let none = posediff::io::outputs::InputImages {
            files: Vec::new(),
            folder: None,
            folder_given: false,
        };
        prepare_output_dir(&self.out, &none, ImagesMode::Move)?;
        let work = self.out.join(FRAMES);
        let mut bars = Bars::default();
        let progress: &mut dyn Progress = if self.quiet { &mut Silent } else { &mut bars };
        let frames = work.join("images");
        let mask_out = work.join("masks");
        let result = (|| -> anyhow::Result<Written> {
            let capture = extract_keyframes(
                &infos,
                &frames,
                &options.pipeline.video,
                self.masks.as_deref().map(|m| (m, mask_out.as_path())),
                progress.counter(),
            )?;
            if !self.quiet {
                let (per_second, per_key) = capture.costs();
                eprintln!(
                    "{} keyframes of {} decoded frames ({per_second:.0} frames/s, {per_key:.2} s per keyframe)",
                    capture.keyframes.len(),
                    capture
                        .videos
                        .iter()
                        .map(|v| v.frames_decoded)
                        .sum::<usize>()
                );
            }
            options.masks = capture.masks.clone();
            let inputs = Inputs::from_capture(capture);
            options.thumbnail_side = (!self.no_view).then(|| thumbnail_side(inputs.names.len()));
            let mut run = run(&inputs, &options, None, progress)?;
            // run.json names the images where they will be.
            run.report.images = inputs
                .names
                .iter()
                .map(|n| self.out.join("images").join(n))
                .collect();
            run.report.resources = Some(Resources::since(start));
            let written = run.write(&self.out, &output_options)?;
            if !self.quiet {
                print_cameras(&run.reconstruction, &written, &self.out);
            }
            Ok(written)
        })();
        let _ = std::fs::remove_dir_all(&work);
        result.map(|_| ())
    }

    fn run_options(&self) -> posediff::Result<RunOptions> {
        let mut pipeline = pipeline_options(
            self.config.as_deref(),
            self.pairs.as_ref(),
            (self.camera_mode, self.camera_model.as_deref()),
            &[],
        )?;
        if let Some(fps) = self.fps {
            pipeline.video.fps = Some(fps);
        }
        if let Some(n) = self.max_frames {
            pipeline.video.max_frames = Some(n);
        }
        for assignment in &self.set {
            pipeline = pipeline.with_assignment(assignment)?;
        }
        pipeline.check()?;
        Ok(RunOptions {
            init: self.init.clone(),
            start_step: self.start_step,
            intrinsics: match (self.focal_px, &self.intrinsics) {
                (Some(f), _) => IntrinsicsSource::FocalPx(f),
                (None, Some(path)) => IntrinsicsSource::File(path.clone()),
                (None, None) => IntrinsicsSource::Estimate,
            },
            refine: match self.refine {
                RefineArg::Converge => RefineMode::Converge,
                RefineArg::Bundle => RefineMode::Bundle,
                RefineArg::Official => RefineMode::Official,
                RefineArg::None => RefineMode::None,
            },
            pipeline,
            matcher: self.matcher.into(),
            weights_dir: self.weights_dir.clone(),
            masks: self.masks.clone(),
            database: self.database.clone(),
            map_database: false,
            shard: None,
            import_from: self.import_from.clone(),
            seed: self.seed,
            samples: self.samples,
            ggs: !self.no_ggs,
            thumbnail_side: None,
        })
    }
}

/// The options tree of a file (`--config`), `--pairs`, `--camera-mode`, `--camera-model` and
/// `--set` assignments, in that order.
///
/// # Errors
/// An unreadable file, an unknown key, a value of the wrong type, a camera model posediff does
/// not estimate.
pub(super) fn pipeline_options(
    config: Option<&Path>,
    pairs: Option<&posediff_matching::PairSelection>,
    (camera_mode, camera_model): (Option<posediff_pipeline::options::CameraMode>, Option<&str>),
    set: &[String],
) -> posediff::Result<PipelineOptions> {
    let mut pipeline = PipelineOptions::default();
    if let Some(path) = config {
        pipeline = pipeline.with_file(path)?;
    }
    if let Some(pairs) = pairs {
        pipeline.pairs.selection = pairs.clone();
    }
    if let Some(mode) = camera_mode {
        pipeline.cameras.mode = mode;
    }
    if let Some(model) = camera_model {
        pipeline.cameras.set_model(model)?;
    }
    for assignment in set {
        pipeline = pipeline.with_assignment(assignment)?;
    }
    Ok(pipeline)
}

/// The cameras and the summary line on stdout.
fn print_cameras(recon: &Reconstruction, written: &Written, out: &Path) {
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
