//! One estimation run, whichever path makes the cameras: the input images checked and named,
//! the options checked before any expensive work, the cameras from the checkpoint-free mapper
//! or from PoseDiffusion, the points triangulated and coloured, and one [`Run`] that the CLI
//! and the Python module write the same way.
//!
//! ```text
//! Inputs::resolve ─► RunOptions::check ─► run ─► Run { reconstruction, report } ─► Run::write
//! ```

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use posediff_geometry::{Camera, PairMatches};

use crate::correspondences::{LearnedMatcher, MatcherChoice, SharedLearned, learned_weight_files};
use crate::error::{PosediffError, Result};
use crate::estimate::estimator::{EstimateInput, Estimator, Progress};
use posediff_pipeline::options::CameraHint;
pub use posediff_pipeline::store::Shard;

use crate::estimate::geometric::{
    GeometricConfig, KnownIntrinsics, Refinement, bundle_refine_cameras,
    estimate_geometric_counted, refine_given_cameras_counted,
};
use crate::estimate::options::PipelineOptions;
use crate::estimate::run_report::{
    MasksReport, MethodReport, NetworkReport, NetworkSeconds, PairCount, PointsSummary, RunReport,
    SampleSpread, SkippedImage, Warning,
};
use crate::io::exif::{ExifCamera, read_exif};
use crate::io::export::{ImageCamera, read_cameras_json_partial};
use crate::io::loader::relative_name;
use crate::io::loader::{check_images, image_files};
use crate::io::outputs::{InputImages, OutputOptions, Written, write_outputs_with_pairs};
use crate::io::records::{Matched, match_by_name};
use crate::io::video::Capture;
use crate::reconstruction::Reconstruction;
use posediff_matching::PairSelection;
use posediff_pipeline::store::SharedStore;

/// The input images, checked and named: the files in use, the folder their names are relative
/// to, and the files left out.
#[derive(Debug, Clone)]
pub struct Inputs {
    /// The files in use and their folder.
    pub images: InputImages,
    /// Each image's name (relative to the folder): the key of every per-image record.
    pub names: Vec<String>,
    /// Images left out as unusable (only with `skip_bad_images`).
    pub skipped: Vec<SkippedImage>,
    /// The videos the images are keyframes of ([`Inputs::from_capture`]).
    pub video: Option<Capture>,
}

impl Inputs {
    /// A folder (its .png/.jpg/.jpeg files, sorted) or image files (in the order given); every
    /// image's header is checked, and unusable images stop the run unless `skip_bad_images`.
    ///
    /// # Errors
    /// A path that does not exist; a folder among files; a folder without images; unusable
    /// images (listed); fewer than two images; two images of the same name.
    pub fn resolve(paths: &[PathBuf], skip_bad_images: bool) -> Result<Self> {
        for path in paths {
            if !path.exists() {
                return Err(PosediffError::NotFound(path.clone()));
            }
        }
        let folder_given = matches!(paths, [one] if one.is_dir());
        let (listed, folder) = match paths {
            [one] if one.is_dir() => (image_files(one)?, Some(one.clone())),
            files => {
                if let Some(dir) = files.iter().find(|f| f.is_dir()) {
                    return Err(PosediffError::InvalidArgument(format!(
                        "{} is a folder: give one folder, or image files",
                        dir.display()
                    )));
                }
                let folder = files
                    .first()
                    .and_then(|f| f.parent())
                    .map(Path::to_path_buf);
                (files.to_vec(), folder)
            }
        };
        let (files, bad) = check_images(&listed);
        if !bad.is_empty() {
            let list: Vec<String> = bad
                .iter()
                .map(|(p, why)| format!("{}: {why}", p.display()))
                .collect();
            if !skip_bad_images {
                return Err(PosediffError::InvalidArgument(format!(
                    "{} unusable image(s) (give --skip-bad-images to go on without them):\n  {}",
                    list.len(),
                    list.join("\n  ")
                )));
            }
            for l in &list {
                log::warn!("skipped {l}");
            }
        }
        if files.len() < 2 {
            return Err(PosediffError::InvalidArgument(format!(
                "need at least 2 images, got {}{}",
                files.len(),
                if bad.is_empty() {
                    String::new()
                } else {
                    format!(" after skipping {} unusable", bad.len())
                }
            )));
        }
        let names: Vec<String> = files
            .iter()
            .map(|p| relative_name(p, folder.as_deref()))
            .collect();
        let mut seen = HashMap::new();
        for (k, n) in names.iter().enumerate() {
            if let Some(first) = seen.insert(n.as_str(), k) {
                return Err(PosediffError::InvalidArgument(format!(
                    "{} and {} have the same name {n:?}: the outputs name images by it; give each image once, with distinct file names",
                    files[first].display(),
                    files[k].display()
                )));
            }
        }
        Ok(Self {
            images: InputImages {
                files,
                folder,
                folder_given,
            },
            names,
            skipped: bad
                .into_iter()
                .map(|(image, reason)| SkippedImage { image, reason })
                .collect(),
            video: None,
        })
    }

