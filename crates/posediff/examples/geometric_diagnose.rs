//! Runs the checkpoint-free estimate on a set with ground truth and prints what each stage did:
//! `cargo run --release -p posediff --example geometric_diagnose -- ../shared/data/middlebury_templeSR [frame indices...]`
#![allow(clippy::print_stdout)]

use std::path::PathBuf;

use anyhow::Context;
use posediff::estimate::geometric::{GeometricConfig, estimate_geometric};
use posediff::io::export::read_cameras_json;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let dir = PathBuf::from(
        args.first()
            .context("usage: geometric_diagnose DIR [indices]")?,
    );
    let gt = read_cameras_json(&dir.join("cameras.json"))?;
    let pick: Vec<usize> = if args.len() > 1 {
        args[1..]
            .iter()
            .map(|a| a.parse())
            .collect::<Result<_, _>>()?
    } else {
        (0..gt.len()).collect()
    };
    let images: Vec<PathBuf> = pick.iter().map(|&i| dir.join(&gt[i].image)).collect();
    let mut config = GeometricConfig::default();
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
    if let Some(v) = env("KP") {
        config.options.matching.features.max_keypoints = v as usize;
    }
    if let Some(v) = env("CT") {
        config.options.matching.features.contrast_threshold = v;
    }
    if let Some(v) = env("MINV") {
        config.options.matching.min_verified = v as usize;
    }
    if let Some(v) = env("RATIO") {
        config.options.matching.ratio = Some(v as f32);
    }
    if let (Some(v), Some(ver)) = (env("VTH"), config.options.matching.verification.as_mut()) {
        ver.threshold_px = v;
    }
    if let Some(v) = env("SIDE") {
        config.options.matching.features.max_image_side = v as u32;
    }
    if env("NOBA").is_some() {
        config.options.mapper.bundle = None;
    }
    if let Some(v) = env("FOCAL") {
        config.intrinsics = posediff::estimate::geometric::KnownIntrinsics::FocalPx(v);
    }
    let e = estimate_geometric(&images, &config)?;
    for (k, c) in e.cameras.iter().enumerate() {
        if let Some(c) = c {
            let p = c.center();
            println!("centre {k:>2}: {:8.3} {:8.3} {:8.3}", p.x, p.y, p.z);
        }
    }
    println!("{}", serde_json::to_string_pretty(&e.report)?);
    for w in &e.warnings {
        println!("warning: {w}");
    }
    let gt_f = gt[pick[0]].camera.intrinsics.fx();
    let size = e.sizes[0];
    println!(
        "GT focal {gt_f:.1} px = phi {:.4}",
        gt_f / f64::from(size.width().max(size.height()))
    );
    {
        use posediff_sfm::sampson_refine::robust_cost;
        use posediff_sfm::{CameraPose as RefineCamera, ImageIntrinsics};
        let set: &[&posediff_geometry::PairMatches] = &e.pairs.iter().collect::<Vec<_>>();
        let layout = ImageIntrinsics::from_sizes(&e.sizes);
        let to_refine = |c: &posediff_geometry::Camera| RefineCamera {
            rotation: nalgebra::Rotation3::from_matrix_unchecked(c.cam_from_world.rotation),
            center: c.center().coords,
        };
        let truth: Vec<_> = pick
            .iter()
            .map(|&i| Some(to_refine(&gt[i].camera)))
            .collect();
        let ours: Vec<_> = e
            .cameras
            .iter()
            .map(|c| c.as_ref().map(to_refine))
            .collect();
        let gt_phi = gt[pick[0]].camera.intrinsics.fx() / layout.scale[0];
        println!(
            "robust cost: ours {:.3} (phi {:.4}), ground truth {:.3} (phi {gt_phi:.4})",
            robust_cost(set, &layout, &ours, e.report.focal_factor, 1.0, 10.0)?,
            e.report.focal_factor,
            robust_cost(set, &layout, &truth, gt_phi, 1.0, 10.0)?,
        );
    }
    for (a, &i) in pick.iter().enumerate() {
        for (b, &j) in pick.iter().enumerate().skip(a + 1) {
            let (Some(ca), Some(cb)) = (e.cameras[a], e.cameras[b]) else {
                continue;
            };
            let rel = |p: &posediff_geometry::Pose, q: &posediff_geometry::Pose| {
                posediff_geometry::epipolar::relative_pose(p, q)
            };
            let est = rel(&ca.cam_from_world, &cb.cam_from_world);
            let truth = rel(&gt[i].camera.cam_from_world, &gt[j].camera.cam_from_world);
            let r = est.rotation * truth.rotation.transpose();
            let rot = ((r.trace() - 1.0) / 2.0)
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees();
            let t = est
                .translation
                .normalize()
                .dot(&truth.translation.normalize())
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees();
            let n = e
                .pairs
                .iter()
                .find(|p| p.first == a && p.second == b)
                .map_or(0, |p| p.len());
            let two_view = e
                .pairs
                .iter()
                .find(|p| p.first == a && p.second == b && !p.is_empty())
                .and_then(|p| {
                    let k = ca.intrinsics.matrix();
                    posediff_matching::two_view::relative_pose(
                        &p.kp1,
                        &p.kp2,
                        &k,
                        &k,
                        &posediff_matching::TwoViewConfig::default(),
                    )
                    .ok()
                    .flatten()
                });
            let tv = match two_view {
                Some(posediff_matching::RelativePose::General {
                    rotation,
                    translation,
                    inliers,
                }) => {
                    let r = rotation * truth.rotation.transpose();
                    format!(
                        "two-view rot {:6.2}° trans {:6.2}° inl {inliers}",
                        ((r.trace() - 1.0) / 2.0)
                            .clamp(-1.0, 1.0)
                            .acos()
                            .to_degrees(),
                        translation
                            .dot(&truth.translation.normalize())
                            .clamp(-1.0, 1.0)
                            .acos()
                            .to_degrees()
                    )
                }
                Some(other) => format!("{other:?}"),
                None => String::new(),
            };
            let good = e
                .pairs
                .iter()
                .find(|p| p.first == a && p.second == b)
                .map_or(0, |p| {
                    let f =
                        posediff_geometry::fundamental_from_cameras(&gt[i].camera, &gt[j].camera);
                    p.kp1
                        .iter()
                        .zip(&p.kp2)
                        .filter(|(x, y)| {
                            posediff_geometry::epipolar::sampson_error(
                                &f,
                                &nalgebra::Point2::new(x[0], x[1]),
                                &nalgebra::Point2::new(y[0], y[1]),
                            )
                            .is_ok_and(|s| s < 4.0)
                        })
                        .count()
                });
            println!(
                "pair {i:>2}-{j:<2} matches {n:>4} (gt-consistent {good:>4})  rot {rot:7.2}°  trans {t:7.2}°  {tv}"
            );
        }
    }
    Ok(())
}
