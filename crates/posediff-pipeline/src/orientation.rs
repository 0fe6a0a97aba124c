//! A learned matcher's orientation passes. ALIKED and DISK are not invariant to in-plane
//! rotation: images upside down relative to the others (the Middlebury temple's last five, a
//! camera turned over) match within their orientation and poorly or wrongly across.
//!
//! - Before the map, the orientation check (`turn_components`): the images grouped by their
//!   strong pairs (`strong_groups`, pure), each smaller group tested by one image extracted
//!   turned, the groups labelled by [`crate::options::OrientationOptions::evidence`] (pure),
//!   the turn kept only where LightGlue confirms it.
//! - After the map, the turned retry of the images it left out (`turn_left_out`).
//!
//! Both go through [`Correspondences`], so they run only for a matcher that
//! [`Correspondences::depends_on_orientation`].

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::time::Instant;

use posediff_geometry::Camera;
use posediff_matching::pairs::{BagOfWords, RetrievalOptions};
use posediff_matching::{ImageFeatures, MatchConfig, PairMatches};
use posediff_sfm::view_graph::UnionFind;

use crate::correspondences::{Correspondences, StepCounter, descriptor_support};
use crate::error::{PosediffError, Result};
use crate::options::{OrientationOptions, RetryOptions};

/// The default of `retry.partners` ([`crate::options::RetryOptions`]).
pub const TURN_PARTNERS: usize = 8;

/// A learned matcher's retry of the images its map left out. ALIKED and DISK are not
/// invariant to in-plane rotation: an image upside down relative to the others (the
/// Middlebury temple's last five, a phone turned over) matches them with few or wrong matches.
/// Each left-out image is extracted again turned by 180° and matched with the estimated images
/// among its [`TURN_PARTNERS`] most similar; it is kept turned when those pairs verify more
/// matches than its upright pairs with estimated images. A kept image's earlier pairs are
/// dropped (their keypoint indices are the upright features') and its pairs with other kept
/// images matched again. Images already turned (by the orientation check) are not retried.
/// Returns the turned images and the new set of pairs, or `None` when no image was left out, fewer than two were estimated, or none is kept
/// turned; `features` hold the turned features of the kept images afterwards.
///
/// # Errors
/// Unreadable images, network and matching errors.
pub(crate) fn turn_left_out(
    images: &[PathBuf],
    features: &mut [ImageFeatures],
    pairs: &[PairMatches],
    cameras: &[Option<Camera>],
    matcher: &dyn Correspondences,
    retry: &RetryOptions,
    counter: &dyn StepCounter,
) -> Result<Option<(Vec<usize>, Vec<PairMatches>)>> {
    if !matcher.depends_on_orientation() {
        return Ok(None);
    }
    let estimated = |i: usize| cameras.get(i).is_some_and(Option::is_some);
    let left: Vec<usize> = (0..features.len())
        .filter(|&i| !estimated(i) && !features[i].half_turned)
        .collect();
    if left.is_empty() || (0..features.len()).filter(|&i| estimated(i)).count() < 2 {
        return Ok(None);
    }
    log::info!(
        "{}{} images left out: matching them turned by 180°",
        crate::progress::WORK_STARTS,
        left.len()
    );
    counter.stage("turned images", left.len() as u64);
    let paths: Vec<&std::path::Path> = left.iter().map(|&j| images[j].as_path()).collect();
    let turned = turned_features(matcher, &paths, counter)?;
    let upright: Vec<(usize, ImageFeatures)> = left
        .iter()
        .zip(turned)
        .map(|(&j, f)| (j, std::mem::replace(&mut features[j], f)))
        .collect();
    let is_left = |i: usize| left.binary_search(&i).is_ok();
    let trial: Vec<(usize, usize)> = posediff_matching::pairs::retrieval_pairs(
        features,
        retry.partners,
        &RetrievalOptions::default(),
    )
    .into_iter()
    .filter(|&(a, b)| (is_left(a) && estimated(b)) || (is_left(b) && estimated(a)))
    .collect();
    let matched = matcher.match_pairs(features, &trial, (counter, "turned pairs"))?;
    // Verified matches with estimated images: turned against upright.
    let mut score: HashMap<usize, (usize, usize)> = HashMap::new();
    for p in &matched {
        let j = if is_left(p.first) { p.first } else { p.second };
        score.entry(j).or_default().0 += p.len();
    }
    for p in pairs {
        if is_left(p.first) && estimated(p.second) {
            score.entry(p.first).or_default().1 += p.len();
        } else if is_left(p.second) && estimated(p.first) {
            score.entry(p.second).or_default().1 += p.len();
        }
    }
    let kept: Vec<usize> = left
        .iter()
        .copied()
        .filter(|j| score.get(j).is_some_and(|&(t, u)| t > u))
        .collect();
    for (j, f) in upright {
        if kept.binary_search(&j).is_err() {
            features[j] = f;
        }
    }
    if kept.is_empty() {
        return Ok(None);
    }
    let is_kept = |i: usize| kept.binary_search(&i).is_ok();
    let both: Vec<(usize, usize)> = pairs
        .iter()
        .filter(|p| is_kept(p.first) && is_kept(p.second))
        .map(|p| (p.first, p.second))
        .collect();
    let mut out: Vec<PairMatches> = pairs
        .iter()
        .filter(|p| !is_kept(p.first) && !is_kept(p.second))
        .cloned()
        .collect();
    out.extend(
        matched
            .into_iter()
            .filter(|p| is_kept(p.first) || is_kept(p.second)),
    );
    out.extend(matcher.match_pairs(features, &both, (counter, "turned pairs"))?);
    out.sort_by_key(|p| (p.first, p.second));
    Ok(Some((kept, out)))
}

