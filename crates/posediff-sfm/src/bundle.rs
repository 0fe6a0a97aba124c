//! Bundle adjustment with tracks: the cameras, the shared focal and triangulated points refined
//! together on reprojection errors (the last stage of the mapper).
//!
//! 1. Each track ([`crate::tracks`]) is triangulated (linear, from normalised rays, by a faer
//!    SVD) from the estimated cameras; points behind a camera, with a widest ray angle below
//!    `min_angle_deg` or observations farther than `max_error_px` from their projections are
//!    left out.
//! 2. Levenberg–Marquardt ([`crate::lm`]) on the reprojection errors (Cauchy loss), with the
//!    points eliminated by the Schur complement: the reduced camera system is a sparse block
//!    system (6 per camera, 1 for the focal; a block wherever two cameras see a common point)
//!    whose symbolic Cholesky factorisation is computed once per adjustment. Gauge as in
//!    [`crate::camera`] (points rescaled with the centres).
//! 3. Observations off by more than `max_error_px` are dropped and the adjustment runs again.
//!
//! Jacobians are analytic: `x_c = exp(ω) R (X − C)` gives `∂x_c/∂ω = −[x_c]ₓ`,
//! `∂x_c/∂C = −R`, `∂x_c/∂X = R`, and `∂uv/∂log φ = uv − pp`.
//!
//! [`adjust_lens`] adds each camera group's radial coefficients (COLMAP's SIMPLE_RADIAL and
//! RADIAL: `uv = pp + f x (1 + k₁ r² + k₂ r⁴)` with `x = x_c / z_c`, `r = |x|`, on the photos'
//! own pixels), one more block of the reduced system per group (one or two coefficients):
//! `∂uv/∂x = f ((1 + k₁ r² + k₂ r⁴) I + (2 k₁ + 4 k₂ r²) x xᵀ)`, `∂uv/∂k₁ = f r² x` and
//! `∂uv/∂k₂ = f r⁴ x`.

use std::collections::HashMap;

use nalgebra::{Matrix2, Matrix3, SMatrix, SVector, Vector2, Vector3};
use posediff_geometry::lens::{
    FISHEYE_PINHOLE, brown_coefficient_jacobian, distort_brown, distort_fisheye,
    fisheye_coefficient_jacobian,
};
use rayon::prelude::*;

use crate::camera::{CameraPose, ParameterLayout, gauge_scale};
use crate::error::Result;
use crate::intrinsics::ImageIntrinsics;
use crate::linalg::{BlockSystem, BlockValues, Solver};
use crate::lm::{CauchySum, LeastSquares, LmOptions, LmReport, Termination, minimize};
use crate::sampson_refine::check_inputs;
use crate::tracks::{Observation, Track};

mod implicit_schur;
pub(crate) mod keyframes;
use implicit_schur::ImplicitSchur;
pub use keyframes::KeyframeOptions;

/// The reduced camera system solved by preconditioned conjugate gradients without forming it
/// (`bundle::implicit_schur`; Ceres' `ITERATIVE_SCHUR` with `SCHUR_JACOBI`), used when an
/// adjustment has at least `min_cameras` free cameras: memory linear in the observations,
/// for adjustments whose reduced system would not fit. Off by default
/// ([`BundleOptions::iterative`]): on the 1000-frame orbit its block-Jacobi preconditioner
/// left a few hundred conjugate-gradient iterations per solve (the orbit's long chain), and
/// the adjustment took 414 s against the sparse Cholesky's 39 s, for the same 65
/// Levenberg–Marquardt iterations and the same cameras (docs/BENCHMARKS.md, "An iterative
/// reduced solver").
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct IterativeSchurOptions {
    /// Free cameras from which the adjustment solves iteratively.
    pub min_cameras: usize,
    /// Relative residual `|r| / |b|` at which a solve stops (Ceres' `eta` forcing term).
    pub tolerance: f64,
    /// Conjugate-gradient iterations per solve.
    pub max_iterations: usize,
}

impl Default for IterativeSchurOptions {
    fn default() -> Self {
        Self {
            min_cameras: 500,
            tolerance: 1e-2,
            max_iterations: 500,
        }
    }
}

/// Bundle-adjustment settings.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct BundleOptions {
    /// Cauchy scale of the reprojection error, pixels.
    pub cauchy_px: f64,
    /// Observations farther than this from their projection are dropped (pixels).
    pub max_error_px: f64,
    /// Smallest widest-ray angle of a triangulated point, degrees.
    pub min_angle_deg: f64,
    /// Refine the shared focal factor.
    pub refine_focal: bool,
    /// Iterations per adjustment.
    pub max_iterations: usize,
    /// Converged when the relative cost decrease of a step is below this (Ceres' default
    /// `function_tolerance`). At 1e-10 the 300-frame orbit and forward walks took 140 and 136
    /// iterations (the last hundred each lowering the cost by 1e-6 to 1e-10, relatively); at
    /// 1e-6, 40 and 25, with the same cameras to 1e-4° in rotation and the same mAA(30)
    /// (docs/BENCHMARKS.md, "Video-scale speed", third session).
    pub tolerance: f64,
    /// Linear solver of the reduced camera system.
    pub solver: Solver,
    /// Observations kept per track, spread evenly over its images (in image order: the widest
    /// baselines of a video stay). The Schur complement costs `Σ k²` per iteration, so a dense
    /// video whose points are seen in hundreds of frames would otherwise make the adjustment
    /// grow with the square of the frames.
    pub max_track_length: usize,
    /// Images a track's kept observations span at most (in image order): a longer track is
    /// cut into consecutive segments of at most this span, each a point of its own with up to
    /// `max_track_length` observations spread over it. The reduced camera system couples two
    /// cameras wherever a point sees both, so tracks spanning hundreds of frames (a forward
    /// walk's points far ahead) make it dense: at 1000 forward frames the adjustment took 98 s
    /// and the camera split's 159 s. At 200 they take 18 s and 14 s, and the cameras are as
    /// close to the truth or closer (forward 1000: mean rotation error 0.016° against 0.017°,
    /// focal 9.6e-4 against 3.5e-3, mAA(30) 0.996 against 0.994; orbit 1000: 0.048° against
    /// 0.068°; forward 300: 0.0074° against 0.0086°); 100 was faster on the orbit but doubled
    /// the forward walk's rotation error (docs/BENCHMARKS.md, "Tracks cut into spans").
    /// Photo sets of fewer images than this are not affected.
    pub max_track_span: usize,
    /// The iterative solver of the reduced camera system for large adjustments (`None`, the
    /// default: the sparse Cholesky at every size; see [`IterativeSchurOptions`] for why).
    pub iterative: Option<IterativeSchurOptions>,
    /// Keyframe adjustment of large sets ([`KeyframeOptions`]; `None`: every camera adjusted
    /// jointly at every size).
    pub keyframes: Option<KeyframeOptions>,
}

impl Default for BundleOptions {
    fn default() -> Self {
        Self {
            cauchy_px: 1.0,
            max_error_px: 4.0,
            min_angle_deg: 1.0,
            refine_focal: true,
            max_iterations: 100,
            tolerance: 1e-6,
            solver: Solver::Sparse,
            max_track_length: 20,
            max_track_span: 200,
            iterative: None,
            keyframes: Some(KeyframeOptions::default()),
        }
    }
}

/// `obs` (one track, any order) in image order cut into consecutive segments spanning fewer
/// than `span` images each (a segment starts at its first image), each spread to at most
/// `max` observations; segments of one observation are left out.
fn segments(obs: Vec<Observation>, max: usize, span: usize) -> Vec<Vec<Observation>> {
    cut(obs, span).into_iter().map(|s| spread(s, max)).collect()
}

/// `obs` (one track, any order) in image order cut into consecutive segments spanning fewer
/// than `span` images each; segments of one observation are left out.
fn cut(mut obs: Vec<Observation>, span: usize) -> Vec<Vec<Observation>> {
    obs.sort_by_key(|o| o.image);
    let mut out = Vec::new();
    let mut start = 0;
    for k in 1..=obs.len() {
        if k == obs.len() || obs[k].image >= obs[start].image + span.max(1) {
            if k - start >= 2 {
                out.push(obs[start..k].to_vec());
            }
            start = k;
        }
    }
    out
}

