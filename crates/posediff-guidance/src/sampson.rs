//! The GGS objective: mean Sampson error of the valid matches under the decoded cameras, and its
//! analytic gradient with respect to the 9-D pose encodings (PoseDiffusion
//! `compute_sampson_distance`).
//!
//! Forward, per iteration:
//! 1. decode every frame (`T`, non-unit quaternion → `R = I + s·M(q)`, `s = 2/|q|²`,
//!    `f = clamp(exp(x + 1.8), 0.1, 20)`), replace every focal by the per-axis **mean**;
//! 2. OpenCV cameras of the `W×H` image (`R_cv = D Rᵀ`, `t_cv = D T`, `D = diag(−1, −1, 1)`,
//!    `K` with `f·min(W,H)/2` and principal point `(W/2, H/2)`);
//! 3. per ordered pair `(a, b)`: `R₁₂ = R_b R_aᵀ`, `t₁₂ = t_b − R₁₂ t_a`, `E = R₁₂ [−R₁₂ᵀ t₁₂]ₓ`,
//!    `F = K⁻ᵀ E K⁻¹`;
//! 4. Sampson error per match; matches with error `≥ sampson_max` (or NaN) are dropped; the
//!    loss is the mean of the rest.
//!
//! Backward: `∂s/∂F` per match is summed per pair (`G_F`), then the chain rule runs through
//! `F = AᵀEA` (`A = K⁻¹`, shared), `E`, the relative pose, the axis flip, the quaternion formula,
//! the mean focal and the clamp (zero gradient outside `[0.1, 20]`). Everything is `f64`.
//!
//! Matches are evaluated per pair in parallel (rayon) when there are enough of them; all buffers
//! are allocated once, in [`SampsonObjective::new`].

use nalgebra::{Matrix3, Vector3};
use posediff_geometry::encoding::{FOCAL_MAX_NDC, FOCAL_MIN_NDC, LOG_FOCAL_BIAS};
use posediff_geometry::epipolar::skew;
use posediff_geometry::pytorch3d::axis_flip;
use posediff_geometry::{ImageSize, PoseEncoding};
use rayon::prelude::*;

use crate::error::{GuidanceError, Result};
use crate::matches::MatchSet;

/// Below this many matches the pairs are evaluated on the calling thread: rayon's fork-join
/// overhead (a few µs) would dominate.
const PARALLEL_MIN_MATCHES: usize = 4096;

/// The official "print" value clamps Sampson errors at this many px² (`clamp(max=10)`).
pub const PRINT_CLAMP_PX2: f64 = 10.0;

/// Which parts of the encoding receive gradient: the official `update_R`, `update_T`,
/// `update_FL` (the others are detached, so their gradient is zero).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UpdateMask {
    /// Quaternion entries 3..7.
    pub rotation: bool,
    /// Translation entries 0..3.
    pub translation: bool,
    /// Log-focal entries 7..9.
    pub focal: bool,
}

impl UpdateMask {
    /// Everything.
    pub const ALL: Self = Self {
        rotation: true,
        translation: true,
        focal: true,
    };
    /// Focal lengths only.
    pub const FOCAL: Self = Self {
        rotation: false,
        translation: false,
        focal: true,
    };
    /// Rotations only.
    pub const ROTATION: Self = Self {
        rotation: true,
        translation: false,
        focal: false,
    };
    /// Translations only.
    pub const TRANSLATION: Self = Self {
        rotation: false,
        translation: true,
        focal: false,
    };
}

/// The value of the objective at one point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Evaluation {
    /// Mean of the valid Sampson errors (px²); NaN-free: 0 when nothing is valid.
    pub loss: f64,
    /// Number of valid matches (Sampson error `< sampson_max`).
    pub n_valid: usize,
    /// Mean over all matches of `min(sampson, 10)`, the value the official code prints.
    pub print_mean: f64,
}

/// One decoded frame.
#[derive(Debug, Clone, Copy)]
struct Frame {
    q: [f64; 4],
    s: f64,
    r_cv: Matrix3<f64>,
    t_cv: Vector3<f64>,
    focal: [f64; 2],
    /// `d focal / d log-focal`, 0 where the clamp is active.
    focal_slope: [f64; 2],
}

