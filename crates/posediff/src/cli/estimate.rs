//! `posediff estimate`: cameras (and points) for a folder of images or a list of files.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use candle_core::Device;
use clap::ValueEnum;
use posediff::colmap::ColmapFormat;
use posediff::export::{ImageCamera, read_cameras_json_partial};
use posediff::geometric::{
    GeometricConfig, KnownIntrinsics, Refinement, estimate_geometric, refine_given_cameras,
};
use posediff::loader::image_files;
use posediff::outputs::{
    ImagesMode, InputImages, OutputOptions, prepare_output_dir, write_outputs,
};
use posediff::reconstruction::Reconstruction;
use posediff::run_report::{
    MethodReport, NetworkReport, NetworkSeconds, PairCount, PointsSummary, RunReport, SampleSpread,
    SkippedImage,
};
use posediff::{EstimateConfig, Estimator, Progress, Silent};
use posediff_matching::Detector;
use posediff_sfm::points::PointOptions;

use super::{Bars, DeviceArg};

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

/// The arguments of `posediff estimate`.
#[derive(clap::Args)]
pub struct Args {
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
        }
    }
}

/// Where the initial cameras come from.
enum InitSource {
    Geometric,
    /// Per image, matched by name (`None`: no camera given).
    File(Vec<Option<posediff_geometry::Camera>>),
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        estimate(self)
    }
}

fn estimate(args: Args) -> anyhow::Result<()> {
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
    let skipped: Vec<SkippedImage> = bad_images
        .iter()
        .map(|(p, why)| SkippedImage {
            image: p.clone(),
            reason: why.clone(),
        })
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
    let device_name = args.device.name();
    if matches!(args.device, DeviceArg::Cuda) && args.weights.is_none() {
        bail!("--device cuda runs the network: it needs --weights");
    }
    let device = if args.weights.is_some() {
        args.device.device()?
    } else {
        Device::Cpu
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
        let mut run = RunReport::new(
            images.clone(),
            MethodReport::Geometric {
                refine: format!("{:?}", geometric.refinement),
                report: Box::new(result.report.clone()),
            },
        );
        run.init = args.init.clone();
        run.skipped_images = skipped;
        run.warnings = warnings;
        run.matches_per_pair = result
            .pairs
            .iter()
            .map(|p| PairCount {
                first: p.first,
                second: p.second,
                matches: p.len(),
            })
            .collect();
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
    let t = &estimate.times;
    let sample_spread = first
        .iter()
        .zip(estimate.spread()?)
        .map(|(c, s)| SampleSpread {
            image: c.image.clone(),
            rotation_deg_max: s.rotation_deg_max,
            center_distance_max: s.center_distance_max,
        })
        .collect();
    let mut run = RunReport::new(
        images.clone(),
        MethodReport::Posediffusion(Box::new(NetworkReport {
            weights: weights.clone(),
            start_step: init_cameras.as_ref().map(|_| args.start_step),
            seed: args.seed,
            samples: args.samples,
            ggs: !args.no_ggs,
            bundle: bundle_report,
            device: device_name,
            seconds: NetworkSeconds {
                load_weights,
                load_images: t.load,
                matching: t.matching,
                features: t.features,
                sampling: t.sampling,
                ggs: t.ggs,
            },
            sample_spread,
        })),
    );
    run.init = args.init.clone();
    run.skipped_images = skipped;
    run.warnings = warnings;
    run.matches_per_pair = estimate
        .matches_per_pair
        .iter()
        .map(|&(first, second, matches)| PairCount {
            first,
            second,
            matches,
        })
        .collect();
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
    mut run: RunReport,
    options: &OutputOptions,
    quiet: bool,
) -> anyhow::Result<()> {
    let (mut recon, points) =
        Reconstruction::triangulate(entries, None, pairs, &PointOptions::default())?;
    // Colours and the viewer's thumbnails from one decode of each image.
    let side = options
        .view
        .then(|| posediff::outputs::thumbnail_side(recon.images.len()));
    let thumbnails = recon.colour_and_thumbnails(&inputs.files, side)?;
    run.points = Some(PointsSummary::new(&points, &PointOptions::default()));
    let written = write_outputs(out, &recon, inputs, &run, options, Some(&thumbnails))?;
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
