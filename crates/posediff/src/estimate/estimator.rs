//! The whole estimation: images → matches (original pixels, mapped into the 224 crops) → DINO
//! features → reverse diffusion with GGS on the last steps → cameras in each original image.

use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use posediff_diffusion::sampler::MeanHook;
use posediff_diffusion::{NoiseSource, PoseDiffusionModel, SeededNoise, sample, sample_from};
use posediff_geometry::{
    Camera, CenterCrop, ImageSize, Intrinsics, MODEL_INPUT_SIDE, PoseEncoding, QuaternionSign,
};
use posediff_guidance::{GgsConfig, GgsSolver, MatchSet};
use posediff_matching::{MatchConfig, PairMatches};

use crate::error::{PosediffError, Result};
use crate::estimate::options::{KnownIntrinsics, resolve_intrinsics};
use crate::io::export::NamedCamera;
use crate::io::loader::{LoadedImage, load_images};

/// Estimation settings; `Default` is the official demo's behaviour (one sample, GGS on).
#[derive(Debug, Clone)]
pub struct EstimateConfig {
    /// Seed of the sampler's noise.
    pub seed: u64,
    /// Samples per image set (a batch dimension).
    pub samples: usize,
    /// Geometry-guided sampling on the last steps; skipped with a warning without matches.
    pub ggs: bool,
    /// GGS settings (official defaults).
    pub ggs_config: GgsConfig,
    /// Matching settings.
    pub matching: MatchConfig,
    /// Known intrinsics: GGS keeps the focal at them (its focal phases are skipped) and the
    /// returned cameras carry them.
    pub intrinsics: KnownIntrinsics,
    /// The learned matcher for GGS, when the run uses it instead of OpenCV's.
    pub learned: Option<crate::correspondences::SharedLearned>,
}

impl Default for EstimateConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            samples: 1,
            ggs: true,
            ggs_config: GgsConfig::default(),
            matching: MatchConfig::default(),
            intrinsics: KnownIntrinsics::Unknown,
            learned: None,
        }
    }
}

/// Wall-clock seconds per stage.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StageTimes {
    /// Reading and preprocessing images.
    pub load: f64,
    /// Keypoints and matching.
    pub matching: f64,
    /// Image features.
    pub features: f64,
    /// Reverse diffusion, GGS included.
    pub sampling: f64,
    /// Of `sampling`, the time spent in GGS.
    pub ggs: f64,
}

/// The result of one estimation.
#[derive(Debug, Clone)]
pub struct Estimate {
    /// Per sample, one camera per image (original pixels, OpenCV convention), in image order.
    pub samples: Vec<Vec<NamedCamera>>,
    /// Per matched pair: `(first, second, matches)`.
    pub matches_per_pair: Vec<(usize, usize, usize)>,
    /// The matches of every pair (original pixels, keypoint ids; undistorted when `lens`);
    /// empty without GGS.
    pub pairs: Vec<PairMatches>,
    /// The photos' lens distortion measured from the matches ([`EstimateInput::lens_from`]),
    /// when one was: the cameras are pinholes of the undistorted pixels, and each image's lens
    /// ([`posediff_pipeline::geometric::RadialLens::lens_camera`]) maps back to the photo.
    pub lens: Option<posediff_pipeline::geometric::RadialLens>,
    /// The calibration's report (`None`: not asked for, or GGS off).
    pub distortion: Option<posediff_pipeline::report::DistortionOutcome>,
    /// Stage timings.
    pub times: StageTimes,
    /// Things the user should know (e.g. GGS skipped).
    pub warnings: Vec<crate::estimate::run_report::Warning>,
}

/// Progress of an estimation, stage by stage (the CLI draws bars; the default does nothing).
pub trait Progress {
    /// A stage begins; `total` steps, 0 when it has no steps to count.
    fn start(&mut self, _stage: &str, _total: u64) {}
    /// One step of the current stage is done.
    fn advance(&mut self) {}
    /// The current stage is done.
    fn finish(&mut self) {}
    /// The same output for stages whose steps finish on any thread (the geometric path's
    /// features and pairs); counts nothing unless overridden.
    fn counter(&self) -> &dyn crate::correspondences::StepCounter {
        &crate::correspondences::NoCounter
    }
}

