//! Everything read from or written to disk: the images, per-image records, and each export
//! format, all from the one [`crate::reconstruction::Reconstruction`].
//!
//! - [`loader`]: the official image loader (sorted files, centre crop, 224 px), PNG writing.
//! - [`records`]: per-image records matched to the images by name, never by position.
//! - [`export`]: cameras.json, nerfstudio (+ PLY) and PyTorch3D writers and readers.
//! - [`colmap`]: COLMAP sparse models, text and binary, with points.
//! - [`database`]: COLMAP 4.2's `database.db` (keypoints, verified matches, two-view geometries).
//! - [`co3d`]: CO3Dv2 annotations and the official test protocol's frame choice.
//! - [`outputs`]: the output folder (COLMAP sparse/0, images, nerfstudio, PLY, viewer).
//! - [`viewer`]: view.html, a self-contained three.js page.
//! - [`exif`]: the camera and focal prior an image's EXIF gives (COLMAP's rules), and writing
//!   EXIF into copies.
//! - [`variants`]: harder copies of a set (zoomed photos) with their ground truth transformed.
//! - [`synthetic_video`]: a `posediff-synth` orbit encoded as a capture video, with exact cameras.
//! - [`video`]: video input: probing, one decoding pass, keyframes written with their account.

pub mod co3d;
pub mod colmap;
pub mod database;
pub mod exif;
pub mod export;
pub mod loader;
pub mod outputs;
pub mod records;
pub mod synthetic_video;
pub mod undistort;
pub mod variants;
pub mod video;
pub mod viewer;
