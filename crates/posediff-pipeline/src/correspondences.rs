//! Which matcher finds the correspondences, for both paths (GGS and the checkpoint-free
//! mapper): OpenCV's SIFT or ORB with mutual nearest neighbours (`posediff-matching`), or ALIKED
//! or DISK keypoints matched by LightGlue (`posediff-learned`). Either way the keypoints are in pixels
//! of the original image and every pair goes through the same MAGSAC verification and
//! minimum of verified matches ([`MatchConfig::verification`], [`MatchConfig::min_verified`]).
//!
//! The learned matcher follows the reference pipeline: each image resized (OpenCV INTER_AREA) to
//! a long side of [`LEARNED_IMAGE_SIDE`], ALIKED's or DISK's top [`LEARNED_MAX_KEYPOINTS`]
//! (detection threshold 0, so weak texture still gets keypoints), the LightGlue trained on that
//! extractor's descriptors with its early exit and point pruning per selected pair, keypoints
//! mapped back to the original pixels.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use candle_core::Device;
use opencv::core::{Mat, Size};
use opencv::prelude::*;
use posediff_geometry::{ImageSize, PairMatches};
use posediff_learned::{
    Aliked, AlikedConfig, Disk, DiskConfig, LightGlue, LightGlueConfig, MatcherInput,
    PreparedImage, RgbImage, WeightSet,
};
use posediff_matching::features::to_original_pixels;
use posediff_matching::{Descriptors, ImageFeatures, MatchConfig};
use rayon::prelude::*;

use crate::error::{PosediffError, Result};

pub use crate::progress::{NoCounter, StepCounter};

pub use crate::options::{LEARNED_IMAGE_SIDE, LEARNED_MAX_KEYPOINTS};

/// The matcher of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MatcherChoice {
    /// OpenCV SIFT, mutual nearest neighbours with Lowe's ratio.
    #[default]
    Sift,
    /// OpenCV ORB, Hamming mutual nearest neighbours.
    Orb,
    /// ALIKED n16 keypoints, LightGlue matches.
    AlikedLightGlue,
    /// ALIKED n16rot keypoints (trained with in-plane rotations), LightGlue matches (the same
    /// LightGlue weights: both ALIKED models give 128-d descriptors).
    AlikedN16RotLightGlue,
    /// DISK keypoints (the released `depth` model), matched by the LightGlue trained on DISK.
    DiskLightGlue,
}

impl MatcherChoice {
    /// The name on the command line and in run.json.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Sift => "sift",
            Self::Orb => "orb",
            Self::AlikedLightGlue => "aliked-lightglue",
            Self::AlikedN16RotLightGlue => "aliked-n16rot-lightglue",
            Self::DiskLightGlue => "disk-lightglue",
        }
    }

    /// The extractor weights of a learned choice (`None` for the OpenCV ones).
    pub fn extractor_weights(self) -> Option<WeightSet> {
        match self {
            Self::AlikedLightGlue => Some(WeightSet::AlikedN16),
            Self::AlikedN16RotLightGlue => Some(WeightSet::AlikedN16Rot),
            Self::DiskLightGlue => Some(WeightSet::Disk),
            Self::Sift | Self::Orb => None,
        }
    }

    /// The OpenCV detector of this choice (SIFT for the learned one, unused there).
    pub fn detector(self) -> posediff_matching::Detector {
        match self {
            Self::Orb => posediff_matching::Detector::Orb,
            _ => posediff_matching::Detector::Sift,
        }
    }
}

impl std::fmt::Display for MatcherChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for MatcherChoice {
    type Err = PosediffError;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "sift" => Ok(Self::Sift),
            "orb" => Ok(Self::Orb),
            "aliked-lightglue" => Ok(Self::AlikedLightGlue),
            "aliked-n16rot-lightglue" => Ok(Self::AlikedN16RotLightGlue),
            "disk-lightglue" => Ok(Self::DiskLightGlue),
            other => Err(PosediffError::InvalidArgument(format!(
                "matcher must be sift, orb, aliked-lightglue, aliked-n16rot-lightglue or \
                 disk-lightglue, got {other:?}"
            ))),
        }
    }
}

/// A learned keypoint extractor.
#[derive(Debug)]
enum Extractor {
    Aliked(Box<Aliked>),
    Disk(Disk),
}

