//! The checkpoint-free mapper on matches made once: the subsets of `subsets.json` for one set,
//! scored like `bench-real`, from a cache of all the set's pairs (matched on the first run), with
//! the pairs the averaging used classified by the ground truth ("wrong": fewer than 80 % of the
//! pair's verified matches within 4 px² of the ground-truth epipolar geometry).
//!
//! `cargo run --profile ci -p posediff --example mapper_replay -- <data> <subsets.json> <set>
//! <cache.json> [sift | aliked-lightglue | aliked-n16rot-lightglue] [weights dir]`
//!
//! A pair's matches do not depend on the other images (features per image, LightGlue and MAGSAC
//! per pair), so a subset's pairs are the cached pairs among its images: the mapper can be
//! changed and re-measured in seconds instead of re-matching every subset.
//!
//! Environment: `CYCLE=off | <degrees>,<min triangles>` (the cycle check), `SUPPORT=off |
//! <minimum>` (the support check of learned pairs; the cache holds each pair's descriptor
//! screen count, `correspondences::descriptor_support`), `SUPPORT_DEG=<degrees>` (its
//! triangle threshold), `SCORE_DROPPED=0|1` (`MapperOptions::score_dropped_as_missing`;
//! default: on for learned matchers, as in the umbrella), `PAIRS=<selection>` (as `--pairs`:
//! each subset matched only on the pairs the selection picks among its images; `screen:K`:
//! each image with the K others of the highest descriptor screen count), `LG_SIDE=<pixels>`
//! and `LG_KP=<keypoints>` (the learned matcher's image side and keypoints, for a new cache),
//! `DENSIFY=<degrees>[,<per image>]` (the second matching pass on the first map's cameras,
//! `geometric::Densify`), `PLAN=1` (the learned `auto` plan: exhaustive up to
//! `LEARNED_EXHAUSTIVE_UP_TO` images, above it the first pass and the second), `PER=1` (a line
//! per subset: its images, mAA(30), pairs used and kept, wrong among them), `MAPCHECK=1` (a line
//! per pair of the result: its matches within 4 px² of the ground truth's and of the estimated
//! cameras' epipolar geometry, and whether the averaging used it), `RECHECK=<fraction>` (the
//! pairs with fewer of their matches within 4 px² of the estimated cameras' geometry dropped,
//! and the mapper run again). The orientation check and the turned retry of
//! `estimate_geometric` need the images themselves and are not replayed.
#![allow(clippy::print_stdout)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use posediff::correspondences::{LearnedMatcher, MatcherChoice, SharedLearned};
use posediff::correspondences::{descriptor_support, extract_all, match_pairs};
use posediff::estimate::geometric::{
    Densify, GeometricConfig, LEARNED_EXHAUSTIVE_UP_TO, LEARNED_FIRST_PASS, densify_pairs,
    estimate_from_supported_matches,
};
use posediff_geometry::epipolar::{fundamental_from_cameras, sampson_error};
use posediff_geometry::{Camera, ImageSize, PairMatches};
use serde_json::{Value, json};

/// A set size above which `auto` is not exhaustive (asks the selection whether it needs features).
const EXHAUSTIVE_BIG: usize = posediff_matching::pairs::EXHAUSTIVE_UP_TO;

/// One subset's outcome: mAA(30), fraction of kept pairs that are wrong, pairs averaged, wrong
/// pairs averaged, pairs kept.
type Outcome = (f64, f64, usize, usize, usize);

/// The cached set: image sizes, every pair's verified matches, raw match counts and descriptor
/// screen counts.
type Cache = (Vec<ImageSize>, Vec<PairMatches>, Vec<usize>, Vec<usize>);

fn save(path: &Path, (sizes, pairs, raw, screen): &Cache) -> Result<()> {
    let pairs: Vec<Value> = pairs
        .iter()
        .zip(raw)
        .zip(screen)
        .map(|((p, raw), screen)| {
            json!({"first": p.first, "second": p.second, "kp1": p.kp1, "kp2": p.kp2,
                   "idx1": p.idx1, "idx2": p.idx2, "raw": raw, "screen": screen})
        })
        .collect();
    let sizes: Vec<[u32; 2]> = sizes.iter().map(|s| [s.width(), s.height()]).collect();
    std::fs::write(
        path,
        serde_json::to_string(&json!({"sizes": sizes, "pairs": pairs}))?,
    )?;
    Ok(())
}