    /// The keyframes of videos ([`crate::io::video::extract_keyframes`]) as the run's images:
    /// named as written, one camera per video (the camera hints), the account in run.json's
    /// `video`.
    pub fn from_capture(capture: Capture) -> Self {
        Self {
            images: InputImages {
                files: capture.files(),
                folder: Some(capture.folder.clone()),
                folder_given: true,
            },
            names: capture.keyframes.iter().map(|k| k.image.clone()).collect(),
            skipped: Vec::new(),
            video: Some(capture),
        }
    }

    /// Each image's camera hint when the inputs say more than EXIF can: a video's frames share
    /// its camera (grouped as one EXIF device would be, so `cameras.mode = auto` gives one
    /// camera per video).
    fn camera_hints(&self) -> Option<Vec<CameraHint>> {
        let capture = self.video.as_ref()?;
        Some(
            capture
                .keyframes
                .iter()
                .map(|k| {
                    let v = &capture.videos[k.video].info;
                    CameraHint {
                        folder: v.stem.clone(),
                        device: Some(format!("video {} ({})", v.stem, v.codec)),
                        focal: Default::default(),
                    }
                })
                .collect(),
        )
    }
}

/// Where the initial cameras come from (`--init`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum InitSource {
    /// The checkpoint-free cameras (`geometric`).
    Geometric,
    /// A cameras.json, matched to the images by name.
    File(PathBuf),
}

impl std::str::FromStr for InitSource {
    type Err = std::convert::Infallible;

    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        Ok(Self::from(PathBuf::from(s)))
    }
}

impl From<PathBuf> for InitSource {
    /// `geometric`, or the path of a cameras.json.
    fn from(p: PathBuf) -> Self {
        if p.as_os_str() == "geometric" {
            Self::Geometric
        } else {
            Self::File(p)
        }
    }
}

impl std::fmt::Display for InitSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Geometric => f.write_str("geometric"),
            Self::File(p) => write!(f, "{}", p.display()),
        }
    }
}

/// Where the intrinsics come from.
#[derive(Debug, Clone, PartialEq)]
pub enum IntrinsicsSource {
    /// Estimated (one shared focal, principal points at the centres).
    Estimate,
    /// One known focal length in pixels for every image.
    FocalPx(f64),
    /// A cameras.json whose `K` per image is used (matched by name; R and t ignored).
    File(PathBuf),
    /// Given per image, in image order.
    PerImage(Vec<posediff_geometry::Intrinsics>),
}

pub use crate::estimate::options::RefineMode;

/// Everything a run is asked to do besides its images and its checkpoint.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Initial cameras.
    pub init: Option<InitSource>,
    /// With a checkpoint and `init`: the diffusion step the initial cameras are noised to.
    pub start_step: usize,
    /// Known or estimated intrinsics.
    pub intrinsics: IntrinsicsSource,
    /// Refinement.
    pub refine: RefineMode,
    /// Every threshold of the checkpoint-free pipeline (`--pairs` is its
    /// `pairs.selection`; `matching.features.detector` follows [`Self::matcher`]).
    pub pipeline: PipelineOptions,
    /// The matcher of both paths.
    pub matcher: MatcherChoice,
    /// Where the learned matcher's weights are (`None`: [`posediff_learned::weights::default_dir`]).
    pub weights_dir: Option<PathBuf>,
    /// Seed of the sampler.
    pub seed: u64,
    /// Samples per image set.
    pub samples: usize,
    /// Geometry-guided sampling (and its matching).
    pub ggs: bool,
    /// Longer side of the viewer's thumbnails, made from the same decode as the colours
    /// (`None`: no thumbnails now; the writer makes them when it needs them).
    pub thumbnail_side: Option<u32>,
    /// `--masks`: a folder of masks named as COLMAP's (`<image name>.png`, zero = ignore).
    pub masks: Option<PathBuf>,
    /// `--database`: COLMAP's database the features and verified matches are read from first
    /// and written to as they are made ([`crate::io::database::Database`]).
    pub database: Option<PathBuf>,
    /// `posediff map`: `database` is only read, whoever wrote it, and its verified pairs are
    /// the pairs mapped (no second pass, no turned retry: nothing is matched).
    pub map_database: bool,
    /// `--shard K/N` (`posediff features` / `posediff match` only): this process does the
    /// `K`-th of `N` parts of the extraction (a contiguous run of images) or of the matching
    /// (every `N`-th selected pair) into its own `database`, for a driver to merge with
    /// [`Self::import_from`] (`posediff.distributed` on Ray).
    pub shard: Option<Shard>,
    /// `--from DB` (repeatable): databases of the same matcher and settings (workers' shards)
    /// whose features and pairs `database` lacks are imported before any work, so only what
    /// none of them did is done here.
    pub import_from: Vec<PathBuf>,
}

