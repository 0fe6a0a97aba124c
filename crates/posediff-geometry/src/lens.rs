//! Camera models with lens distortion, the one place they live: COLMAP's model names and
//! parameter orders (`sensor/models.h`), OpenCV's pixel convention (pixel centres at integers,
//! as everywhere in this crate; COLMAP's principal point is this one plus ½).
//!
//! | model | parameters |
//! |---|---|
//! | `SIMPLE_PINHOLE` | f, cx, cy |
//! | `PINHOLE` | fx, fy, cx, cy |
//! | `SIMPLE_RADIAL` | f, cx, cy, k |
//! | `RADIAL` | f, cx, cy, k1, k2 |
//! | `OPENCV` | fx, fy, cx, cy, k1, k2, p1, p2 |
//! | `OPENCV_FISHEYE` | fx, fy, cx, cy, k1, k2, k3, k4 |
//!
//! A point `(x, y, z)` in the camera frame goes to normalised `(u, v) = (x/z, y/z)`, is
//! distorted to `(u_d, v_d)` (radial `u·(1 + k1 r² + k2 r⁴)`, OpenCV's tangential terms, or the
//! fisheye's `θ_d/r` with `θ = atan r`), and lands at `(fx u_d + cx, fy v_d + cy)`. Unprojection
//! inverts the distortion by Newton's method with the analytic Jacobian and fails (never
//! returns a wrong ray) where it does not converge.

use nalgebra::{Matrix2, Matrix2x4, Vector2, Vector3};

use crate::camera::Intrinsics;
use crate::error::{GeometryError, Result};

/// A camera model (COLMAP's names).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CameraModel {
    /// `f, cx, cy`.
    SimplePinhole,
    /// `fx, fy, cx, cy`.
    Pinhole,
    /// `f, cx, cy, k`.
    SimpleRadial,
    /// `f, cx, cy, k1, k2`.
    Radial,
    /// `fx, fy, cx, cy, k1, k2, p1, p2`.
    OpenCv,
    /// `fx, fy, cx, cy, k1, k2, k3, k4` (equidistant).
    OpenCvFisheye,
}

impl CameraModel {
    /// Every model.
    pub const ALL: [Self; 6] = [
        Self::SimplePinhole,
        Self::Pinhole,
        Self::SimpleRadial,
        Self::Radial,
        Self::OpenCv,
        Self::OpenCvFisheye,
    ];

    /// COLMAP's name.
    pub fn name(self) -> &'static str {
        match self {
            Self::SimplePinhole => "SIMPLE_PINHOLE",
            Self::Pinhole => "PINHOLE",
            Self::SimpleRadial => "SIMPLE_RADIAL",
            Self::Radial => "RADIAL",
            Self::OpenCv => "OPENCV",
            Self::OpenCvFisheye => "OPENCV_FISHEYE",
        }
    }

    /// COLMAP's model id (`CAMERA_MODEL_ID` in its database and binary models).
    pub fn colmap_id(self) -> i32 {
        match self {
            Self::SimplePinhole => 0,
            Self::Pinhole => 1,
            Self::SimpleRadial => 2,
            Self::Radial => 3,
            Self::OpenCv => 4,
            Self::OpenCvFisheye => 5,
        }
    }

    /// The model of a name.
    ///
    /// # Errors
    /// An unknown name (the error lists the known ones).
    pub fn from_name(name: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|m| m.name() == name)
            .ok_or(GeometryError::InvalidIntrinsics {
                reason: "unknown camera model (known: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, \
                         RADIAL, OPENCV, OPENCV_FISHEYE)",
            })
    }

    /// Number of parameters.
    pub fn num_params(self) -> usize {
        match self {
            Self::SimplePinhole => 3,
            Self::Pinhole | Self::SimpleRadial => 4,
            Self::Radial => 5,
            Self::OpenCv | Self::OpenCvFisheye => 8,
        }
    }

    /// Whether the model has one focal for both axes.
    fn single_focal(self) -> bool {
        matches!(
            self,
            Self::SimplePinhole | Self::SimpleRadial | Self::Radial
        )
    }
}

