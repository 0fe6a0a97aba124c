//! The mapper's camera parametrisation and gauge, shared by every refinement.
//!
//! A camera is a world → camera rotation and a centre (`x_cam = R (X − C)`, OpenCV). A
//! refinement moves it by 6 values `[ω, δC]` (`R ← exp(ω) R`, `C ← C + δC`). The gauge: one
//! reference camera is held fixed (no parameters) and after every step the centres (and points)
//! are rescaled about the reference's centre to unit mean distance (the scale is not observable).

use nalgebra::{Rotation3, Vector3};

/// One camera's extrinsics: `x_cam = R (X − C)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPose {
    /// World → camera rotation.
    pub rotation: Rotation3<f64>,
    /// Camera centre in the world.
    pub center: Vector3<f64>,
}

impl CameraPose {
    /// Moved by `[ω, δC]` (`p[0..6]`).
    pub fn moved(&self, p: &[f64]) -> Self {
        Self {
            rotation: Rotation3::from_scaled_axis(Vector3::new(p[0], p[1], p[2])) * self.rotation,
            center: self.center + Vector3::new(p[3], p[4], p[5]),
        }
    }

    /// The pose of an OpenCV camera (`x_cam = R X + t`): its rotation (projected onto SO(3))
    /// and its centre `C = −Rᵀ t`.
    pub fn of_camera(camera: &posediff_geometry::Camera) -> Self {
        Self {
            rotation: Rotation3::from_matrix(&camera.cam_from_world.rotation),
            center: camera.center().coords,
        }
    }

    /// This camera moved by the similarity of the world that takes camera `before` to `after`
    /// while keeping what it sees, with scale `s` about it: `X ↦ s Q (X − C_b) + C_a`,
    /// `Q = R_aᵀ R_b`, so `C ↦ s Q (C − C_b) + C_a` and `R ↦ R Qᵀ` (`before` itself goes to
    /// `after`).
    pub fn warped(&self, before: &Self, after: &Self, s: f64) -> Self {
        let q = after.rotation.inverse() * before.rotation;
        Self {
            rotation: self.rotation * q.inverse(),
            center: after.center + s * (q * (self.center - before.center)),
        }
    }

    /// The translation `t = −R C` of `x_cam = R X + t`.
    pub fn translation(&self) -> Vector3<f64> {
        -(self.rotation * self.center)
    }
}

/// Where each camera's 6 parameters sit in the parameter vector (`None`: the reference or not
/// estimated), the focal factors' indices when refined (one per camera group), and the
/// parameter count.
#[derive(Debug, Clone, PartialEq)]
pub struct ParameterLayout {
    /// Offset of each camera's 6 values.
    pub offset: Vec<Option<usize>>,
    /// Index of each group's `log φ_g` (`None`: that factor is fixed).
    pub focal: Vec<Option<usize>>,
    /// Parameters in all.
    pub n_params: usize,
    /// Block index of each camera in a block system (cameras first, then the focals).
    pub block: Vec<Option<usize>>,
    /// Block index of each group's focal (`None` when fixed).
    pub focal_block: Vec<Option<usize>>,
    /// Block sizes (6 per free camera, 1 per free focal).
    pub block_sizes: Vec<usize>,
}

impl ParameterLayout {
    /// The layout of `cameras` with `reference` fixed and one shared focal when `refine_focal`.
    pub fn new(cameras: &[Option<CameraPose>], reference: usize, refine_focal: bool) -> Self {
        Self::with_focals(cameras, reference, &[refine_focal])
    }

    /// The layout of `cameras` with `reference` fixed and the focal factor of each group `g`
    /// with `free[g]` refined.
    pub fn with_focals(cameras: &[Option<CameraPose>], reference: usize, free: &[bool]) -> Self {
        let mut next = 0;
        let mut blocks = 0;
        let mut block = Vec::with_capacity(cameras.len());
        let offset = cameras
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let free = c.is_some() && i != reference;
                block.push(free.then(|| {
                    blocks += 1;
                    blocks - 1
                }));
                free.then(|| {
                    next += 6;
                    next - 6
                })
            })
            .collect();
        let mut block_sizes = vec![6; blocks];
        let mut focal = Vec::with_capacity(free.len());
        let mut focal_block = Vec::with_capacity(free.len());
        for &f in free {
            focal.push(f.then_some(next));
            focal_block.push(f.then_some(block_sizes.len()));
            if f {
                next += 1;
                block_sizes.push(1);
            }
        }
        Self {
            offset,
            focal,
            n_params: next,
            block,
            focal_block,
            block_sizes,
        }
    }

    /// The cameras and the focal factors moved by `step` (the first `n_params` values); fixed
    /// factors are returned as given.
    pub fn apply(
        &self,
        cameras: &[Option<CameraPose>],
        factors: &[f64],
        step: &[f64],
    ) -> (Vec<Option<CameraPose>>, Vec<f64>) {
        let moved = cameras
            .iter()
            .zip(&self.offset)
            .map(|(c, o)| match (c, o) {
                (Some(c), Some(o)) => Some(c.moved(&step[*o..*o + 6])),
                (c, _) => *c,
            })
            .collect();
        let factors = factors
            .iter()
            .enumerate()
            .map(|(g, phi)| match self.focal.get(g).copied().flatten() {
                Some(i) => phi * step[i].exp(),
                None => *phi,
            })
            .collect();
        (moved, factors)
    }
}

/// The factor that rescales the centres about the reference's to unit mean distance, and the
/// origin (the reference's centre); `None` when there is nothing to rescale.
pub fn gauge_scale(
    cameras: &[Option<CameraPose>],
    reference: usize,
) -> Option<(Vector3<f64>, f64)> {
    let origin = cameras.get(reference).copied().flatten()?.center;
    let (mut sum, mut count) = (0.0, 0usize);
    for c in cameras.iter().flatten() {
        sum += (c.center - origin).norm();
        count += 1;
    }
    let mean = sum / count.max(1) as f64;
    (mean > 0.0 && mean.is_finite()).then_some((origin, 1.0 / mean))
}

/// Rescales the centres about the reference's to unit mean distance.
pub fn normalize_scale(cameras: &mut [Option<CameraPose>], reference: usize) {
    if let Some((origin, s)) = gauge_scale(cameras, reference) {
        for c in cameras.iter_mut().flatten() {
            c.center = origin + (c.center - origin) * s;
        }
    }
}