fn load(path: &Path) -> Result<Cache> {
    let v: Value = serde_json::from_str(&std::fs::read_to_string(path)?)?;
    let sizes: Vec<[u32; 2]> = serde_json::from_value(v["sizes"].clone())?;
    let sizes = sizes
        .iter()
        .map(|s| ImageSize::new(s[0], s[1]))
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let list = v["pairs"].as_array().context("no pairs")?;
    let raw = list
        .iter()
        .map(|p| Ok(serde_json::from_value(p["raw"].clone())?))
        .collect::<Result<_>>()?;
    let screen = list
        .iter()
        .map(|p| {
            serde_json::from_value(p["screen"].clone()).with_context(|| {
                format!(
                    "{}: no screen counts (an older cache): delete it",
                    path.display()
                )
            })
        })
        .collect::<Result<_>>()?;
    let pairs = list
        .iter()
        .map(|p| {
            Ok(PairMatches {
                first: serde_json::from_value(p["first"].clone())?,
                second: serde_json::from_value(p["second"].clone())?,
                kp1: serde_json::from_value(p["kp1"].clone())?,
                kp2: serde_json::from_value(p["kp2"].clone())?,
                idx1: serde_json::from_value(p["idx1"].clone())?,
                idx2: serde_json::from_value(p["idx2"].clone())?,
            })
        })
        .collect::<Result<_>>()?;
    Ok((sizes, pairs, raw, screen))
}

/// The fraction of `p`'s matches within 4 px² of the ground-truth epipolar geometry.
fn correct_fraction(p: &PairMatches, a: &Camera, b: &Camera) -> f64 {
    let f = fundamental_from_cameras(a, b);
    let good = p
        .kp1
        .iter()
        .zip(&p.kp2)
        .filter(|(x, y)| {
            sampson_error(
                &f,
                &nalgebra::Point2::new(x[0], x[1]),
                &nalgebra::Point2::new(y[0], y[1]),
            )
            .is_ok_and(|e| e < 4.0)
        })
        .count();
    good as f64 / p.len().max(1) as f64
}