/// Sums over the matches of one pair.
#[derive(Debug, Clone, Copy, Default)]
struct PairSums {
    loss: f64,
    n_valid: usize,
    print: f64,
    /// `Σ_valid ∂s/∂F`, row-major.
    grad_f: [f64; 9],
}

/// The GGS objective for a fixed set of matches, with its buffers.
#[derive(Debug, Clone)]
pub struct SampsonObjective<'m> {
    matches: &'m MatchSet,
    sampson_max: f64,
    /// Half the shorter side: NDC → px.
    ndc_scale: f64,
    center: [f64; 2],
    frames: Vec<Frame>,
    /// `A = K⁻¹` at the last evaluation.
    k_inv: Matrix3<f64>,
    mean_focal_px: [f64; 2],
    pair_f: Vec<Matrix3<f64>>,
    pair_sums: Vec<PairSums>,
    grad_r_cv: Vec<Matrix3<f64>>,
    grad_t_cv: Vec<Vector3<f64>>,
    n_valid: usize,
}

/// Sampson error of one match and whether it counts.
#[inline(always)]
fn match_terms(f: &[f64; 9], u1: f64, v1: f64, u2: f64, v2: f64) -> (f64, f64, f64, f64, f64, f64) {
    let l2x = f[0] * u1 + f[1] * v1 + f[2];
    let l2y = f[3] * u1 + f[4] * v1 + f[5];
    let l2z = f[6] * u1 + f[7] * v1 + f[8];
    let l1x = f[0] * u2 + f[3] * v2 + f[6];
    let l1y = f[1] * u2 + f[4] * v2 + f[7];
    let e = u2 * l2x + v2 * l2y + l2z;
    let d = l2x * l2x + l2y * l2y + l1x * l1x + l1y * l1y;
    (e, d, l2x, l2y, l1x, l1y)
}

/// Lane accumulators of [`pair_sums`]: one partial sum per SIMD lane, so that the loop has
/// no loop-carried dependency on a single register and vectorises without reassociation.
struct Lanes<const L: usize> {
    loss: [f64; L],
    n_valid: [f64; L],
    print: [f64; L],
    grad_f: [[f64; L]; 9],
}

impl<const L: usize> Lanes<L> {
    fn new() -> Self {
        Self {
            loss: [0.0; L],
            n_valid: [0.0; L],
            print: [0.0; L],
            grad_f: [[0.0; L]; 9],
        }
    }

    /// Adds `L` matches, branch-free.
    #[inline(always)]
    fn add(&mut self, f: &[f64; 9], m: (&[f64; L], &[f64; L], &[f64; L], &[f64; L]), max: f64) {
        let (u1, v1, u2, v2) = m;
        for l in 0..L {
            let (a1, b1, a2, b2) = (u1[l], v1[l], u2[l], v2[l]);
            let (e, d, l2x, l2y, l1x, l1y) = match_terms(f, a1, b1, a2, b2);
            let inv_d = 1.0 / d;
            let s = e * e * inv_d;
            self.print[l] += s.min(PRINT_CLAMP_PX2);
            // `s < max` is false for NaN (d = 0): such matches are dropped, as officially.
            let valid = s < max;
            self.loss[l] += if valid { s } else { 0.0 };
            self.n_valid[l] += if valid { 1.0 } else { 0.0 };
            // ∂s/∂F_ij = a x2_i x1_j + b (l2_i x1_j [i<2] + x2_i l1_j [j<2]),
            // a = 2e/d, b = −2e²/d² = −2s/d.
            let a = if valid { 2.0 * e * inv_d } else { 0.0 };
            let b = if valid { -2.0 * s * inv_d } else { 0.0 };
            let c0 = a * a2 + b * l2x;
            let c1 = a * b2 + b * l2y;
            let (p0, p1) = (b * l1x, b * l1y);
            let g = &mut self.grad_f;
            g[0][l] += c0 * a1 + a2 * p0;
            g[1][l] += c0 * b1 + a2 * p1;
            g[2][l] += c0;
            g[3][l] += c1 * a1 + b2 * p0;
            g[4][l] += c1 * b1 + b2 * p1;
            g[5][l] += c1;
            g[6][l] += a * a1 + p0;
            g[7][l] += a * b1 + p1;
            g[8][l] += a;
        }
    }