/// ALIKED or DISK + LightGlue with their released weights, loaded once.
#[derive(Debug)]
pub struct LearnedMatcher {
    extractor: Extractor,
    lightglue: LightGlue,
    /// ALIKED's detection settings.
    pub aliked_config: AlikedConfig,
    /// DISK's detection settings.
    pub disk_config: DiskConfig,
    /// Matching settings.
    pub lightglue_config: LightGlueConfig,
    /// Long side the images are resized to.
    pub image_side: u32,
}

/// The LightGlue trained on the descriptors of extractor `extractor`.
fn lightglue_for(extractor: WeightSet) -> WeightSet {
    match extractor {
        WeightSet::Disk => WeightSet::DiskLightGlue,
        _ => WeightSet::AlikedLightGlue,
    }
}

/// The weight files of the learned matcher with extractor weights `extractor` (an ALIKED set
/// or DISK) in `dir` and its LightGlue, checked to exist (before any image is read).
///
/// # Errors
/// A missing file, with the command that fetches it.
pub fn learned_weight_files(dir: &Path, extractor: WeightSet) -> Result<(PathBuf, PathBuf)> {
    Ok((
        extractor.locate(dir)?,
        lightglue_for(extractor).locate(dir)?,
    ))
}

impl LearnedMatcher {
    /// Takes the options tree's `learned` settings: the long side the images are resized to,
    /// the keypoints per image (ALIKED's and DISK's) and LightGlue's precision.
    pub fn configure(&mut self, options: &crate::options::LearnedOptions) {
        self.image_side = options.image_side;
        self.aliked_config.max_keypoints = options.max_keypoints;
        self.disk_config.max_keypoints = options.max_keypoints;
        self.set_precision(options.precision.matmul());
    }

    /// Computes LightGlue's large products at `precision` from now on
    /// ([`crate::options::LearnedOptions::precision`]; F32 when loaded).
    pub fn set_precision(&mut self, precision: posediff_diffusion::MatmulPrecision) {
        self.lightglue.set_precision(precision);
    }

    /// The precision of LightGlue's large products.
    pub fn precision(&self) -> posediff_diffusion::MatmulPrecision {
        self.lightglue.precision()
    }

    /// Loads ALIKED n16 and LightGlue from `dir` (see [`posediff_learned::weights`]) onto the
    /// CPU.
    ///
    /// # Errors
    /// Missing or malformed weight files.
    pub fn load(dir: &Path) -> Result<Self> {
        Self::load_with(dir, WeightSet::AlikedN16)
    }

    /// As [`Self::load`] with the extractor weights `extractor` (`AlikedN16`, `AlikedN16Rot` or
    /// `Disk`) and the LightGlue trained on its descriptors.
    ///
    /// # Errors
    /// Missing or malformed weight files; a weight set that is not an extractor.
    pub fn load_with(dir: &Path, extractor: WeightSet) -> Result<Self> {
        let (file, lightglue) = learned_weight_files(dir, extractor)?;
        let extractor = match extractor {
            WeightSet::AlikedN16 | WeightSet::AlikedN16Rot => {
                Extractor::Aliked(Box::new(Aliked::load(&file, &Device::Cpu)?))
            }
            WeightSet::Disk => Extractor::Disk(Disk::load(&file)?),
            other => {
                return Err(PosediffError::InvalidArgument(format!(
                    "{} is a matcher's weights, not a keypoint extractor's",
                    other.stem()
                )));
            }
        };
        let lightglue = LightGlue::load(&lightglue, &Device::Cpu)?;
        Ok(Self {
            extractor,
            lightglue,
            aliked_config: AlikedConfig {
                max_keypoints: LEARNED_MAX_KEYPOINTS,
                ..AlikedConfig::default()
            },
            disk_config: DiskConfig {
                max_keypoints: LEARNED_MAX_KEYPOINTS,
                ..DiskConfig::default()
            },
            lightglue_config: LightGlueConfig::default(),
            image_side: LEARNED_IMAGE_SIDE,
        })
    }

    /// The LightGlue network itself (for probes that need its per-pair record).
    pub fn lightglue(&self) -> &LightGlue {
        &self.lightglue
    }

    /// The extractor's keypoints and descriptors of one image, in its original pixels.
    ///
    /// # Errors
    /// Unreadable images (named), network errors.
    pub fn extract(&self, path: &Path) -> Result<ImageFeatures> {
        self.extract_turned(path, false)
    }