/// At most `max` of `obs`, evenly spaced, the first and the last kept.
fn spread(obs: Vec<Observation>, max: usize) -> Vec<Observation> {
    let n = obs.len();
    if max < 2 || n <= max {
        return obs;
    }
    (0..max)
        .map(|i| obs[(i * (n - 1) + (max - 1) / 2) / (max - 1)])
        .collect()
}

/// What the adjustment did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct BundleReport {
    /// Tracks given.
    pub tracks: usize,
    /// Points triangulated and adjusted.
    pub points: usize,
    /// Observations used in the last adjustment, with those of the cameras refined alone
    /// ([`BundleOptions::keyframes`]).
    pub observations: usize,
    /// Accepted steps over both adjustments.
    pub iterations: usize,
    /// Why the last adjustment stopped.
    pub termination: Termination,
    /// Whether both adjustments stopped at a minimum (not at the iteration limit).
    pub converged: bool,
    /// RMS reprojection error of those observations at the end, pixels.
    pub rms_px: f64,
    /// Conjugate-gradient iterations over both adjustments (0: solved by the sparse Cholesky,
    /// [`BundleOptions::iterative`]).
    pub linear_iterations: usize,
    /// Iterative solves that stopped at their iteration limit before their tolerance.
    pub linear_unconverged: usize,
    /// The keyframe adjustment, when it was used ([`BundleOptions::keyframes`]).
    pub keyframes: Option<KeyframeReport>,
}

/// What the keyframe adjustment did (run.json's `bundle_keyframes`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct KeyframeReport {
    /// Cameras adjusted jointly with the points, promotions included.
    pub keyframes: usize,
    /// Of those, promoted: too few points to be refined alone, or a camera group's only one.
    pub promoted: usize,
    /// Cameras refined alone against the adjusted points.
    pub refined_alone: usize,
    /// Cameras left where they were: fewer than `keyframes.min_inliers` points within
    /// `max_error_px` of them.
    pub unrefined: usize,
}

/// A triangulated point with the observations it keeps.
#[derive(Debug, Clone, PartialEq)]
pub struct Point {
    /// World position.
    pub xyz: Vector3<f64>,
    /// Its observations in the joint adjustment.
    pub observations: Vec<Observation>,
    /// Its observations by cameras refined alone against it after the joint adjustment (the
    /// keyframe adjustment's other cameras, [`BundleOptions::keyframes`]; empty otherwise), in
    /// image order, each within `max_error_px` of its projection.
    pub alone: Vec<Observation>,
}

/// Projection of `x` by camera `c` with focal `f`, and the point in the camera frame; `None`
/// behind the camera.
pub fn project(
    c: &CameraPose,
    f: f64,
    pp: [f64; 2],
    x: &Vector3<f64>,
) -> Option<([f64; 2], Vector3<f64>)> {
    let xc = c.rotation * (x - c.center);
    (xc.z > 1e-12).then(|| ([f * xc.x / xc.z + pp[0], f * xc.y / xc.z + pp[1]], xc))
}

/// A camera's lens coefficients `[k₁, k₂, p₁, p₂]` (COLMAP's OPENCV, on `x_c / z_c`; RADIAL's
/// are `k₁, k₂` with `p₁ = p₂ = 0`, SIMPLE_RADIAL's `k` is `k₁` alone).
pub type LensCoefficients = [f64; 4];

/// No distortion.
pub const PINHOLE: LensCoefficients = [0.0; 4];

/// The distortion model of the [`LensCoefficients`] of an adjustment: Brown's polynomial
/// (COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV: `k₁, k₂, p₁, p₂`) or OpenCV's fisheye (COLMAP's
/// OPENCV_FISHEYE: `k₁…k₄` on `θ = atan r`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LensKind {
    /// `distort_brown`.
    #[default]
    Brown,
    /// `distort_fisheye`.
    Fisheye,
}

impl LensKind {
    /// The distorted normalised coordinates and their Jacobian.
    fn distort(self, k: LensCoefficients, u: f64, v: f64) -> (Vector2<f64>, Matrix2<f64>) {
        match self {
            Self::Brown => distort_brown(k, u, v),
            Self::Fisheye => distort_fisheye(k, u, v),
        }
    }

    /// `∂(u_d, v_d)/∂k`.
    fn coefficient_jacobian(self, u: f64, v: f64) -> SMatrix<f64, 2, 4> {
        match self {
            Self::Brown => brown_coefficient_jacobian(u, v),
            Self::Fisheye => fisheye_coefficient_jacobian(u, v),
        }
    }

    /// The coefficients that are (Brown: exactly; fisheye: to `θ⁹`) the pinhole projection: the
    /// start of an adjustment whose points come from pinhole cameras.
    pub fn pinhole(self) -> LensCoefficients {
        match self {
            Self::Brown => PINHOLE,
            Self::Fisheye => FISHEYE_PINHOLE,
        }
    }
}

/// [`project`] through a lens with coefficients `k` (COLMAP's OPENCV, on `x_c / z_c`; the
/// distortion is [`posediff_geometry::lens::distort_brown`], the one place lens models are
/// computed); [`PINHOLE`] is [`project`] exactly.
pub fn project_radial(
    c: &CameraPose,
    f: f64,
    pp: [f64; 2],
    k: LensCoefficients,
    x: &Vector3<f64>,
) -> Option<([f64; 2], Vector3<f64>)> {
    project_lens(c, f, pp, (LensKind::Brown, k), x)
}

/// [`project`] through a lens of either kind ([`project_radial`] for Brown's).
pub fn project_lens(
    c: &CameraPose,
    f: f64,
    pp: [f64; 2],
    (kind, k): (LensKind, LensCoefficients),
    x: &Vector3<f64>,
) -> Option<([f64; 2], Vector3<f64>)> {
    if kind == LensKind::Brown && k == PINHOLE {
        return project(c, f, pp, x);
    }
    let xc = c.rotation * (x - c.center);
    (xc.z > 1e-12).then(|| {
        let (d, _) = kind.distort(k, xc.x / xc.z, xc.y / xc.z);
        ([f * d.x + pp[0], f * d.y + pp[1]], xc)
    })
}

/// `∂uv/∂x_c` of the pinhole projection with focal `f` at `x_c`.
pub(crate) fn pinhole_jacobian(f: f64, xc: &Vector3<f64>) -> SMatrix<f64, 2, 3> {
    let iz = 1.0 / xc.z;
    SMatrix::<f64, 2, 3>::new(
        f * iz,
        0.0,
        -f * xc.x * iz * iz,
        0.0,
        f * iz,
        -f * xc.y * iz * iz,
    )
}

/// Linear triangulation from normalised rays (faer SVD); `None` when degenerate, behind a
/// camera or narrower than `min_angle` (radians).
pub fn triangulate(
    obs: &[Observation],
    cameras: &[Option<CameraPose>],
    intrinsics: &ImageIntrinsics,
    phi: f64,
    min_angle: f64,
) -> Option<Vector3<f64>> {
    let used: Vec<(&Observation, CameraPose)> = obs
        .iter()
        .filter_map(|o| cameras.get(o.image).copied().flatten().map(|c| (o, c)))
        .collect();
    if used.len() < 2 {
        return None;
    }
    let mut rays = Vec::with_capacity(used.len());
    let mut rows = Vec::with_capacity(used.len());
    for (o, c) in &used {
        let x = intrinsics.k_inverse(phi, o.image) * Vector3::new(o.xy[0], o.xy[1], 1.0);
        rows.push(([x.x, x.y], *c.rotation.matrix(), c.translation()));
        rays.push(c.rotation.inverse() * x.normalize());
    }
    let point = crate::points::dlt(&rows)?;
    let mut widest: f64 = 0.0;
    for (i, ri) in rays.iter().enumerate() {
        for rj in &rays[i + 1..] {
            widest = widest.max(ri.dot(rj).clamp(-1.0, 1.0).acos());
        }
    }
    let in_front = used
        .iter()
        .all(|(_, c)| (c.rotation * (point - c.center)).z > 0.0);
    (in_front && widest >= min_angle && point.iter().all(|v| v.is_finite())).then_some(point)
}