/// No progress output.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Progress for Silent {}

/// Reports sampler steps to a [`Progress`], replacing means with GGS where it has a solver.
struct SamplingProgress<'a, 'm> {
    ggs: Option<GgsHook<'m>>,
    progress: &'a mut dyn Progress,
}

impl MeanHook for SamplingProgress<'_, '_> {
    fn replace_mean(&mut self, mean: &Tensor, t: usize) -> posediff_diffusion::Result<Tensor> {
        match self.ggs.as_mut() {
            Some(h) => h.replace_mean(mean, t),
            None => Ok(mean.clone()),
        }
    }

    fn step_done(&mut self, _t: usize) {
        self.progress.advance();
    }
}

/// How far the samples of one camera disagree.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct CameraSpread {
    /// Largest rotation angle between a sample and sample 0, degrees.
    pub rotation_deg_max: f64,
    /// Largest distance between a sample's camera centre and sample 0's, in sample 0's units.
    pub center_distance_max: f64,
}

impl Estimate {
    /// Per camera, the spread of the samples around sample 0, after aligning each sample's world
    /// to sample 0's (PyTorch3D's extrinsics alignment, as the official demo aligns). Empty for
    /// one sample.
    ///
    /// # Errors
    /// Degenerate alignments.
    pub fn spread(&self) -> Result<Vec<CameraSpread>> {
        let Some((first, rest)) = self.samples.split_first() else {
            return Ok(Vec::new());
        };
        if rest.is_empty() {
            return Ok(Vec::new());
        }
        let base: Vec<_> = first.iter().map(|c| c.camera).collect();
        let mut out = vec![
            CameraSpread {
                rotation_deg_max: 0.0,
                center_distance_max: 0.0,
            };
            base.len()
        ];
        for sample in rest {
            let cams: Vec<_> = sample.iter().map(|c| c.camera).collect();
            let sim = posediff_geometry::align_cameras_by_extrinsics(&cams, &base)?;
            for ((o, c), b) in out.iter_mut().zip(&cams).zip(&base) {
                let aligned = sim.transform_camera(c);
                // The aligned camera frame is scaled by the similarity; its centre is not.
                let angle = posediff_geometry::rotation_angle_between_deg(
                    &b.cam_from_world.rotation,
                    &aligned.cam_from_world.rotation,
                );
                o.rotation_deg_max = o.rotation_deg_max.max(angle);
                o.center_distance_max = o
                    .center_distance_max
                    .max((aligned.center() - b.center()).norm());
            }
        }
        Ok(out)
    }
}

/// GGS as the sampler's mean hook, each sample of the batch on its own.
pub struct GgsHook<'m> {
    solver: GgsSolver<'m>,
    seconds: f64,
    /// Known focal entries (encoding entries 7 and 8) per frame, written into the mean first.
    focal: Option<Vec<[f64; 2]>>,
}

impl<'m> GgsHook<'m> {
    /// A hook running `config`'s GGS on `matches` (224-crop pixels).
    ///
    /// # Errors
    /// An invalid GGS configuration.
    pub fn new(matches: &'m MatchSet, config: GgsConfig) -> Result<Self> {
        Ok(Self {
            solver: GgsSolver::new(matches, config)?,
            seconds: 0.0,
            focal: None,
        })
    }

    /// Holds every frame's focal at known values: encoding entries 7 and 8 per frame are
    /// overwritten before each GGS call, and `config.fix_focal` should be set.
    pub fn with_known_focal(mut self, entries: Vec<[f64; 2]>) -> Self {
        self.focal = Some(entries);
        self
    }

    /// Seconds spent in GGS so far.
    pub fn seconds(&self) -> f64 {
        self.seconds
    }
}