    fn reduce_into(&self, out: &mut PairSums) {
        for l in 0..L {
            out.loss += self.loss[l];
            out.n_valid += self.n_valid[l] as usize;
            out.print += self.print[l];
            for (o, g) in out.grad_f.iter_mut().zip(&self.grad_f) {
                *o += g[l];
            }
        }
    }
}

/// SIMD width the kernel is written for (4 × f64 = one AVX2 register).
const LANES: usize = 8;

/// Sums the Sampson errors of one pair's matches and their gradient with respect to `F`.
#[inline(always)]
fn pair_sums_generic(f: &[f64; 9], m: (&[f64], &[f64], &[f64], &[f64]), max: f64) -> PairSums {
    let (u1, u1_tail) = m.0.as_chunks::<LANES>();
    let (v1, v1_tail) = m.1.as_chunks::<LANES>();
    let (u2, u2_tail) = m.2.as_chunks::<LANES>();
    let (v2, v2_tail) = m.3.as_chunks::<LANES>();
    let mut lanes = Lanes::<LANES>::new();
    for (((a1, b1), a2), b2) in u1.iter().zip(v1).zip(u2).zip(v2) {
        lanes.add(f, (a1, b1, a2, b2), max);
    }
    let mut tail = Lanes::<1>::new();
    for (((a1, b1), a2), b2) in u1_tail.iter().zip(v1_tail).zip(u2_tail).zip(v2_tail) {
        tail.add(f, (&[*a1], &[*b1], &[*a2], &[*b2]), max);
    }
    let mut out = PairSums::default();
    lanes.reduce_into(&mut out);
    tail.reduce_into(&mut out);
    out
}

/// [`pair_sums_generic`] compiled for AVX2 + FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn pair_sums_avx2(f: &[f64; 9], m: (&[f64], &[f64], &[f64], &[f64]), max: f64) -> PairSums {
    pair_sums_generic(f, m, max)
}

/// [`pair_sums_generic`] compiled for AVX-512 (8 × f64 per register).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2,fma")]
fn pair_sums_avx512(f: &[f64; 9], m: (&[f64], &[f64], &[f64], &[f64]), max: f64) -> PairSums {
    pair_sums_generic(f, m, max)
}

/// Sums the Sampson errors of one pair's matches and their gradient with respect to `F`,
/// with the widest instruction set the CPU has.
#[allow(unsafe_code)]
fn pair_sums(f: &[f64; 9], m: (&[f64], &[f64], &[f64], &[f64]), max: f64) -> PairSums {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512vl")
        && std::arch::is_x86_feature_detected!("avx512dq")
        && std::arch::is_x86_feature_detected!("fma")
    {
        // SAFETY: `pair_sums_avx512` requires exactly the features detected here.
        return unsafe { pair_sums_avx512(f, m, max) };
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: `pair_sums_avx2` only requires AVX2 and FMA, which were just detected on
        // this CPU. This is the crate's only unsafe code: runtime SIMD dispatch.
        return unsafe { pair_sums_avx2(f, m, max) };
    }
    pair_sums_generic(f, m, max)
}

fn row_major(m: &Matrix3<f64>) -> [f64; 9] {
    [
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
    ]
}

/// The relative pose of a pair and its essential matrix in the official form
/// `R₁₂ [−R₁₂ᵀ t₁₂]ₓ`.
fn pair_pose(frames: &[Frame], a: usize, b: usize) -> (Matrix3<f64>, Vector3<f64>, Matrix3<f64>) {
    let (fa, fb) = (&frames[a], &frames[b]);
    let r12 = fb.r_cv * fa.r_cv.transpose();
    let t12 = fb.t_cv - r12 * fa.t_cv;
    let e = r12 * skew(&(-(r12.transpose() * t12)));
    (r12, t12, e)
}