/// One observation's linearisation.
#[derive(Debug, Clone, Copy)]
struct ObservationLinearisation {
    image: usize,
    /// Its index among the point's observations.
    index: usize,
    /// `∂uv/∂[ω, δC]`.
    jc: SMatrix<f64, 2, 6>,
    /// `∂uv/∂log φ_g` of the image's group.
    jf: SVector<f64, 2>,
    /// `∂uv/∂[k₁, k₂, p₁, p₂]` of the group's lens coefficients.
    jk: SMatrix<f64, 2, 4>,
    /// `∂uv/∂X`.
    jp: SMatrix<f64, 2, 3>,
    r: SVector<f64, 2>,
    w: f64,
}

/// One point's linearisation: `C = Σ w J_pᵀJ_p`, `g_p`, and its observations.
#[derive(Debug, Clone)]
struct PointLinearisation {
    c: Matrix3<f64>,
    g: Vector3<f64>,
    obs: Vec<ObservationLinearisation>,
}

/// Cameras, each group's focal factor, each group's radial coefficients, points.
type State = (
    Vec<Option<CameraPose>>,
    Vec<f64>,
    Vec<LensCoefficients>,
    Vec<Vector3<f64>>,
);

/// Where each group's radial coefficients sit when they are refined: after the layout's
/// cameras and focals, one block of one (`k₁`) or two (`k₁, k₂`) parameters per free group.
#[derive(Debug, Clone, Default)]
struct LensLayout {
    /// Per group, the index of its `k₁` and how many coefficients are free (`None`: fixed).
    param: Vec<Option<(usize, usize)>>,
    /// Per group, its block (`None`: fixed).
    block: Vec<Option<usize>>,
}

impl LensLayout {
    /// The first `free[g]` (0, 1 or 2) coefficients of each group after `layout`'s parameters
    /// and blocks; returns the parameter count and the block sizes with them.
    fn new(layout: &ParameterLayout, free: &[usize]) -> (Self, usize, Vec<usize>) {
        let mut n_params = layout.n_params;
        let mut sizes = layout.block_sizes.clone();
        let mut lens = Self::default();
        for &m in free {
            let m = m.min(4);
            lens.param.push((m > 0).then_some((n_params, m)));
            lens.block.push((m > 0).then_some(sizes.len()));
            if m > 0 {
                n_params += m;
                sizes.push(m);
            }
        }
        (lens, n_params, sizes)
    }
}

/// The blocks of the reduced system one point touches (its free cameras and the free focals
/// and coefficients of their groups), and where their products live; fixed per adjustment.
#[derive(Debug, Clone, Default)]
struct PointBlocks {
    /// Per observation: its camera's, its group focal's and its group coefficient's entry in
    /// `entries` (`None`: fixed).
    obs: Vec<(Option<usize>, Option<usize>, Option<usize>)>,
    /// The distinct blocks touched.
    entries: Vec<usize>,
    /// The slot of each entry pair `(u, v)`, `v ≤ u`, at `u (u + 1) / 2 + v`.
    slots: Vec<usize>,
}

fn pair_index(u: usize, v: usize) -> usize {
    let (u, v) = (u.max(v), u.min(v));
    u * (u + 1) / 2 + v
}

impl PointBlocks {
    fn new(
        obs: &[Observation],
        intrinsics: &ImageIntrinsics,
        layout: &ParameterLayout,
        lens: &LensLayout,
    ) -> Self {
        let mut entries: Vec<usize> = Vec::new();
        let mut entry = |block: Option<usize>| {
            block.map(|b| match entries.iter().position(|&e| e == b) {
                Some(u) => u,
                None => {
                    entries.push(b);
                    entries.len() - 1
                }
            })
        };
        let obs = obs
            .iter()
            .map(|o| {
                let g = intrinsics.group[o.image];
                let camera = entry(layout.block[o.image]);
                let focal = entry(layout.focal_block[g]);
                let coefficient = entry(lens.block.get(g).copied().flatten());
                (camera, focal, coefficient)
            })
            .collect();
        Self {
            obs,
            entries,
            slots: Vec::new(),
        }
    }

    /// Every entry pair's block pair (for the pattern).
    fn block_pairs(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.entries
            .iter()
            .enumerate()
            .flat_map(move |(u, &a)| self.entries[..=u].iter().map(move |&b| (a, b)))
    }

    fn find_slots(&mut self, system: &BlockSystem) {
        self.slots = self
            .block_pairs()
            .map(|(a, b)| system.slot(a, b).unwrap_or(usize::MAX))
            .collect();
    }
}

/// The distinct block pairs of the points' [`PointBlocks::block_pairs`], sorted. A track of
/// `k` observations has `k(k+1)/2` of them: on the 1000-frame forward walk, tracks of up to
/// `max_track_span` (200) frames make tens of millions with repeats for some 10⁵ distinct
/// pairs, a transient list of hundreds of megabytes that was the run's peak memory. So the
/// list is sorted and deduplicated whenever it grows past twice its distinct pairs (plus a
/// million): it never holds much more than that, and the result is the same.
fn distinct_block_pairs(blocks: &[PointBlocks]) -> Vec<(usize, usize)> {
    distinct_pairs(blocks.iter().map(PointBlocks::block_pairs), 1 << 20)
}

/// The distinct pairs of `lists`, sorted, deduplicated whenever more than `slack` past twice
/// the distinct pairs so far ([`distinct_block_pairs`]).
fn distinct_pairs<I: IntoIterator<Item = (usize, usize)>>(
    lists: impl Iterator<Item = I>,
    slack: usize,
) -> Vec<(usize, usize)> {
    let mut pairs: Vec<(usize, usize)> = Vec::new();
    let mut distinct = 0;
    for list in lists {
        pairs.extend(list);
        if pairs.len() > 2 * distinct + slack {
            pairs.sort_unstable();
            pairs.dedup();
            distinct = pairs.len();
        }
    }
    pairs.sort_unstable();
    pairs.dedup();
    pairs
}

/// Points the Schur complement is split into ([`Problem::solve`]): enough runs for the
/// threads of a large machine, few enough that their copies of the reduced system stay small.
const SCHUR_PARTS: usize = 8;

/// A point's `C` damped as every solve of the reduced system damps it (`C_kk (1 + λ) + 1e-12`),
/// inverted; `None` when not invertible (more damping makes it so).
fn damped_inverse(c: &Matrix3<f64>, lambda: f64) -> Option<Matrix3<f64>> {
    let mut c = *c;
    for k in 0..3 {
        c[(k, k)] = c[(k, k)] * (1.0 + lambda) + 1e-12;
    }
    c.try_inverse()
}

/// Adds one observation's `E = J_uᵀ W J_p` and gradient `J_uᵀ W r` to its entries' `es`, `gs`
/// (`entries`: its camera's, focal's and lens coefficients' entry; rows beyond a block's
/// size are never read).
fn add_coupling(
    o: &ObservationLinearisation,
    (camera, focal, coefficient): (Option<usize>, Option<usize>, Option<usize>),
    es: &mut [SMatrix<f64, 6, 3>],
    gs: &mut [SVector<f64, 6>],
) {
    if let Some(u) = camera {
        es[u] += o.jc.transpose() * o.jp * o.w;
        gs[u] += o.jc.transpose() * o.r * o.w;
    }
    if let Some(v) = focal {
        let e = o.jf.transpose() * o.jp * o.w;
        for j in 0..3 {
            es[v][(0, j)] += e[(0, j)];
        }
        gs[v][0] += o.jf.dot(&o.r) * o.w;
    }
    if let Some(l) = coefficient {
        let e = o.jk.transpose() * o.jp * o.w;
        let g = o.jk.transpose() * o.r * o.w;
        for i in 0..4 {
            for j in 0..3 {
                es[l][(i, j)] += e[(i, j)];
            }
            gs[l][i] += g[i];
        }
    }
}