    /// [`Self::extract`] on the image turned by 180° when `half_turn`: the keypoints are still
    /// given in the original image's pixels (`x ↦ w − 1 − x`, `y ↦ h − 1 − y` from the turned
    /// image's), the descriptors are those of the turned image. ALIKED and DISK are not
    /// invariant to in-plane rotation, so an image upside down relative to the others matches
    /// them only this way. The features say so (`half_turned`), and [`Self::prepare`] gives
    /// LightGlue the keypoints where they lie in the turned image.
    ///
    /// # Errors
    /// As [`Self::extract`].
    pub fn extract_turned(&self, path: &Path, half_turn: bool) -> Result<ImageFeatures> {
        let decoded =
            posediff_matching::image_check::decode(path, opencv::imgcodecs::IMREAD_COLOR)?;
        let bgr = if half_turn {
            let mut turned = Mat::default();
            opencv::core::rotate(&decoded, &mut turned, opencv::core::ROTATE_180)?;
            turned
        } else {
            decoded
        };
        let (w, h) = (bgr.cols(), bgr.rows());
        let image_size = ImageSize::new(w as u32, h as u32)?;
        let s = f64::from(self.image_side) / f64::from(w.max(h));
        let (nw, nh) = (
            (f64::from(w) * s).round() as i32,
            (f64::from(h) * s).round() as i32,
        );
        let mut resized = Mat::default();
        opencv::imgproc::resize(
            &bgr,
            &mut resized,
            Size::new(nw, nh),
            0.0,
            0.0,
            opencv::imgproc::INTER_AREA,
        )?;
        let mut rgb = Mat::default();
        opencv::imgproc::cvt_color_def(&resized, &mut rgb, opencv::imgproc::COLOR_BGR2RGB)?;
        let rgb = if rgb.is_continuous() {
            rgb
        } else {
            rgb.try_clone()?
        };
        let image = RgbImage {
            width: nw as usize,
            height: nh as usize,
            data: rgb.data_bytes()?,
        };
        let (name, kp) = match &self.extractor {
            Extractor::Aliked(net) => ("ALIKED", net.extract(&image, &self.aliked_config)),
            Extractor::Disk(net) => ("DISK", net.extract(&image, &self.disk_config)),
        };
        let kp = kp.map_err(|e| PosediffError::Context {
            what: format!("{name} on {}", path.display()),
            source: Box::new(e.into()),
        })?;
        let scale = [f64::from(nw) / f64::from(w), f64::from(nh) / f64::from(h)];
        Ok(ImageFeatures {
            image_size,
            keypoints: kp
                .positions
                .iter()
                .map(|p| {
                    let k = to_original_pixels([f64::from(p[0]), f64::from(p[1])], scale);
                    if half_turn {
                        half_turned(k, image_size)
                    } else {
                        k
                    }
                })
                .collect(),
            descriptors: Descriptors::Float {
                data: kp.descriptors,
                dim: kp.dim,
            },
            half_turned: half_turn,
        })
    }

    /// [`Self::extract_turned`] on every image of `paths`, in order, a few at a time: the
    /// network's own parallelism uses two cores at 1.3×, two images side by side at about
    /// 1.8×; the bound keeps the memory of a many-core machine to a few images' feature maps
    /// (about 0.2 GB each at 1024 px). Each image is a step on `counter`.
    ///
    /// # Errors
    /// As [`Self::extract`].
    pub fn extract_many(
        &self,
        paths: &[&Path],
        half_turn: bool,
        counter: &dyn StepCounter,
    ) -> Result<Vec<ImageFeatures>> {
        let at_once = rayon::current_num_threads().clamp(1, EXTRACT_AT_ONCE);
        let mut out = Vec::with_capacity(paths.len());
        for chunk in paths.chunks(at_once) {
            out.extend(
                chunk
                    .par_iter()
                    .map(|p| {
                        let f = self.extract_turned(p, half_turn);
                        counter.step();
                        f
                    })
                    .collect::<Result<Vec<_>>>()?,
            );
        }
        Ok(out)
    }

    /// What LightGlue computes from one image alone ([`LightGlue::prepare_image`]), so that an
    /// image matched with several others is prepared once. For features of a turned image
    /// ([`Self::extract_turned`]) LightGlue sees the keypoints where they lie in the turned
    /// image its descriptors come from.
    ///
    /// # Errors
    /// Features that are not the extractor's; network errors.
    pub fn prepare(&self, f: &ImageFeatures) -> Result<PreparedImage> {
        let data = match &f.descriptors {
            Descriptors::Float { data, dim } if *dim == self.lightglue.input_dim() => data,
            _ => {
                return Err(PosediffError::InvalidArgument(
                    "LightGlue needs the learned extractor's 128-d float descriptors".into(),
                ));
            }
        };
        let positions: Vec<[f32; 2]> = f
            .keypoints
            .iter()
            .map(|&k| {
                let k = if f.half_turned {
                    half_turned(k, f.image_size)
                } else {
                    k
                };
                [k[0] as f32, k[1] as f32]
            })
            .collect();
        Ok(self.lightglue.prepare_image(&MatcherInput {
            positions: &positions,
            descriptors: data,
            image_size: [f.image_size.width() as f32, f.image_size.height() as f32],
        })?)
    }

