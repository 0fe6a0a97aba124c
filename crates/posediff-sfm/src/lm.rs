//! One Levenberg–Marquardt core for every refinement of the mapper (the Sampson refinement and
//! the bundle adjustment): damped Gauss–Newton steps `(H + λ·diag(H) + ε) δ = −g`, accepted when
//! the robust cost falls, with λ lowered after a success and raised after a failure. The
//! problem owns its linearisation (so the bundle adjustment can eliminate its points) and its
//! gauge (it re-fixes it in [`LeastSquares::apply`]).

use crate::error::Result;

/// A running sum of Cauchy losses `½c² ln(1 + e²/c²)` with one logarithm per batch of terms:
/// `Σ ln(1 + xᵢ) = ln Π(1 + xᵢ)`, the product taken until it would pass [`Self::LIMIT`].
///
/// The costs of the Sampson refinement and the bundle adjustment sum millions of these per
/// evaluation; at one `ln` each the logarithm was 15 % of a 300-frame orbit's mapper (perf,
/// docs/BENCHMARKS.md "Video-scale speed"). Every factor is ≥ 1, so the product only grows and
/// its rounding (one ulp per factor) is the same size as a sum of logarithms' rounding. A NaN
/// term makes the sum NaN, as the plain sum would.
#[derive(Debug, Clone, Copy)]
pub struct CauchySum {
    c2: f64,
    product: f64,
    logs: f64,
}

impl CauchySum {
    /// Where a product is closed with its logarithm (far below `f64::MAX`, so one more
    /// factor below the limit cannot overflow).
    pub const LIMIT: f64 = 1e150;

    /// An empty sum with Cauchy scale `cauchy` (`c`).
    #[must_use]
    pub fn new(cauchy: f64) -> Self {
        Self {
            c2: cauchy * cauchy,
            product: 1.0,
            logs: 0.0,
        }
    }

    /// Adds the loss of one squared residual `e2`.
    #[inline]
    pub fn add(&mut self, e2: f64) {
        let factor = 1.0 + e2 / self.c2;
        let product = self.product * factor;
        if product < Self::LIMIT {
            self.product = product;
        } else {
            self.logs += self.product.ln();
            if factor < Self::LIMIT {
                self.product = factor;
            } else {
                // A huge (or NaN) factor alone.
                self.logs += factor.ln();
                self.product = 1.0;
            }
        }
    }

    /// The sum so far.
    #[must_use]
    pub fn total(&self) -> f64 {
        0.5 * self.c2 * (self.logs + self.product.ln())
    }
}

/// A robust least-squares problem.
pub trait LeastSquares {
    /// The parameters being refined.
    type State: Clone;

    /// Number of free parameters (0: nothing to refine).
    fn n_params(&self) -> usize;

    /// The robust cost at `state`.
    fn cost(&self, state: &Self::State) -> f64;

    /// Linearises at `state` (normal equations, undamped), kept until the next call.
    ///
    /// # Errors
    /// Whatever building the system can fail with.
    fn linearize(&mut self, state: &Self::State) -> Result<()>;

    /// The step of the last linearisation with damping `lambda`; `Ok(None)` when the damped
    /// system is not positive definite (the damping is raised and the step tried again).
    ///
    /// # Errors
    /// Linear-algebra failures other than a non-positive pivot.
    fn solve(&mut self, lambda: f64) -> Result<Option<Vec<f64>>>;

    /// `state` moved by `step`, with the gauge fixed again.
    fn apply(&self, state: &Self::State, step: &[f64]) -> Self::State;
}

/// Settings of [`minimize`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct LmOptions {
    /// Accepted steps at most.
    pub max_iterations: usize,
    /// Converged when a step lowers the cost by less than this, relatively.
    pub tolerance: f64,
    /// Initial damping.
    pub initial_lambda: f64,
    /// Damping increases tried per iteration before giving up.
    pub max_tries: usize,
    /// Converged when no component of an accepted step is larger than this (in the
    /// problem's own parameter units; Ceres' `parameter_tolerance` in the maximum norm);
    /// 0: only the cost decides. For problems whose robust cost keeps falling by a steady
    /// small fraction while the parameters no longer move in any way that matters.
    pub step_tolerance: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            tolerance: 1e-10,
            initial_lambda: 1e-4,
            max_tries: 12,
            step_tolerance: 0.0,
        }
    }
}