/// The reduced camera system of `linear`'s points at damping `lambda`, into a part of
/// `system`'s pattern, with each point's `C⁻¹`; `None` when a point's `C` is not invertible.
fn eliminate(
    system: &BlockSystem,
    linear: &[PointLinearisation],
    blocks: &[PointBlocks],
    lambda: f64,
) -> Option<(BlockValues, Vec<Matrix3<f64>>)> {
    let mut part = system.zero_part();
    let mut inverses = Vec::with_capacity(linear.len());
    // Per entry of a point: E = Σ J_uᵀ W J_p (rows beyond the block's size unused), E C⁻¹
    // and the gradient; buffers reused from point to point.
    let mut es: Vec<SMatrix<f64, 6, 3>> = Vec::new();
    let mut ecs: Vec<SMatrix<f64, 6, 3>> = Vec::new();
    let mut gs: Vec<SVector<f64, 6>> = Vec::new();
    // Per point: the direct terms J_uᵀ W J_v of each observation, then minus the point's
    // elimination, S = A − Σ E C⁻¹ Eᵀ and rhs = −g + Σ E C⁻¹ g_p, each lower block once.
    for (lin, blocks) in linear.iter().zip(blocks) {
        let c_inv = damped_inverse(&lin.c, lambda)?;
        let entries = blocks.entries.len();
        es.clear();
        es.resize(entries, SMatrix::zeros());
        gs.clear();
        gs.resize(entries, SVector::zeros());
        for o in &lin.obs {
            let (camera, focal, coefficient) = blocks.obs[o.index];
            add_coupling(o, (camera, focal, coefficient), &mut es, &mut gs);
            if let Some(u) = camera {
                let h = o.jc.transpose() * o.jc * o.w;
                let b = blocks.entries[u];
                system.add_block_in(&mut part, blocks.slots[pair_index(u, u)], b, b, |i, j| {
                    h[(i, j)]
                });
            }
            if let Some(v) = focal {
                let h = o.jf.norm_squared() * o.w;
                let b = blocks.entries[v];
                system.add_block_in(&mut part, blocks.slots[pair_index(v, v)], b, b, |_, _| h);
                if let Some(u) = camera {
                    let h = o.jf.transpose() * o.jc * o.w;
                    let bu = blocks.entries[u];
                    system.add_block_in(
                        &mut part,
                        blocks.slots[pair_index(u, v)],
                        b,
                        bu,
                        |_, j| h[(0, j)],
                    );
                }
            }
            if let Some(l) = coefficient {
                // Rows beyond the block's size (k₂ of a SIMPLE_RADIAL block) are never read.
                let h = o.jk.transpose() * o.jk * o.w;
                let b = blocks.entries[l];
                system.add_block_in(&mut part, blocks.slots[pair_index(l, l)], b, b, |i, j| {
                    h[(i, j)]
                });
                if let Some(u) = camera {
                    let h = o.jk.transpose() * o.jc * o.w;
                    let bu = blocks.entries[u];
                    system.add_block_in(
                        &mut part,
                        blocks.slots[pair_index(u, l)],
                        b,
                        bu,
                        |i, j| h[(i, j)],
                    );
                }
                if let Some(v) = focal {
                    let h = o.jk.transpose() * o.jf * o.w;
                    let bv = blocks.entries[v];
                    system.add_block_in(
                        &mut part,
                        blocks.slots[pair_index(v, l)],
                        b,
                        bv,
                        |i, _| h[i],
                    );
                }
            }
        }
        let cg = c_inv * lin.g;
        ecs.clear();
        ecs.extend(es.iter().map(|e| e * c_inv));
        for u in 0..entries {
            let bu = blocks.entries[u];
            let v = es[u] * cg;
            let g = gs[u];
            system.add_rhs_in(&mut part, bu, |i| -g[i] + v[i]);
            for (w, (ew, &bw)) in es.iter().zip(&blocks.entries).enumerate().take(u + 1) {
                let m = ecs[u] * ew.transpose();
                system.add_block_in(&mut part, blocks.slots[pair_index(u, w)], bu, bw, |i, j| {
                    -m[(i, j)]
                });
            }
        }
        inverses.push(c_inv);
    }
    Some((part, inverses))
}

/// A solve of the reduced system: the cameras' (and focals', coefficients') step, and each
/// point's `C⁻¹` for the back-substitution.
type Solved = (Vec<f64>, Vec<Matrix3<f64>>);

/// How the reduced camera system is solved.
enum Reduced {
    /// Formed, and factorised by a sparse (or dense) Cholesky.
    Explicit(Box<BlockSystem>),
    /// Never formed: conjugate gradients on products computed from the observations.
    Implicit(ImplicitSchur),
}

/// The explicit reduced system of `linear`'s points at damping `lambda`, solved by `system`'s
/// Cholesky; the solution and each point's `C⁻¹`, `None` when not positive definite at this
/// damping.
fn solve_explicit(
    system: &mut BlockSystem,
    linear: &[PointLinearisation],
    blocks: &[PointBlocks],
    lambda: f64,
) -> Result<Option<Solved>> {
    // The points in `SCHUR_PARTS` runs, each eliminated into its own copy of the reduced
    // system's values by one task, then added in order: the same sum on any thread count.
    // The runs go as many at a time as there are threads, each batch added and dropped before
    // the next, so that at most that many copies live at once (all eight at once were 0.6 GB
    // of the 1000-frame forward walk's 2.2 GB peak; docs/BENCHMARKS.md, "COLMAP at 1000 frames in the same
    // run, and peak memory").
    let chunk = linear.len().div_ceil(SCHUR_PARTS).max(1);
    let runs: Vec<_> = linear.chunks(chunk).zip(blocks.chunks(chunk)).collect();
    let at_once = rayon::current_num_threads().clamp(1, SCHUR_PARTS);
    let mut inverses = Vec::with_capacity(linear.len());
    system.clear();
    for batch in runs.chunks(at_once) {
        let shared = &*system;
        let parts: Vec<Option<(BlockValues, Vec<Matrix3<f64>>)>> = batch
            .par_iter()
            .map(|(linear, blocks)| eliminate(shared, linear, blocks, lambda))
            .collect();
        for part in parts {
            // A point not invertible at this damping: more damping makes it so.
            let Some((v, inv)) = part else {
                return Ok(None);
            };
            system.add_part(&v);
            inverses.extend(inv);
        }
    }
    Ok(system
        .solve_regularised(lambda)?
        .map(|delta| (delta, inverses)))
}

struct Problem<'a> {
    intrinsics: &'a ImageIntrinsics,
    /// Each point's observations (borrowed from the points being adjusted).
    observations: Vec<&'a [Observation]>,
    layout: ParameterLayout,
    /// The radial coefficients refined (none by [`bundle_adjust`]).
    lens: LensLayout,
    /// Their model.
    kind: LensKind,
    /// Parameters in all: the layout's and the free coefficients.
    n_params: usize,
    reference: usize,
    cauchy: f64,
    system: Reduced,
    linear: Vec<PointLinearisation>,
    /// Point steps of the last solve.
    point_steps: Vec<Vector3<f64>>,
    /// Per point, the blocks it touches.
    blocks: Vec<PointBlocks>,
}

impl Problem<'_> {
    fn focal(&self, factors: &[f64], image: usize) -> f64 {
        factors[self.intrinsics.group[image]] * self.intrinsics.scale[image]
    }
}

