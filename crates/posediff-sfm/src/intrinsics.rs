//! The one place the mapper builds intrinsics: per image a fixed principal point and a focal
//! `f_i = φ · s_i`, with `φ` shared by all images (unknown or given) and `s_i` a per-image scale
//! (the longer side when the focal is unknown, the known focal when it is given: then `φ = 1`).

use nalgebra::Matrix3;
use posediff_geometry::{ImageSize, Intrinsics};

use crate::error::{Result, SfmError};

/// `K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]`.
pub fn k_matrix(f: f64, principal: [f64; 2]) -> Matrix3<f64> {
    Matrix3::new(f, 0.0, principal[0], 0.0, f, principal[1], 0.0, 0.0, 1.0)
}

/// `K⁻¹` of [`k_matrix`].
pub fn k_inverse(f: f64, principal: [f64; 2]) -> Matrix3<f64> {
    Matrix3::new(
        1.0 / f,
        0.0,
        -principal[0] / f,
        0.0,
        1.0 / f,
        -principal[1] / f,
        0.0,
        0.0,
        1.0,
    )
}

/// The image centre in OpenCV pixels (pixel centres at integers).
pub fn image_centre(size: ImageSize) -> [f64; 2] {
    [
        (f64::from(size.width()) - 1.0) / 2.0,
        (f64::from(size.height()) - 1.0) / 2.0,
    ]
}

/// The focal scale `s` of `f = φ·s` for an unknown focal: the longer side.
pub fn focal_scale(size: ImageSize) -> f64 {
    f64::from(size.width().max(size.height()))
}

/// Fixed per-image intrinsics other than the shared focal factor `φ`.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageIntrinsics {
    /// Principal point per image (pixels).
    pub principal: Vec<[f64; 2]>,
    /// `f_i = φ · scale_i` per image.
    pub scale: Vec<f64>,
}

impl ImageIntrinsics {
    /// Unknown focal: principal points at the image centres, scales the longer sides.
    pub fn from_sizes(sizes: &[ImageSize]) -> Self {
        Self {
            principal: sizes.iter().map(|s| image_centre(*s)).collect(),
            scale: sizes.iter().map(|s| focal_scale(*s)).collect(),
        }
    }

    /// Known intrinsics (`φ = 1`); square pixels are assumed: the mean of `fx` and `fy`.
    pub fn from_known(known: &[Intrinsics]) -> Self {
        Self {
            principal: known.iter().map(|k| [k.cx(), k.cy()]).collect(),
            scale: known.iter().map(|k| 0.5 * (k.fx() + k.fy())).collect(),
        }
    }

    /// Number of images.
    pub fn len(&self) -> usize {
        self.scale.len()
    }

    /// True without images.
    pub fn is_empty(&self) -> bool {
        self.scale.is_empty()
    }

    /// The focal of image `i` in pixels at `φ`.
    pub fn focal(&self, phi: f64, i: usize) -> f64 {
        phi * self.scale[i]
    }

    /// `K_i` at `φ`.
    pub fn k(&self, phi: f64, i: usize) -> Matrix3<f64> {
        k_matrix(self.focal(phi, i), self.principal[i])
    }

    /// `K_i⁻¹` at `φ`.
    pub fn k_inverse(&self, phi: f64, i: usize) -> Matrix3<f64> {
        k_inverse(self.focal(phi, i), self.principal[i])
    }

    /// Image `i`'s intrinsics at `φ`.
    ///
    /// # Errors
    /// A non-positive or non-finite focal.
    pub fn intrinsics(&self, phi: f64, i: usize) -> Result<Intrinsics> {
        let f = self.focal(phi, i);
        let c = self.principal[i];
        Intrinsics::new(f, f, c[0], c[1]).map_err(SfmError::from)
    }

    /// Checks the lengths against `n` images.
    ///
    /// # Errors
    /// Lengths that differ.
    pub fn check(&self, n: usize) -> Result<()> {
        for (what, len) in [
            ("principal points", self.principal.len()),
            ("focal scales", self.scale.len()),
        ] {
            if len != n {
                return Err(SfmError::LengthMismatch {
                    what,
                    left: n,
                    right: len,
                });
            }
        }
        if self.scale.iter().any(|s| !(*s > 0.0 && s.is_finite())) {
            return Err(SfmError::InvalidInput(
                "focal scales must be positive and finite".into(),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn k_and_its_inverse() {
        let k = k_matrix(500.0, [319.5, 239.5]);
        let p = k * k_inverse(500.0, [319.5, 239.5]);
        assert!((p - Matrix3::identity()).norm() < 1e-14);
        let size = ImageSize::new(640, 480).unwrap();
        let l = ImageIntrinsics::from_sizes(&[size]);
        assert_eq!(l.principal[0], [319.5, 239.5]);
        assert_eq!(l.focal(1.2, 0), 768.0);
        assert!(l.check(2).is_err());
    }
}