/// `M(q)` of `R = I + s M(q)` (PyTorch3D `quaternion_to_matrix`, `q = (r, i, j, k)`).
fn quaternion_m(q: &[f64; 4]) -> Matrix3<f64> {
    let [r, i, j, k] = *q;
    Matrix3::new(
        -(j * j + k * k),
        i * j - k * r,
        i * k + j * r,
        i * j + k * r,
        -(i * i + k * k),
        j * k - i * r,
        i * k - j * r,
        j * k + i * r,
        -(i * i + j * j),
    )
}

/// `∂M/∂q_c` for `c = r, i, j, k`.
fn quaternion_m_derivatives(q: &[f64; 4]) -> [Matrix3<f64>; 4] {
    let [r, i, j, k] = *q;
    [
        Matrix3::new(0.0, -k, j, k, 0.0, -i, -j, i, 0.0),
        Matrix3::new(0.0, j, k, j, -2.0 * i, -r, k, r, -2.0 * i),
        Matrix3::new(-2.0 * j, i, r, i, 0.0, k, -r, k, -2.0 * j),
        Matrix3::new(-2.0 * k, -r, i, r, -2.0 * k, j, i, j, 0.0),
    ]
}

/// `vee` of the gradient of a skew matrix: `∂L/∂w` for `W = [w]ₓ`.
fn skew_gradient(g: &Matrix3<f64>) -> Vector3<f64> {
    Vector3::new(
        g[(2, 1)] - g[(1, 2)],
        g[(0, 2)] - g[(2, 0)],
        g[(1, 0)] - g[(0, 1)],
    )
}

impl<'m> SampsonObjective<'m> {
    /// The objective for `matches` in images of `image_size` (the official pipeline: 224×224).
    ///
    /// # Errors
    /// A non-positive or NaN `sampson_max`.
    pub fn new(matches: &'m MatchSet, image_size: ImageSize, sampson_max: f64) -> Result<Self> {
        if sampson_max.is_nan() || sampson_max <= 0.0 {
            return Err(GuidanceError::InvalidConfig {
                reason: "sampson_max must be positive",
            });
        }
        let n = matches.n_frames();
        let p = matches.groups().len();
        let (w, h) = (
            f64::from(image_size.width()),
            f64::from(image_size.height()),
        );
        let empty = Frame {
            q: [1.0, 0.0, 0.0, 0.0],
            s: 2.0,
            r_cv: Matrix3::identity(),
            t_cv: Vector3::zeros(),
            focal: [1.0, 1.0],
            focal_slope: [0.0, 0.0],
        };
        Ok(Self {
            matches,
            sampson_max,
            ndc_scale: w.min(h) / 2.0,
            center: [w / 2.0, h / 2.0],
            frames: vec![empty; n],
            k_inv: Matrix3::identity(),
            mean_focal_px: [1.0, 1.0],
            pair_f: vec![Matrix3::zeros(); p],
            pair_sums: vec![PairSums::default(); p],
            grad_r_cv: vec![Matrix3::zeros(); n],
            grad_t_cv: vec![Vector3::zeros(); n],
            n_valid: 0,
        })
    }

    /// The matches this objective evaluates.
    pub fn matches(&self) -> &MatchSet {
        self.matches
    }