/// `images` extracted turned by 180° by a matcher that depends on the orientation.
fn turned_features(
    matcher: &dyn Correspondences,
    images: &[&std::path::Path],
    counter: &dyn StepCounter,
) -> Result<Vec<ImageFeatures>> {
    matcher.extract_turned(images, counter)?.ok_or_else(|| {
        PosediffError::InvalidArgument("this matcher does not extract turned images".into())
    })
}

/// The default of `orientation.strong_pair` ([`crate::options::OrientationOptions`]).
pub const STRONG_PAIR: usize = 80;

/// The default of `orientation.tests` ([`crate::options::OrientationOptions`]).
pub const TURN_TESTS: usize = 8;

/// The groups of images joined by pairs of at least `minimum` verified matches, the largest
/// first (ties: the one with the lowest image first); an image without such a pair is a group
/// of its own.
pub(crate) fn strong_groups(n: usize, pairs: &[PairMatches], minimum: usize) -> Vec<Vec<usize>> {
    let mut sets = UnionFind::new(n);
    for p in pairs.iter().filter(|p| p.len() >= minimum) {
        if p.first < n && p.second < n {
            sets.union(p.first, p.second);
        }
    }
    let mut groups: HashMap<usize, Vec<usize>> = HashMap::new();
    for i in 0..n {
        groups.entry(sets.find(i)).or_default().push(i);
    }
    let mut out: Vec<Vec<usize>> = groups.into_values().collect();
    out.sort_by(|a, b| b.len().cmp(&a.len()).then(a.first().cmp(&b.first())));
    out
}

