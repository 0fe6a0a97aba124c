//! CO3Dv2 annotations in the RelPose++/PoseDiffusion layout (`{category}_{split}.jgz`: gzip
//! JSON `{sequence_name: [frame, ...]}`, frame = `{filepath, bbox, R, T, focal_length,
//! principal_point}` in PyTorch3D conventions, NDC of the original image), and the official
//! test protocol's choice of frames (SPEC.md §7.2).

use std::io::Read;
use std::path::{Path, PathBuf};

use posediff_geometry::camera_json::Pytorch3dParams;
use posediff_geometry::pytorch3d::CropBox;
use posediff_geometry::{
    Camera, Canonicalized, CenterCrop, ImageSize, MODEL_INPUT_SIDE, Pose, Pytorch3dCamera,
    canonicalize,
};
use posediff_metrics::numpy_rng::LegacyRandomState;
use serde::Deserialize;

use crate::error::{PosediffError, Result};

/// The 41 training ("seen") categories of the official CO3Dv2 loader.
pub const SEEN_CATEGORIES: [&str; 41] = [
    "apple",
    "backpack",
    "banana",
    "baseballbat",
    "baseballglove",
    "bench",
    "bicycle",
    "bottle",
    "bowl",
    "broccoli",
    "cake",
    "car",
    "carrot",
    "cellphone",
    "chair",
    "cup",
    "donut",
    "hairdryer",
    "handbag",
    "hydrant",
    "keyboard",
    "laptop",
    "microwave",
    "motorcycle",
    "mouse",
    "orange",
    "parkingmeter",
    "pizza",
    "plant",
    "stopsign",
    "teddybear",
    "toaster",
    "toilet",
    "toybus",
    "toyplane",
    "toytrain",
    "toytruck",
    "tv",
    "umbrella",
    "vase",
    "wineglass",
];

/// The 10 held-out ("unseen") categories.
pub const UNSEEN_CATEGORIES: [&str; 10] = [
    "ball",
    "book",
    "couch",
    "frisbee",
    "hotdog",
    "kite",
    "remote",
    "sandwich",
    "skateboard",
    "suitcase",
];

/// The official loader's minimum frames per sequence (`min_num_images`).
pub const DEFAULT_MIN_FRAMES: usize = 50;
/// Frames drawn per test sequence in `test.py`.
pub const DEFAULT_TEST_FRAMES: usize = 10;
/// A sequence with any frame whose `T0 + T1 + T2` exceeds this is dropped.
pub const MAX_TRANSLATION_SUM: f64 = 1e5;

/// One annotated frame.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct Co3dFrame {
    /// Image path relative to the CO3D root.
    pub filepath: String,
    /// Mask bounding box `[x0, y0, x1, y1]` (unused with the centre crop).
    pub bbox: [f64; 4],
    /// The PyTorch3D camera, NDC of the original image.
    #[serde(flatten)]
    pub camera: Pytorch3dParams,
}

impl Co3dFrame {
    /// The PyTorch3D camera of the annotation.
    pub fn pytorch3d(&self) -> Pytorch3dCamera {
        self.camera.camera()
    }

    /// The extrinsics in the OpenCV convention.
    pub fn cam_from_world(&self) -> Pose {
        self.pytorch3d().opencv_pose()
    }

    /// The camera of the official 224-px centre crop of this frame's image (`image_size`: the
    /// image file's size): `adjust_camera_to_bbox_crop_` with the centre square (the loader's
    /// `center_box`, integer offsets as the demo loader), then `adjust_camera_to_image_scale_`
    /// to 224, as an OpenCV camera of the crop.
    ///
    /// # Errors
    /// Invalid intrinsics.
    pub fn crop_camera(&self, image_size: ImageSize) -> Result<Camera> {
        let crop = CenterCrop::official(image_size, MODEL_INPUT_SIDE);
        let side = f64::from(crop.side);
        let box_ = CropBox {
            x0: f64::from(crop.left),
            y0: f64::from(crop.top),
            width: side,
            height: side,
        };
        let target = f64::from(MODEL_INPUT_SIDE);
        let mut p3d = self.pytorch3d();
        p3d.intrinsics = p3d
            .intrinsics
            .adjusted_to_crop(
                f64::from(image_size.width()),
                f64::from(image_size.height()),
                &box_,
            )
            .adjusted_to_scale((side, side), (target, target));
        Ok(p3d.to_opencv(ImageSize::new(MODEL_INPUT_SIDE, MODEL_INPUT_SIDE)?)?)
    }
}