/// A camera model with its parameters (COLMAP's order, OpenCV pixels).
#[derive(Debug, Clone, PartialEq)]
pub struct LensCamera {
    model: CameraModel,
    params: Vec<f64>,
}

/// Newton steps of [`LensCamera::unproject`] before it gives up.
const UNDISTORT_ITERATIONS: usize = 100;
/// Converged when the distorted point is reproduced to this (normalised units).
const UNDISTORT_TOLERANCE: f64 = 1e-12;

/// Brown–Conrady distortion (COLMAP's SIMPLE_RADIAL, RADIAL and OPENCV) of the normalised
/// coordinates `(u, v)` with `[k1, k2, p1, p2]`, and `∂(u_d, v_d)/∂(u, v)`.
pub fn distort_brown([k1, k2, p1, p2]: [f64; 4], u: f64, v: f64) -> (Vector2<f64>, Matrix2<f64>) {
    let r2 = u * u + v * v;
    let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
    // ∂radial/∂u = (2 k1 + 4 k2 r²) u.
    let dr = 2.0 * k1 + 4.0 * k2 * r2;
    let ud = u * radial + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u);
    let vd = v * radial + 2.0 * p2 * u * v + p1 * (r2 + 2.0 * v * v);
    let j = Matrix2::new(
        radial + u * dr * u + 2.0 * p1 * v + 6.0 * p2 * u,
        u * dr * v + 2.0 * p1 * u + 2.0 * p2 * v,
        v * dr * u + 2.0 * p2 * v + 2.0 * p1 * u,
        radial + v * dr * v + 2.0 * p2 * u + 6.0 * p1 * v,
    );
    (Vector2::new(ud, vd), j)
}

/// `∂(u_d, v_d)/∂(k1, k2, p1, p2)` of [`distort_brown`] at `(u, v)`: the columns `r² (u, v)`,
/// `r⁴ (u, v)`, `(2uv, r² + 2v²)` and `(r² + 2u², 2uv)` (what a bundle adjustment refining the
/// coefficients needs; they do not depend on the coefficients).
pub fn brown_coefficient_jacobian(u: f64, v: f64) -> Matrix2x4<f64> {
    let r2 = u * u + v * v;
    Matrix2x4::new(
        r2 * u,
        r2 * r2 * u,
        2.0 * u * v,
        r2 + 2.0 * u * u,
        r2 * v,
        r2 * r2 * v,
        r2 + 2.0 * v * v,
        2.0 * u * v,
    )
}

/// OpenCV's fisheye (COLMAP's OPENCV_FISHEYE) distortion of the normalised coordinates
/// `(u, v)` with `[k1, k2, k3, k4]`: `θ = atan r`, `θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`,
/// `(u_d, v_d) = (θ_d / r) (u, v)`; and `∂(u_d, v_d)/∂(u, v)`.
pub fn distort_fisheye(d: [f64; 4], u: f64, v: f64) -> (Vector2<f64>, Matrix2<f64>) {
    let r2 = u * u + v * v;
    let r = r2.sqrt();
    if r < 1e-12 {
        return (Vector2::new(u, v), Matrix2::identity());
    }
    let theta = r.atan();
    let t2 = theta * theta;
    let poly = 1.0 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3])));
    let theta_d = theta * poly;
    // dθ_d/dθ = 1 + 3 k1 θ² + 5 k2 θ⁴ + 7 k3 θ⁶ + 9 k4 θ⁸.
    let dtd = 1.0 + t2 * (3.0 * d[0] + t2 * (5.0 * d[1] + t2 * (7.0 * d[2] + t2 * 9.0 * d[3])));
    let s = theta_d / r;
    // ds/dr = (dθ_d/dθ · 1/(1 + r²) · r − θ_d) / r².
    let ds = (dtd / (1.0 + r2) * r - theta_d) / r2;
    let (dru, drv) = (u / r, v / r);
    let j = Matrix2::new(
        s + u * ds * dru,
        u * ds * drv,
        v * ds * dru,
        s + v * ds * drv,
    );
    (Vector2::new(u * s, v * s), j)
}