    /// LightGlue on one pair, then the verification of `config`.
    ///
    /// # Errors
    /// Features that are not the extractor's; OpenCV errors in the verification.
    pub fn match_pair(
        &self,
        a: &ImageFeatures,
        b: &ImageFeatures,
        first: usize,
        second: usize,
        config: &MatchConfig,
    ) -> Result<PairMatches> {
        let (pa, pb) = (self.prepare(a)?, self.prepare(b)?);
        self.match_prepared((a, &pa), (b, &pb), first, second, config)
    }

    /// [`Self::match_pair`] on images already [prepared](Self::prepare).
    ///
    /// # Errors
    /// OpenCV errors in the verification, network errors.
    pub fn match_prepared(
        &self,
        a: (&ImageFeatures, &PreparedImage),
        b: (&ImageFeatures, &PreparedImage),
        first: usize,
        second: usize,
        config: &MatchConfig,
    ) -> Result<PairMatches> {
        let raw = self.match_prepared_raw(a, b, first, second)?;
        Ok(posediff_matching::verify(raw, config)?)
    }

    /// LightGlue's matches of two prepared images before any verification.
    ///
    /// # Errors
    /// Prepared images of other keypoint counts than the features; network errors.
    pub fn match_prepared_raw(
        &self,
        (a, pa): (&ImageFeatures, &PreparedImage),
        (b, pb): (&ImageFeatures, &PreparedImage),
        first: usize,
        second: usize,
    ) -> Result<PairMatches> {
        if pa.len() != a.keypoints.len() || pb.len() != b.keypoints.len() {
            return Err(PosediffError::InvalidArgument(format!(
                "pair ({first}, {second}): prepared images of {} and {} keypoints for features \
                 of {} and {}",
                pa.len(),
                pb.len(),
                a.keypoints.len(),
                b.keypoints.len()
            )));
        }
        let m = self
            .lightglue
            .match_prepared(pa, pb, &self.lightglue_config)?;
        Ok(posediff_matching::raw_matches(
            a, b, first, second, &m.matches,
        ))
    }
}

/// A pixel of an image of `size` after a turn by 180° about its centre (its own inverse).
fn half_turned(k: [f64; 2], size: ImageSize) -> [f64; 2] {
    [
        f64::from(size.width()) - 1.0 - k[0],
        f64::from(size.height()) - 1.0 - k[1],
    ]
}

/// A loaded learned matcher shared by the configurations that use it (equal when it is the same
/// load).
#[derive(Debug, Clone)]
pub struct SharedLearned(pub Arc<LearnedMatcher>);

impl PartialEq for SharedLearned {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// Features of images and the verified matches of requested pairs: what every pass of the
/// pipeline asks of a matcher (the first matching, the orientation check, the second pass, the
/// turned retry). OpenCV's SIFT/ORB ([`OpenCvCorrespondences`]) and a learned extractor with
/// its LightGlue ([`LearnedCorrespondences`]) implement it; the mapper never sees either.
pub trait Correspondences: Sync {
    /// The features of every image, in order; each image a step of stage "features" on
    /// `counter` where the matcher counts them. (The controller refuses fewer than two images
    /// before; a store extracts what it lacks, which may be one image.)
    ///
    /// # Errors
    /// Unreadable images (named), extraction errors.
    fn extract(&self, images: &[PathBuf], counter: &dyn StepCounter) -> Result<Vec<ImageFeatures>>;

    /// The verified matches of `pairs` (indices into `features`), each pair a step of stage
    /// `name` on `counter` where the matcher counts them; pairs without enough verified matches
    /// are left out.
    ///
    /// # Errors
    /// Invalid pairs, matching errors.
    fn match_pairs(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        stage: (&dyn StepCounter, &str),
    ) -> Result<Vec<PairMatches>>;

