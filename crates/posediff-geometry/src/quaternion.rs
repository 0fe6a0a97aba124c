//! Quaternions, real part first, exactly as PyTorch3D (and so PoseDiffusion) uses them.
//!
//! A quaternion `q = (w, x, y, z)` maps to the rotation matrix
//!
//! ```text
//! s = 2 / |q|²
//! [[1 − s(y²+z²), s(xy − zw),     s(xz + yw)   ],
//!  [s(xy + zw),   1 − s(x²+z²),   s(yz − xw)   ],
//!  [s(xz − yw),   s(yz + xw),     1 − s(x²+y²) ]]
//! ```
//!
//! which is PyTorch3D's `quaternion_to_matrix`. Dividing by `|q|²` means a non-unit quaternion
//! gives the same proper rotation as its normalisation: the official pose decode never normalises
//! and relies on this.
//!
//! # Pitfalls
//! - Order is w-first (`[w, x, y, z]`), not nalgebra's `[x, y, z, w]` storage order.
//! - PyTorch3D uses this matrix as the *row-vector* rotation of its cameras
//!   (`X_cam = X_world · R`); in the OpenCV convention it appears transposed (see
//!   [`crate::pytorch3d`]).
//! - `q` and `−q` are the same rotation; which one matrix→quaternion returns depends on the
//!   PyTorch3D version ([`QuaternionSign`]).

use nalgebra::Matrix3;

use crate::error::{GeometryError, Result, ensure_finite};

/// The floor PyTorch3D's `matrix_to_quaternion` puts under the candidate denominators
/// (`q_abs.max(0.1)`), pytorch3d/transforms/rotation_conversions.py.
const CANDIDATE_DENOMINATOR_FLOOR: f64 = 0.1;

/// A quaternion `w + xi + yj + zk`, real part first. Not necessarily of unit norm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quaternion {
    /// Real part.
    pub w: f64,
    /// First imaginary part.
    pub x: f64,
    /// Second imaginary part.
    pub y: f64,
    /// Third imaginary part.
    pub z: f64,
}

/// Which of the two quaternions `q`, `−q` of a rotation [`Quaternion::from_rotation_matrix`]
/// returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum QuaternionSign {
    /// PyTorch3D ≤ 0.7.5 (what the official code was run with): the component of largest
    /// magnitude is positive.
    #[default]
    LargestComponentPositive,
    /// PyTorch3D ≥ 0.7.6 (`standardize_quaternion`): `w ≥ 0`.
    NonNegativeReal,
}

impl Quaternion {
    /// The identity rotation `(1, 0, 0, 0)`.
    pub const IDENTITY: Self = Self {
        w: 1.0,
        x: 0.0,
        y: 0.0,
        z: 0.0,
    };

    /// Builds a quaternion from its four components, real part first.
    pub const fn new(w: f64, x: f64, y: f64, z: f64) -> Self {
        Self { w, x, y, z }
    }

    /// Builds a quaternion from `[w, x, y, z]`.
    pub const fn from_wxyz(q: [f64; 4]) -> Self {
        Self::new(q[0], q[1], q[2], q[3])
    }

    /// The components as `[w, x, y, z]`.
    pub const fn to_wxyz(self) -> [f64; 4] {
        [self.w, self.x, self.y, self.z]
    }

    /// `w² + x² + y² + z²`.
    pub fn norm_squared(self) -> f64 {
        self.w * self.w + self.x * self.x + self.y * self.y + self.z * self.z
    }

    /// The same rotation with `w ≥ 0` (PyTorch3D's `standardize_quaternion`).
    pub fn standardized(self) -> Self {
        if self.w < 0.0 {
            Self::new(-self.w, -self.x, -self.y, -self.z)
        } else {
            self
        }
    }

    /// The rotation matrix of this quaternion (PyTorch3D `quaternion_to_matrix`), accepting
    /// non-unit quaternions by dividing by `|q|²`.
    ///
    /// # Errors
    /// [`GeometryError::ZeroQuaternion`] for `|q| = 0`, [`GeometryError::NonFinite`] for NaN or
    /// infinite components.
    pub fn to_rotation_matrix(self) -> Result<Matrix3<f64>> {
        ensure_finite("quaternion", &self.to_wxyz())?;
        let n2 = self.norm_squared();
        if n2 == 0.0 || !n2.is_finite() {
            return Err(GeometryError::ZeroQuaternion);
        }
        let s = 2.0 / n2;
        let Self {
            w: r,
            x: i,
            y: j,
            z: k,
        } = self;
        Ok(Matrix3::new(
            1.0 - s * (j * j + k * k),
            s * (i * j - k * r),
            s * (i * k + j * r),
            s * (i * j + k * r),
            1.0 - s * (i * i + k * k),
            s * (j * k - i * r),
            s * (i * k - j * r),
            s * (j * k + i * r),
            1.0 - s * (i * i + j * j),
        ))
    }

