//! Geometry-guided sampling exactly as the released PoseDiffusion code runs it
//! (`util/geometry_guided_sampling.py`; SPEC.md §5), not the paper's equation.
//!
//! At a diffusion step `t < start_step` the posterior mean `μ` (one 9-D encoding per frame) is
//! *replaced* by the result of five optimisation phases on the mean valid Sampson error:
//!
//! | phase | updates | iterations (official) |
//! |---|---|---|
//! | 1 | R, T, focal | `2·iter_num` = 200 |
//! | 2 | focal | 100 |
//! | 3 | R | 100 |
//! | 4 | T | 100 |
//! | 5 | R, T, focal | 200 |
//!
//! Each phase is a fresh SGD with momentum 0.9 (`buf = g` on the first step, then
//! `buf = 0.9 buf + g`; `μ −= lr·buf`). Before each step the gradient is clipped to the adaptive
//! bound `alpha·‖μ ⊙ 1[|g| > 0]‖ / lr` (`clip_grad_norm_`: scale by `max/(‖g‖ + 1e−6)` when
//! that is below 1). A phase stops early when the number of valid matches per frame falls below
//! `min_matches`.
//!
//! # Deviation
//! The official code would take the mean of an empty set (NaN) when no match is valid and
//! `min_matches` is 0; here the phase stops instead. Nothing else differs.

use posediff_geometry::{ImageSize, MODEL_INPUT_SIDE, PoseEncoding};

use crate::error::{GuidanceError, Result};
use crate::matches::MatchSet;
use crate::sampson::{Evaluation, SampsonObjective, UpdateMask};

/// `clip_grad_norm_`'s epsilon in the clip coefficient `max / (‖g‖ + 1e−6)`.
const CLIP_EPS: f64 = 1e-6;

/// The momentum of the official `torch.optim.SGD(..., momentum=0.9)`.
pub const SGD_MOMENTUM: f64 = 0.9;

/// GGS settings; `Default` is the official `cfgs/default.yaml` `GGS` block.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GgsConfig {
    /// SGD learning rate (official 0.01).
    pub learning_rate: f64,
    /// Iterations of the single-attribute phases; the all-attribute phases run twice as many
    /// (official 100).
    pub iter_num: usize,
    /// Sampson errors at or above this (px²) are dropped (official 10).
    pub sampson_max: f64,
    /// A phase stops when valid matches per frame fall below this (official 10; 0 disables).
    pub min_matches: f64,
    /// Relative step bound of the adaptive gradient clipping (official 1e-4).
    pub alpha: f64,
    /// GGS runs at diffusion steps `t < start_step` (official 10).
    pub start_step: usize,
    /// The image the keypoints are in (official: the 224×224 crop).
    pub image_size: ImageSize,
    /// Known intrinsics: no phase updates the focal lengths and the focal-only phase is skipped
    /// (not official; `false` by default).
    pub fix_focal: bool,
}

impl Default for GgsConfig {
    fn default() -> Self {
        Self {
            learning_rate: 0.01,
            iter_num: 100,
            sampson_max: 10.0,
            min_matches: 10.0,
            alpha: 1e-4,
            start_step: 10,
            image_size: match ImageSize::new(MODEL_INPUT_SIDE, MODEL_INPUT_SIDE) {
                Ok(size) => size,
                Err(_) => unreachable!("224×224 is a valid size"),
            },
            fix_focal: false,
        }
    }
}

impl GgsConfig {
    fn validate(&self) -> Result<()> {
        if !(self.learning_rate > 0.0 && self.learning_rate.is_finite()) {
            return Err(GuidanceError::InvalidConfig {
                reason: "learning_rate must be positive and finite",
            });
        }
        if !(self.alpha >= 0.0 && self.alpha.is_finite()) {
            return Err(GuidanceError::InvalidConfig {
                reason: "alpha must be non-negative and finite",
            });
        }
        if self.min_matches.is_nan() || self.min_matches < 0.0 {
            return Err(GuidanceError::InvalidConfig {
                reason: "min_matches must be non-negative",
            });
        }
        Ok(())
    }

    /// The five official phases: update mask and iteration count. With `fix_focal` the masks
    /// leave the focal alone and the focal-only phase has no iterations.
    pub fn phases(&self) -> [(UpdateMask, usize); 5] {
        let n = self.iter_num;
        let all = UpdateMask {
            focal: !self.fix_focal,
            ..UpdateMask::ALL
        };
        [
            (all, 2 * n),
            (UpdateMask::FOCAL, if self.fix_focal { 0 } else { n }),
            (UpdateMask::ROTATION, n),
            (UpdateMask::TRANSLATION, n),
            (all, 2 * n),
        ]
    }
}

/// What happened in one GGS iteration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IterationRecord {
    /// Phase index 0..5.
    pub phase: usize,
    /// The objective before the step.
    pub evaluation: Evaluation,
    /// `‖g‖` before clipping.
    pub grad_norm: f64,
    /// The clipping bound `alpha·‖μ ⊙ 1[|g|>0]‖/lr`.
    pub max_norm: f64,
}