    /// [`Self::match_pairs`] with each pair's matches before verification (`(raw, verified)`,
    /// for COLMAP's `matches` table beside its `two_view_geometries`; `None` where the matcher
    /// does not keep them: the verified ones are stored in both then). Pairs are not left out.
    ///
    /// # Errors
    /// As [`Self::match_pairs`].
    fn match_pairs_with_raw(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        stage: (&dyn StepCounter, &str),
    ) -> Result<Vec<(Option<PairMatches>, PairMatches)>> {
        Ok(self
            .match_pairs(features, pairs, stage)?
            .into_iter()
            .map(|m| (None, m))
            .collect())
    }

    /// Whether the matcher's features change with the image's in-plane orientation (learned
    /// extractors: ALIKED and DISK are not rotation-invariant), so that images upside down
    /// relative to the others need matching turned.
    fn depends_on_orientation(&self) -> bool;

    /// The features of `images` turned by 180° (keypoints in the image's own pixels,
    /// [`ImageFeatures::half_turned`] set), or `None` for a matcher that does not depend on the
    /// image's orientation: the orientation check and the turned retry run only where this
    /// gives features.
    ///
    /// # Errors
    /// As [`Self::extract`].
    fn extract_turned(
        &self,
        images: &[&Path],
        counter: &dyn StepCounter,
    ) -> Result<Option<Vec<ImageFeatures>>>;
}

/// The log line an extraction starts with (the bad-input tests check that no such line precedes
/// an error that needs no computation).
fn log_extraction(images: usize) {
    log::info!(
        "{}extracting features of {images} images",
        crate::progress::WORK_STARTS
    );
}

/// OpenCV's SIFT or ORB, mutual nearest neighbours and MAGSAC (`posediff-matching`).
#[derive(Debug, Clone, Copy)]
pub struct OpenCvCorrespondences<'a>(pub &'a MatchConfig);

impl Correspondences for OpenCvCorrespondences<'_> {
    fn extract(&self, images: &[PathBuf], counter: &dyn StepCounter) -> Result<Vec<ImageFeatures>> {
        log_extraction(images.len());
        counter.stage("features", 0);
        Ok(images
            .par_iter()
            .map(|p| posediff_matching::features::extract(p, &self.0.features))
            .collect::<std::result::Result<Vec<_>, _>>()?)
    }

    fn match_pairs(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        (counter, name): (&dyn StepCounter, &str),
    ) -> Result<Vec<PairMatches>> {
        counter.stage(name, 0);
        Ok(posediff_matching::match_pairs(features, pairs, self.0)?)
    }

    fn match_pairs_with_raw(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        (counter, name): (&dyn StepCounter, &str),
    ) -> Result<Vec<(Option<PairMatches>, PairMatches)>> {
        counter.stage(name, 0);
        Ok(
            posediff_matching::match_pairs_with_raw(features, pairs, self.0)?
                .into_iter()
                .map(|(raw, verified)| (Some(raw), verified))
                .collect(),
        )
    }

    /// SIFT and ORB describe each keypoint in its own orientation.
    fn depends_on_orientation(&self) -> bool {
        false
    }

    /// SIFT and ORB describe each keypoint in its own orientation: nothing to turn.
    fn extract_turned(
        &self,
        _images: &[&Path],
        _counter: &dyn StepCounter,
    ) -> Result<Option<Vec<ImageFeatures>>> {
        Ok(None)
    }
}

/// ALIKED or DISK keypoints matched by their LightGlue (`posediff-learned`), verified by the
/// same MAGSAC and minimum as OpenCV's matches (`config`).
#[derive(Debug, Clone, Copy)]
pub struct LearnedCorrespondences<'a> {
    /// The networks.
    pub learned: &'a SharedLearned,
    /// The verification and minimum of verified matches.
    pub config: &'a MatchConfig,
}

impl Correspondences for LearnedCorrespondences<'_> {
    fn extract(&self, images: &[PathBuf], counter: &dyn StepCounter) -> Result<Vec<ImageFeatures>> {
        log_extraction(images.len());
        counter.stage("features", images.len() as u64);
        let paths: Vec<&Path> = images.iter().map(PathBuf::as_path).collect();
        self.learned.0.extract_many(&paths, false, counter)
    }

    fn match_pairs(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        stage: (&dyn StepCounter, &str),
    ) -> Result<Vec<PairMatches>> {
        Ok(
            learned_match_pairs(&self.learned.0, features, pairs, self.config, stage, false)?
                .into_iter()
                .map(|(_, verified)| verified)
                .collect(),
        )
    }

    fn match_pairs_with_raw(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        stage: (&dyn StepCounter, &str),
    ) -> Result<Vec<(Option<PairMatches>, PairMatches)>> {
        learned_match_pairs(&self.learned.0, features, pairs, self.config, stage, true)
    }

    fn depends_on_orientation(&self) -> bool {
        true
    }

    fn extract_turned(
        &self,
        images: &[&Path],
        counter: &dyn StepCounter,
    ) -> Result<Option<Vec<ImageFeatures>>> {
        self.learned.0.extract_many(images, true, counter).map(Some)
    }
}