    fn decode(&mut self, encodings: &[PoseEncoding]) -> Result<()> {
        if encodings.len() != self.frames.len() {
            return Err(GuidanceError::LengthMismatch {
                what: "encodings vs frames of the matches",
                left: encodings.len(),
                right: self.frames.len(),
            });
        }
        let flip = axis_flip();
        let mut sum = [0.0; 2];
        for (frame, enc) in self.frames.iter_mut().zip(encodings) {
            let x = &enc.0;
            if !x.iter().all(|v| v.is_finite()) {
                return Err(GuidanceError::NonFinite {
                    what: "pose encoding",
                });
            }
            let q = [x[3], x[4], x[5], x[6]];
            let n2: f64 = q.iter().map(|v| v * v).sum();
            if n2 == 0.0 {
                return Err(posediff_geometry::GeometryError::ZeroQuaternion.into());
            }
            let s = 2.0 / n2;
            let r = Matrix3::identity() + quaternion_m(&q) * s;
            frame.q = q;
            frame.s = s;
            frame.r_cv = flip * r.transpose();
            frame.t_cv = flip * Vector3::new(x[0], x[1], x[2]);
            for axis in 0..2 {
                let raw = (x[7 + axis] + LOG_FOCAL_BIAS).exp();
                frame.focal[axis] = raw.clamp(FOCAL_MIN_NDC, FOCAL_MAX_NDC);
                frame.focal_slope[axis] = if (FOCAL_MIN_NDC..=FOCAL_MAX_NDC).contains(&raw) {
                    raw
                } else {
                    0.0
                };
                sum[axis] += frame.focal[axis];
            }
        }
        let n = self.frames.len() as f64;
        self.mean_focal_px = [sum[0] / n * self.ndc_scale, sum[1] / n * self.ndc_scale];
        let [fx, fy] = self.mean_focal_px;
        let [cx, cy] = self.center;
        self.k_inv = Matrix3::new(
            1.0 / fx,
            0.0,
            -cx / fx,
            0.0,
            1.0 / fy,
            -cy / fy,
            0.0,
            0.0,
            1.0,
        );
        Ok(())
    }

    /// Evaluates the objective at `encodings` (one per frame) and keeps what
    /// [`Self::gradient`] needs.
    ///
    /// # Errors
    /// Wrong number of encodings, non-finite values, a zero quaternion.
    pub fn evaluate(&mut self, encodings: &[PoseEncoding]) -> Result<Evaluation> {
        self.decode(encodings)?;
        let a = self.k_inv;
        for (g, f) in self.matches.groups().iter().zip(self.pair_f.iter_mut()) {
            let (_, _, e) = pair_pose(&self.frames, g.first, g.second);
            *f = a.transpose() * e * a;
        }
        let m = self.matches;
        let max = self.sampson_max;
        let work = |(g, (f, out)): (&crate::matches::PairGroup, (&Matrix3<f64>, &mut PairSums))| {
            let r = g.start..g.end;
            *out = pair_sums(
                &row_major(f),
                (
                    &m.u1[r.clone()],
                    &m.v1[r.clone()],
                    &m.u2[r.clone()],
                    &m.v2[r],
                ),
                max,
            );
        };
        if m.len() >= PARALLEL_MIN_MATCHES {
            m.groups()
                .par_iter()
                .zip(self.pair_f.par_iter().zip(self.pair_sums.par_iter_mut()))
                .for_each(work);
        } else {
            m.groups()
                .iter()
                .zip(self.pair_f.iter().zip(self.pair_sums.iter_mut()))
                .for_each(work);
        }
        let (mut loss, mut n_valid, mut print) = (0.0, 0, 0.0);
        for s in &self.pair_sums {
            loss += s.loss;
            n_valid += s.n_valid;
            print += s.print;
        }
        self.n_valid = n_valid;
        Ok(Evaluation {
            loss: if n_valid > 0 {
                loss / n_valid as f64
            } else {
                0.0
            },
            n_valid,
            print_mean: if m.is_empty() {
                0.0
            } else {
                print / m.len() as f64
            },
        })
    }

