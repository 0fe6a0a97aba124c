//! The checkpoint-free global mapper of posediff: camera poses (and sparse points) from
//! pairwise matches and two-view geometries, as a global structure-from-motion pipeline
//! (GLOMAP's order of stages).
//!
//! | stage | module |
//! |---|---|
//! | view graph: components, union-find | [`view_graph`] |
//! | a shared focal: self-calibration, homographies | [`focal`], [`intrinsics`] |
//! | a focal per camera, cameras from the data (ViewGraphCalibrator) | [`view_graph_calibration`] |
//! | radial distortion from the pairs' epipolar residuals (one k1 per camera) | [`distortion_calibration`] |
//! | rotation averaging (MST + Cauchy IRLS) | [`rotation_averaging`] |
//! | translation averaging (LUD, scales eliminated) | [`translation_averaging`] |
//! | Sampson refinement (GGS's objective to convergence) | [`sampson_refine`] |
//! | tracks by union-find over keypoint ids | [`tracks`] |
//! | resection of the cameras on view-graph bridges (PnP on the other side's tracks) | [`resection`] |
//! | bundle adjustment (Schur complement) | [`bundle`] |
//! | cameras split by a focal per image in the bundle adjustment (cameras from the data) | [`camera_split`] |
//! | radial distortion from the tracks (the lens in the bundle adjustment, photo pixels) | [`lens_refinement`] |
//! | sparse points for export (any cameras) | [`points`] |
//! | all of it, with one options struct per stage | [`mapper`] |
//! | the geometry the mapper asks of its caller (two-view, resection) | [`solver`] |
//! | cameras from elsewhere refined (Sampson, then bundle adjustment) | [`bundle_refine`] |
//!
//! Every linear solve is faer's ([`linalg`]): sparse Cholesky with the symbolic factorisation
//! computed once per problem for every system whose size grows with the images, dense faer for
//! the small ones. Every refinement is one Levenberg–Marquardt core ([`lm`]) with analytic
//! Jacobians. Degeneracy is reported (an error, or an image marked not estimated with its
//! reason), never replaced by a guess.
//!
//! The crate takes matches ([`posediff_geometry::PairMatches`], with keypoint ids) and a
//! [`mapper::GeometrySolver`] for relative and absolute poses: it never depends on OpenCV or candle.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

/// `impl serde::Serialize` writing a value as its `as_str()` name (the reports' enums).
#[cfg(feature = "serde")]
macro_rules! serialize_as_str {
    ($($t:ty),*) => {$(
        impl serde::Serialize for $t {
            fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
                s.serialize_str(self.as_str())
            }
        }
    )*};
}

pub mod bundle;
pub mod bundle_refine;
pub mod camera;
pub mod camera_split;
pub mod distortion_calibration;
pub mod error;
pub mod focal;
pub mod intrinsics;
pub mod lens_refinement;
pub mod linalg;
pub mod lm;
pub mod mapper;
pub mod points;
pub mod report;
pub mod resection;
pub mod rotation_averaging;
pub mod sampson_refine;
pub mod solver;
#[cfg(test)]
mod test_scenes;
pub mod tracks;
pub mod translation_averaging;
pub mod view_graph;
pub mod view_graph_calibration;

pub use camera::CameraPose;
pub use error::{Result, SfmError};
pub use intrinsics::ImageIntrinsics;
pub use linalg::Solver;
pub use mapper::{GlobalMapper, MapperOptions};
pub use report::MapperReport;