/// A change made to one image's features (found by the image's path) after every extraction.
pub type AdjustFeatures<'a> = dyn Fn(&Path, &mut ImageFeatures) -> Result<()> + Sync + 'a;

/// A matcher whose features, upright and turned, pass through `adjust` after every extraction
/// (masks: [`posediff_matching::mask::apply_mask`]; the lens's undistortion); matching itself
/// is the inner matcher's.
pub struct Adjusted<'a> {
    /// The matcher.
    pub inner: Box<dyn Correspondences + 'a>,
    /// The change, per image.
    pub adjust: Box<AdjustFeatures<'a>>,
}

impl Adjusted<'_> {
    fn apply(&self, paths: Vec<&Path>, features: &mut [ImageFeatures]) -> Result<()> {
        use rayon::prelude::*;
        features
            .par_iter_mut()
            .zip(paths)
            .try_for_each(|(f, path)| (self.adjust)(path, f))
    }
}

impl Correspondences for Adjusted<'_> {
    fn extract(&self, images: &[PathBuf], counter: &dyn StepCounter) -> Result<Vec<ImageFeatures>> {
        let mut features = self.inner.extract(images, counter)?;
        self.apply(images.iter().map(PathBuf::as_path).collect(), &mut features)?;
        Ok(features)
    }

    fn match_pairs(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        stage: (&dyn StepCounter, &str),
    ) -> Result<Vec<PairMatches>> {
        self.inner.match_pairs(features, pairs, stage)
    }

    fn match_pairs_with_raw(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        stage: (&dyn StepCounter, &str),
    ) -> Result<Vec<(Option<PairMatches>, PairMatches)>> {
        self.inner.match_pairs_with_raw(features, pairs, stage)
    }

    fn depends_on_orientation(&self) -> bool {
        self.inner.depends_on_orientation()
    }

    fn extract_turned(
        &self,
        images: &[&Path],
        counter: &dyn StepCounter,
    ) -> Result<Option<Vec<ImageFeatures>>> {
        let Some(mut features) = self.inner.extract_turned(images, counter)? else {
            return Ok(None);
        };
        // Turned features keep their keypoints in the image's own pixels.
        self.apply(images.to_vec(), &mut features)?;
        Ok(Some(features))
    }
}

/// A borrowed matcher is a matcher (to wrap one without owning it).
impl<T: Correspondences + ?Sized> Correspondences for &T {
    fn extract(&self, images: &[PathBuf], counter: &dyn StepCounter) -> Result<Vec<ImageFeatures>> {
        (**self).extract(images, counter)
    }

    fn match_pairs(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        stage: (&dyn StepCounter, &str),
    ) -> Result<Vec<PairMatches>> {
        (**self).match_pairs(features, pairs, stage)
    }

    fn match_pairs_with_raw(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        stage: (&dyn StepCounter, &str),
    ) -> Result<Vec<(Option<PairMatches>, PairMatches)>> {
        (**self).match_pairs_with_raw(features, pairs, stage)
    }

    fn depends_on_orientation(&self) -> bool {
        (**self).depends_on_orientation()
    }

    fn extract_turned(
        &self,
        images: &[&Path],
        counter: &dyn StepCounter,
    ) -> Result<Option<Vec<ImageFeatures>>> {
        (**self).extract_turned(images, counter)
    }
}

/// The matcher the options ask for: `learned` when given, else OpenCV's with `config`.
pub fn correspondences<'a>(
    config: &'a MatchConfig,
    learned: Option<&'a SharedLearned>,
) -> Box<dyn Correspondences + 'a> {
    match learned {
        Some(learned) => Box::new(LearnedCorrespondences { learned, config }),
        None => Box::new(OpenCvCorrespondences(config)),
    }
}

/// Features of every image with the configured matcher (`learned` when given, else OpenCV).
///
/// # Errors
/// Fewer than two images, unreadable images (named), extraction errors.
pub fn extract_all(
    images: &[PathBuf],
    config: &MatchConfig,
    learned: Option<&SharedLearned>,
) -> Result<Vec<ImageFeatures>> {
    extract_all_counted(images, config, learned, &NoCounter)
}