impl Default for RunOptions {
    fn default() -> Self {
        Self {
            init: None,
            start_step: DEFAULT_START_STEP,
            intrinsics: IntrinsicsSource::Estimate,
            refine: RefineMode::Converge,
            pipeline: PipelineOptions::default(),
            matcher: MatcherChoice::Sift,
            weights_dir: None,
            seed: 0,
            samples: 1,
            ggs: true,
            thumbnail_side: None,
            masks: None,
            database: None,
            map_database: false,
            shard: None,
            import_from: Vec::new(),
        }
    }
}

/// The diffusion step initial cameras are noised to by default.
pub const DEFAULT_START_STEP: usize = 30;

impl RunOptions {
    /// The checks that need no image: counts and numbers in range.
    ///
    /// # Errors
    /// An option out of range, naming it.
    pub fn check(&self) -> Result<()> {
        self.pipeline.check()?;
        if self.samples == 0 {
            return Err(PosediffError::InvalidArgument(
                "--samples must be at least 1".into(),
            ));
        }
        if let IntrinsicsSource::FocalPx(f) = self.intrinsics
            && !(f.is_finite() && f > 0.0)
        {
            return Err(PosediffError::InvalidArgument(format!(
                "--focal-px must be a positive, finite number of pixels, got {f}"
            )));
        }
        if self.start_step > 99 {
            return Err(PosediffError::InvalidArgument(format!(
                "--start-step must be 0-99 (a step of the 100-step schedule), got {}",
                self.start_step
            )));
        }
        if (self.shard.is_some() || !self.import_from.is_empty()) && self.database.is_none() {
            return Err(PosediffError::InvalidArgument(
                "--shard and --from work on a database: give --database D".into(),
            ));
        }
        if self.map_database && (self.shard.is_some() || !self.import_from.is_empty()) {
            return Err(PosediffError::InvalidArgument(
                "posediff map only reads its database: merge workers' databases with \
                 `posediff match --database D --from W` first"
                    .into(),
            ));
        }
        if let Some(p) = self
            .import_from
            .iter()
            .find(|p| Some(*p) == self.database.as_ref())
        {
            return Err(PosediffError::invalid(
                p,
                "--from names the --database itself: give the workers' databases",
            ));
        }
        if let Some(p) = self.import_from.iter().find(|p| !p.is_file()) {
            return Err(PosediffError::NotFound(p.clone()));
        }
        if let Some(InitSource::File(p)) = &self.init
            && !p.is_file()
        {
            return Err(PosediffError::NotFound(p.clone()));
        }
        if let IntrinsicsSource::File(p) = &self.intrinsics
            && !p.is_file()
        {
            return Err(PosediffError::NotFound(p.clone()));
        }
        if let Some(extractor) = self.matcher.extractor_weights() {
            learned_weight_files(&self.learned_weights_dir(), extractor)?;
        }
        if let Some(dir) = &self.masks
            && !dir.is_dir()
        {
            return Err(PosediffError::InvalidArgument(format!(
                "--masks {}: not a folder (give the folder of <image name>.png masks)",
                dir.display()
            )));
        }
        Ok(())
    }

    /// The folder the learned matcher's weights are read from.
    pub fn learned_weights_dir(&self) -> PathBuf {
        self.weights_dir
            .clone()
            .unwrap_or_else(posediff_learned::weights::default_dir)
    }

    /// The learned matcher when the options ask for it, loaded once.
    ///
    /// # Errors
    /// Missing or malformed weights.
    pub fn load_learned(&self) -> Result<Option<SharedLearned>> {
        let Some(extractor) = self.matcher.extractor_weights() else {
            return Ok(None);
        };
        let dir = self.learned_weights_dir();
        let mut matcher = LearnedMatcher::load_with(&dir, extractor)?;
        matcher.configure(&self.pipeline.learned);
        Ok(Some(SharedLearned(std::sync::Arc::new(matcher))))
    }

    /// The options tree as the run uses it: the detector is the matcher's.
    pub fn pipeline_options(&self) -> PipelineOptions {
        let mut o = self.pipeline.clone();
        o.matching.features.detector = self.matcher.detector();
        o
    }

    fn geometric_config(&self, intrinsics: &KnownIntrinsics) -> GeometricConfig {
        let options = self.pipeline_options();
        let sampson = options.mapper.sampson.unwrap_or_default();
        GeometricConfig {
            intrinsics: intrinsics.clone(),
            refinement: match self.refine {
                RefineMode::Converge | RefineMode::Bundle => Refinement::Converge(sampson),
                RefineMode::Official => {
                    Refinement::Official(posediff_guidance::GgsConfig::default())
                }
                RefineMode::None => Refinement::None,
            },
            options,
            learned: None,
            hints: Vec::new(),
            masks: HashMap::new(),
            store: None,
        }
    }
}