/// The ground truth of a set of frames as the official loader returns it: crop cameras
/// ([`Co3dFrame::crop_camera`]) canonicalised (optical-axis intersection, camera 0's distance,
/// camera 0's PyTorch3D frame; SPEC.md §2).
///
/// # Errors
/// Mismatched lengths, invalid intrinsics, degenerate geometry (parallel optical axes).
pub fn normalized_ground_truth(
    frames: &[&Co3dFrame],
    image_sizes: &[ImageSize],
) -> Result<Canonicalized> {
    if frames.len() != image_sizes.len() {
        return Err(bad_file(
            Path::new("ground truth"),
            format!("{} frames, {} image sizes", frames.len(), image_sizes.len()),
        ));
    }
    let cams = frames
        .iter()
        .zip(image_sizes)
        .map(|(f, s)| f.crop_camera(*s))
        .collect::<Result<Vec<_>>>()?;
    Ok(canonicalize(&cams)?)
}

/// One annotated sequence, frames in annotation order.
#[derive(Debug, Clone, PartialEq)]
pub struct Co3dSequence {
    /// Sequence name.
    pub name: String,
    /// Its frames.
    pub frames: Vec<Co3dFrame>,
}

fn bad_file(path: &Path, why: String) -> PosediffError {
    PosediffError::invalid(path, why)
}

/// Reads `{category}_{split}.jgz`, sequences in file order.
///
/// # Errors
/// Missing files, bad gzip, JSON that does not have the documented fields (the message names
/// the file, the sequence and the field).
pub fn load_annotations(path: &Path) -> Result<Vec<Co3dSequence>> {
    let file = std::fs::File::open(path).map_err(|e| PosediffError::read(path, e))?;
    let compressed = file.metadata().map(|m| m.len()).unwrap_or(0);
    // JSON compresses about 10x; more than 200x (or 1 GiB) is a bomb, not annotations.
    let limit = compressed.saturating_mul(200).clamp(1 << 20, 1 << 30);
    let mut text = String::new();
    let read = flate2::read::GzDecoder::new(file)
        .take(limit + 1)
        .read_to_string(&mut text)
        .map_err(|e| bad_file(path, format!("not a gzip JSON file: {e}")))?;
    if read as u64 > limit {
        return Err(bad_file(
            path,
            format!("decompresses to more than {limit} bytes: not annotations"),
        ));
    }
    let raw: serde_json::Map<String, serde_json::Value> = serde_json::from_str(&text)
        .map_err(|e| bad_file(path, format!("not a JSON object of sequences: {e}")))?;
    raw.into_iter()
        .map(|(name, frames)| {
            let frames: Vec<Co3dFrame> = serde_json::from_value(frames)
                .map_err(|e| bad_file(path, format!("sequence {name}: {e}")))?;
            Ok(Co3dSequence { name, frames })
        })
        .collect()
}

/// The official loader's filter: at least `min_frames` frames and no frame with
/// `T0 + T1 + T2 > 1e5`.
pub fn usable_sequences(sequences: &[Co3dSequence], min_frames: usize) -> Vec<&Co3dSequence> {
    sequences
        .iter()
        .filter(|s| s.frames.len() >= min_frames)
        .filter(|s| {
            s.frames
                .iter()
                .all(|f| f.camera.t.iter().sum::<f64>() <= MAX_TRANSLATION_SUM)
        })
        .collect()
}

/// `test.py`'s frames for each sequence, in order: `rng.choice(len, num_frames, replace=False)`
/// per sequence with at least `num_frames` frames (others get none and draw nothing), then
/// sorted by file path.
///
/// # Errors
/// Never for valid counts (kept for the RNG's contract).
pub fn official_frame_ids(
    sequences: &[&Co3dSequence],
    num_frames: usize,
    rng: &mut LegacyRandomState,
) -> Result<Vec<Vec<usize>>> {
    sequences
        .iter()
        .map(|s| {
            if s.frames.len() < num_frames {
                return Ok(Vec::new());
            }
            let mut ids = rng.choice_without_replacement(s.frames.len(), num_frames)?;
            ids.sort_by(|a, b| s.frames[*a].filepath.cmp(&s.frames[*b].filepath));
            Ok(ids)
        })
        .collect::<std::result::Result<_, _>>()
        .map_err(|e: posediff_metrics::MetricsError| {
            bad_file(Path::new("frame selection"), e.to_string())
        })
}

/// The image of a frame under the CO3D root.
pub fn frame_path(root: &Path, frame: &Co3dFrame) -> PathBuf {
    root.join(&frame.filepath)
}