impl LeastSquares for Problem<'_> {
    type State = State;

    fn n_params(&self) -> usize {
        self.n_params
    }

    fn cost(&self, (cams, factors, ks, points): &State) -> f64 {
        let per_point: Vec<f64> = self
            .observations
            .par_iter()
            .zip(points)
            .map(|(obs, x)| {
                let mut total = CauchySum::new(self.cauchy);
                for o in obs.iter() {
                    let Some(c) = cams[o.image] else { continue };
                    let f = self.focal(factors, o.image);
                    let k = ks[self.intrinsics.group[o.image]];
                    total.add(
                        match project_lens(
                            &c,
                            f,
                            self.intrinsics.principal[o.image],
                            (self.kind, k),
                            x,
                        ) {
                            Some((uv, _)) => (uv[0] - o.xy[0]).powi(2) + (uv[1] - o.xy[1]).powi(2),
                            None => 1e6,
                        },
                    );
                }
                total.total()
            })
            .collect();
        per_point.iter().sum()
    }

    fn linearize(&mut self, (cams, factors, ks, points): &State) -> Result<()> {
        let c2 = self.cauchy * self.cauchy;
        let this = &*self;
        let linear = this
            .observations
            .par_iter()
            .zip(points)
            .map(|(obs, x)| {
                let mut lin = PointLinearisation {
                    c: Matrix3::zeros(),
                    g: Vector3::zeros(),
                    obs: Vec::with_capacity(obs.len()),
                };
                for (index, o) in obs.iter().enumerate() {
                    let Some(cam) = cams[o.image] else { continue };
                    let f = this.focal(factors, o.image);
                    let pp = this.intrinsics.principal[o.image];
                    let k = ks[this.intrinsics.group[o.image]];
                    let Some((uv, xc)) = project_lens(&cam, f, pp, (this.kind, k), x) else {
                        continue;
                    };
                    let r = SVector::<f64, 2>::new(uv[0] - o.xy[0], uv[1] - o.xy[1]);
                    let w = 1.0 / (1.0 + r.norm_squared() / c2);
                    let iz = 1.0 / xc.z;
                    let (u, v) = (xc.x * iz, xc.y * iz);
                    let d = if this.kind == LensKind::Brown && k == PINHOLE {
                        pinhole_jacobian(f, &xc)
                    } else {
                        // ∂uv/∂x_c = f ∂x_d/∂x · ∂x/∂x_c, with ∂x/∂x_c = [I | −x] / z.
                        let (_, jd) = this.kind.distort(k, u, v);
                        jd * f * SMatrix::<f64, 2, 3>::new(iz, 0.0, -u * iz, 0.0, iz, -v * iz)
                    };
                    let jp = d * cam.rotation.matrix();
                    let skew = Matrix3::new(0.0, -xc.z, xc.y, xc.z, 0.0, -xc.x, -xc.y, xc.x, 0.0);
                    let mut jc = SMatrix::<f64, 2, 6>::zeros();
                    jc.fixed_view_mut::<2, 3>(0, 0).copy_from(&(d * (-skew)));
                    jc.fixed_view_mut::<2, 3>(0, 3).copy_from(&(-jp));
                    let jf = SVector::<f64, 2>::new(uv[0] - pp[0], uv[1] - pp[1]);
                    let jk = this.kind.coefficient_jacobian(u, v) * f;
                    lin.c += jp.transpose() * jp * w;
                    lin.g += jp.transpose() * r * w;
                    lin.obs.push(ObservationLinearisation {
                        image: o.image,
                        index,
                        jc,
                        jf,
                        jk,
                        jp,
                        r,
                        w,
                    });
                }
                lin
            })
            .collect();
        self.linear = linear;
        Ok(())
    }

    fn solve(&mut self, lambda: f64) -> Result<Option<Vec<f64>>> {
        let (delta, inverses) = match &mut self.system {
            Reduced::Explicit(system) => {
                match solve_explicit(system, &self.linear, &self.blocks, lambda)? {
                    Some(solved) => solved,
                    None => return Ok(None),
                }
            }
            Reduced::Implicit(implicit) => {
                match implicit.solve(&self.linear, &self.blocks, lambda) {
                    Some(solved) => solved,
                    None => return Ok(None),
                }
            }
        };
        // Back-substitution: δp = −C⁻¹ (g_p + Σ J_pᵀ W (J_c δc + J_f δf)).
        let layout = &self.layout;
        let lens = &self.lens;
        let group = &self.intrinsics.group;
        self.point_steps = self
            .linear
            .par_iter()
            .zip(&inverses)
            .map(|(lin, c_inv)| {
                let mut v = lin.g;
                for o in &lin.obs {
                    let mut duv = SVector::<f64, 2>::zeros();
                    if let Some(off) = layout.offset[o.image] {
                        duv += o.jc * SVector::<f64, 6>::from_fn(|i, _| delta[off + i]);
                    }
                    if let Some(fi) = layout.focal[group[o.image]] {
                        duv += o.jf * delta[fi];
                    }
                    if let Some((ki, m)) = lens.param.get(group[o.image]).copied().flatten() {
                        for c in 0..m {
                            duv += o.jk.column(c) * delta[ki + c];
                        }
                    }
                    v += o.jp.transpose() * duv * o.w;
                }
                -(c_inv * v)
            })
            .collect();
        Ok(Some(delta))
    }

    fn apply(&self, (cams, factors, ks, points): &State, step: &[f64]) -> State {
        let (mut moved, factors) = self.layout.apply(cams, factors, step);
        let ks = ks
            .iter()
            .enumerate()
            .map(|(g, k)| match self.lens.param.get(g).copied().flatten() {
                Some((i, m)) => {
                    let mut k = *k;
                    for (c, kc) in k.iter_mut().enumerate().take(m) {
                        *kc += step[i + c];
                    }
                    k
                }
                None => *k,
            })
            .collect();
        let mut points: Vec<Vector3<f64>> = points
            .iter()
            .zip(&self.point_steps)
            .map(|(x, s)| x + s)
            .collect();
        if let Some((origin, s)) = gauge_scale(&moved, self.reference) {
            for c in moved.iter_mut().flatten() {
                c.center = origin + (c.center - origin) * s;
            }
            for x in &mut points {
                *x = origin + (*x - origin) * s;
            }
        }
        (moved, factors, ks, points)
    }
}

/// Keeps the observations within `max_error_px` of their projection (through each group's
/// radial coefficient `ks[g]`); points with fewer than two left are dropped.
fn filter(
    points: Vec<Point>,
    cameras: &[Option<CameraPose>],
    lens: (&ImageIntrinsics, f64, &[LensCoefficients], LensKind),
    max_error_px: f64,
) -> Vec<Point> {
    points
        .into_iter()
        .filter_map(|mut p| keeps_close(&mut p, cameras, lens, max_error_px).then_some(p))
        .collect()
}

/// [`filter`] of `points` with a value per point (`held[k]` belongs to `points[k]`) that
/// follows its point.
fn filter_held<T>(
    points: Vec<Point>,
    held: Vec<T>,
    cameras: &[Option<CameraPose>],
    lens: (&ImageIntrinsics, f64, &[LensCoefficients], LensKind),
    max_error_px: f64,
) -> (Vec<Point>, Vec<T>) {
    points
        .into_iter()
        .zip(held)
        .filter_map(|(mut p, h)| keeps_close(&mut p, cameras, lens, max_error_px).then_some((p, h)))
        .unzip()
}

/// Keeps `p`'s observations within `max_error_px` of their projection; whether two are left.
fn keeps_close(
    p: &mut Point,
    cameras: &[Option<CameraPose>],
    (intrinsics, phi, ks, kind): (&ImageIntrinsics, f64, &[LensCoefficients], LensKind),
    max_error_px: f64,
) -> bool {
    let xyz = p.xyz;
    p.observations.retain(|o| {
        cameras[o.image].is_some_and(|c| {
            project_lens(
                &c,
                intrinsics.focal(phi, o.image),
                intrinsics.principal[o.image],
                (kind, ks[intrinsics.group[o.image]]),
                &xyz,
            )
            .is_some_and(|(uv, _)| (uv[0] - o.xy[0]).hypot(uv[1] - o.xy[1]) <= max_error_px)
        })
    });
    p.observations.len() >= 2
}