/// The mask of each image in `dir` (COLMAP's naming: `<image name>.png`), checked before any
/// work: each one a whole JPEG or PNG of its image's size. Images without one are listed (used
/// whole, as COLMAP does).
///
/// # Errors
/// A broken or unreadable mask, or one of another size than its image (both named).
pub fn mask_files(
    dir: &Path,
    files: &[PathBuf],
    names: &[String],
) -> Result<(HashMap<PathBuf, PathBuf>, MasksReport)> {
    use posediff_matching::image_check::{header_size, header_size_of, image_problem};
    let mut masks = HashMap::new();
    let mut missing = Vec::new();
    for (file, name) in files.iter().zip(names) {
        let mask = dir.join(format!("{name}.png"));
        if !mask.exists() {
            missing.push(name.clone());
            continue;
        }
        let bytes = std::fs::read(&mask).map_err(|source| PosediffError::Read {
            path: mask.clone(),
            source,
        })?;
        if let Some(why) = image_problem(&bytes) {
            return Err(PosediffError::invalid(
                &mask,
                format!("unusable mask: {why}"),
            ));
        }
        // The image's size from its header alone (it was read whole by the input check).
        let image = header_size_of(file).map_err(|source| PosediffError::Read {
            path: file.clone(),
            source,
        })?;
        let (m, i) = (header_size(&bytes), image);
        // An EXIF-turned photo decodes with its sides swapped: either way round is checked
        // here, the decoded sizes again when the mask is applied.
        if m.is_none() || i.is_none() || (m != i && m != i.map(|(w, h)| (h, w))) {
            return Err(PosediffError::invalid(
                &mask,
                format!(
                    "the mask is {} but {} is {}: a mask has its image's size",
                    m.map_or("of unknown size".into(), |(w, h)| format!("{w}x{h}")),
                    file.display(),
                    i.map_or("of unknown size".into(), |(w, h)| format!("{w}x{h}")),
                ),
            ));
        }
        masks.insert(file.clone(), mask);
    }
    let report = MasksReport {
        folder: dir.to_owned(),
        masked: masks.len(),
        missing,
    };
    Ok((masks, report))
}

/// A loaded checkpoint for [`run`], with what run.json says of it.
#[derive(Debug, Clone, Copy)]
pub struct Network<'a> {
    /// The model.
    pub estimator: &'a Estimator,
    /// Its file.
    pub weights: &'a Path,
    /// `cpu` or `cuda`.
    pub device: &'static str,
    /// Seconds spent loading it.
    pub load_seconds: f64,
}

/// The result of a run: cameras and points, and the report (run.json without its outputs).
#[derive(Debug, Clone)]
pub struct Run {
    /// Images with cameras (or `None` where not estimated), keypoints and points.
    pub reconstruction: Reconstruction,
    /// What the run did.
    pub report: RunReport,
    /// The images, for the writers (links, thumbnails, colours).
    pub inputs: InputImages,
    /// The viewer's thumbnails when [`RunOptions::thumbnail_side`] asked for them.
    pub thumbnails: Option<Vec<Option<Vec<u8>>>>,
    /// The verified matches the cameras and points come from (for `database.db`).
    pub pairs: Vec<PairMatches>,
}

impl Run {
    /// Writes every output into `out` (see [`crate::io::outputs`]); `out` should have passed
    /// [`crate::io::outputs::prepare_output_dir`].
    ///
    /// # Errors
    /// As [`crate::io::outputs::write_outputs_with_pairs`].
    pub fn write(&self, out: &Path, options: &OutputOptions) -> Result<Written> {
        write_outputs_with_pairs(
            out,
            &self.reconstruction,
            &self.pairs,
            &self.inputs,
            &self.report,
            options,
            self.thumbnails.as_deref(),
        )
    }
}

/// Initial cameras, resolved against the images.
enum Init {
    Geometric,
    /// Per image (`None`: no camera given).
    Given(Vec<Option<Camera>>),
}

/// Where `posediff features` and `posediff match` stop ([`run_stages`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopAfter {
    /// Only `--from`'s features and pairs imported (a distributed run's driver merging its
    /// tasks' databases): nothing is read, selected, extracted or matched.
    Import,
    /// Features of every image stored.
    Features,
    /// Features of every image stored, and the first pass's pair selection (for the workers
    /// of a distributed run to match the same pairs without selecting them again).
    Selection,
    /// The first pass's pairs matched and stored.
    Matching,
}

/// What [`run_stages`] leaves in the database.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StagesSummary {
    /// Images with features.
    pub images: usize,
    /// Pairs matched (`Matching` only).
    pub pairs: usize,
    /// Of those, pairs with enough verified matches.
    pub verified: usize,
    /// The pair selection's rules (`Matching` only).
    pub selection: String,
    /// Images' features and pairs imported from `--from` before any work.
    pub imported: (usize, usize),
}