/// [`extract_all`], counting the learned extractor's images on `counter` (stage "features").
///
/// # Errors
/// As [`extract_all`].
pub fn extract_all_counted(
    images: &[PathBuf],
    config: &MatchConfig,
    learned: Option<&SharedLearned>,
    counter: &dyn StepCounter,
) -> Result<Vec<ImageFeatures>> {
    if images.len() < 2 {
        return Err(PosediffError::TooFewImages {
            needed: 2,
            got: images.len(),
        });
    }
    correspondences(config, learned).extract(images, counter)
}

/// Matches `pairs` with the configured matcher.
///
/// # Errors
/// Invalid pairs, matching errors.
pub fn match_pairs(
    features: &[ImageFeatures],
    pairs: &[(usize, usize)],
    config: &MatchConfig,
    learned: Option<&SharedLearned>,
) -> Result<Vec<PairMatches>> {
    match_pairs_counted(features, pairs, config, learned, (&NoCounter, "matching"))
}

/// [`match_pairs`], counting the learned matcher's pairs on `counter` as stage `name`.
///
/// # Errors
/// As [`match_pairs`].
pub fn match_pairs_counted(
    features: &[ImageFeatures],
    pairs: &[(usize, usize)],
    config: &MatchConfig,
    learned: Option<&SharedLearned>,
    stage: (&dyn StepCounter, &str),
) -> Result<Vec<PairMatches>> {
    correspondences(config, learned).match_pairs(features, pairs, stage)
}

/// LightGlue on `pairs`, each image prepared once per window of pairs ([`prepared_windows`]).
/// Each pair's verified matches, with those before verification when `keep_raw`.
#[allow(clippy::type_complexity)]
fn learned_match_pairs(
    l: &LearnedMatcher,
    features: &[ImageFeatures],
    pairs: &[(usize, usize)],
    config: &MatchConfig,
    (counter, name): (&dyn StepCounter, &str),
    keep_raw: bool,
) -> Result<Vec<(Option<PairMatches>, PairMatches)>> {
    counter.stage(name, pairs.len() as u64);
    posediff_matching::check_pairs(features.len(), pairs)?;
    let mut out: Vec<Option<(Option<PairMatches>, PairMatches)>> = vec![None; pairs.len()];
    for window in prepared_windows(pairs, PREPARED_IMAGES) {
        // Each image of the window once, then its pairs.
        let mut images: Vec<usize> = window
            .iter()
            .flat_map(|&k| [pairs[k].0, pairs[k].1])
            .collect();
        images.sort_unstable();
        images.dedup();
        let prepared: Vec<PreparedImage> = images
            .par_iter()
            .map(|&i| l.prepare(&features[i]))
            .collect::<Result<_>>()?;
        // By the sorted image list: no slot per image of the whole set in every window.
        let of = |i: usize| -> Result<&PreparedImage> {
            images
                .binary_search(&i)
                .ok()
                .and_then(|k| prepared.get(k))
                .ok_or_else(|| {
                    PosediffError::InvalidArgument(format!("image {i} was not prepared"))
                })
        };
        let matched: Vec<(Option<PairMatches>, PairMatches)> = window
            .par_iter()
            .map(|&k| {
                let (i, j) = pairs[k];
                let raw =
                    l.match_prepared_raw((&features[i], of(i)?), (&features[j], of(j)?), i, j);
                counter.step();
                let raw = raw?;
                let kept = keep_raw.then(|| raw.clone());
                Ok((kept, posediff_matching::verify(raw, config)?))
            })
            .collect::<Result<_>>()?;
        for (&k, m) in window.iter().zip(matched) {
            out[k] = Some(m);
        }
    }
    Ok(out.into_iter().flatten().collect())
}

/// Most images the learned extractor works on at once ([`extract_all`]).
const EXTRACT_AT_ONCE: usize = 4;

/// Most images whose LightGlue preparation is held at once in [`match_pairs`] (about 3 MiB each
/// at 2048 keypoints): the memory stays bounded however many images a run has.
const PREPARED_IMAGES: usize = 24;