/// `∂(u_d, v_d)/∂(k1, k2, k3, k4)` of [`distort_fisheye`] at `(u, v)`: the columns
/// `θ^{2j+1} / r · (u, v)`, `j = 1…4` (zero at the centre).
pub fn fisheye_coefficient_jacobian(u: f64, v: f64) -> Matrix2x4<f64> {
    let r = (u * u + v * v).sqrt();
    if r < 1e-12 {
        return Matrix2x4::zeros();
    }
    let theta = r.atan();
    let t2 = theta * theta;
    let (a, b) = (u / r, v / r);
    let mut power = theta * t2;
    let mut j = Matrix2x4::zeros();
    for c in 0..4 {
        j[(0, c)] = power * a;
        j[(1, c)] = power * b;
        power *= t2;
    }
    j
}

/// The OPENCV_FISHEYE coefficients that make it the pinhole projection to the order of `θ⁹`:
/// `tan θ = θ (1 + θ²/3 + 2θ⁴/15 + 17θ⁶/315 + 62θ⁸/2835 + …)` (a fisheye start for an adjustment
/// whose points come from pinhole cameras).
pub const FISHEYE_PINHOLE: [f64; 4] = [1.0 / 3.0, 2.0 / 15.0, 17.0 / 315.0, 62.0 / 2835.0];

impl LensCamera {
    /// A camera of `model` with `params`.
    ///
    /// # Errors
    /// The wrong number of parameters, a non-finite one, a focal that is not positive.
    pub fn new(model: CameraModel, params: Vec<f64>) -> Result<Self> {
        if params.len() != model.num_params() {
            return Err(GeometryError::LengthMismatch {
                what: "camera model parameters",
                left: model.num_params(),
                right: params.len(),
            });
        }
        crate::error::ensure_finite("camera model parameters", &params)?;
        let camera = Self { model, params };
        let (fx, fy) = camera.focal();
        if !(fx > 0.0 && fy > 0.0) {
            return Err(GeometryError::InvalidIntrinsics {
                reason: "focal lengths must be positive",
            });
        }
        Ok(camera)
    }

    /// The pinhole camera of `k` (`PINHOLE`).
    pub fn pinhole(k: &Intrinsics) -> Self {
        Self {
            model: CameraModel::Pinhole,
            params: vec![k.fx(), k.fy(), k.cx(), k.cy()],
        }
    }

    /// The model.
    pub fn model(&self) -> CameraModel {
        self.model
    }

    /// The parameters (COLMAP's order).
    pub fn params(&self) -> &[f64] {
        &self.params
    }

    /// `(fx, fy)`.
    pub fn focal(&self) -> (f64, f64) {
        if self.model.single_focal() {
            (self.params[0], self.params[0])
        } else {
            (self.params[0], self.params[1])
        }
    }

    /// `(cx, cy)`, OpenCV pixels.
    pub fn principal(&self) -> (f64, f64) {
        if self.model.single_focal() {
            (self.params[1], self.params[2])
        } else {
            (self.params[2], self.params[3])
        }
    }

    /// The pinhole part.
    ///
    /// # Errors
    /// Never for a camera built by [`Self::new`] (kept for the intrinsics' own checks).
    pub fn intrinsics(&self) -> Result<Intrinsics> {
        let ((fx, fy), (cx, cy)) = (self.focal(), self.principal());
        Intrinsics::new(fx, fy, cx, cy)
    }

    /// The distortion parameters (after focal and principal point).
    pub fn distortion(&self) -> &[f64] {
        let skip = if self.model.single_focal() { 3 } else { 4 };
        &self.params[skip..]
    }

    /// Whether the model distorts at all (a model with all distortion parameters 0 does not).
    pub fn is_distorted(&self) -> bool {
        self.distortion().iter().any(|d| *d != 0.0)
    }