impl MeanHook for GgsHook<'_> {
    fn replace_mean(&mut self, mean: &Tensor, t: usize) -> posediff_diffusion::Result<Tensor> {
        let start = Instant::now();
        let (b, n, d) = mean.dims3()?;
        let flat: Vec<f64> = mean.flatten_all()?.to_dtype(DType::F64)?.to_vec1()?;
        let mut out = Vec::with_capacity(flat.len());
        for sample in flat.chunks(n * d) {
            let mut enc: Vec<PoseEncoding> = sample
                .chunks(d)
                .map(|c| {
                    let mut row = [0.0; 9];
                    row.copy_from_slice(c);
                    PoseEncoding(row)
                })
                .collect();
            if let Some(focal) = &self.focal {
                for (e, f) in enc.iter_mut().zip(focal) {
                    e.0[7] = f[0];
                    e.0[8] = f[1];
                }
            }
            self.solver.run(&mut enc, None).map_err(|e| {
                posediff_diffusion::DiffusionError::Hook {
                    what: "GGS on the posterior mean",
                    step: t,
                    detail: e.to_string(),
                }
            })?;
            out.extend(enc.iter().flat_map(|e| e.0));
        }
        self.seconds += start.elapsed().as_secs_f64();
        Ok(Tensor::from_vec(out, (b, n, d), mean.device())?.to_dtype(mean.dtype())?)
    }
}

/// What [`Estimator::sample_encodings`] samples from.
#[derive(Debug, Clone, Copy)]
pub struct SamplingInput<'a> {
    /// Preprocessed images `(N, 3, 224, 224)` in `[0, 1]`.
    pub images: &'a Tensor,
    /// GGS on these matches (224-crop pixels) on the last steps.
    pub matches: Option<&'a MatchSet>,
    /// Known focal lengths per image (224-crop pixels): GGS keeps them.
    pub focal: Option<&'a [[f64; 2]]>,
    /// Start from these encodings `(N, 9)` noised to this step (`posediff_diffusion::
    /// sample_from`) instead of pure noise.
    pub init: Option<(&'a Tensor, usize)>,
}

impl<'a> SamplingInput<'a> {
    /// `images`, from pure noise, without GGS.
    pub fn new(images: &'a Tensor) -> Self {
        Self {
            images,
            matches: None,
            focal: None,
            init: None,
        }
    }
}

/// What [`Estimator::estimate`] estimates.
#[derive(Clone, Copy)]
pub struct EstimateInput<'a> {
    /// The image files.
    pub images: &'a [PathBuf],
    /// The folder the images' names are relative to.
    pub root: Option<&'a Path>,
    /// Initial cameras (one per image) and the step they are noised to.
    pub init: Option<(&'a [Camera], usize)>,
    /// The checkpoint-free path's configuration whose lens calibration
    /// ([`posediff_pipeline::geometric::calibrate_lens`]: `cameras.distortion`, the camera
    /// mode and EXIF hints, unknown intrinsics only) undistorts GGS's matches before they are
    /// mapped into the 224 crops; `None`: the matches as matched (pinhole photos).
    pub lens_from: Option<&'a posediff_pipeline::geometric::GeometricConfig>,
    /// The matcher GGS's features and matches come from instead of matching with the
    /// configuration's `matching` here (`--database`: the store's wrapper around that same
    /// matching, which reads what the database holds and writes what it lacks); every pair.
    pub matcher: Option<&'a dyn posediff_pipeline::correspondences::Correspondences>,
}

impl std::fmt::Debug for EstimateInput<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EstimateInput")
            .field("images", &self.images)
            .field("root", &self.root)
            .field("init", &self.init)
            .field("lens_from", &self.lens_from)
            .field("matcher", &self.matcher.map(|_| "a stored matcher"))
            .finish()
    }
}

impl<'a> EstimateInput<'a> {
    /// `images`, named by their paths, from pure noise.
    pub fn new(images: &'a [PathBuf]) -> Self {
        Self {
            images,
            root: None,
            init: None,
            lens_from: None,
            matcher: None,
        }
    }
}

/// A loaded model and its settings.
#[derive(Debug)]
pub struct Estimator {
    model: PoseDiffusionModel,
    device: Device,
    config: EstimateConfig,
}

impl Estimator {
    /// Loads a checkpoint (`.pth` or safetensors) to run in F32 on `device`.
    ///
    /// # Errors
    /// Unreadable or mis-shaped checkpoints.
    pub fn load(weights: &Path, device: Device, config: EstimateConfig) -> Result<Self> {
        let model = PoseDiffusionModel::load(weights, DType::F32, &device)?;
        Ok(Self {
            model,
            device,
            config,
        })
    }