/// The record of one GGS call.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct GgsReport {
    /// Every iteration that took a step, in order.
    pub iterations: Vec<IterationRecord>,
    /// `μ` after each phase.
    pub phase_outputs: Vec<Vec<PoseEncoding>>,
    /// Phases cut short by `min_matches` (or by having no valid match).
    pub stopped_phases: Vec<usize>,
}

/// Reusable GGS state for one set of matches: the objective's buffers, the gradient and the
/// momentum buffer. Allocates only in [`GgsSolver::new`] and when recording a report.
#[derive(Debug, Clone)]
pub struct GgsSolver<'m> {
    config: GgsConfig,
    objective: SampsonObjective<'m>,
    grad: Vec<[f64; 9]>,
    momentum: Vec<[f64; 9]>,
}

impl<'m> GgsSolver<'m> {
    /// A solver for `matches` with `config`.
    ///
    /// # Errors
    /// An invalid configuration.
    pub fn new(matches: &'m MatchSet, config: GgsConfig) -> Result<Self> {
        config.validate()?;
        let n = matches.n_frames();
        Ok(Self {
            config,
            objective: SampsonObjective::new(matches, config.image_size, config.sampson_max)?,
            grad: vec![[0.0; 9]; n],
            momentum: vec![[0.0; 9]; n],
        })
    }

    /// The configuration.
    pub fn config(&self) -> &GgsConfig {
        &self.config
    }

    /// The objective (for evaluating Sampson errors at some encodings).
    pub fn objective(&mut self) -> &mut SampsonObjective<'m> {
        &mut self.objective
    }

    /// Official `GGS_optimize`: one phase of `iterations` SGD steps on `mean` (in place),
    /// gradient restricted to `mask`. Returns whether the phase ran to the end.
    ///
    /// # Errors
    /// Encodings that cannot be decoded or of the wrong count.
    pub fn optimize_phase(
        &mut self,
        mean: &mut [PoseEncoding],
        mask: UpdateMask,
        iterations: usize,
        phase: usize,
        mut record: Option<&mut GgsReport>,
    ) -> Result<bool> {
        let cfg = self.config;
        let n_frames = mean.len() as f64;
        for it in 0..iterations {
            let evaluation = self.objective.evaluate(mean)?;
            if evaluation.n_valid == 0 || (evaluation.n_valid as f64) / n_frames < cfg.min_matches {
                return Ok(false);
            }
            self.objective.gradient(mask, &mut self.grad)?;
            let (mut g2, mut m2) = (0.0, 0.0);
            for (g_row, mu_row) in self.grad.iter().zip(mean.iter()) {
                for (g, mu) in g_row.iter().zip(mu_row.0.iter()) {
                    g2 += g * g;
                    if g.abs() > 0.0 {
                        m2 += mu * mu;
                    }
                }
            }
            let grad_norm = g2.sqrt();
            let max_norm = cfg.alpha * m2.sqrt() / cfg.learning_rate;
            let clip = (max_norm / (grad_norm + CLIP_EPS)).min(1.0);
            for ((g_row, buf_row), mu_row) in self
                .grad
                .iter()
                .zip(self.momentum.iter_mut())
                .zip(mean.iter_mut())
            {
                for c in 0..9 {
                    let g = g_row[c] * clip;
                    buf_row[c] = if it == 0 {
                        g
                    } else {
                        SGD_MOMENTUM * buf_row[c] + g
                    };
                    mu_row.0[c] -= cfg.learning_rate * buf_row[c];
                }
            }
            if let Some(report) = record.as_deref_mut() {
                report.iterations.push(IterationRecord {
                    phase,
                    evaluation,
                    grad_norm,
                    max_norm,
                });
            }
        }
        Ok(true)
    }

    /// Official `geometry_guided_sampling`: the five phases on `mean`, in place.
    ///
    /// # Errors
    /// Encodings that cannot be decoded or of the wrong count.
    pub fn run(
        &mut self,
        mean: &mut [PoseEncoding],
        mut record: Option<&mut GgsReport>,
    ) -> Result<()> {
        if let Some(report) = record.as_deref_mut() {
            let total: usize = self.config.phases().iter().map(|p| p.1).sum();
            report.iterations.reserve(total);
        }
        for (phase, (mask, iterations)) in self.config.phases().into_iter().enumerate() {
            let completed =
                self.optimize_phase(mean, mask, iterations, phase, record.as_deref_mut())?;
            if let Some(report) = record.as_deref_mut() {
                report.phase_outputs.push(mean.to_vec());
                if !completed {
                    report.stopped_phases.push(phase);
                }
            }
        }
        Ok(())
    }
}

/// One GGS call with a fresh solver: replaces `mean` by its geometry-guided refinement.
///
/// # Errors
/// As [`GgsSolver::new`] and [`GgsSolver::run`].
pub fn geometry_guided_sampling(
    mean: &mut [PoseEncoding],
    matches: &MatchSet,
    config: GgsConfig,
) -> Result<GgsReport> {
    let mut report = GgsReport::default();
    GgsSolver::new(matches, config)?.run(mean, Some(&mut report))?;
    Ok(report)
}