    /// The quaternion of a rotation matrix by PyTorch3D's `matrix_to_quaternion` algorithm: four
    /// candidates, keep the best-conditioned one; the result has unit norm for a rotation.
    ///
    /// # Errors
    /// [`GeometryError::NonFinite`] for NaN or infinite entries.
    pub fn from_rotation_matrix(m: &Matrix3<f64>, sign: QuaternionSign) -> Result<Self> {
        ensure_finite("rotation matrix", m.iter())?;
        let (m00, m01, m02) = (m[(0, 0)], m[(0, 1)], m[(0, 2)]);
        let (m10, m11, m12) = (m[(1, 0)], m[(1, 1)], m[(1, 2)]);
        let (m20, m21, m22) = (m[(2, 0)], m[(2, 1)], m[(2, 2)]);
        let sqrt_positive = |v: f64| if v > 0.0 { v.sqrt() } else { 0.0 };
        let q_abs = [
            sqrt_positive(1.0 + m00 + m11 + m22),
            sqrt_positive(1.0 + m00 - m11 - m22),
            sqrt_positive(1.0 - m00 + m11 - m22),
            sqrt_positive(1.0 - m00 - m11 + m22),
        ];
        // torch.argmax returns the first maximum.
        let mut best = 0;
        for (idx, &v) in q_abs.iter().enumerate().skip(1) {
            if v > q_abs[best] {
                best = idx;
            }
        }
        let a = q_abs[best];
        let candidate = match best {
            0 => [a * a, m21 - m12, m02 - m20, m10 - m01],
            1 => [m21 - m12, a * a, m10 + m01, m02 + m20],
            2 => [m02 - m20, m10 + m01, a * a, m12 + m21],
            _ => [m10 - m01, m20 + m02, m21 + m12, a * a],
        };
        let denom = 2.0 * a.max(CANDIDATE_DENOMINATOR_FLOOR);
        let q = Self::from_wxyz(candidate.map(|c| c / denom));
        Ok(match sign {
            QuaternionSign::LargestComponentPositive => q,
            QuaternionSign::NonNegativeReal => q.standardized(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_round_trips() {
        let m = Quaternion::IDENTITY.to_rotation_matrix().unwrap();
        assert_eq!(m, Matrix3::identity());
        let q = Quaternion::from_rotation_matrix(&m, QuaternionSign::default()).unwrap();
        assert_eq!(q, Quaternion::IDENTITY);
    }

    #[test]
    fn non_unit_quaternion_gives_the_same_rotation() {
        let q = Quaternion::new(0.3, -0.5, 0.7, 0.2);
        let scaled = Quaternion::new(3.0 * q.w, 3.0 * q.x, 3.0 * q.y, 3.0 * q.z);
        let a = q.to_rotation_matrix().unwrap();
        let b = scaled.to_rotation_matrix().unwrap();
        assert!((a - b).norm() < 1e-14);
        assert!((a.transpose() * a - Matrix3::identity()).norm() < 1e-14);
        assert!((a.determinant() - 1.0).abs() < 1e-14);
    }

    #[test]
    fn zero_and_nan_quaternions_are_errors() {
        assert_eq!(
            Quaternion::new(0.0, 0.0, 0.0, 0.0).to_rotation_matrix(),
            Err(GeometryError::ZeroQuaternion)
        );
        assert!(matches!(
            Quaternion::new(f64::NAN, 0.0, 0.0, 1.0).to_rotation_matrix(),
            Err(GeometryError::NonFinite { .. })
        ));
    }

    #[test]
    fn rotation_about_z_has_the_right_handedness() {
        // 90° about +z: (w, z) = (cos 45°, sin 45°) maps x to y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let m = Quaternion::new(h, 0.0, 0.0, h)
            .to_rotation_matrix()
            .unwrap();
        let y = m * nalgebra::Vector3::x();
        assert!((y - nalgebra::Vector3::y()).norm() < 1e-15);
    }

    #[test]
    fn sign_conventions_differ_only_in_sign() {
        // A rotation whose largest component is x, with w < 0 in the first convention.
        let q = Quaternion::new(-0.2, 0.9, 0.3, -0.1);
        let m = q.to_rotation_matrix().unwrap();
        let a =
            Quaternion::from_rotation_matrix(&m, QuaternionSign::LargestComponentPositive).unwrap();
        let b = Quaternion::from_rotation_matrix(&m, QuaternionSign::NonNegativeReal).unwrap();
        assert!(a.x > 0.0 && a.w < 0.0);
        assert!(b.w >= 0.0 && b.x < 0.0);
        for (u, v) in a.to_wxyz().iter().zip(b.to_wxyz()) {
            assert!((u + v).abs() < 1e-15);
        }
    }
}