    /// Distorted normalised coordinates of `(u, v)` and `∂(u_d, v_d)/∂(u, v)`.
    pub fn distort(&self, u: f64, v: f64) -> (Vector2<f64>, Matrix2<f64>) {
        let d = self.distortion();
        match self.model {
            CameraModel::SimplePinhole | CameraModel::Pinhole => {
                (Vector2::new(u, v), Matrix2::identity())
            }
            CameraModel::SimpleRadial | CameraModel::Radial | CameraModel::OpenCv => {
                let (k1, k2) = (d[0], d.get(1).copied().unwrap_or(0.0));
                let (p1, p2) = if self.model == CameraModel::OpenCv {
                    (d[2], d[3])
                } else {
                    (0.0, 0.0)
                };
                distort_brown([k1, k2, p1, p2], u, v)
            }
            CameraModel::OpenCvFisheye => distort_fisheye([d[0], d[1], d[2], d[3]], u, v),
        }
    }

    /// The pixel of camera-frame point `p`; `None` behind the camera (`z ≤ 0`).
    pub fn project(&self, p: &Vector3<f64>) -> Option<Vector2<f64>> {
        (p.z > 0.0).then(|| {
            let ((fx, fy), (cx, cy)) = (self.focal(), self.principal());
            let (d, _) = self.distort(p.x / p.z, p.y / p.z);
            Vector2::new(fx * d.x + cx, fy * d.y + cy)
        })
    }

    /// The photo's pixel of the undistorted pixel `p` (the pixel the pinhole part of this
    /// camera gives; `p` itself for a model without distortion).
    pub fn distort_pixel(&self, p: &Vector2<f64>) -> Vector2<f64> {
        let ((fx, fy), (cx, cy)) = (self.focal(), self.principal());
        let (d, _) = self.distort((p.x - cx) / fx, (p.y - cy) / fy);
        Vector2::new(fx * d.x + cx, fy * d.y + cy)
    }

    /// The undistorted pixel of the photo's pixel `p`, the inverse of [`Self::distort_pixel`].
    ///
    /// # Errors
    /// As [`Self::unproject`].
    pub fn undistort_pixel(&self, p: &Vector2<f64>) -> Result<Vector2<f64>> {
        let ((fx, fy), (cx, cy)) = (self.focal(), self.principal());
        let x = self.unproject(p)?;
        Ok(Vector2::new(fx * x.x + cx, fy * x.y + cy))
    }

    /// `∂pixel/∂p` of [`Self::project`] at camera-frame point `p` (`z > 0`), for the solvers.
    pub fn project_jacobian(&self, p: &Vector3<f64>) -> nalgebra::Matrix2x3<f64> {
        let (fx, fy) = self.focal();
        let iz = 1.0 / p.z;
        let (u, v) = (p.x * iz, p.y * iz);
        let (_, jd) = self.distort(u, v);
        let duv = nalgebra::Matrix2x3::new(iz, 0.0, -u * iz, 0.0, iz, -v * iz);
        nalgebra::Matrix2::new(fx, 0.0, 0.0, fy) * jd * duv
    }

    /// The normalised undistorted coordinates `(u, v)` (the ray `(u, v, 1)`) of a pixel.
    ///
    /// # Errors
    /// A non-finite pixel; a distortion whose inversion does not converge there (outside the
    /// region where the model is invertible).
    pub fn unproject(&self, pixel: &Vector2<f64>) -> Result<Vector2<f64>> {
        crate::error::ensure_finite("pixel", pixel.iter())?;
        let ((fx, fy), (cx, cy)) = (self.focal(), self.principal());
        let target = Vector2::new((pixel.x - cx) / fx, (pixel.y - cy) / fy);
        if !self.is_distorted() {
            return Ok(target);
        }
        // A root beyond a fold of the distortion (where its Jacobian turns orientation) is a
        // ray the lens never images: an error, like no convergence.
        let folded = GeometryError::Degenerate {
            what: "undistortion",
            reason: "the pixel lies beyond the fold of the lens model's distortion",
        };
        let mut x = target;
        for _ in 0..UNDISTORT_ITERATIONS {
            let (d, j) = self.distort(x.x, x.y);
            let residual = d - target;
            if residual.norm() < UNDISTORT_TOLERANCE {
                return if unfolded(&j) { Ok(x) } else { Err(folded) };
            }
            let Some(step) = j.try_inverse().map(|inv| inv * residual) else {
                break;
            };
            x -= step;
            if !x.iter().all(|v| v.is_finite()) {
                break;
            }
        }
        let (d, j) = self.distort(x.x, x.y);
        if (d - target).norm() < 1e-9 {
            return if unfolded(&j) { Ok(x) } else { Err(folded) };
        }
        Err(GeometryError::Degenerate {
            what: "undistortion",
            reason: "the lens model's inversion does not converge at this pixel",
        })
    }
}

