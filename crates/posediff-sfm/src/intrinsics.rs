//! The one place the mapper builds intrinsics: per image a fixed principal point and a focal
//! `f_i = φ · s_i`, with `φ` shared by all images (unknown or given) and `s_i` a per-image scale
//! (the longer side when the focal is unknown, the known focal when it is given: then `φ = 1`).
//!
//! Images are grouped into cameras (`group`, COLMAP's camera id): the bundle adjustment refines
//! one focal factor per group (`f_i = φ_g · s_i`), and the stages before it use the shared `φ`
//! with each group's ratio to the first folded into `s_i`
//! ([`crate::view_graph_calibration`] estimates those ratios).

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
    /// The camera (group) of each image: `0..groups()`, every group used. Images of one group
    /// share their focal factor in the bundle adjustment.
    pub group: Vec<usize>,
}

impl ImageIntrinsics {
    /// One camera for all images with these principal points and focal scales.
    pub fn new(principal: Vec<[f64; 2]>, scale: Vec<f64>) -> Self {
        let group = vec![0; scale.len()];
        Self {
            principal,
            scale,
            group,
        }
    }

    /// Unknown focal: principal points at the image centres, scales the longer sides; one
    /// camera.
    pub fn from_sizes(sizes: &[ImageSize]) -> Self {
        Self::new(
            sizes.iter().map(|s| image_centre(*s)).collect(),
            sizes.iter().map(|s| focal_scale(*s)).collect(),
        )
    }

    /// Known intrinsics (`φ = 1`); square pixels are assumed: the mean of `fx` and `fy`.
    pub fn from_known(known: &[Intrinsics]) -> Self {
        Self::new(
            known.iter().map(|k| [k.cx(), k.cy()]).collect(),
            known.iter().map(|k| 0.5 * (k.fx() + k.fy())).collect(),
        )
    }

    /// The number of cameras (groups).
    pub fn groups(&self) -> usize {
        self.group.iter().max().map_or(0, |g| g + 1)
    }

    /// Folds per-group focal factors into the scales: `s_i ← s_i · φ_g / φ_0`; returns `φ_0`,
    /// with which [`Self::focal`] gives each image its group's focal.
    pub fn fold_factors(&mut self, factors: &[f64]) -> f64 {
        let Some(&first) = factors.first() else {
            return 1.0;
        };
        for (s, g) in self.scale.iter_mut().zip(&self.group) {
            if let Some(f) = factors.get(*g) {
                *s *= f / first;
            }
        }
        first
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
            ("camera groups", self.group.len()),
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
        let mut used = vec![false; self.groups()];
        for g in &self.group {
            used[*g] = true;
        }
        if let Some(g) = used.iter().position(|u| !u) {
            return Err(SfmError::InvalidInput(format!(
                "camera group {g} of {} has no image",
                used.len()
            )));
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