/// `posediff features` / `posediff match`: the checkpoint-free path's extraction (and its
/// first matching pass) into `options.database`, resuming from what it holds, then stop.
///
/// # Errors
/// No `--database`; as [`run`].
pub fn run_stages(
    inputs: &Inputs,
    options: &RunOptions,
    stop: StopAfter,
    progress: &mut dyn Progress,
) -> Result<StagesSummary> {
    if options.database.is_none() {
        return Err(PosediffError::InvalidArgument(
            "features and matches are stored in a database: give --database D".into(),
        ));
    }
    let c = configure(inputs, options, false)?;
    let files = &inputs.images.files;
    progress.start("geometry", 0);
    let result = match stop {
        StopAfter::Import => Ok(StagesSummary {
            images: 0,
            pairs: 0,
            verified: 0,
            selection: String::new(),
            imported: c.imported,
        }),
        StopAfter::Features => {
            let part = match options.shard {
                Some(s) => &files[s.images(files.len())],
                None => &files[..],
            };
            let extracted = if part.is_empty() {
                Ok(Vec::new())
            } else {
                c.geometric
                    .correspondences()
                    .extract(part, progress.counter())
            };
            extracted.map(|f| StagesSummary {
                images: f.len(),
                pairs: 0,
                verified: 0,
                selection: String::new(),
                imported: c.imported,
            })
        }
        StopAfter::Selection => posediff_pipeline::geometric::extract_and_select(
            files,
            &c.geometric,
            progress.counter(),
        )
        .map(|(pairs, selection)| StagesSummary {
            images: files.len(),
            pairs,
            verified: 0,
            selection,
            imported: c.imported,
        }),
        StopAfter::Matching => {
            let matched = match options.shard {
                Some(s) => posediff_pipeline::geometric::extract_and_match_shard(
                    files,
                    &c.geometric,
                    s,
                    progress.counter(),
                ),
                None => posediff_pipeline::geometric::extract_and_match(
                    files,
                    &c.geometric,
                    progress.counter(),
                ),
            };
            matched.map(|(pairs, selection)| StagesSummary {
                images: files.len(),
                pairs: pairs.len(),
                verified: pairs.iter().filter(|p| !p.is_empty()).count(),
                selection,
                imported: c.imported,
            })
        }
    };
    progress.finish();
    result
}

/// What a run has worked out before any image is read: the known intrinsics, the initial
/// cameras, the controller's configuration (with `--database`'s store opened), the masks.
struct Configured {
    known: KnownIntrinsics,
    init: Option<Init>,
    geometric: GeometricConfig,
    masks: Option<MasksReport>,
    warnings: Vec<Warning>,
    needs_matches: bool,
    /// Images and pairs taken from `--from` (see [`RunOptions::import_from`]).
    imported: (usize, usize),
}

