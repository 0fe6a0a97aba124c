//! Per-pair statistics of the learned matcher on a set with ground truth: LightGlue's raw
//! matches, MAGSAC inliers, the inlier ratio, and the fraction of inliers within 4 px² (Sampson)
//! of the ground-truth epipolar geometry, with the pair's ground-truth rotation angle.
//!
//! `cargo run --release -p posediff --example learned_pairs -- <set folder> <weights dir>
//! [aliked-n16 | aliked-n16rot] [screen] [probe=<layer>] [turned=<i,j,…>]` (a set folder holds
//! `images/` and `cameras.json`). One line per pair on stdout.
//!
//! With `turned=<i,j,…>`, those images (0-based, in name order) are extracted turned by 180°
//! and LightGlue sees their turned positions, as after the estimate's orientation check.
//!
//! With `probe=<layer>`, LightGlue also counts the matches of its assignment head after that
//! layer (0-based; `LightGlueConfig::overlap_check` with no minimum, so the final matches are
//! unchanged): the columns `early`, `stop` (layers run) and `vscore` (the mean LightGlue score
//! of the verified matches).
//!
//! With `screen`, two cheap pair screens are measured beside it, as the columns `mnn` (mutual
//! nearest neighbours of the ALIKED descriptors with Lowe's ratio, then the same MAGSAC: the
//! SIFT path's matcher on ALIKED's features) and `lg512` (LightGlue on each image's 512
//! strongest keypoints, then MAGSAC), both verified counts without a minimum; stderr gets
//! their seconds and, per threshold, how many pairs a screen would pass on to the full
//! LightGlue, how many good pairs it would lose and how many wrong ones it would keep.

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
    let usage =
        "usage: learned_pairs <set folder> <weights dir> [aliked-n16 | aliked-n16rot] [screen]";
    let (set, weights, rest) = match args.as_slice() {
        [set, weights, rest @ ..] => (set, weights, rest),
        _ => anyhow::bail!(usage),
    };
    let mut aliked = posediff_learned::WeightSet::AlikedN16;
    let mut screen = false;
    let mut probe = None;
    let mut turned_list: Vec<usize> = Vec::new();
    for a in rest {
        if let Some(layer) = a.to_str().and_then(|a| a.strip_prefix("probe=")) {
            probe = Some(layer.parse::<usize>()?);
            continue;
        }
        if let Some(list) = a.to_str().and_then(|a| a.strip_prefix("turned=")) {
            turned_list = list
                .split(',')
                .map(str::parse)
                .collect::<std::result::Result<_, _>>()?;
            continue;
        }
        match a.to_str() {
            Some("aliked-n16") => aliked = posediff_learned::WeightSet::AlikedN16,
            Some("aliked-n16rot") => aliked = posediff_learned::WeightSet::AlikedN16Rot,
            Some("screen") => screen = true,
            _ => anyhow::bail!(usage),
        }
    }
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
    let mut features = extract_all(&images, &MatchConfig::default(), Some(&learned))?;
    for &i in &turned_list {
        let path = images
            .get(i)
            .context("turned= names an image beyond the set")?;
        features[i] = learned.0.extract_turned(path, true)?;
    }
    anyhow::ensure!(
        turned_list.is_empty() || probe.is_none(),
        "turned= and probe= do not go together"
    );
    let pairs = posediff_matching::exhaustive_pairs(images.len());
    let raw_config = MatchConfig {
        verification: None,
        ..MatchConfig::default()
    };
    let (raw, probed) = match probe {
        None => (
            match_pairs(&features, &pairs, &raw_config, Some(&learned))?,
            Vec::new(),
        ),
        Some(layer) => probe_pairs(&features, &pairs, &learned, layer)?,
    };
    // The verification of the default configuration, on the same raw matches.
    let config = MatchConfig::default();
    let verified = raw
        .iter()
        .map(|r| Ok(posediff_matching::verify(r.clone(), &config)?))
        .collect::<Result<Vec<_>>>()?;
    let screens = if screen {
        screens(&features, &pairs, &learned)?
    } else {
        Vec::new()
    };
    let mut kept = Vec::new();
    println!(
        "i j gt_angle raw inliers ratio good_fraction{}{}",
        if screen { " mnn lg512" } else { "" },
        if probe.is_some() {
            " early stop vscore"
        } else {
            ""
        }
    );
    for (k, ((r, v), &(i, j))) in raw.iter().zip(&verified).zip(&pairs).enumerate() {
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
        let good_fraction = good as f64 / v.len().max(1) as f64;
        let scores: Vec<String> = screens.iter().map(|(_, _, s)| s[k].to_string()).collect();
        let probed = probed
            .get(k)
            .map(|(early, stop, scores)| {
                // The mean LightGlue score of the verified matches.
                let vs: f32 = v
                    .idx1
                    .iter()
                    .zip(&v.idx2)
                    .filter_map(|(&a, &b)| scores.get(&(a, b)))
                    .sum::<f32>()
                    / v.len().max(1) as f32;
                format!(" {} {stop} {vs:.3}", early.map_or(-1, |e| e as i64))
            })
            .unwrap_or_default();
        println!(
            "{i} {j} {angle:.1} {} {} {:.3} {good_fraction:.3}{}{}{probed}",
            r.len(),
            v.len(),
            v.len() as f64 / r.len().max(1) as f64,
            if screen { " " } else { "" },
            scores.join(" ")
        );
        // Kept pairs: good (≥ 80 % within 4 px²) or wrong.
        if !v.is_empty() {
            kept.push((k, good_fraction >= 0.8, angle));
        }
    }
    for (name, seconds, scores) in &screens {
        eprintln!("screen {name}: {seconds:.1} s for {} pairs", pairs.len());
        for threshold in [5, 10, 15, 20] {
            let passed = scores.iter().filter(|&&s| s >= threshold).count();
            let lost: Vec<String> = kept
                .iter()
                .filter(|(k, good, _)| *good && scores[*k] < threshold)
                .map(|(_, _, a)| format!("{a:.0}°"))
                .collect();
            let wrong_kept = kept
                .iter()
                .filter(|(k, good, _)| !*good && scores[*k] >= threshold)
                .count();
            eprintln!(
                "  >= {threshold}: passes {passed} pairs, loses {} good pairs [{}], keeps {wrong_kept} of {} wrong",
                lost.len(),
                lost.join(" "),
                kept.iter().filter(|(_, g, _)| !*g).count()
            );
        }
    }
    Ok(())
}