/// One adjustment of `points` (in place) with the cameras, each group's focal factor and the
/// first `refine_lens[g]` radial coefficients of `ks[g]` (an empty slice: none).
fn adjust(
    points: &mut [Point],
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<CameraPose>],
    (factors, ks): (&mut [f64], &mut [LensCoefficients]),
    reference: usize,
    options: &BundleOptions,
    (refine_lens, kind): (&[usize], LensKind),
) -> Result<(LmReport, LinearSolves)> {
    // A group's focal (and coefficient) is refined when one of its images is observed by a
    // camera.
    let mut observed = vec![false; factors.len()];
    for p in points.iter() {
        for o in &p.observations {
            if cameras[o.image].is_some() {
                observed[intrinsics.group[o.image]] = true;
            }
        }
    }
    let free: Vec<bool> = observed
        .iter()
        .map(|&o| o && options.refine_focal)
        .collect();
    let layout = ParameterLayout::with_focals(cameras, reference, &free);
    let free_lens: Vec<usize> = observed
        .iter()
        .enumerate()
        .map(|(g, &o)| {
            if o {
                refine_lens.get(g).copied().unwrap_or(0)
            } else {
                0
            }
        })
        .collect();
    let (lens, n_params, block_sizes) = LensLayout::new(&layout, &free_lens);
    let mut blocks: Vec<PointBlocks> = points
        .iter()
        .map(|p| PointBlocks::new(&p.observations, intrinsics, &layout, &lens))
        .collect();
    let free_cameras = layout.offset.iter().flatten().count();
    let system = match options.iterative {
        Some(iterative) if free_cameras >= iterative.min_cameras => {
            Reduced::Implicit(ImplicitSchur::new(&block_sizes, iterative))
        }
        _ => {
            let system = BlockSystem::new(
                "bundle adjustment (reduced camera system)",
                &block_sizes,
                distinct_block_pairs(&blocks),
                options.solver,
            )?;
            for b in &mut blocks {
                b.find_slots(&system);
            }
            Reduced::Explicit(Box::new(system))
        }
    };
    let observations: Vec<&[Observation]> =
        points.iter().map(|p| p.observations.as_slice()).collect();
    let mut problem = Problem {
        intrinsics,
        observations,
        layout,
        lens,
        kind,
        n_params,
        reference,
        cauchy: options.cauchy_px,
        system,
        linear: Vec::new(),
        point_steps: Vec::new(),
        blocks,
    };
    let mut state: State = (
        cameras.to_vec(),
        factors.to_vec(),
        ks.to_vec(),
        points.iter().map(|p| p.xyz).collect(),
    );
    let lm = LmOptions {
        max_iterations: options.max_iterations,
        tolerance: options.tolerance,
        ..LmOptions::default()
    };
    let report = minimize(&mut problem, &mut state, &lm)?;
    let linear = match &problem.system {
        Reduced::Explicit(_) => LinearSolves::default(),
        Reduced::Implicit(implicit) => LinearSolves {
            iterations: implicit.iterations,
            unconverged: implicit.unconverged,
        },
    };
    drop(problem);
    cameras.copy_from_slice(&state.0);
    factors.copy_from_slice(&state.1);
    ks.copy_from_slice(&state.2);
    for (p, x) in points.iter_mut().zip(state.3) {
        p.xyz = x;
    }
    Ok((report, linear))
}

/// The iterative solves of one adjustment.
#[derive(Debug, Clone, Copy, Default)]
struct LinearSolves {
    iterations: usize,
    unconverged: usize,
}

/// Adjusts `cameras` (`None`: not estimated) and the focal factors in place on `tracks`:
/// `factors[g]` is camera group `g`'s (`intrinsics.group`; image `i`'s focal is
/// `factors[group[i]] · scale[i]`), each refined when [`BundleOptions::refine_focal`] and one
/// of its images is estimated. The reference camera is held fixed. Returns the adjusted points
/// with the observations they keep.
///
/// # Errors
/// Cameras, intrinsics or factors of the wrong length, a reference without a camera, a
/// non-positive focal factor, a reduced camera system that is not positive definite at any
/// damping.
pub fn bundle_adjust(
    tracks: &[Track],
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<CameraPose>],
    factors: &mut [f64],
    reference: usize,
    options: &BundleOptions,
) -> Result<(Vec<Point>, BundleReport)> {
    let groups = intrinsics.groups();
    if factors.len() != groups {
        return Err(crate::error::SfmError::LengthMismatch {
            what: "focal factors (one per camera group)",
            left: groups,
            right: factors.len(),
        });
    }
    for &phi in factors.iter() {
        check_inputs(cameras.len(), intrinsics, cameras, phi, reference)?;
    }
    let min_angle = options.min_angle_deg.to_radians();
    let is_estimated: Vec<bool> = cameras.iter().map(Option::is_some).collect();
    let estimated = |t: &Track| -> Vec<Observation> {
        t.iter()
            .filter(|o| is_estimated.get(o.image).copied().unwrap_or(false))
            .copied()
            .collect()
    };
    let mut report = BundleReport {
        tracks: tracks.len(),
        converged: true,
        termination: Termination::NothingToRefine,
        ..BundleReport::default()
    };
    let keyframes = options
        .keyframes
        .and_then(|k| keyframes::spaced(cameras, reference, &k).map(|key| (key, k)));
    let Some((mut key, key_options)) = keyframes else {
        let (at_start, phi) = folded(intrinsics, factors);
        let points: Vec<Point> = tracks
            .par_iter()
            .flat_map_iter(|t| {
                segments(
                    estimated(t),
                    options.max_track_length,
                    options.max_track_span,
                )
            })
            .filter_map(|t| {
                triangulate(&t, cameras, &at_start, phi, min_angle).map(|xyz| Point {
                    xyz,
                    observations: t,
                    alone: Vec::new(),
                })
            })
            .collect();
        let held = vec![(); points.len()];
        let (points, _) = adjust_twice(
            (points, held),
            intrinsics,
            cameras,
            factors,
            reference,
            options,
            &mut report,
        )?;
        return Ok((points, report));
    };

    // Keyframes: promotions first (a camera seeing too few points of tracks with two keyframe
    // observations, a group without a keyframe).
    let n = cameras.len();
    let seen = tracks
        .par_iter()
        .fold(
            || vec![0usize; n],
            |mut seen, t| {
                for s in cut(estimated(t), options.max_track_span) {
                    if s.iter().filter(|o| key[o.image]).count() >= 2 {
                        for o in s.iter().filter(|o| !key[o.image]) {
                            seen[o.image] += 1;
                        }
                    }
                }
                seen
            },
        )
        .reduce(
            || vec![0usize; n],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
                a
            },
        );
    let promoted = keyframes::promote(&mut key, cameras, &seen, intrinsics, key_options.min_points);
    // The gauge of the keyframes (the joint adjustment keeps their mean distance to the
    // reference at one), given to every camera so the others start in the same frame.
    let mut key_cameras: Vec<Option<CameraPose>> = cameras
        .iter()
        .zip(&key)
        .map(|(c, &k)| c.filter(|_| k))
        .collect();
    if let Some((origin, s)) = gauge_scale(&key_cameras, reference) {
        for c in cameras.iter_mut().chain(key_cameras.iter_mut()).flatten() {
            c.center = origin + (c.center - origin) * s;
        }
    }
    let (at_start, phi) = folded(intrinsics, factors);
    // Each segment's point from its keyframe observations, the others held beside it.
    let (points, held): (Vec<Point>, Vec<Vec<Observation>>) = tracks
        .par_iter()
        .flat_map_iter(|t| {
            cut(estimated(t), options.max_track_span)
                .into_iter()
                .filter_map(|s| {
                    let (keyed, others): (Vec<Observation>, Vec<Observation>) =
                        s.into_iter().partition(|o| key[o.image]);
                    (keyed.len() >= 2).then(|| (spread(keyed, options.max_track_length), others))
                })
        })
        .filter_map(|(t, others)| {
            triangulate(&t, &key_cameras, &at_start, phi, min_angle).map(|xyz| {
                (
                    Point {
                        xyz,
                        observations: t,
                        alone: Vec::new(),
                    },
                    others,
                )
            })
        })
        .unzip();
    let (mut points, held) = adjust_twice(
        (points, held),
        intrinsics,
        &mut key_cameras,
        factors,
        reference,
        options,
        &mut report,
    )?;
    let mut per_image: Vec<Vec<(usize, Observation)>> = vec![Vec::new(); n];
    for (j, others) in held.into_iter().enumerate() {
        for o in others {
            per_image[o.image].push((j, o));
        }
    }
    // Each other camera starts moved as the keyframe it shares the most adjusted points with
    // was moved (a warp of the world that keeps what that keyframe sees; the nearest keyframe
    // in image order when it shares none), then the keyframes take their adjusted poses.
    let moved_keys: Vec<(usize, CameraPose, CameraPose)> = (0..n)
        .filter_map(|i| Some((i, cameras[i]?, key_cameras[i]?)))
        .collect();
    let warp_from: Vec<Option<usize>> = (0..n)
        .into_par_iter()
        .map(|i| {
            cameras[i]?;
            if key[i] {
                return Some(i);
            }
            let mut shared: HashMap<usize, usize> = HashMap::new();
            for (j, _) in &per_image[i] {
                for o in &points[*j].observations {
                    *shared.entry(o.image).or_default() += 1;
                }
            }
            shared
                .into_iter()
                .max_by_key(|&(k, count)| (count, std::cmp::Reverse(k)))
                .map(|(k, _)| k)
                .or_else(|| {
                    let near = moved_keys.partition_point(|(k, _, _)| *k < i);
                    [near.checked_sub(1), Some(near)]
                        .into_iter()
                        .flatten()
                        .filter_map(|k| moved_keys.get(k))
                        .min_by_key(|(k, _, _)| k.abs_diff(i))
                        .map(|(k, _, _)| *k)
                })
        })
        .collect();
    for (i, from) in warp_from.iter().enumerate() {
        if let (Some(pose), Some(k)) = (cameras[i], from)
            && let (Some(before), Some(after)) = (cameras[*k], key_cameras[*k])
            && *k != i
        {
            cameras[i] = Some(pose.warped(&before, &after, 1.0));
        }
    }
    for (c, k) in cameras.iter_mut().zip(&key_cameras) {
        if k.is_some() {
            *c = *k;
        }
    }
    // Every other camera alone against the adjusted points.
    let (at_end, phi) = folded(intrinsics, factors);
    let alone: Vec<usize> = (0..n)
        .filter(|&i| cameras[i].is_some() && !key[i])
        .collect();
    let refined = alone
        .par_iter()
        .map(|&i| {
            let Some(start) = cameras[i] else {
                return Ok(None);
            };
            let list = &per_image[i];
            let correspondences: Vec<(Vector3<f64>, [f64; 2])> =
                list.iter().map(|(j, o)| (points[*j].xyz, o.xy)).collect();
            let refined = keyframes::refine_pose(
                (start, None),
                &correspondences,
                (at_end.focal(phi, i), at_end.principal[i]),
                options,
                &key_options,
            )?;
            Ok(refined.map(|r| {
                let kept: Vec<(usize, Observation)> = r.inliers.iter().map(|&k| list[k]).collect();
                (i, r.pose, kept)
            }))
        })
        .collect::<Result<Vec<_>>>()?;
    let refined_alone = refined.iter().flatten().count();
    for (i, pose, kept) in refined.into_iter().flatten() {
        cameras[i] = Some(pose);
        for (j, o) in kept {
            points[j].alone.push(o);
        }
    }
    points
        .par_iter_mut()
        .for_each(|p| p.alone.sort_by_key(|o| o.image));
    // The gauge of all the cameras, as a joint adjustment leaves it.
    if let Some((origin, s)) = gauge_scale(cameras, reference) {
        for c in cameras.iter_mut().flatten() {
            c.center = origin + (c.center - origin) * s;
        }
        for p in &mut points {
            p.xyz = origin + (p.xyz - origin) * s;
        }
    }
    report.keyframes = Some(KeyframeReport {
        keyframes: key
            .iter()
            .zip(cameras.iter())
            .filter(|(k, c)| **k && c.is_some())
            .count(),
        promoted,
        refined_alone,
        unrefined: alone.len() - refined_alone,
    });
    let (rms, count) = rms_error(
        true,
        &points,
        cameras,
        (
            &at_end,
            phi,
            &vec![PINHOLE; intrinsics.groups()],
            LensKind::Brown,
        ),
    );
    report.points = points.len();
    report.observations = count;
    report.rms_px = rms;
    Ok((points, report))
}