/// The checks and set-up of [`run`] and [`run_stages`], before any expensive work.
fn configure(inputs: &Inputs, options: &RunOptions, network: bool) -> Result<Configured> {
    options.check()?;
    let names = &inputs.names;
    let files = &inputs.images.files;
    let known = match &options.intrinsics {
        IntrinsicsSource::Estimate => KnownIntrinsics::Unknown,
        IntrinsicsSource::FocalPx(f) => KnownIntrinsics::FocalPx(*f),
        IntrinsicsSource::PerImage(k) => {
            if k.len() != files.len() {
                return Err(PosediffError::InvalidArgument(format!(
                    "{} intrinsics for {} images",
                    k.len(),
                    files.len()
                )));
            }
            KnownIntrinsics::PerImage(k.clone())
        }
        IntrinsicsSource::File(path) => {
            let given = read_per_image(path, names, "--intrinsics")?
                .complete("--intrinsics", path)
                .map_err(|e| PosediffError::invalid(path, e))?;
            KnownIntrinsics::PerImage(
                given
                    .iter()
                    .map(|g| {
                        g.camera.map(|c| c.intrinsics).ok_or_else(|| {
                            PosediffError::invalid(path, format!("no K for {}", g.image))
                        })
                    })
                    .collect::<Result<Vec<_>>>()?,
            )
        }
    };
    let mut warnings = Vec::new();
    let init = match &options.init {
        None => None,
        Some(InitSource::Geometric) => Some(Init::Geometric),
        Some(InitSource::File(path)) => {
            let matched = read_per_image(path, names, "--init")?;
            if matched.matched() == 0 {
                return Err(PosediffError::invalid(
                    path,
                    matched.mismatch("--init", path),
                ));
            }
            if !matched.images_without_record.is_empty()
                || !matched.records_without_image.is_empty()
            {
                warnings.push(Warning::InitMismatch(matched.mismatch("--init", path)));
            }
            let cams: Vec<Option<Camera>> = matched
                .per_image
                .into_iter()
                .map(|r| r.and_then(|r| r.camera))
                .collect();
            if cams.iter().all(Option::is_none) {
                return Err(PosediffError::invalid(
                    path,
                    "--init: none of its cameras is estimated",
                ));
            }
            Some(Init::Given(cams))
        }
    };
    let mut geometric = options.geometric_config(&known);
    let masks = match &options.masks {
        Some(dir) => {
            if network {
                return Err(PosediffError::InvalidArgument(
                    "--masks is not applied with --weights yet (GGS's matching ignores it): \
                     run without --weights, or without --masks"
                        .into(),
                ));
            }
            let (masks, report) = mask_files(dir, files, names)?;
            geometric.masks = masks;
            Some(report)
        }
        None => None,
    };
    if matches!(known, KnownIntrinsics::Unknown) {
        geometric.hints = match inputs.camera_hints() {
            Some(h) => h,
            None => camera_hints(files, names)?,
        };
    }
    if inputs.video.is_some() && geometric.options.pairs.selection == PairSelection::Auto {
        // A video's keyframes overlap their neighbours by construction.
        geometric.options.pairs.selection = geometric.options.video.pairs.clone();
    }
    let needs_matches = !network || options.ggs;
    if let (Some(path), false) = (&options.database, needs_matches) {
        // --no-ggs skips matching: the database would be opened and nothing stored in it.
        return Err(PosediffError::invalid(
            path,
            "--database stores the features and matches GGS uses, and --no-ggs skips them: \
             drop one of the two",
        ));
    }
    if needs_matches {
        geometric.learned = options.load_learned()?;
    }
    let imported = if let Some(path) = &options.database {
        let masks: Vec<(&PathBuf, &PathBuf)> = {
            let mut m: Vec<_> = geometric.masks.iter().collect();
            m.sort();
            m
        };
        // With --weights the database holds GGS's features and matches (its own matching).
        let matching = if network {
            ggs_matching(options)
        } else {
            geometric.options.matching
        };
        let mut settings = serde_json::json!({
            "matching": matching,
            "masks": masks,
        });
        if options.matcher.extractor_weights().is_some() {
            // The learned matcher's image side, keypoints and precision decide its features
            // and matches too: a database made with other ones is refused, not mixed.
            settings["learned"] = serde_json::to_value(geometric.options.learned)?;
        }
        let identity = crate::io::database::StoreIdentity {
            matcher: options.matcher.as_str().to_owned(),
            settings: settings.to_string(),
        };
        let images = files
            .iter()
            .zip(names)
            .enumerate()
            .map(|(i, (path, name))| crate::io::database::StoreImage {
                path: path.clone(),
                name: name.clone(),
                focal: geometric.hints.get(i).map(|h| h.focal).unwrap_or_default(),
                camera: crate::io::database::shared_camera_key(
                    geometric.options.cameras.mode,
                    geometric.hints.get(i),
                ),
            })
            .collect();
        let mut imported = (0, 0);
        let store = if options.map_database {
            geometric.options.densify.when = posediff_pipeline::options::DensifyWhen::Never;
            geometric.options.retry.enabled = false;
            geometric.options.orientation.enabled = false;
            crate::io::database::Database::open_for_mapping(path, images)?
        } else {
            let from_images = images.clone();
            let db = crate::io::database::Database::open(path, &identity, images)?;
            for from in &options.import_from {
                let worker = crate::io::database::Database::open_source(
                    from,
                    &identity,
                    from_images.clone(),
                )?;
                let (i, p) = db.import(&worker, files)?;
                imported = (imported.0 + i, imported.1 + p);
            }
            db
        };
        geometric.store = Some(SharedStore(std::sync::Arc::new(store)));
        imported
    } else {
        (0, 0)
    };
    Ok(Configured {
        known,
        init,
        geometric,
        masks,
        warnings,
        needs_matches,
        imported,
    })
}

/// Estimates the cameras of `inputs` with the checkpoint-free mapper, or with PoseDiffusion
/// when `network` is given, then triangulates and colours the points.
///
/// # Errors
/// Invalid options; a cameras.json (`init`, intrinsics) that names none of the images; every
/// error of the estimation itself.
pub fn run(
    inputs: &Inputs,
    options: &RunOptions,
    network: Option<Network<'_>>,
    progress: &mut dyn Progress,
) -> Result<Run> {
    let Configured {
        known,
        init,
        geometric,
        masks,
        mut warnings,
        needs_matches,
        imported: _,
    } = {
        if let Some(s) = options.shard {
            return Err(PosediffError::InvalidArgument(format!(
                "--shard {s} splits `posediff features` and `posediff match`; an estimation maps \
                 every image: merge the shards' databases with --from instead"
            )));
        }
        configure(inputs, options, network.is_some())?
    };
    let names = &inputs.names;
    let files = &inputs.images.files;
    let (entries, pairs, mut report) = match network {
        None => {
            progress.start("geometry", 0);
            let result = match &init {
                Some(Init::Given(cams)) => {
                    refine_given_cameras_counted(files, cams, &geometric, progress.counter())
                }
                _ => estimate_geometric_counted(files, &geometric, progress.counter()),
            };
            progress.finish();
            let result = result?;
            warnings.extend(result.warnings.iter().cloned());
            let entries: Vec<ImageCamera> = names
                .iter()
                .zip(&result.cameras)
                .zip(&result.sizes)
                .enumerate()
                .map(|(i, ((name, camera), size))| {
                    // The calibrated distortion, as a COLMAP model around each camera.
                    let lens = match (&result.lens, camera) {
                        (Some(lens), Some(c)) => Some(lens.lens_camera(i, &c.intrinsics)?),
                        _ => None,
                    };
                    Ok(ImageCamera {
                        image: name.clone(),
                        size: *size,
                        camera: *camera,
                        lens,
                    })
                })
                .collect::<Result<_>>()?;
            let mut report = RunReport::new(
                files.clone(),
                MethodReport::Geometric {
                    refine: options.refine,
                    report: Box::new(result.report.clone()),
                },
            );
            report.matches_per_pair = pair_counts(&result.pairs);
            report.options = Some(geometric.options.clone());
            (entries, result.pairs, report)
        }
        Some(net) => network_run(
            inputs,
            options,
            net,
            &known,
            &geometric,
            init,
            &mut warnings,
            progress,
        )?,
    };
    for w in &warnings {
        log::warn!("{w}");
    }
    report.init = options.init.as_ref().map(ToString::to_string);
    report.matcher = needs_matches.then(|| options.matcher.as_str());
    report.skipped_images = inputs.skipped.clone();
    report.masks = masks;
    report.video = inputs.video.clone();
    report.warnings = warnings;
    let point_options = options.pipeline.points;
    let (mut reconstruction, points) =
        Reconstruction::triangulate(entries, None, &pairs, &point_options)?;
    // Colours (and the viewer's thumbnails) from one decode of each image.
    let thumbnails = reconstruction.colour_and_thumbnails(files, options.thumbnail_side)?;
    report.points = Some(PointsSummary::new(&points, &point_options));
    Ok(Run {
        reconstruction,
        report,
        inputs: inputs.images.clone(),
        thumbnails: options.thumbnail_side.map(|_| thumbnails),
        pairs,
    })
}

