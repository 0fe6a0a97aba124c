//! The official GGS schedule on cameras from the mapper (`--refine official`): the cameras in
//! their 224 crops, the matches mapped into the crops, the five phases of
//! `posediff_guidance::GgsSolver`.

use posediff_geometry::{
    Camera, CenterCrop, ImageSize, MODEL_INPUT_SIDE, PairMatches, PoseEncoding, QuaternionSign,
};
use posediff_guidance::{GgsConfig, GgsSolver};

use crate::error::{PosediffError, Result};

/// The official GGS schedule on the estimated cameras, in place: each camera into its 224 crop
/// and encoded, the matches of the estimated images mapped into the crops, the five phases, and
/// back to original pixels.
///
/// # Errors
/// Cameras that cannot be encoded; invalid GGS settings.
pub fn official_ggs(
    cameras: &mut [Option<Camera>],
    pairs: &[PairMatches],
    config: &GgsConfig,
) -> Result<()> {
    let members: Vec<usize> = (0..cameras.len())
        .filter(|&i| cameras[i].is_some())
        .collect();
    if members.len() < 2 {
        return Ok(());
    }
    let crops: Vec<Option<CenterCrop>> = cameras
        .iter()
        .map(|c| c.map(|c| CenterCrop::official(c.image_size, MODEL_INPUT_SIDE)))
        .collect();
    let set = model_frame_matches(pairs, &crops)?;
    let mut encodings = members
        .iter()
        .map(|&i| match (cameras[i], crops[i]) {
            (Some(c), Some(crop)) => Ok(PoseEncoding::from_camera(
                &crop.camera_to_model(&c)?,
                QuaternionSign::default(),
            )?),
            _ => Err(PosediffError::InvalidArgument("missing camera".into())),
        })
        .collect::<Result<Vec<_>>>()?;
    GgsSolver::new(&set, *config)?.run(&mut encodings, None)?;
    let model = ImageSize::new(MODEL_INPUT_SIDE, MODEL_INPUT_SIDE)?;
    for (&i, e) in members.iter().zip(&encodings) {
        if let (Some(c), Some(crop)) = (cameras[i].as_mut(), crops[i]) {
            let mut refined = crop.camera_from_model(&e.to_camera(model)?, c.image_size)?;
            if config.fix_focal {
                refined.intrinsics = c.intrinsics;
            }
            *c = refined;
        }
    }
    Ok(())
}

/// Matches in original pixels → the 224-crop frame of each image, as a GGS match set over the
/// images that have a crop (`crops[i]`: image `i`'s crop, `None` to leave it out). The set's
/// frame `k` is the `k`-th image with a crop; pairs touching an image without one are
/// skipped.
///
/// # Errors
/// Invalid pairs.
pub fn model_frame_matches(
    pairs: &[PairMatches],
    crops: &[Option<CenterCrop>],
) -> Result<posediff_guidance::MatchSet> {
    let mut frame_of = vec![None; crops.len()];
    let mut members = 0;
    for (slot, crop) in frame_of.iter_mut().zip(crops) {
        if crop.is_some() {
            *slot = Some(members);
            members += 1;
        }
    }
    let (mut kp1, mut kp2, mut frames) = (Vec::new(), Vec::new(), Vec::new());
    for p in pairs {
        let (Some(Some(a)), Some(Some(b)), Some(Some(ca)), Some(Some(cb))) = (
            frame_of.get(p.first),
            frame_of.get(p.second),
            crops.get(p.first),
            crops.get(p.second),
        ) else {
            continue;
        };
        for (x, y) in p.kp1.iter().zip(&p.kp2) {
            kp1.push(ca.to_model(*x));
            kp2.push(cb.to_model(*y));
            frames.push((*a, *b));
        }
    }
    Ok(posediff_guidance::MatchSet::new(
        members, &kp1, &kp2, &frames,
    )?)
}