/// The intrinsics with `factors` folded into the scales, and the first factor (the stages
/// that see one focal per image).
fn folded(intrinsics: &ImageIntrinsics, factors: &[f64]) -> (ImageIntrinsics, f64) {
    let mut folded = intrinsics.clone();
    let phi = folded.fold_factors(factors);
    (folded, phi)
}

/// The two adjustments of [`bundle_adjust`]: observations farther than `max_error_px` left out,
/// one adjustment, the far ones left out again, another; `held[k]` follows `points[k]`. Fills
/// `report`'s iterations, termination, points, observations and RMS.
fn adjust_twice<T>(
    (points, held): (Vec<Point>, Vec<T>),
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<CameraPose>],
    factors: &mut [f64],
    reference: usize,
    options: &BundleOptions,
    report: &mut BundleReport,
) -> Result<(Vec<Point>, Vec<T>)> {
    let groups = intrinsics.groups();
    let (at_start, phi) = folded(intrinsics, factors);
    let pinhole = vec![PINHOLE; groups];
    let (mut points, held) = filter_held(
        points,
        held,
        cameras,
        (&at_start, phi, &pinhole, LensKind::Brown),
        options.max_error_px,
    );
    if points.is_empty() {
        return Ok((points, held));
    }
    let mut ks = pinhole.clone();
    let (first, first_solves) = adjust(
        &mut points,
        intrinsics,
        cameras,
        (factors, &mut ks),
        reference,
        options,
        (&[], LensKind::Brown),
    )?;
    let (between, phi) = folded(intrinsics, factors);
    let (mut points, held) = filter_held(
        points,
        held,
        cameras,
        (&between, phi, &ks, LensKind::Brown),
        options.max_error_px,
    );
    let (second, second_solves) = adjust(
        &mut points,
        intrinsics,
        cameras,
        (factors, &mut ks),
        reference,
        options,
        (&[], LensKind::Brown),
    )?;
    let (t1, t2) = (first.termination, second.termination);
    report.iterations = first.iterations + second.iterations;
    report.linear_iterations = first_solves.iterations + second_solves.iterations;
    report.linear_unconverged = first_solves.unconverged + second_solves.unconverged;
    report.converged = t1.converged() && t2.converged();
    // The stage that did not converge, if one did not (else the last).
    report.termination = if t1.converged() { t2 } else { t1 };
    let (at_end, phi) = folded(intrinsics, factors);
    let (rms, count) = rms_error(
        false,
        &points,
        cameras,
        (&at_end, phi, &ks, LensKind::Brown),
    );
    report.points = points.len();
    report.observations = count;
    report.rms_px = rms;
    Ok((points, held))
}

/// The RMS reprojection error of `points`' observations with a camera (pixels), those of
/// cameras refined alone too when `with_alone`, and their count.
fn rms_error(
    with_alone: bool,
    points: &[Point],
    cameras: &[Option<CameraPose>],
    (intrinsics, phi, ks, kind): (&ImageIntrinsics, f64, &[LensCoefficients], LensKind),
) -> (f64, usize) {
    let (mut sum, mut count) = (0.0, 0usize);
    for p in points {
        let alone = if with_alone { &p.alone[..] } else { &[] };
        for o in p.observations.iter().chain(alone) {
            if let Some(c) = cameras[o.image]
                && let Some((uv, _)) = project_lens(
                    &c,
                    intrinsics.focal(phi, o.image),
                    intrinsics.principal[o.image],
                    (kind, ks[intrinsics.group[o.image]]),
                    &p.xyz,
                )
            {
                sum += (uv[0] - o.xy[0]).powi(2) + (uv[1] - o.xy[1]).powi(2);
                count += 1;
            }
        }
    }
    let rms = if count > 0 {
        (sum / count as f64).sqrt()
    } else {
        0.0
    };
    (rms, count)
}

/// What [`adjust_lens`] did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct LensAdjustment {
    /// Points adjusted.
    pub points: usize,
    /// Observations used.
    pub observations: usize,
    /// The robust (Cauchy) cost before and after.
    pub cost_before: f64,
    /// See `cost_before`.
    pub cost_after: f64,
    /// RMS reprojection error before and after, pixels.
    pub rms_before_px: f64,
    /// See `rms_before_px`.
    pub rms_after_px: f64,
    /// Accepted steps.
    pub iterations: usize,
    /// Why it stopped.
    pub termination: Termination,
}