    /// The same model with other settings (the weights are shared, not copied).
    pub fn with_config(&self, config: EstimateConfig) -> Self {
        Self {
            model: self.model.clone(),
            device: self.device.clone(),
            config,
        }
    }

    /// Its settings.
    pub fn config(&self) -> &EstimateConfig {
        &self.config
    }

    /// An estimator around an already loaded model.
    pub fn from_model(model: PoseDiffusionModel, device: Device, config: EstimateConfig) -> Self {
        Self {
            model,
            device,
            config,
        }
    }

    /// Samples encodings `(samples, N, 9)` (see [`SamplingInput`]), reporting the stages
    /// "features" and "sampling" to `progress`.
    ///
    /// # Errors
    /// Shape, model or GGS errors; a start step outside the schedule.
    pub fn sample_encodings(
        &self,
        input: SamplingInput<'_>,
        noise: &mut dyn NoiseSource,
        times: &mut StageTimes,
        progress: &mut dyn Progress,
    ) -> Result<Tensor> {
        let SamplingInput {
            images,
            matches,
            focal,
            init,
        } = input;
        progress.start("features", 0);
        let start = Instant::now();
        let n = images.dim(0)?;
        let z = self.model.image_features(&images.unsqueeze(0)?)?;
        if !posediff_diffusion::sampler::all_finite(&z)? {
            return Err(posediff_diffusion::DiffusionError::NonFinite {
                what: "DINO features",
                step: posediff_diffusion::checkpoint::TIMESTEPS - 1,
            }
            .into());
        }
        let z = z
            .broadcast_as((self.config.samples, n, z.dim(2)?))?
            .contiguous()?;
        times.features = start.elapsed().as_secs_f64();
        log::info!("features of {n} images in {:.2} s", times.features);
        progress.finish();
        let steps = init.map_or(self.model.schedule.len(), |(_, s)| s + 1);
        progress.start("sampling", steps as u64);
        let start = Instant::now();
        let ggs = matches
            .map(|m| -> Result<GgsHook<'_>> {
                let mut config = self.config.ggs_config;
                config.fix_focal |= focal.is_some();
                let hook = GgsHook::new(m, config)?;
                Ok(match focal {
                    Some(f) => hook.with_known_focal(f.to_vec()),
                    None => hook,
                })
            })
            .transpose()?;
        // Without GGS the hook only observes: a start step of 0 never replaces a mean.
        let start_step = if ggs.is_some() {
            self.config.ggs_config.start_step
        } else {
            0
        };
        let mut hook = SamplingProgress { ggs, progress };
        let out = match init {
            None => sample(
                &self.model.denoiser,
                &self.model.schedule,
                &z,
                noise,
                Some((&mut hook, start_step)),
                None,
            )?,
            Some((x0, from_step)) => {
                let x0 = x0
                    .unsqueeze(0)?
                    .broadcast_as((self.config.samples, n, 9))?
                    .contiguous()?;
                sample_from(
                    &self.model.denoiser,
                    &self.model.schedule,
                    &z,
                    noise,
                    &x0,
                    from_step,
                    Some((&mut hook, start_step)),
                    None,
                )?
            }
        };
        times.ggs = hook.ggs.as_ref().map_or(0.0, GgsHook::seconds);
        times.sampling = start.elapsed().as_secs_f64();
        log::info!(
            "sampling in {:.2} s (GGS {:.2} s)",
            times.sampling,
            times.ggs
        );
        hook.progress.finish();
        Ok(out)
    }

    /// Estimates the cameras of [`EstimateInput::images`] (at least two files), reporting its
    /// stages ("images", "matching", "features", "sampling") to `progress`. With
    /// [`EstimateInput::init`] the reverse diffusion starts from those cameras (one per image,
    /// original pixels, any world frame) noised to the start step instead of from pure noise;
    /// they are taken into the model's frame as in training: each into its 224 crop, then the
    /// official normalisation (camera 0's PyTorch3D frame, optical-axis scale).
    ///
    /// # Errors
    /// Too few or unreadable images, matching, model or GGS errors; initial cameras of the
    /// wrong count or that cannot be normalised; a start step outside the schedule.
    pub fn estimate(
        &self,
        input: EstimateInput<'_>,
        progress: &mut dyn Progress,
    ) -> Result<Estimate> {
        let EstimateInput {
            images,
            root,
            init,
            lens_from,
            matcher,
        } = input;
        if let Some((cams, _)) = init
            && cams.len() != images.len()
        {
            return Err(PosediffError::InvalidArgument(format!(
                "{} initial cameras for {} images",
                cams.len(),
                images.len()
            )));
        }
        if images.len() < 2 {
            return Err(PosediffError::TooFewImages {
                needed: 2,
                got: images.len(),
            });
        }
        let mut times = StageTimes::default();
        let mut warnings = Vec::new();
        log::info!(
            "{}loading {} images",
            crate::progress::WORK_STARTS,
            images.len()
        );
        progress.start("images", 0);
        let start = Instant::now();
        let loaded = load_images(images)?;
        let side = MODEL_INPUT_SIDE as usize;
        let pixels: Vec<f32> = loaded
            .iter()
            .flat_map(|l| l.pixels.iter().copied())
            .collect();
        let tensor = Tensor::from_vec(pixels, (loaded.len(), 3, side, side), &self.device)?;
        times.load = start.elapsed().as_secs_f64();
        progress.finish();

        let mut matches_per_pair = Vec::new();
        let mut all_pairs = Vec::new();
        let mut lens = None;
        let mut distortion = None;
        let match_set = if self.config.ggs {
            progress.start("matching", 0);
            let start = Instant::now();
            let mut pairs = match matcher {
                Some(m) => {
                    let counter = progress.counter();
                    let features = m.extract(images, counter)?;
                    let all = posediff_matching::exhaustive_pairs(images.len());
                    m.match_pairs(&features, &all, (counter, "pairs"))?
                }
                None => {
                    crate::correspondences::match_images(
                        images,
                        None,
                        &self.config.matching,
                        self.config.learned.as_ref(),
                    )?
                    .1
                }
            };
            if let Some(config) = lens_from {
                // The photos' distortion, measured from the matches as the checkpoint-free
                // path does; the model's cameras are pinholes of the undistorted pixels.
                let sizes: Vec<ImageSize> = loaded.iter().map(|l| l.size).collect();
                let (measured, outcome) =
                    posediff_pipeline::geometric::calibrate_lens(&sizes, &pairs, config)?;
                if let Some(l) = &measured {
                    l.undistort_pairs(&mut pairs);
                }
                lens = measured;
                distortion = Some(outcome);
            }
            times.matching = start.elapsed().as_secs_f64();
            progress.finish();
            matches_per_pair = pairs.iter().map(|p| (p.first, p.second, p.len())).collect();
            let crops: Vec<Option<CenterCrop>> = loaded.iter().map(|l| Some(l.crop)).collect();
            let set = model_frame_matches(&pairs, &crops)?;
            log::info!(
                "matching: {} pairs, {} with matches, {} matches in {:.2} s",
                pairs.len(),
                pairs.iter().filter(|p| !p.is_empty()).count(),
                set.len(),
                times.matching
            );
            all_pairs = pairs;
            if set.is_empty() {
                log::warn!("GGS skipped: no image pair has verified matches");
                warnings.push(crate::estimate::run_report::Warning::GgsSkipped);
                None
            } else {
                Some(set)
            }
        } else {
            None
        };
        let mut noise = SeededNoise::new(self.config.seed);
        let init_tensor = init
            .map(|(cams, step)| -> Result<(Tensor, usize)> {
                let in_crops = cams
                    .iter()
                    .zip(&loaded)
                    .map(|(c, l)| Ok(l.crop.camera_to_model(c)?))
                    .collect::<Result<Vec<_>>>()?;
                Ok((model_encodings(&in_crops, &self.device)?, step))
            })
            .transpose()?;
        let sizes: Vec<ImageSize> = loaded.iter().map(|l| l.size).collect();
        let known = resolve_intrinsics(&self.config.intrinsics, &sizes)?;
        let focal_entries = known
            .as_ref()
            .map(|k| known_focal_entries(k, &loaded))
            .transpose()?;
        let encodings = self.sample_encodings(
            SamplingInput {
                images: &tensor,
                matches: match_set.as_ref(),
                focal: focal_entries.as_deref(),
                init: init_tensor.as_ref().map(|(t, s)| (t, *s)),
            },
            &mut noise,
            &mut times,
            progress,
        )?;
        let flat: Vec<f64> = encodings.flatten_all()?.to_dtype(DType::F64)?.to_vec1()?;
        let model_size = ImageSize::new(MODEL_INPUT_SIDE, MODEL_INPUT_SIDE)?;
        let names: Vec<String> = images.iter().map(|p| relative_name(p, root)).collect();
        let samples = flat
            .chunks(loaded.len() * 9)
            .map(|sample| {
                sample
                    .chunks(9)
                    .zip(&loaded)
                    .zip(&names)
                    .enumerate()
                    .map(|(index, ((e, l), name))| {
                        let mut row = [0.0; 9];
                        row.copy_from_slice(e);
                        let at_224 = PoseEncoding(row).to_camera(model_size)?;
                        let mut camera = l.crop.camera_from_model(&at_224, l.size)?;
                        if let Some(k) = &known {
                            camera.intrinsics = k[index];
                        }
                        if let Some(lens) = &lens {
                            // A lens model has one focal and its own centre: the network's
                            // two focals averaged, the principal point the lens's (the crop
                            // centre, within half a pixel).
                            let (cx, cy) = lens.lenses[index].principal();
                            let k = camera.intrinsics;
                            let f = 0.5 * (k.fx() + k.fy());
                            camera.intrinsics = Intrinsics::new(f, f, cx, cy)?;
                        }
                        Ok(NamedCamera {
                            image: name.clone(),
                            camera,
                        })
                    })
                    .collect::<Result<Vec<_>>>()
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Estimate {
            samples,
            matches_per_pair,
            pairs: all_pairs,
            times,
            warnings,
            lens,
            distortion,
        })
    }
}