/// GGS's matching: the checkpoint path's own (`EstimateConfig`: hloc's 4096 keypoints), only
/// the detector following `--matcher`.
fn ggs_matching(options: &RunOptions) -> posediff_matching::MatchConfig {
    let mut matching = crate::EstimateConfig::default().matching;
    matching.features.detector = options.matcher.detector();
    matching
}

/// The PoseDiffusion path: cameras, the matches of GGS, the report.
#[allow(clippy::too_many_arguments)] // the pieces of one run, each used once
fn network_run(
    inputs: &Inputs,
    options: &RunOptions,
    net: Network<'_>,
    known: &KnownIntrinsics,
    geometric: &GeometricConfig,
    init: Option<Init>,
    warnings: &mut Vec<Warning>,
    progress: &mut dyn Progress,
) -> Result<(Vec<ImageCamera>, Vec<PairMatches>, RunReport)> {
    let names = &inputs.names;
    let files = &inputs.images.files;
    let init_cameras: Option<Vec<Camera>> = match init {
        None => None,
        Some(source) => {
            let given = match source {
                Init::Geometric => {
                    progress.start("geometry", 0);
                    // The database holds GGS's features: the start is matched apart.
                    let apart = GeometricConfig {
                        store: None,
                        ..geometric.clone()
                    };
                    let g = estimate_geometric_counted(files, &apart, progress.counter());
                    progress.finish();
                    let g = g?;
                    warnings.extend(g.warnings);
                    g.cameras
                }
                Init::Given(cams) => cams,
            };
            let Some(fallback) = given.iter().flatten().next().copied() else {
                return Err(PosediffError::InvalidArgument(
                    "the initial estimate has no camera".into(),
                ));
            };
            let missing: Vec<&str> = names
                .iter()
                .zip(&given)
                .filter(|(_, c)| c.is_none())
                .map(|(n, _)| n.as_str())
                .collect();
            if !missing.is_empty() {
                warnings.push(Warning::NoInitialCamera(
                    missing.iter().map(|m| (*m).to_owned()).collect(),
                ));
            }
            Some(given.iter().map(|c| c.unwrap_or(fallback)).collect())
        }
    };
    let mut config = crate::EstimateConfig {
        seed: options.seed,
        samples: options.samples,
        ggs: options.ggs,
        intrinsics: known.clone(),
        ..net.estimator.config().clone()
    };
    config.matching = ggs_matching(options);
    config.learned = geometric.learned.clone();
    // --database: GGS's features and matches read from and written to it.
    let stored = (geometric.store.is_some() && options.ggs).then(|| GeometricConfig {
        options: PipelineOptions {
            matching: config.matching,
            ..geometric.options.clone()
        },
        ..geometric.clone()
    });
    let matcher = stored.as_ref().map(GeometricConfig::correspondences);
    let estimator = net.estimator.with_config(config);
    let estimate = estimator.estimate(
        EstimateInput {
            images: files,
            root: inputs.images.folder.as_deref(),
            init: init_cameras.as_deref().map(|c| (c, options.start_step)),
            lens_from: Some(geometric),
            matcher: matcher.as_deref(),
        },
        progress,
    )?;
    let mut first = estimate.samples[0].clone();
    let mut bundle = None;
    if options.refine == RefineMode::Bundle {
        if estimate.pairs.iter().all(|p| p.is_empty()) {
            return Err(PosediffError::InvalidArgument(
                "--refine bundle needs verified matches (none were found, or --no-ggs was given)"
                    .into(),
            ));
        }
        let mut cams: Vec<Camera> = first.iter().map(|c| c.camera).collect();
        let mapper = &options.pipeline.mapper;
        let report = bundle_refine_cameras(
            &mut cams,
            &estimate.pairs,
            !matches!(known, KnownIntrinsics::Unknown),
            (
                &mapper.sampson.unwrap_or_default(),
                &mapper.bundle.unwrap_or_default(),
            ),
        )?;
        for (named, c) in first.iter_mut().zip(cams) {
            named.camera = c;
        }
        bundle = Some(report);
    }
    let entries: Vec<ImageCamera> = first
        .iter()
        .enumerate()
        .map(|(i, c)| {
            // The measured distortion, as a COLMAP model around each camera.
            let lens = estimate
                .lens
                .as_ref()
                .map(|lens| lens.lens_camera(i, &c.camera.intrinsics))
                .transpose()?;
            Ok(ImageCamera {
                image: c.image.clone(),
                size: c.camera.image_size,
                camera: Some(c.camera),
                lens,
            })
        })
        .collect::<Result<_>>()?;
    warnings.extend(estimate.warnings.iter().cloned());
    if estimate.pairs.iter().all(|p| p.is_empty()) {
        warnings.push(Warning::NoVerifiedMatches);
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
    let mut report = RunReport::new(
        files.clone(),
        MethodReport::Posediffusion(Box::new(NetworkReport {
            weights: net.weights.to_owned(),
            start_step: init_cameras.as_ref().map(|_| options.start_step),
            seed: options.seed,
            samples: options.samples,
            ggs: options.ggs,
            distortion: estimate.distortion.clone().map(|mut d| {
                // Each camera's k at its image's focal, as the checkpoint-free path reports.
                if let Some(lens) = &estimate.lens {
                    d.k1 = first
                        .iter()
                        .enumerate()
                        .map(|(i, c)| Some(lens.coefficients(i, c.camera.intrinsics.fx())[0]))
                        .collect();
                }
                d
            }),
            bundle,
            device: net.device,
            seconds: NetworkSeconds {
                load_weights: net.load_seconds,
                load_images: t.load,
                matching: t.matching,
                features: t.features,
                sampling: t.sampling,
                ggs: t.ggs,
            },
            sample_spread,
        })),
    );
    report.options = Some(geometric.options.clone());
    report.matches_per_pair = estimate
        .matches_per_pair
        .iter()
        .map(|&(first, second, matches)| PairCount {
            first,
            second,
            matches,
        })
        .collect();
    Ok((entries, estimate.pairs, report))
}

fn pair_counts(pairs: &[PairMatches]) -> Vec<PairCount> {
    pairs
        .iter()
        .map(|p| PairCount {
            first: p.first,
            second: p.second,
            matches: p.len(),
        })
        .collect()
}

/// Each image's folder and EXIF camera, for `cameras.mode`'s groups and focal priors.
///
/// # Errors
/// An image that cannot be opened.
pub fn camera_hints(files: &[PathBuf], names: &[String]) -> Result<Vec<CameraHint>> {
    use rayon::prelude::*;
    files
        .par_iter()
        .zip(names)
        .map(|(file, name)| {
            let folder = Path::new(name)
                .parent()
                .map(|p| p.to_string_lossy().into_owned())
                .unwrap_or_default();
            let exif = read_exif(file)?;
            Ok(ExifCamera::hint(exif.as_ref(), folder))
        })
        .collect()
}

/// A cameras.json's entries matched to the images by name; their cameras must be pinhole.
fn read_per_image(path: &Path, names: &[String], what: &str) -> Result<Matched<ImageCamera>> {
    let given = read_cameras_json_partial(path).map_err(|e| PosediffError::Context {
        what: format!("reading {what} {}", path.display()),
        source: Box::new(e),
    })?;
    let distorted = crate::io::export::distorted_images(path)?;
    if let Some(first) = distorted.first() {
        return Err(PosediffError::invalid(
            path,
            format!(
                "{what}: {} camera(s) with lens distortion ({first}, …); {what} takes pinhole \
                 cameras: undistort the images first (COLMAP's image_undistorter) and give \
                 their PINHOLE cameras",
                distorted.len()
            ),
        ));
    }
    match_by_name(
        names,
        given.into_iter().map(|g| (g.image.clone(), g)).collect(),
    )
    .map_err(|e| PosediffError::invalid(path, format!("{what}: {e}")))
}

pub use crate::progress::WORK_STARTS;

/// Loads a checkpoint, timing it (for [`Network::load_seconds`]).
///
/// # Errors
/// As [`Estimator::load`].
pub fn load_estimator(weights: &Path, device: candle_core::Device) -> Result<(Estimator, f64)> {
    if !weights.is_file() {
        return Err(PosediffError::NotFound(weights.to_owned()));
    }
    let clock = Instant::now();
    log::info!("loading the checkpoint {}", weights.display());
    let estimator = Estimator::load(weights, device, crate::EstimateConfig::default())?;
    Ok((estimator, clock.elapsed().as_secs_f64()))
}