/// Whether the distortion keeps its orientation at a point: both eigenvalues of its Jacobian
/// positive (a positive determinant alone also passes two negative ones, the far side of a
/// radial fold where the ray comes out mirrored).
fn unfolded(j: &Matrix2<f64>) -> bool {
    j.determinant() > 0.0 && j.trace() > 0.0
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn cameras() -> Vec<LensCamera> {
        vec![
            LensCamera::new(CameraModel::SimplePinhole, vec![500.0, 319.5, 239.5]).unwrap(),
            LensCamera::new(CameraModel::Pinhole, vec![500.0, 510.0, 320.0, 240.0]).unwrap(),
            LensCamera::new(CameraModel::SimpleRadial, vec![500.0, 319.5, 239.5, -0.12]).unwrap(),
            LensCamera::new(CameraModel::Radial, vec![500.0, 319.5, 239.5, -0.12, 0.02]).unwrap(),
            LensCamera::new(
                CameraModel::OpenCv,
                vec![500.0, 505.0, 320.0, 241.0, -0.12, 0.02, 0.001, -0.002],
            )
            .unwrap(),
            LensCamera::new(
                CameraModel::OpenCvFisheye,
                vec![400.0, 402.0, 320.0, 240.0, 0.05, -0.01, 0.002, -0.001],
            )
            .unwrap(),
        ]
    }

    fn points() -> Vec<Vector3<f64>> {
        let mut out = Vec::new();
        for x in [-0.5, -0.1, 0.0, 0.2, 0.45] {
            for y in [-0.4, 0.0, 0.1, 0.35] {
                out.push(Vector3::new(x, y, 1.0) * 2.5);
            }
        }
        out
    }

    /// Project then unproject is the identity, for every model.
    #[test]
    fn unprojection_inverts_projection() {
        for c in cameras() {
            for p in points() {
                let px = c.project(&p).unwrap();
                let ray = c.unproject(&px).unwrap();
                let want = Vector2::new(p.x / p.z, p.y / p.z);
                assert!(
                    (ray - want).norm() < 1e-10,
                    "{:?} {p:?}: {ray:?}",
                    c.model()
                );
            }
            assert!(c.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
        }
    }

    /// The analytic Jacobians against central differences.
    #[test]
    fn jacobians_match_finite_differences() {
        let h = 1e-6;
        for c in cameras() {
            for p in points() {
                let j = c.project_jacobian(&p);
                for k in 0..3 {
                    let mut e = Vector3::zeros();
                    e[k] = h;
                    let fd =
                        (c.project(&(p + e)).unwrap() - c.project(&(p - e)).unwrap()) / (2.0 * h);
                    for r in 0..2 {
                        assert!(
                            (fd[r] - j[(r, k)]).abs() < 1e-5 * fd[r].abs().max(1.0),
                            "{:?} {p:?} ({r},{k}): {} vs {}",
                            c.model(),
                            fd[r],
                            j[(r, k)]
                        );
                    }
                }
            }
        }
    }

    /// The coefficient Jacobians (what a bundle adjustment refining a lens needs) against
    /// central differences, Brown's and the fisheye's; and the fisheye coefficients that stand
    /// for a pinhole are one to within 1e-4 of a ray's tangent out to 35° (5e-5 measured).
    #[test]
    fn coefficient_jacobians_match_finite_differences() {
        let h = 1e-7;
        type Distortion = fn([f64; 4], f64, f64) -> (Vector2<f64>, Matrix2<f64>);
        type Columns = fn(f64, f64) -> Matrix2x4<f64>;
        let models: [(Distortion, Columns, [f64; 4]); 2] = [
            (
                distort_brown,
                brown_coefficient_jacobian,
                [-0.1, 0.02, 0.003, -0.002],
            ),
            (
                distort_fisheye,
                fisheye_coefficient_jacobian,
                [0.05, -0.01, 0.004, -0.001],
            ),
        ];
        for (distort, columns, k) in models {
            for (u, v) in [(0.3, -0.2), (-0.6, 0.4), (0.05, 0.7)] {
                let j = columns(u, v);
                for c in 0..4 {
                    let (mut plus, mut minus) = (k, k);
                    plus[c] += h;
                    minus[c] -= h;
                    let fd = (distort(plus, u, v).0 - distort(minus, u, v).0) / (2.0 * h);
                    for r in 0..2 {
                        assert!(
                            (fd[r] - j[(r, c)]).abs() < 1e-6,
                            "({u}, {v}) column {c} row {r}: {} vs {}",
                            fd[r],
                            j[(r, c)]
                        );
                    }
                }
            }
        }
        for step in 1..=35 {
            let theta = f64::from(step).to_radians();
            let (d, _) = distort_fisheye(FISHEYE_PINHOLE, theta.tan(), 0.0);
            let off = d.x / theta.tan() - 1.0;
            assert!(off.abs() < 1e-4, "{step}°: {off}");
        }
        assert_eq!(fisheye_coefficient_jacobian(0.0, 0.0), Matrix2x4::zeros());
    }

    /// A known value: the radial models shrink a point at r = 0.5 by 1 + k1 r² + k2 r⁴, and
    /// the fisheye bends by atan; a transpose or sign flip in the parameters would show.
    #[test]
    fn known_values() {
        let c = LensCamera::new(CameraModel::Radial, vec![100.0, 10.0, 20.0, -0.2, 0.1]).unwrap();
        let px = c.project(&Vector3::new(0.5, 0.0, 1.0)).unwrap();
        let scale = 1.0 - 0.2 * 0.25 + 0.1 * 0.0625;
        assert!((px.x - (100.0 * 0.5 * scale + 10.0)).abs() < 1e-12);
        assert!((px.y - 20.0).abs() < 1e-12);
        let f = LensCamera::new(
            CameraModel::OpenCvFisheye,
            vec![100.0, 100.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
        .unwrap();
        let px = f.project(&Vector3::new(1.0, 0.0, 1.0)).unwrap();
        assert!((px.x - 100.0 * std::f64::consts::FRAC_PI_4).abs() < 1e-12);
        assert_eq!(
            CameraModel::from_name("OPENCV").unwrap(),
            CameraModel::OpenCv
        );
        assert!(CameraModel::from_name("FOV").is_err());
        assert!(LensCamera::new(CameraModel::Radial, vec![100.0, 1.0, 2.0]).is_err());
        assert!(LensCamera::new(CameraModel::SimplePinhole, vec![-1.0, 1.0, 2.0]).is_err());
    }

    /// A distortion that folds over (strong negative k1 far out) is an error, not a wrong ray.
    #[test]
    fn a_diverging_undistortion_is_an_error() {
        let c = LensCamera::new(CameraModel::SimpleRadial, vec![100.0, 0.0, 0.0, -0.5]).unwrap();
        // u_d = u (1 − 0.5 u²) peaks at u = 0.816 (u_d = 0.544): beyond it, no inverse.
        assert!(c.unproject(&Vector2::new(70.0, 0.0)).is_err());
        assert!(c.unproject(&Vector2::new(30.0, 0.0)).is_ok());
    }
}