/// A learned matcher's orientation check before the map. ALIKED and DISK are not invariant to
/// in-plane rotation: where some images are upside down relative to the others (the Middlebury
/// temple's last five, a camera turned over), LightGlue matches each orientation well within
/// itself and poorly or wrongly across, so the strong pairs ([`STRONG_PAIR`]) fall into groups
/// by orientation. Each group besides the largest ([`TURN_TESTS`] at most) is tested by its
/// best-matched image, extracted again turned by 180°: the descriptor screen
/// ([`descriptor_support`], about 10 ms a pair) counts its verified matches, upright and
/// turned, with the [`TURN_PARTNERS`] most similar images of other groups. Groups are then
/// labelled from the largest along the clearest evidence
/// ([`crate::options::OrientationOptions::evidence`]), and the
/// images of the groups found turned relative to the largest are extracted turned, their pairs
/// matched again, and the turned images matched with their [`TURN_PARTNERS`] most similar
/// images. The turn is kept when the turned images' pairs with the others verify more matches
/// than they did upright. Returns the turned images (`features` holding their turned features)
/// and the new pairs, or `None` (nothing changed) when the
/// strong pairs form one group, no group is found turned, or LightGlue does not confirm it.
///
/// # Errors
/// Unreadable images, network and matching errors.
pub(crate) fn turn_components(
    images: &[PathBuf],
    features: &mut [ImageFeatures],
    pairs: &[PairMatches],
    words: Option<&BagOfWords>,
    (matcher, orientation, matching): (&dyn Correspondences, &OrientationOptions, &MatchConfig),
    counter: &dyn StepCounter,
) -> Result<Option<(Vec<usize>, Vec<PairMatches>)>> {
    if !matcher.depends_on_orientation() {
        return Ok(None);
    }
    let n = features.len();
    let clock = Instant::now();
    let groups = strong_groups(n, pairs, orientation.strong_pair);
    if groups.len() < 2 {
        return Ok(None);
    }
    let mut group_of = vec![0usize; n];
    for (g, members) in groups.iter().enumerate() {
        for &i in members {
            group_of[i] = g;
        }
    }
    let mut strength = vec![0usize; n];
    for p in pairs.iter().filter(|p| p.len() >= orientation.strong_pair) {
        for i in [p.first, p.second] {
            if let Some(s) = strength.get_mut(i) {
                *s += p.len();
            }
        }
    }
    let reps: Vec<usize> = groups
        .iter()
        .skip(1)
        .take(orientation.tests)
        .filter_map(|g| {
            g.iter()
                .copied()
                .max_by_key(|&i| (strength[i], std::cmp::Reverse(i)))
        })
        .collect();
    log::info!(
        "{}the strong pairs form {} groups: testing {} turned by 180°",
        crate::progress::WORK_STARTS,
        groups.len(),
        reps.len()
    );
    let is_rep = |i: usize| reps.contains(&i);
    counter.stage("orientation check", reps.len() as u64);
    let paths: Vec<&std::path::Path> = reps.iter().map(|&r| images[r].as_path()).collect();
    let rep_turned = turned_features(matcher, &paths, counter)?;
    // Each representative with the most similar images of other groups, upright and turned
    // (one vocabulary; not other representatives, which are turned during the screen), as
    // (representative, partner).
    let built;
    let words = match words.filter(|w| w.len() == n) {
        Some(w) => Some(w),
        None => {
            built = BagOfWords::build(features, &RetrievalOptions::default());
            built.as_ref()
        }
    };
    let mut trial: Vec<(usize, usize)> = Vec::new();
    if let Some(words) = words {
        for (&r, t) in reps.iter().zip(&rep_turned) {
            let keep = |j: usize| group_of[j] != group_of[r] && !is_rep(j);
            for h in [
                words.histogram_of(r).unwrap_or_default(),
                words.histogram(t),
            ] {
                trial.extend(
                    words
                        .most_similar(&h, orientation.partners, keep)
                        .into_iter()
                        .map(|p| (r, p)),
                );
            }
        }
    }
    trial.sort_unstable();
    trial.dedup();
    let upright: Vec<ImageFeatures> = reps
        .iter()
        .zip(rep_turned)
        .map(|(&r, f)| std::mem::replace(&mut features[r], f))
        .collect();
    let screened: Vec<(usize, usize)> = trial.iter().map(|&(r, p)| (r.min(p), r.max(p))).collect();
    let opposite = descriptor_support(features, &screened, matching);
    let mut rep_turned: HashMap<usize, ImageFeatures> = reps
        .iter()
        .zip(upright)
        .map(|(&r, f)| (r, std::mem::replace(&mut features[r], f)))
        .collect();
    let opposite = opposite?;
    let same = descriptor_support(features, &screened, matching)?;
    // Evidence between groups, (smaller, larger) group index ↦ (same, opposite).
    let mut evidence: HashMap<(usize, usize), (usize, usize)> = HashMap::new();
    for (k, &(r, p)) in trial.iter().enumerate() {
        let (a, b) = (group_of[r], group_of[p]);
        let e = evidence.entry((a.min(b), a.max(b))).or_default();
        e.0 += same[k];
        e.1 += opposite[k];
    }
    let mut edges: Vec<((usize, usize), bool, usize)> = evidence
        .iter()
        .filter_map(|(&g, &(s, o))| orientation.evidence(s, o).map(|flip| (g, flip, s.max(o))))
        .collect();
    edges.sort_by(|x, y| y.2.cmp(&x.2).then(x.0.cmp(&y.0)));
    // Labels from the largest group, strongest evidence first.
    let mut label: Vec<Option<bool>> = vec![None; groups.len()];
    label[0] = Some(false);
    loop {
        let next = edges
            .iter()
            .find_map(|&((a, b), flip, _)| match (label[a], label[b]) {
                (Some(l), None) => Some((b, l != flip)),
                (None, Some(l)) => Some((a, l != flip)),
                _ => None,
            });
        let Some((g, l)) = next else { break };
        label[g] = Some(l);
    }
    let mut flipped: Vec<usize> = groups
        .iter()
        .zip(&label)
        .filter(|(_, l)| **l == Some(true))
        .flat_map(|(g, _)| g.iter().copied())
        .filter(|&i| !features[i].half_turned)
        .collect();
    flipped.sort_unstable();
    log::info!(
        "{}orientation check: {} images turned against the largest group ({:.1} s)",
        crate::progress::WORK_STARTS,
        flipped.len(),
        clock.elapsed().as_secs_f64()
    );
    if flipped.is_empty() {
        return Ok(None);
    }
    // The turned features: the representatives' from the screen, the others extracted.
    let rest: Vec<usize> = flipped
        .iter()
        .copied()
        .filter(|i| !rep_turned.contains_key(i))
        .collect();
    let paths: Vec<&std::path::Path> = rest.iter().map(|&i| images[i].as_path()).collect();
    counter.stage("turned images", rest.len() as u64);
    for (&i, f) in rest.iter().zip(turned_features(matcher, &paths, counter)?) {
        rep_turned.insert(i, f);
    }
    let mut upright: Vec<(usize, ImageFeatures)> = Vec::new();
    for &i in &flipped {
        if let Some(f) = rep_turned.remove(&i) {
            upright.push((i, std::mem::replace(&mut features[i], f)));
        }
    }
    let is_flipped = |i: usize| flipped.binary_search(&i).is_ok();
    let mut again: Vec<(usize, usize)> = pairs
        .iter()
        .filter(|p| is_flipped(p.first) || is_flipped(p.second))
        .map(|p| (p.first, p.second))
        .collect();
    // Pairs the selection did not give (it saw the upright features): each turned image with
    // its most similar images by its turned features.
    let had: HashSet<(usize, usize)> = pairs.iter().map(|p| (p.first, p.second)).collect();
    if let Some(words) = words {
        for &i in &flipped {
            let near =
                words.most_similar(&words.histogram(&features[i]), orientation.partners, |j| {
                    j != i
                });
            again.extend(
                near.into_iter()
                    .map(|j| (i.min(j), i.max(j)))
                    .filter(|p| !had.contains(p)),
            );
        }
    }
    again.sort_unstable();
    again.dedup();
    let matched = matcher.match_pairs(features, &again, (counter, "turned pairs"))?;
    // Kept only when the turned images verify more matches with the others turned than they
    // did upright (LightGlue's word over the screen's, as the retry of left-out images asks;
    // pairs within the turned images turn at both ends and are left out of the count).
    let across = |p: &&PairMatches| is_flipped(p.first) != is_flipped(p.second);
    let before: usize = pairs.iter().filter(across).map(PairMatches::len).sum();
    let after: usize = matched.iter().filter(across).map(PairMatches::len).sum();
    log::info!(
        "{}orientation check: the turned images' pairs verify {after} matches against {before}",
        crate::progress::WORK_STARTS
    );
    if after <= before {
        for (i, f) in upright {
            features[i] = f;
        }
        return Ok(None);
    }
    let mut out: Vec<PairMatches> = pairs
        .iter()
        .filter(|p| !is_flipped(p.first) && !is_flipped(p.second))
        .cloned()
        .collect();
    out.extend(matched);
    out.sort_by_key(|p| (p.first, p.second));
    Ok(Some((flipped, out)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn counted(first: usize, second: usize, count: usize) -> PairMatches {
        PairMatches::placeholder(first, second, count)
    }

    /// Strong pairs join, weak ones do not; groups come largest first, then by their first
    /// image, and an image without a strong pair is a group of its own.
    #[test]
    fn strong_groups_follow_the_strong_pairs_only() {
        let pairs = [
            counted(0, 1, 200),
            counted(1, 2, 80),
            counted(2, 3, 79),
            counted(3, 4, 500),
            counted(5, 6, 100),
            counted(4, 5, 20),
        ];
        let groups = strong_groups(8, &pairs, STRONG_PAIR);
        assert_eq!(groups, vec![vec![0, 1, 2], vec![3, 4], vec![5, 6], vec![7]]);
        assert_eq!(
            strong_groups(3, &[], STRONG_PAIR),
            vec![vec![0], vec![1], vec![2]]
        );
    }
}