    /// The gradient of the loss of the last [`Self::evaluate`] with respect to the encodings,
    /// written into `grad` (one row of 9 per frame), zero where `mask` detaches. All zero when no
    /// match was valid.
    ///
    /// # Errors
    /// `grad` of the wrong length.
    pub fn gradient(&mut self, mask: UpdateMask, grad: &mut [[f64; 9]]) -> Result<()> {
        let n = self.frames.len();
        if grad.len() != n {
            return Err(GuidanceError::LengthMismatch {
                what: "gradient rows vs frames",
                left: grad.len(),
                right: n,
            });
        }
        for row in grad.iter_mut() {
            *row = [0.0; 9];
        }
        if self.n_valid == 0 {
            return Ok(());
        }
        let inv_valid = 1.0 / self.n_valid as f64;
        self.grad_r_cv.fill(Matrix3::zeros());
        self.grad_t_cv.fill(Vector3::zeros());
        let a = self.k_inv;
        let mut grad_a = Matrix3::zeros();
        for (p, g) in self.matches.groups().iter().enumerate() {
            let gf = Matrix3::from_row_slice(&self.pair_sums[p].grad_f) * inv_valid;
            let (r12, t12, e) = pair_pose(&self.frames, g.first, g.second);
            // F = Aᵀ E A.
            let ge = a * gf * a.transpose();
            grad_a += e * a * gf.transpose() + e.transpose() * a * gf;
            // E = R₁₂ W, W = [w]ₓ, w = −R₁₂ᵀ t₁₂.
            let w = -(r12.transpose() * t12);
            let mut g_r12 = ge * skew(&w).transpose();
            let g_w = skew_gradient(&(r12.transpose() * ge));
            g_r12 -= t12 * g_w.transpose();
            let g_t12 = -(r12 * g_w);
            // t₁₂ = t_b − R₁₂ t_a.
            let (fa, fb) = (self.frames[g.first], self.frames[g.second]);
            self.grad_t_cv[g.second] += g_t12;
            self.grad_t_cv[g.first] -= r12.transpose() * g_t12;
            g_r12 -= g_t12 * fa.t_cv.transpose();
            // R₁₂ = R_b R_aᵀ.
            self.grad_r_cv[g.second] += g_r12 * fa.r_cv;
            self.grad_r_cv[g.first] += g_r12.transpose() * fb.r_cv;
        }
        let flip = axis_flip();
        for (i, row) in grad.iter_mut().enumerate() {
            let frame = &self.frames[i];
            if mask.translation {
                let g_t = flip * self.grad_t_cv[i];
                row[..3].copy_from_slice(g_t.as_slice());
            }
            if mask.rotation {
                // R_cv = D Rᵀ  ⇒  ∂L/∂R = (D G_cv)ᵀ; R = I + s M(q), s = 2/|q|².
                let g_r = (flip * self.grad_r_cv[i]).transpose();
                let m = quaternion_m(&frame.q);
                let g_m = g_r.dot(&m);
                let dm = quaternion_m_derivatives(&frame.q);
                for c in 0..4 {
                    let ds = -frame.s * frame.s * frame.q[c];
                    row[3 + c] = ds * g_m + frame.s * g_r.dot(&dm[c]);
                }
            }
        }
        if mask.focal {
            // A = K⁻¹: A00 = 1/fx, A02 = −cx/fx (likewise y); fx = mean focal · ndc_scale.
            let [fx, fy] = self.mean_focal_px;
            let [cx, cy] = self.center;
            let g_fx = (-grad_a[(0, 0)] + grad_a[(0, 2)] * cx) / (fx * fx);
            let g_fy = (-grad_a[(1, 1)] + grad_a[(1, 2)] * cy) / (fy * fy);
            let per_frame = [
                g_fx * self.ndc_scale / n as f64,
                g_fy * self.ndc_scale / n as f64,
            ];
            for (row, frame) in grad.iter_mut().zip(&self.frames) {
                for axis in 0..2 {
                    row[7 + axis] = per_frame[axis] * frame.focal_slope[axis];
                }
            }
        }
        Ok(())
    }

    /// The Sampson error of every match, in the caller's order, at `encodings` (diagnostics and
    /// tests; allocates).
    ///
    /// # Errors
    /// As [`Self::evaluate`].
    pub fn sampson_errors(&mut self, encodings: &[PoseEncoding]) -> Result<Vec<f64>> {
        self.evaluate(encodings)?;
        let m = self.matches;
        let mut out = vec![0.0; m.len()];
        for (g, f) in m.groups().iter().zip(&self.pair_f) {
            let f = row_major(f);
            for k in g.start..g.end {
                let (e, d, ..) = match_terms(&f, m.u1[k], m.v1[k], m.u2[k], m.v2[k]);
                out[m.original_index()[k]] = e * e / d;
            }
        }
        Ok(out)
    }
}