/// Why [`minimize`] stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Termination {
    /// The relative decrease of the last step fell below the tolerance.
    #[default]
    Converged,
    /// No component of the last step was larger than [`LmOptions::step_tolerance`].
    SmallStep,
    /// No damping in `max_tries` lowered the cost: a (local) minimum to the solver's precision.
    NoDecrease,
    /// `max_iterations` steps were taken.
    IterationLimit,
    /// Nothing to refine (no free parameter).
    NothingToRefine,
}

#[cfg(feature = "serde")]
serialize_as_str!(Termination);

impl Termination {
    /// Whether the problem is at a minimum (not stopped by the iteration limit).
    pub fn converged(self) -> bool {
        !matches!(self, Self::IterationLimit)
    }

    /// A short name for reports.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Converged => "converged",
            Self::SmallStep => "small step",
            Self::NoDecrease => "no decrease",
            Self::IterationLimit => "iteration limit",
            Self::NothingToRefine => "nothing to refine",
        }
    }
}

/// What [`minimize`] did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LmReport {
    /// Accepted steps.
    pub iterations: usize,
    /// Linear solves, accepted or not.
    pub solves: usize,
    /// Cost before.
    pub initial_cost: f64,
    /// Cost after.
    pub final_cost: f64,
    /// Why it stopped.
    pub termination: Termination,
}