/// The pairs (indices into `pairs`) in windows that touch at most `max_images` images each, in
/// the order of their images (`(min, max)` ascending), so that an image's pairs mostly share a
/// window and it is prepared once. Every index appears exactly once.
fn prepared_windows(pairs: &[(usize, usize)], max_images: usize) -> Vec<Vec<usize>> {
    let key = |k: usize| {
        let (i, j) = pairs[k];
        (i.min(j), i.max(j))
    };
    let mut order: Vec<usize> = (0..pairs.len()).collect();
    order.sort_by_key(|&k| key(k));
    let mut windows = Vec::new();
    let mut window: Vec<usize> = Vec::new();
    let mut images = std::collections::BTreeSet::new();
    for k in order {
        let (i, j) = pairs[k];
        let new = usize::from(!images.contains(&i)) + usize::from(!images.contains(&j));
        if !window.is_empty() && images.len() + new > max_images.max(2) {
            windows.push(std::mem::take(&mut window));
            images.clear();
        }
        images.insert(i);
        images.insert(j);
        window.push(k);
    }
    if !window.is_empty() {
        windows.push(window);
    }
    windows
}

/// The evidence of each pair that does not come from the learned matcher: the extractor's own
/// descriptors matched by mutual nearest neighbours with Lowe's ratio and verified by the same
/// MAGSAC, without a minimum (the verified count; 0 for a pair whose matches do not verify).
/// Costs about 10 ms a pair at 2048 keypoints, against about a second for LightGlue.
///
/// # Errors
/// Invalid pairs, OpenCV errors.
pub fn descriptor_support(
    features: &[ImageFeatures],
    pairs: &[(usize, usize)],
    config: &MatchConfig,
) -> Result<Vec<usize>> {
    let screen = MatchConfig {
        ratio: Some(posediff_matching::DEFAULT_RATIO),
        verification: Some(config.verification.unwrap_or_default()),
        min_verified: 0,
        ..*config
    };
    Ok(posediff_matching::match_pairs(features, pairs, &screen)?
        .iter()
        .map(PairMatches::len)
        .collect())
}

/// Features of every image, then the matches of `pairs` (all `i < j` when `None`).
///
/// # Errors
/// As [`extract_all`] and [`match_pairs`].
pub fn match_images(
    images: &[PathBuf],
    pairs: Option<&[(usize, usize)]>,
    config: &MatchConfig,
    learned: Option<&SharedLearned>,
) -> Result<(Vec<ImageFeatures>, Vec<PairMatches>)> {
    let all;
    let pairs = match pairs {
        Some(p) => p,
        None => {
            all = posediff_matching::exhaustive_pairs(images.len());
            &all
        }
    };
    // The cheap check before the extraction.
    posediff_matching::check_pairs(images.len(), pairs)?;
    let features = extract_all(images, config, learned)?;
    let matches = match_pairs(&features, pairs, config, learned)?;
    Ok((features, matches))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_cover_every_pair_once_within_the_image_bound() {
        let n = 30;
        let mut pairs: Vec<(usize, usize)> = Vec::new();
        for i in 0..n {
            for j in i + 1..n {
                // Some pairs given in the other order, and a shuffled list.
                pairs.push(if (i + j) % 3 == 0 { (j, i) } else { (i, j) });
            }
        }
        pairs.reverse();
        for bound in [2, 5, 24, 100] {
            let windows = prepared_windows(&pairs, bound);
            let mut seen = vec![0usize; pairs.len()];
            for w in &windows {
                assert!(!w.is_empty());
                let mut images: Vec<usize> =
                    w.iter().flat_map(|&k| [pairs[k].0, pairs[k].1]).collect();
                images.sort_unstable();
                images.dedup();
                assert!(
                    images.len() <= bound,
                    "{} images at bound {bound}",
                    images.len()
                );
                for &k in w {
                    seen[k] += 1;
                }
            }
            assert!(seen.iter().all(|&c| c == 1), "bound {bound}");
            if bound >= n {
                assert_eq!(windows.len(), 1);
            }
        }
        // Sequential pairs of a long video: each window holds about `bound` consecutive frames,
        // so each frame is prepared about once, not once per pair.
        let seq: Vec<(usize, usize)> = (0..1000)
            .flat_map(|i| (1..=3).map(move |d| (i, i + d)))
            .collect();
        let windows = prepared_windows(&seq, 24);
        let prepared: usize = windows
            .iter()
            .map(|w| {
                let mut images: Vec<usize> = w.iter().flat_map(|&k| [seq[k].0, seq[k].1]).collect();
                images.sort_unstable();
                images.dedup();
                images.len()
            })
            .sum();
        assert!(prepared < 1300, "{prepared} preparations for 1003 frames");
        assert!(prepared_windows(&[], 24).is_empty());
    }
}