/// The matching configuration of `matcher` (the learned one loaded from `weights`, else the
/// default folder). `LG_SIDE=<pixels>`, `LG_KP=<keypoints>`: the learned matcher's image side
/// and keypoint budget (defaults 1024 and 2048).
fn matching_config(matcher: MatcherChoice, weights: Option<&String>) -> Result<GeometricConfig> {
    let mut config = GeometricConfig::default();
    config.options.matching.features.detector = matcher.detector();
    if let Some(aliked) = matcher.extractor_weights() {
        let weights = weights.map_or_else(posediff_learned::weights::default_dir, PathBuf::from);
        let mut learned = LearnedMatcher::load_with(&weights, aliked)?;
        if let Ok(v) = std::env::var("LG_SIDE") {
            learned.image_side = v.parse()?;
        }
        if let Ok(v) = std::env::var("LG_KP") {
            learned.aliked_config.max_keypoints = v.parse()?;
            learned.disk_config.max_keypoints = v.parse()?;
        }
        config.learned = Some(SharedLearned(std::sync::Arc::new(learned)));
    }
    Ok(config)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [data, subsets, set, cache, rest @ ..] = args.as_slice() else {
        anyhow::bail!(
            "usage: mapper_replay <data> <subsets.json> <set> <cache.json> [matcher] [weights]"
        );
    };
    let matcher: MatcherChoice = rest
        .first()
        .map_or(Ok(MatcherChoice::Sift), |m| m.parse())?;
    let dir = Path::new(data).join(set);
    let gt = posediff::io::export::read_cameras_json(&dir.join("cameras.json"))?;
    let names: Vec<&str> = gt.iter().map(|c| c.image.as_str()).collect();
    let cache = PathBuf::from(cache);
    let (sizes, pairs, raw_counts, screen) = if cache.exists() {
        load(&cache)?
    } else {
        let config = matching_config(matcher, rest.get(1))?;
        let images: Vec<PathBuf> = names.iter().map(|n| dir.join(n)).collect();
        let started = std::time::Instant::now();
        let learned = config.learned.as_ref();
        let features = extract_all(&images, &config.options.matching, learned)?;
        let list = posediff_matching::exhaustive_pairs(images.len());
        let raw_config = posediff_matching::MatchConfig {
            verification: None,
            ..config.options.matching
        };
        let raw = match_pairs(&features, &list, &raw_config, learned)?;
        let raw_counts: Vec<usize> = raw.iter().map(PairMatches::len).collect();
        let verified = raw
            .into_iter()
            .map(|r| Ok(posediff_matching::verify(r, &config.options.matching)?))
            .collect::<Result<Vec<_>>>()?;
        eprintln!(
            "matched {} pairs of {} images in {:.1} s",
            verified.len(),
            images.len(),
            started.elapsed().as_secs_f64()
        );
        let started = std::time::Instant::now();
        let screen = descriptor_support(&features, &list, &config.options.matching)?;
        eprintln!(
            "descriptor screen of {} pairs in {:.1} s",
            list.len(),
            started.elapsed().as_secs_f64()
        );
        let sizes: Vec<ImageSize> = features.iter().map(|f| f.image_size).collect();
        let cached = (sizes, verified, raw_counts, screen);
        save(&cache, &cached)?;
        cached
    };
    anyhow::ensure!(sizes.len() == gt.len(), "the cache is of another set");
    // PREFILTER=<minimum>[,2]: LightGlue only on the pairs whose descriptor screen reaches the
    // minimum (with `,2` also on the pairs two such hops apart); the others count as unmatched.
    let mut pairs = pairs;
    if let Ok(v) = std::env::var("PREFILTER") {
        let (minimum, hops) = match v.split_once(',') {
            Some((m, h)) => (m.parse::<usize>()?, h.parse::<usize>()?),
            None => (v.parse::<usize>()?, 1),
        };
        let n = sizes.len();
        let mut near = vec![vec![false; n]; n];
        for (p, s) in pairs.iter().zip(&screen) {
            if *s >= minimum {
                near[p.first][p.second] = true;
                near[p.second][p.first] = true;
            }
        }
        let candidate = |i: usize, j: usize| {
            near[i][j] || (hops >= 2 && (0..n).any(|k| near[i][k] && near[k][j]))
        };
        let mut matched = 0;
        for p in &mut pairs {
            if candidate(p.first, p.second) {
                matched += 1;
            } else {
                p.kp1.clear();
                p.kp2.clear();
                p.idx1.clear();
                p.idx2.clear();
            }
        }
        println!(
            "prefilter {v}: LightGlue on {matched} of {} pairs",
            pairs.len()
        );
    }
    // PAIRS=<selection> (as `--pairs`, e.g. `retrieval:5`): each subset keeps only the pairs
    // that the selection picks among its images (retrieval on the extractor's features,
    // extracted once more here); the others count as unmatched.
    // PAIRS=screen:K: each image with the K others of the highest descriptor screen count.
    let screen_k: Option<usize> = std::env::var("PAIRS")
        .ok()
        .and_then(|v| v.strip_prefix("screen:").map(str::to_owned))
        .map(|k| k.parse())
        .transpose()?;
    let selection: Option<posediff_matching::PairSelection> = std::env::var("PAIRS")
        .ok()
        .filter(|_| screen_k.is_none())
        .map(|v| v.parse())
        .transpose()
        .map_err(anyhow::Error::msg)?;
    let plan = std::env::var("PLAN").is_ok_and(|v| v == "1");
    let selection_features = match &selection {
        _ if plan => Some(()),
        Some(s) if s.needs_features(2 * EXHAUSTIVE_BIG) => Some(()),
        _ => None,
    };
    let selection_features = match selection_features {
        Some(()) => {
            let config = matching_config(matcher, rest.get(1))?;
            let images: Vec<PathBuf> = names.iter().map(|n| dir.join(n)).collect();
            Some(extract_all(
                &images,
                &config.options.matching,
                config.learned.as_ref(),
            )?)
        }
        _ => None,
    };
    let by_pair: BTreeMap<(usize, usize), &PairMatches> =
        pairs.iter().map(|p| ((p.first, p.second), p)).collect();
    let screen_of: BTreeMap<(usize, usize), usize> = pairs
        .iter()
        .zip(&screen)
        .map(|(p, s)| ((p.first, p.second), *s))
        .collect();
    // SUPPORT=off, or SUPPORT=<minimum>: the support check of learned pairs (default: the
    // configuration's, off); SIFT's pairs are always their descriptors' own.
    let support_min = match std::env::var("SUPPORT").ok().as_deref() {
        Some("off") => None,
        Some(v) => Some(v.parse::<usize>()?),
        None => GeometricConfig::default().options.support.min_verified,
    }
    .filter(|_| matcher.extractor_weights().is_some());
    let correct: BTreeMap<(usize, usize), f64> = pairs
        .iter()
        .filter(|p| !p.is_empty())
        .map(|p| {
            let f = correct_fraction(p, &gt[p.first].camera, &gt[p.second].camera);
            ((p.first, p.second), f)
        })
        .collect();

    // Per kept pair of the whole set: what a pair filter could look at.
    let mut table = String::from("i j gt_angle raw inliers ratio correct spread screen\n");
    for ((p, raw), screen) in pairs.iter().zip(&raw_counts).zip(&screen) {
        if p.is_empty() {
            continue;
        }
        let (a, b) = (&gt[p.first].camera, &gt[p.second].camera);
        let angle = posediff_geometry::epipolar::rotation_angle_between_deg(
            &a.cam_from_world.rotation,
            &b.cam_from_world.rotation,
        );
        let spread = |pts: &[[f64; 2]], size: ImageSize| {
            let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
            for q in pts {
                for k in 0..2 {
                    lo[k] = lo[k].min(q[k]);
                    hi[k] = hi[k].max(q[k]);
                }
            }
            (hi[0] - lo[0]) * (hi[1] - lo[1]) / (f64::from(size.width()) * f64::from(size.height()))
        };
        table += &format!(
            "{} {} {angle:.1} {raw} {} {:.3} {:.3} {:.3} {screen}\n",
            p.first,
            p.second,
            p.len(),
            p.len() as f64 / (*raw).max(1) as f64,
            correct[&(p.first, p.second)],
            spread(&p.kp1, sizes[p.first]).min(spread(&p.kp2, sizes[p.second])),
        );
    }
    std::fs::write(cache.with_extension("pairs.txt"), table)?;

    let file: Value = serde_json::from_str(&std::fs::read_to_string(subsets)?)?;
    let mut groups: BTreeMap<usize, Vec<Outcome>> = BTreeMap::new();
    for subset in file["datasets"][set.as_str()]["subsets"]
        .as_array()
        .context("no such set in subsets.json")?
    {
        let members: Vec<usize> = subset["images"]
            .as_array()
            .context("no images")?
            .iter()
            .map(|i| {
                let name = i.as_str().unwrap_or_default();
                names
                    .iter()
                    .position(|n| *n == name)
                    .with_context(|| format!("unknown image {name}"))
            })
            .collect::<Result<_>>()?;
        let m = members.len();
        // ONLY=<N>: the subsets of that size alone (e.g. the whole set, timed).
        if std::env::var("ONLY").is_ok_and(|v| v.parse::<usize>().is_ok_and(|k| k != m)) {
            continue;
        }
        let mut sub = Vec::new();
        for a in 0..m {
            for b in a + 1..m {
                let (i, j) = (members[a], members[b]);
                let pair = if let Some(p) = by_pair.get(&(i, j)) {
                    (*p).clone()
                } else if let Some(p) = by_pair.get(&(j, i)) {
                    PairMatches {
                        first: i,
                        second: j,
                        kp1: p.kp2.clone(),
                        kp2: p.kp1.clone(),
                        idx1: p.idx2.clone(),
                        idx2: p.idx1.clone(),
                    }
                } else {
                    continue;
                };
                sub.push(PairMatches {
                    first: a,
                    second: b,
                    ..pair
                });
            }
        }
        let full_sub = sub.clone();
        let mut selected = m * (m - 1) / 2;
        // PLAN=1: what `auto` does with a learned matcher (GeometricConfig::plan): above
        // LEARNED_EXHAUSTIVE_UP_TO images the first pass, then the second (Densify).
        let planned = plan && m > LEARNED_EXHAUSTIVE_UP_TO;
        let selection = if planned {
            Some(posediff_matching::PairSelection::Rules(
                LEARNED_FIRST_PASS.to_vec(),
            ))
        } else {
            selection.clone()
        };
        let densify: Option<Densify> = match std::env::var("DENSIFY").ok() {
            Some(v) => {
                let (deg, k) = v.split_once(',').unwrap_or((&v, "5"));
                Some(Densify {
                    max_angle_deg: deg.parse()?,
                    per_image: k.parse()?,
                })
            }
            None => planned.then(Densify::default),
        };
        if let Some(selection) = &selection {
            let features: Option<Vec<_>> = selection_features
                .as_ref()
                .map(|f| members.iter().map(|&i| f[i].clone()).collect());
            let chosen: std::collections::HashSet<(usize, usize)> =
                posediff_matching::select_pairs(m, selection, features.as_deref())?
                    .into_iter()
                    .collect();
            selected = chosen.len();
            sub.retain(|p| chosen.contains(&(p.first, p.second)));
        }
        if let Some(k) = screen_k {
            let mut chosen = std::collections::HashSet::new();
            for a in 0..m {
                let mut others: Vec<(usize, usize)> = (0..m)
                    .filter(|&b| b != a)
                    .map(|b| {
                        let (i, j) = (members[a], members[b]);
                        (b, screen_of[&(i.min(j), i.max(j))])
                    })
                    .collect();
                others.sort_by(|x, y| y.1.cmp(&x.1).then(x.0.cmp(&y.0)));
                for &(b, _) in others.iter().take(k) {
                    chosen.insert((a.min(b), a.max(b)));
                }
            }
            selected = chosen.len();
            sub.retain(|p| chosen.contains(&(p.first, p.second)));
        }
        let sub_sizes: Vec<ImageSize> = members.iter().map(|&i| sizes[i]).collect();
        let gt_cams: Vec<Camera> = members.iter().map(|&i| gt[i].camera).collect();
        let kept = sub.iter().filter(|p| !p.is_empty()).count();
        let wrong_kept = sub
            .iter()
            .filter(|p| !p.is_empty())
            .filter(|p| correct[&(members[p.first], members[p.second])] < 0.8)
            .count();
        let mut replay_config = GeometricConfig::default();
        if let Ok(v) = std::env::var("SUPPORT_DEG") {
            replay_config.options.mapper.support_triangle_deg = v.parse()?;
        }
        // As the umbrella does with a learned matcher; SCORE_DROPPED=0|1 overrides.
        replay_config.options.mapper.score_dropped_as_missing = match std::env::var("SCORE_DROPPED")
        {
            Ok(v) => v == "1",
            Err(_) => matcher.extractor_weights().is_some(),
        };
        // CYCLE=off, or CYCLE=<degrees>,<min triangles>: the cycle check to replay with.
        match std::env::var("CYCLE").ok().as_deref() {
            Some("off") => replay_config.options.mapper.cycle_check = None,
            Some(v) => {
                let (d, t) = v.split_once(',').context("CYCLE=<degrees>,<triangles>")?;
                replay_config.options.mapper.cycle_check = Some(posediff_sfm::mapper::CycleCheck {
                    threshold_deg: d.parse()?,
                    min_triangles: t.parse()?,
                });
            }
            None => {}
        }
        let support = support_min.map(|minimum| {
            sub.iter()
                .map(|p| {
                    let (i, j) = (members[p.first], members[p.second]);
                    screen_of[&(i.min(j), i.max(j))] >= minimum
                })
                .collect()
        });
        let mapper_clock = std::time::Instant::now();
        let mut result = estimate_from_supported_matches(
            &sub_sizes,
            sub.clone(),
            support.clone(),
            &replay_config,
        );
        // DENSIFY=<degrees>: a second pass that adds the pairs not yet matched whose estimated
        // cameras are within <degrees> of each other (the spatial matcher's idea), then maps
        // again.
        if let (Some(d), Ok(e)) = (densify, result.as_ref()) {
            if std::env::var("ONLY").is_ok() {
                println!(
                    "  first pass: mapper {:.1} s, {:?}",
                    mapper_clock.elapsed().as_secs_f64(),
                    e.report.times
                );
            }
            let have: std::collections::HashSet<(usize, usize)> =
                sub.iter().map(|p| (p.first, p.second)).collect();
            let extra: std::collections::HashSet<(usize, usize)> =
                densify_pairs(&e.cameras, &have, &d).into_iter().collect();
            let mut more = sub.clone();
            more.extend(
                full_sub
                    .iter()
                    .filter(|p| extra.contains(&(p.first, p.second)))
                    .cloned(),
            );
            selected += extra.len();
            result = estimate_from_supported_matches(&sub_sizes, more, support, &replay_config);
        }
        // RECHECK=<fraction>: the pairs with fewer than that fraction of their matches within
        // 4 px² of the estimated cameras' epipolar geometry dropped, and the mapper run again.
        if let (Ok(min), Ok(e)) = (
            std::env::var("RECHECK").map(|v| v.parse::<f64>()),
            result.as_ref(),
        ) {
            let min = min?;
            let consistent: Vec<PairMatches> = e
                .pairs
                .iter()
                .filter(|p| match (&e.cameras[p.first], &e.cameras[p.second]) {
                    (Some(a), Some(b)) => p.is_empty() || correct_fraction(p, a, b) >= min,
                    _ => true,
                })
                .cloned()
                .collect();
            if consistent.len() < e.pairs.len() {
                result =
                    estimate_from_supported_matches(&sub_sizes, consistent, None, &replay_config);
            }
        }
        let mapper_s = mapper_clock.elapsed().as_secs_f64();
        let (maa, used, wrong_used) = match result {
            Ok(e) => {
                let pred: Vec<_> = e
                    .cameras
                    .iter()
                    .map(|c| c.map(|c| c.cam_from_world))
                    .collect();
                let (scores, _) = posediff::bench::score_set(&gt_cams, &pred)?;
                if std::env::var("ONLY").is_ok() {
                    println!(
                        "  RRA@5/15/30 {:?}, RTA@5/15/30 {:?}",
                        scores.rra, scores.rta
                    );
                }
                if std::env::var("MAPCHECK").is_ok() {
                    for p in e.pairs.iter().filter(|p| !p.is_empty()) {
                        let (i, j) = (members[p.first], members[p.second]);
                        let est = match (&e.cameras[p.first], &e.cameras[p.second]) {
                            (Some(a), Some(b)) => correct_fraction(p, a, b),
                            _ => -1.0,
                        };
                        let used = e
                            .report
                            .mapper
                            .as_ref()
                            .is_some_and(|m| m.averaged_pairs.contains(&[p.first, p.second]));
                        println!(
                            "MAPCHECK N{m} {i}-{j} n {} gt {:.3} est {est:.3} used {used}",
                            p.len(),
                            correct[&(i.min(j), i.max(j))]
                        );
                    }
                }
                let used = e
                    .report
                    .mapper
                    .as_ref()
                    .map_or(&[][..], |m| &m.averaged_pairs);
                let wrong: Vec<String> = used
                    .iter()
                    .filter(|[a, b]| {
                        let (i, j) = (members[*a], members[*b]);
                        correct.get(&(i.min(j), i.max(j))).copied().unwrap_or(0.0) < 0.8
                    })
                    .map(|[a, b]| format!("{}-{}", members[*a], members[*b]))
                    .collect();
                if m > 10 {
                    let support = e
                        .report
                        .mapper
                        .as_ref()
                        .and_then(|m| m.support.as_ref())
                        .map_or_else(String::new, |s| {
                            format!(
                                ", support: {} supported, {} confirmed, {} rejected",
                                s.supported, s.confirmed, s.rejected
                            )
                        });
                    println!(
                        "  {m} images ({selected} pairs matched, mapper {mapper_s:.1} s, times {:?}): focal {:.3}, wrong pairs used: {}{support}",
                        e.report.times,
                        e.report.focal_factor,
                        wrong.join(" ")
                    );
                }
                (scores.maa_30, used.len(), wrong.len())
            }
            Err(e) => {
                println!("  subset of {m} failed: {e}");
                (0.0, 0, 0)
            }
        };
        if std::env::var("PER").is_ok() {
            println!(
                "  subset of {m}: images {members:?}, mAA(30) {maa:.3}, used {used} (wrong {wrong_used}), kept {kept} (wrong {wrong_kept})"
            );
        }
        groups.entry(m).or_default().push((
            maa,
            wrong_kept as f64 / kept.max(1) as f64,
            used,
            wrong_used,
            kept,
        ));
    }
    println!("{set}: N, mAA(30), pairs kept, wrong kept, pairs averaged, wrong averaged (means)");
    for (m, runs) in &groups {
        let k = runs.len() as f64;
        let mean = |f: &dyn Fn(&Outcome) -> f64| runs.iter().map(f).sum::<f64>() / k;
        println!(
            "N {m:>2}: mAA {:.3}  kept {:.1}  wrong kept {:.1} %  averaged {:.1}  wrong averaged {:.2}",
            mean(&|r| r.0),
            mean(&|r| r.4 as f64),
            100.0 * mean(&|r| r.1),
            mean(&|r| r.2 as f64),
            mean(&|r| r.3 as f64),
        );
    }
    Ok(())
}