/// Minimises `problem` from `state` (in place).
///
/// # Errors
/// A problem whose linearisation or solve fails.
pub fn minimize<P: LeastSquares>(
    problem: &mut P,
    state: &mut P::State,
    options: &LmOptions,
) -> Result<LmReport> {
    let mut cost = problem.cost(state);
    let mut report = LmReport {
        initial_cost: cost,
        final_cost: cost,
        termination: Termination::IterationLimit,
        ..LmReport::default()
    };
    if problem.n_params() == 0 {
        report.termination = Termination::NothingToRefine;
        return Ok(report);
    }
    if options.max_iterations == 0 {
        return Ok(report);
    }
    let mut lambda = options.initial_lambda;
    while report.iterations < options.max_iterations {
        problem.linearize(state)?;
        let mut accepted = None;
        for _ in 0..options.max_tries {
            report.solves += 1;
            let Some(step) = problem.solve(lambda)? else {
                lambda *= 10.0;
                continue;
            };
            let moved = problem.apply(state, &step);
            let new_cost = problem.cost(&moved);
            if new_cost.is_finite() && new_cost < cost {
                let largest = step.iter().fold(0.0_f64, |a, b| a.max(b.abs()));
                accepted = Some((moved, new_cost, largest));
                break;
            }
            lambda *= 5.0;
        }
        let Some((moved, new_cost, largest)) = accepted else {
            report.termination = Termination::NoDecrease;
            break;
        };
        let decrease = (cost - new_cost) / cost.max(1e-300);
        *state = moved;
        cost = new_cost;
        lambda = (lambda / 3.0).max(1e-12);
        report.iterations += 1;
        if decrease < options.tolerance {
            report.termination = Termination::Converged;
            break;
        }
        if largest <= options.step_tolerance {
            report.termination = Termination::SmallStep;
            break;
        }
    }
    report.final_cost = cost;
    Ok(report)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_batched_cauchy_sum_is_the_sum_of_the_losses() {
        let c = 2.5;
        let rho = |e2: f64| 0.5 * c * c * (1.0 + e2 / (c * c)).ln();
        // Many small residuals, some huge ones (each closes a batch), one past the limit alone.
        let mut s = 7u64;
        let mut e2s: Vec<f64> = (0..100_000)
            .map(|_| {
                s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
                ((s >> 11) as f64 / (1u64 << 53) as f64 * 20.0).powi(2)
            })
            .collect();
        e2s.extend([1e12, 1e200, 0.0, 3.0, 1e6]);
        let mut sum = CauchySum::new(c);
        for &e2 in &e2s {
            sum.add(e2);
        }
        let plain: f64 = e2s.iter().map(|&e2| rho(e2)).sum();
        assert!(
            (sum.total() - plain).abs() <= 1e-12 * plain,
            "{} vs {plain}",
            sum.total()
        );
        assert_eq!(CauchySum::new(c).total(), 0.0);
        let mut nan = CauchySum::new(c);
        nan.add(1.0);
        nan.add(f64::NAN);
        nan.add(1.0);
        assert!(nan.total().is_nan(), "a NaN term is not hidden");
    }

    /// Rosenbrock as residuals (1 − x, 10(y − x²)), solved by the core with a dense 2×2 solve.
    struct Rosenbrock {
        h: [[f64; 2]; 2],
        g: [f64; 2],
    }

    impl LeastSquares for Rosenbrock {
        type State = [f64; 2];
        fn n_params(&self) -> usize {
            2
        }
        fn cost(&self, s: &[f64; 2]) -> f64 {
            0.5 * ((1.0 - s[0]).powi(2) + (10.0 * (s[1] - s[0] * s[0])).powi(2))
        }
        fn linearize(&mut self, s: &[f64; 2]) -> Result<()> {
            let r = [1.0 - s[0], 10.0 * (s[1] - s[0] * s[0])];
            let j = [[-1.0, 0.0], [-20.0 * s[0], 10.0]];
            for a in 0..2 {
                self.g[a] = j[0][a] * r[0] + j[1][a] * r[1];
                for b in 0..2 {
                    self.h[a][b] = j[0][a] * j[0][b] + j[1][a] * j[1][b];
                }
            }
            Ok(())
        }
        fn solve(&mut self, lambda: f64) -> Result<Option<Vec<f64>>> {
            let a = self.h[0][0] * (1.0 + lambda);
            let d = self.h[1][1] * (1.0 + lambda);
            let (b, det) = (self.h[0][1], a * d - self.h[0][1] * self.h[0][1]);
            if det <= 0.0 {
                return Ok(None);
            }
            Ok(Some(vec![
                -(d * self.g[0] - b * self.g[1]) / det,
                -(a * self.g[1] - b * self.g[0]) / det,
            ]))
        }
        fn apply(&self, s: &[f64; 2], step: &[f64]) -> [f64; 2] {
            [s[0] + step[0], s[1] + step[1]]
        }
    }

    #[test]
    fn minimises_rosenbrock_and_says_why_it_stopped() {
        let mut p = Rosenbrock {
            h: [[0.0; 2]; 2],
            g: [0.0; 2],
        };
        let mut s = [-1.2, 1.0];
        let r = minimize(&mut p, &mut s, &LmOptions::default()).unwrap();
        assert!(
            (s[0] - 1.0).abs() < 1e-6 && (s[1] - 1.0).abs() < 1e-6,
            "{s:?}"
        );
        assert!(r.termination.converged() && r.final_cost < r.initial_cost);
        let mut s = [-1.2, 1.0];
        let options = LmOptions {
            max_iterations: 2,
            ..LmOptions::default()
        };
        let r = minimize(&mut p, &mut s, &options).unwrap();
        assert_eq!(r.termination, Termination::IterationLimit);
        assert_eq!(r.iterations, 2);
    }

    /// A step tolerance stops at the first step that moves no parameter by more than it, and
    /// reports it as converged; the same start without it runs on to the cost's minimum.
    #[test]
    fn a_small_step_stops_the_descent() {
        let mut p = Rosenbrock {
            h: [[0.0; 2]; 2],
            g: [0.0; 2],
        };
        let mut full = [-1.2, 1.0];
        let whole = minimize(&mut p, &mut full, &LmOptions::default()).unwrap();
        assert!(
            whole.termination.converged() && whole.termination != Termination::SmallStep,
            "{whole:?}"
        );
        // Stop once the steps shrink below 1e-3: before the minimum, after some steps.
        let mut s = [-1.2, 1.0];
        let options = LmOptions {
            step_tolerance: 1e-3,
            ..LmOptions::default()
        };
        let r = minimize(&mut p, &mut s, &options).unwrap();
        assert_eq!(r.termination, Termination::SmallStep);
        assert!(r.termination.converged());
        assert!(
            r.iterations > 1 && r.iterations < whole.iterations,
            "{} of {}",
            r.iterations,
            whole.iterations
        );
        // Within a few steps' length of the minimum, and not at it to 1e-9.
        let off = ((s[0] - 1.0).powi(2) + (s[1] - 1.0).powi(2)).sqrt();
        assert!(off < 1e-2 && off > 0.0, "{s:?}");
        assert!(r.final_cost >= whole.final_cost);
    }
}