/// LightGlue on every pair with an overlap check after `layer` and no minimum: the raw matches
/// and, per pair, the early count (`None` where the pair exited before the layer) and the
/// layers run.
#[allow(clippy::type_complexity)]
fn probe_pairs(
    features: &[posediff_matching::ImageFeatures],
    pairs: &[(usize, usize)],
    learned: &SharedLearned,
    layer: usize,
) -> Result<(
    Vec<posediff_matching::PairMatches>,
    Vec<(
        Option<usize>,
        usize,
        std::collections::HashMap<(u32, u32), f32>,
    )>,
)> {
    let config = posediff_learned::LightGlueConfig {
        overlap_check: Some(posediff_learned::lightglue::OverlapCheck {
            after_layer: layer,
            min_matches: 0,
        }),
        ..learned.0.lightglue_config
    };
    let prepared = features
        .iter()
        .map(|f| Ok(learned.0.prepare(f)?))
        .collect::<Result<Vec<_>>>()?;
    let mut raw = Vec::new();
    let mut probed = Vec::new();
    for &(i, j) in pairs {
        let m = learned
            .0
            .lightglue()
            .match_prepared(&prepared[i], &prepared[j], &config)?;
        raw.push(posediff_matching::raw_matches(
            &features[i],
            &features[j],
            i,
            j,
            &m.matches,
        ));
        let scores = m
            .matches
            .iter()
            .zip(&m.scores)
            .map(|(&(a, b), &s)| ((a as u32, b as u32), s))
            .collect();
        probed.push((m.early_matches, m.stop, scores));
    }
    Ok((raw, probed))
}

/// The verified counts of the two screens per pair, with their seconds.
fn screens(
    features: &[posediff_matching::ImageFeatures],
    pairs: &[(usize, usize)],
    learned: &SharedLearned,
) -> Result<Vec<(&'static str, f64, Vec<usize>)>> {
    let no_minimum = MatchConfig {
        min_verified: 0,
        ..MatchConfig::default()
    };
    let started = std::time::Instant::now();
    let mnn: Vec<usize> = posediff_matching::match_pairs(features, pairs, &no_minimum)?
        .iter()
        .map(posediff_matching::PairMatches::len)
        .collect();
    let mnn_seconds = started.elapsed().as_secs_f64();
    // ALIKED's keypoints come strongest first.
    let strongest: Vec<_> = features
        .iter()
        .map(|f| {
            let n = f.keypoints.len().min(512);
            let mut g = f.clone();
            g.keypoints.truncate(n);
            if let posediff_matching::Descriptors::Float { data, dim } = &mut g.descriptors {
                data.truncate(n * *dim);
            }
            g
        })
        .collect();
    let started = std::time::Instant::now();
    let lg: Vec<usize> = match_pairs(&strongest, pairs, &no_minimum, Some(learned))?
        .iter()
        .map(posediff_matching::PairMatches::len)
        .collect();
    Ok(vec![
        ("mnn", mnn_seconds, mnn),
        ("lg512", started.elapsed().as_secs_f64(), lg),
    ])
}