/// The encoding's focal entries (7, 8) of known intrinsics, per image, in its 224 crop.
fn known_focal_entries(known: &[Intrinsics], loaded: &[LoadedImage]) -> Result<Vec<[f64; 2]>> {
    known
        .iter()
        .zip(loaded)
        .map(|(k, l)| {
            let camera = Camera::new(*k, posediff_geometry::Pose::identity(), l.size);
            let e = PoseEncoding::from_camera(
                &l.crop.camera_to_model(&camera)?,
                QuaternionSign::default(),
            )?;
            Ok([e.0[7], e.0[8]])
        })
        .collect()
}

/// Cameras of the 224 crops → the model's normalised encodings `(N, 9)` (F32): the official
/// normalisation (camera 0's PyTorch3D frame at the origin, unit distance to the optical-axis
/// intersection; without an intersection, e.g. parallel axes, the translation-norm variant).
///
/// # Errors
/// Cameras that cannot be normalised or encoded.
pub fn model_encodings(cameras: &[Camera], device: &Device) -> Result<Tensor> {
    let flat = normalised_encodings(cameras)?;
    Ok(Tensor::from_vec(flat, (cameras.len(), 9), device)?)
}

/// The rows of [`model_encodings`] as `n × 9` values (F32, row-major): what the official
/// dataset feeds the model as `x0` for a set of crop cameras.
///
/// # Errors
/// Cameras that cannot be normalised or encoded.
pub fn normalised_encodings(cameras: &[Camera]) -> Result<Vec<f32>> {
    let canonical = posediff_geometry::normalize::canonicalize(cameras)
        .or_else(|_| posediff_geometry::normalize::canonicalize_without_optical_axis(cameras))?;
    Ok(canonical
        .cameras
        .iter()
        .map(|c| PoseEncoding::from_camera(c, QuaternionSign::default()).map(|e| e.0))
        .collect::<std::result::Result<Vec<_>, _>>()?
        .into_iter()
        .flatten()
        .map(|v| v as f32)
        .collect())
}

pub use crate::io::loader::relative_name;

pub use posediff_pipeline::geometric::model_frame_matches;