/// One bundle adjustment of already triangulated `points` whose observations are in the
/// photos' own pixels, with the first `free[g]` (0, 1 or 2) of each camera group's radial
/// coefficients `ks[g]` (COLMAP's RADIAL `k₁, k₂`, on `x_c / z_c`; SIMPLE_RADIAL: one) refined
/// beside the cameras, the focal factors (when [`BundleOptions::refine_focal`]) and the points;
/// observations farther than `max_error_px` from their projection at the start are left out.
/// Everything is updated in place; the reference camera is held fixed.
///
/// # Errors
/// As [`bundle_adjust`]; `ks` or `free` of another length than the groups.
pub fn adjust_lens(
    points: Vec<Point>,
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<CameraPose>],
    (factors, ks, free): (&mut [f64], &mut [LensCoefficients], &[usize]),
    kind: LensKind,
    reference: usize,
    options: &BundleOptions,
) -> Result<(Vec<Point>, LensAdjustment)> {
    let groups = intrinsics.groups();
    for (what, len) in [
        ("focal factors (one per camera group)", factors.len()),
        ("radial coefficients (one per camera group)", ks.len()),
        (
            "free radial coefficients (one per camera group)",
            free.len(),
        ),
    ] {
        if len != groups {
            return Err(crate::error::SfmError::LengthMismatch {
                what,
                left: groups,
                right: len,
            });
        }
    }
    for &phi in factors.iter() {
        check_inputs(cameras.len(), intrinsics, cameras, phi, reference)?;
    }
    let mut folded = intrinsics.clone();
    let phi = folded.fold_factors(factors);
    let mut points = filter(
        points,
        cameras,
        (&folded, phi, ks, kind),
        options.max_error_px,
    );
    let (rms_before_px, _) = rms_error(false, &points, cameras, (&folded, phi, ks, kind));
    let (lm, _) = adjust(
        &mut points,
        intrinsics,
        cameras,
        (factors, ks),
        reference,
        options,
        (free, kind),
    )?;
    let mut folded = intrinsics.clone();
    let phi = folded.fold_factors(factors);
    let (rms_after_px, observations) = rms_error(false, &points, cameras, (&folded, phi, ks, kind));
    let report = LensAdjustment {
        points: points.len(),
        observations,
        cost_before: lm.initial_cost,
        cost_after: lm.final_cost,
        rms_before_px,
        rms_after_px,
        iterations: lm.iterations,
        termination: lm.termination,
    };
    Ok((points, report))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn block_pairs_are_deduplicated_as_they_come() {
        // Tracks of random lengths over 50 cameras, their pairs with repeats.
        let mut seed = 7u64;
        let mut next = |m: usize| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as usize % m
        };
        let lists: Vec<Vec<(usize, usize)>> = (0..400)
            .map(|_| {
                let start = next(45);
                let k = 1 + next(6);
                let cams: Vec<usize> = (start..start + k).collect();
                cams.iter()
                    .enumerate()
                    .flat_map(|(u, &a)| cams[..=u].iter().map(move |&b| (a, b)))
                    .collect()
            })
            .collect();
        let mut all: Vec<(usize, usize)> = lists.iter().flatten().copied().collect();
        let total = all.len();
        all.sort_unstable();
        all.dedup();
        assert!(all.len() < total / 2, "the test needs repeats");
        for slack in [0, 1, 7, 1 << 20] {
            assert_eq!(
                distinct_pairs(lists.iter().cloned(), slack),
                all,
                "slack {slack}"
            );
        }
    }

    #[test]
    fn long_tracks_are_spread_evenly() {
        let obs: Vec<Observation> = (0..100)
            .map(|i| Observation {
                image: i,
                keypoint: 0,
                xy: [0.0, 0.0],
            })
            .collect();
        let kept: Vec<usize> = spread(obs.clone(), 5).iter().map(|o| o.image).collect();
        assert_eq!(kept.len(), 5);
        assert_eq!((kept[0], kept[4]), (0, 99));
        assert!(
            kept.windows(2).all(|w| w[1] > w[0] && w[1] - w[0] >= 24),
            "{kept:?}"
        );
        assert_eq!(spread(obs[..4].to_vec(), 5).len(), 4);
    }

    /// A track is cut where its span reaches the bound (in image order, whatever the order
    /// given), each segment spread; a lone observation at the end is left out.
    #[test]
    fn long_tracks_are_cut_into_segments_of_bounded_span() {
        let obs = |images: &[usize]| -> Vec<Observation> {
            images
                .iter()
                .map(|&image| Observation {
                    image,
                    keypoint: 0,
                    xy: [0.0, 0.0],
                })
                .collect()
        };
        let images = |s: &[Vec<Observation>]| -> Vec<Vec<usize>> {
            s.iter()
                .map(|o| o.iter().map(|o| o.image).collect())
                .collect()
        };
        let track: Vec<usize> = (0..250).rev().collect();
        let cut = segments(obs(&track), 20, 100);
        assert_eq!(cut.len(), 3);
        assert_eq!((cut[0][0].image, cut[0][19].image), (0, 99));
        assert_eq!((cut[2][0].image, cut[2][19].image), (200, 249));
        assert!(cut.iter().all(|s| s.len() == 20));
        assert_eq!(
            images(&segments(obs(&[3, 1, 2, 150]), 20, 100)),
            [[1, 2, 3]]
        );
        assert_eq!(
            images(&segments(obs(&[5, 7, 105, 106]), 20, 100)),
            [[5, 7], [105, 106]]
        );
        // A span at least the track's: the track itself, spread.
        assert_eq!(segments(obs(&track), 20, 1000).len(), 1);
    }

    /// The analytic reprojection Jacobian against central differences, through a pinhole and
    /// through a radial lens (the coefficient's column too).
    #[test]
    fn reprojection_jacobian_matches_finite_differences() {
        for k in [
            PINHOLE,
            [-0.12, 0.0, 0.0, 0.0],
            [0.05, -0.02, 0.0, 0.0],
            [-0.1, 0.03, 0.0, 0.0],
            [-0.1, 0.03, 0.002, -0.001],
        ] {
            check_jacobian(LensKind::Brown, k);
        }
        for k in [FISHEYE_PINHOLE, [0.2, 0.05, -0.01, 0.004]] {
            check_jacobian(LensKind::Fisheye, k);
        }
    }

    fn check_jacobian(kind: LensKind, k: LensCoefficients) {
        let intrinsics = ImageIntrinsics::new(vec![[320.0, 240.0]], vec![640.0]);
        let cam = CameraPose {
            rotation: Rotation3::from_euler_angles(0.1, -0.2, 0.3),
            center: Vector3::new(0.2, -0.1, -3.0),
        };
        let x = Vector3::new(0.3, 0.2, 0.5);
        let phi = 1.1;
        let obs = vec![Observation {
            image: 0,
            keypoint: 0,
            xy: [0.0, 0.0],
        }];
        let layout = ParameterLayout::new(&[Some(cam)], usize::MAX, true);
        let (lens, n_params, sizes) = LensLayout::new(&layout, &[4]);
        assert_eq!((n_params, sizes.as_slice()), (11, &[6, 1, 4][..]));
        let mut problem = Problem {
            intrinsics: &intrinsics,
            observations: vec![&obs],
            layout,
            lens,
            kind,
            n_params,
            reference: usize::MAX,
            cauchy: 1.0,
            system: Reduced::Explicit(Box::new(
                BlockSystem::new("t", &sizes, [(0, 1), (0, 2), (1, 2)], Solver::Dense).unwrap(),
            )),
            linear: Vec::new(),
            point_steps: Vec::new(),
            blocks: Vec::new(),
        };
        problem
            .linearize(&(vec![Some(cam)], vec![phi], vec![k], vec![x]))
            .unwrap();
        let lin = problem.linear[0].obs[0];
        let uv = |theta: &[f64; 14]| {
            let c = cam.moved(&theta[0..6]);
            let p = x + Vector3::new(theta[7], theta[8], theta[9]);
            project_lens(
                &c,
                intrinsics.focal(phi * theta[6].exp(), 0),
                [320.0, 240.0],
                (
                    kind,
                    [
                        k[0] + theta[10],
                        k[1] + theta[11],
                        k[2] + theta[12],
                        k[3] + theta[13],
                    ],
                ),
                &p,
            )
            .unwrap()
            .0
        };
        let h = 1e-6;
        for q in 0..14 {
            let (mut plus, mut minus) = ([0.0; 14], [0.0; 14]);
            plus[q] = h;
            minus[q] = -h;
            let (a, b) = (uv(&plus), uv(&minus));
            for row in 0..2 {
                let fd = (a[row] - b[row]) / (2.0 * h);
                let analytic = match q {
                    0..6 => lin.jc[(row, q)],
                    6 => lin.jf[row],
                    10..14 => lin.jk[(row, q - 10)],
                    _ => lin.jp[(row, q - 7)],
                };
                assert!(
                    (fd - analytic).abs() <= 1e-6 * fd.abs().max(1.0),
                    "{kind:?} k {k:?}, param {q} row {row}: {fd} vs {analytic}"
                );
            }
        }
    }
}
