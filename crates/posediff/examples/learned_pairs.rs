//! Per-pair statistics of the learned matcher on a set with ground truth: LightGlue's raw
//! matches, MAGSAC inliers, the inlier ratio, and the fraction of inliers within 4 px² (Sampson)
//! of the ground-truth epipolar geometry, with the pair's ground-truth rotation angle.
//!
//! `cargo run --release -p posediff --example learned_pairs -- <set folder> <weights dir>
//! [aliked-n16 | aliked-n16rot]` (a set folder holds `images/` and `cameras.json`). One line
//! per pair on stdout.

use std::path::PathBuf;

use anyhow::{Context, Result};
use posediff::correspondences::{LearnedMatcher, SharedLearned, extract_all, match_pairs};
use posediff_geometry::epipolar::{
    fundamental_from_cameras, rotation_angle_between_deg, sampson_error,
};
use posediff_matching::MatchConfig;

#[allow(clippy::print_stdout)]
fn main() -> Result<()> {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let (set, weights, aliked) = match args.as_slice() {
        [set, weights] => (set, weights, posediff_learned::WeightSet::AlikedN16),
        [set, weights, v] if v.as_os_str() == "aliked-n16" => {
            (set, weights, posediff_learned::WeightSet::AlikedN16)
        }
        [set, weights, v] if v.as_os_str() == "aliked-n16rot" => {
            (set, weights, posediff_learned::WeightSet::AlikedN16Rot)
        }
        _ => anyhow::bail!(
            "usage: learned_pairs <set folder> <weights dir> [aliked-n16 | aliked-n16rot]"
        ),
    };
    let gt = posediff::io::export::read_cameras_json(&set.join("cameras.json"))?;
    let mut images: Vec<PathBuf> = std::fs::read_dir(set.join("images"))?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()?;
    images.sort();
    let cams = images
        .iter()
        .map(|p| {
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            gt.iter()
                .find(|c| c.image.ends_with(&name))
                .map(|c| c.camera)
                .with_context(|| format!("no ground truth for {name}"))
        })
        .collect::<Result<Vec<_>>>()?;
    let learned = SharedLearned(std::sync::Arc::new(LearnedMatcher::load_with(
        weights, aliked,
    )?));
    let features = extract_all(&images, &MatchConfig::default(), Some(&learned))?;
    let pairs = posediff_matching::exhaustive_pairs(images.len());
    let raw_config = MatchConfig {
        verification: None,
        ..MatchConfig::default()
    };
    let raw = match_pairs(&features, &pairs, &raw_config, Some(&learned))?;
    // The verification of the default configuration, on the same raw matches.
    let config = MatchConfig::default();
    let verified = raw
        .iter()
        .map(|r| Ok(posediff_matching::verify(r.clone(), &config)?))
        .collect::<Result<Vec<_>>>()?;
    println!("i j gt_angle raw inliers ratio good_fraction");
    for ((r, v), &(i, j)) in raw.iter().zip(&verified).zip(&pairs) {
        let (a, b) = (cams[i], cams[j]);
        let f = fundamental_from_cameras(&a, &b);
        let good = v
            .kp1
            .iter()
            .zip(&v.kp2)
            .filter(|(x, y)| {
                let (x, y) = (
                    nalgebra::Point2::new(x[0], x[1]),
                    nalgebra::Point2::new(y[0], y[1]),
                );
                sampson_error(&f, &x, &y).is_ok_and(|e| e < 4.0)
            })
            .count();
        let angle =
            rotation_angle_between_deg(&a.cam_from_world.rotation, &b.cam_from_world.rotation);
        println!(
            "{i} {j} {angle:.1} {} {} {:.3} {:.3}",
            r.len(),
            v.len(),
            v.len() as f64 / r.len().max(1) as f64,
            good as f64 / v.len().max(1) as f64
        );
    }
    Ok(())
}
