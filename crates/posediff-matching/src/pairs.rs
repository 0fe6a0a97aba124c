//! Which image pairs to match: exhaustive for small sets, and for large ones (video frames,
//! hundreds of photos) sequential neighbours plus retrieval, as COLMAP's sequential and
//! vocabulary-tree matchers and GLOMAP's pipelines do.
//!
//! Retrieval ranks images by a bag of visual words (Sivic & Zisserman, ICCV 2003; Nistér &
//! Stewénius, CVPR 2006) built from the set's own descriptors: a vocabulary by k-means on a
//! sample of the descriptors, each image a tf-idf-weighted, L2-normalised word histogram, and
//! pairs of the highest cosine similarity. It needs nothing beyond the features already
//! extracted (no pretrained vocabulary to download), and costs `O(D·k)` for `D` quantised
//! descriptors plus `O(N²·k)` for the similarities — small against matching.

use std::fmt;
use std::str::FromStr;

use nalgebra::DMatrix;
use rayon::prelude::*;

use crate::error::{MatchingError, Result};
use crate::features::{Descriptors, ImageFeatures};

/// Up to this many images the default is every pair.
pub const EXHAUSTIVE_UP_TO: usize = 60;

/// One rule of a pair selection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PairRule {
    /// Every pair `i < j`.
    Exhaustive,
    /// Each image with the next `k` in input order (video frames).
    Sequential(usize),
    /// Each image with its `k` most similar images by the bag of words.
    Retrieval(usize),
}

/// A pair selection: the union of its rules, or `Auto` (exhaustive up to
/// [`EXHAUSTIVE_UP_TO`] images, `sequential:10,retrieval:20` above).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum PairSelection {
    /// Exhaustive for small sets, sequential + retrieval for large ones.
    #[default]
    Auto,
    /// The union of the rules.
    Rules(Vec<PairRule>),
}

/// What `auto` means: every pair up to `exhaustive_up_to` images, above it each image with
/// the next `sequential` and its `retrieval` most similar (measured on the synthetic orbits and
/// forward paths of `cargo xtask bench-scale`, docs/BENCHMARKS.md: 60 images exhaustive cost
/// about as much as `sequential:10,retrieval:20`, which kept every scale's mAA(30) at 1.000).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct AutoPairs {
    /// Sets of up to this many images are matched exhaustively.
    pub exhaustive_up_to: usize,
    /// Above it: each image with the next this many (input order).
    pub sequential: usize,
    /// Above it: each image with its this many most similar by the bag of words.
    pub retrieval: usize,
}

impl Default for AutoPairs {
    fn default() -> Self {
        Self {
            exhaustive_up_to: EXHAUSTIVE_UP_TO,
            sequential: 10,
            retrieval: 20,
        }
    }
}

impl PairSelection {
    /// The rules used for `n` images, `auto` as [`AutoPairs::default`].
    pub fn rules(&self, n: usize) -> Vec<PairRule> {
        self.rules_with(n, &AutoPairs::default())
    }

    /// The rules used for `n` images, `auto` as `auto` says.
    pub fn rules_with(&self, n: usize, auto: &AutoPairs) -> Vec<PairRule> {
        match self {
            Self::Auto if n <= auto.exhaustive_up_to => vec![PairRule::Exhaustive],
            Self::Auto => vec![
                PairRule::Sequential(auto.sequential),
                PairRule::Retrieval(auto.retrieval),
            ],
            Self::Rules(r) => r.clone(),
        }
    }

    /// Whether any rule needs descriptors (retrieval).
    pub fn needs_features(&self, n: usize) -> bool {
        self.rules(n)
            .iter()
            .any(|r| matches!(r, PairRule::Retrieval(_)))
    }
}

impl fmt::Display for PairRule {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Exhaustive => write!(f, "exhaustive"),
            Self::Sequential(k) => write!(f, "sequential:{k}"),
            Self::Retrieval(k) => write!(f, "retrieval:{k}"),
        }
    }
}

impl fmt::Display for PairSelection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Auto => write!(f, "auto"),
            Self::Rules(r) => {
                let parts: Vec<String> = r.iter().map(ToString::to_string).collect();
                write!(f, "{}", parts.join(","))
            }
        }
    }
}

/// The spatial pair plan on estimated poses (COLMAP's spatial matcher, by viewing
/// direction): for each estimated camera (`rotations[i]`, world → camera; `None`: not
/// estimated), its nearest estimated cameras by the rotation between them, within
/// `max_angle_deg`, that are not in `matched` (`(min, max)` pairs), `per_image` at most; sorted
/// `(i, j)` with `i < j`, without repeats. `O(n²)` rotation comparisons.
pub fn spatial_pairs(
    rotations: &[Option<nalgebra::Matrix3<f64>>],
    matched: &std::collections::HashSet<(usize, usize)>,
    max_angle_deg: f64,
    per_image: usize,
) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    for (i, a) in rotations.iter().enumerate() {
        let Some(a) = a else { continue };
        let mut near: Vec<(f64, usize)> = rotations
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i && !matched.contains(&(i.min(j), i.max(j))))
            .filter_map(|(j, b)| {
                let b = b.as_ref()?;
                let angle = posediff_geometry::epipolar::rotation_angle_between_deg(a, b);
                (angle.is_finite() && angle <= max_angle_deg).then_some((angle, j))
            })
            .collect();
        near.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
        out.extend(
            near.iter()
                .take(per_image)
                .map(|&(_, j)| (i.min(j), i.max(j))),
        );
    }
    out.sort_unstable();
    out.dedup();
    out
}

/// As its text (`auto`, `sequential:10,retrieval:20`), the form `--pairs` takes.
#[cfg(feature = "serde")]
impl serde::Serialize for PairSelection {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

#[cfg(feature = "serde")]
impl<'de> serde::Deserialize<'de> for PairSelection {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

impl FromStr for PairSelection {
    type Err = String;

    /// `auto`, `exhaustive`, `sequential:K`, `retrieval:K`, or a comma-separated union
    /// (e.g. `sequential:10,retrieval:20`); `K ≥ 1`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        if s.trim() == "auto" {
            return Ok(Self::Auto);
        }
        let mut rules = Vec::new();
        for part in s.split(',').map(str::trim) {
            let rule = match part.split_once(':') {
                None if part == "exhaustive" => PairRule::Exhaustive,
                Some((name, k)) => {
                    let k: usize = k.parse().ok().filter(|k| *k >= 1).ok_or_else(|| {
                        format!("`{part}`: the count after `:` must be a whole number ≥ 1")
                    })?;
                    match name {
                        "sequential" => PairRule::Sequential(k),
                        "retrieval" => PairRule::Retrieval(k),
                        _ => return Err(format!("unknown pair rule `{name}` in `{part}`")),
                    }
                }
                None => {
                    return Err(format!(
                        "unknown pair rule `{part}`: use auto, exhaustive, sequential:K or retrieval:K"
                    ));
                }
            };
            rules.push(rule);
        }
        Ok(Self::Rules(rules))
    }
}

/// The pairs `i < j` of `n` images that `selection` chooses, sorted and without repeats.
/// `features` (one per image) is needed only for retrieval.
///
/// # Errors
/// A retrieval rule without features, or features for a different number of images.
pub fn select_pairs(
    n: usize,
    selection: &PairSelection,
    features: Option<&[ImageFeatures]>,
) -> Result<Vec<(usize, usize)>> {
    select_pairs_with(n, selection, features, None)
}

/// [`select_pairs`] with the bag of words of `features` already built (with
/// [`RetrievalOptions::default`]): retrieval rules use it instead of building their own.
///
/// # Errors
/// As [`select_pairs`].
pub fn select_pairs_with(
    n: usize,
    selection: &PairSelection,
    features: Option<&[ImageFeatures]>,
    words: Option<&BagOfWords>,
) -> Result<Vec<(usize, usize)>> {
    let mut pairs = Vec::new();
    for rule in selection.rules(n) {
        match rule {
            PairRule::Exhaustive => {
                pairs.extend((0..n).flat_map(|i| (i + 1..n).map(move |j| (i, j))));
            }
            PairRule::Sequential(k) => {
                pairs.extend((0..n).flat_map(|i| (i + 1..n.min(i + 1 + k)).map(move |j| (i, j))));
            }
            PairRule::Retrieval(k) => match features {
                Some(f) if f.len() == n => match words {
                    Some(w) if w.len() == n => pairs.extend(w.pairs(k)),
                    _ => pairs.extend(retrieval_pairs(f, k, &RetrievalOptions::default())),
                },
                _ => {
                    return Err(MatchingError::InvalidConfig(
                        "retrieval pair selection needs the features of every image",
                    ));
                }
            },
        }
    }
    pairs.sort_unstable();
    pairs.dedup();
    Ok(pairs)
}

/// Settings of the bag of words.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct RetrievalOptions {
    /// Visual words (k-means centres).
    pub words: usize,
    /// Descriptors per image that are quantised (the first ones: the strongest keypoints).
    pub per_image: usize,
    /// Descriptors sampled for the vocabulary.
    pub training_samples: usize,
    /// Lloyd iterations.
    pub iterations: usize,
}

impl Default for RetrievalOptions {
    fn default() -> Self {
        Self {
            words: 512,
            per_image: 1024,
            training_samples: 50_000,
            iterations: 8,
        }
    }
}

/// Descriptors as float rows (binary ones bit by bit).
fn float_rows(d: &Descriptors, max_rows: usize) -> (Vec<f32>, usize) {
    match d {
        Descriptors::Float { data, dim } => {
            let rows = (data.len() / dim.max(&1)).min(max_rows);
            (data[..rows * dim].to_vec(), *dim)
        }
        Descriptors::Bytes { data, dim } => {
            let rows = (data.len() / dim.max(&1)).min(max_rows);
            (crate::features::byte_floats(&data[..rows * dim]), *dim)
        }
        Descriptors::Binary { data, words } => {
            let rows = (data.len() / words.max(&1)).min(max_rows);
            let dim = 64 * words;
            let mut out = Vec::with_capacity(rows * dim);
            for r in 0..rows {
                for w in &data[r * words..(r + 1) * words] {
                    out.extend((0..64).map(|b| ((w >> b) & 1) as f32));
                }
            }
            (out, dim)
        }
    }
}

/// Rows per task of [`assign`].
const ASSIGN_ROWS: usize = 1024;

/// Index of the nearest centre of each row of `rows` (row-major, `dim` wide): squared L2 via
/// matrix products, `ASSIGN_ROWS` rows per task in parallel (each row's products are the
/// same whichever task computes them).
fn assign(rows: &[f32], dim: usize, centres: &DMatrix<f32>) -> Vec<usize> {
    let norms: Vec<f32> = centres.row_iter().map(|c| c.norm_squared()).collect();
    let ct = centres.transpose();
    let chunks: Vec<Vec<usize>> = rows
        .par_chunks(ASSIGN_ROWS * dim.max(1))
        .map(|chunk| {
            let block = DMatrix::from_row_slice(chunk.len() / dim.max(1), dim, chunk);
            let dots = &block * &ct;
            (0..block.nrows())
                .map(|i| {
                    (0..centres.nrows())
                        .map(|c| (c, norms[c] - 2.0 * dots[(i, c)]))
                        .min_by(|a, b| a.1.total_cmp(&b.1))
                        .map_or(0, |(c, _)| c)
                })
                .collect()
        })
        .collect();
    chunks.concat()
}

/// A tf-idf bag of visual words over a set of images: the vocabulary (k-means on their
/// descriptors), its inverse document frequencies and each image's normalised histogram.
/// Deterministic (no random state: the vocabulary is seeded from evenly spaced samples).
#[derive(Debug, Clone)]
pub struct BagOfWords {
    centres: DMatrix<f32>,
    idf: Vec<f32>,
    dim: usize,
    per_image: usize,
    /// One normalised row per image of the set (zero for an image without descriptors).
    histograms: DMatrix<f32>,
}

impl BagOfWords {
    /// The vocabulary and histograms of `features`; `None` when they hold no descriptors.
    pub fn build(features: &[ImageFeatures], options: &RetrievalOptions) -> Option<Self> {
        let n = features.len();
        let per_image: Vec<(Vec<f32>, usize)> = features
            .iter()
            .map(|f| float_rows(&f.descriptors, options.per_image))
            .collect();
        let dim = per_image.iter().map(|p| p.1).max().unwrap_or(0);
        let total: usize = per_image.iter().map(|(d, w)| d.len() / (*w).max(1)).sum();
        if dim == 0 || total == 0 {
            return None;
        }
        // Vocabulary: evenly spaced samples, the first `words` of them as initial centres.
        let stride = (total / options.training_samples.max(1)).max(1);
        let mut sample = Vec::new();
        let mut index = 0usize;
        for (data, w) in &per_image {
            if *w != dim {
                continue;
            }
            for row in data.chunks_exact(dim) {
                if index.is_multiple_of(stride) {
                    sample.extend_from_slice(row);
                }
                index += 1;
            }
        }
        let samples = sample.len() / dim;
        let words = options.words.min(samples).max(1);
        let step = (samples / words).max(1);
        let mut centres =
            DMatrix::from_fn(words, dim, |c, d| sample[((c * step) % samples) * dim + d]);
        for _ in 0..options.iterations {
            let labels = assign(&sample, dim, &centres);
            let mut sums = DMatrix::<f32>::zeros(words, dim);
            let mut counts = vec![0usize; words];
            for (row, &l) in sample.chunks_exact(dim).zip(&labels) {
                counts[l] += 1;
                for (d, &x) in row.iter().enumerate() {
                    sums[(l, d)] += x;
                }
            }
            for c in 0..words {
                if counts[c] > 0 {
                    for d in 0..dim {
                        centres[(c, d)] = sums[(c, d)] / counts[c] as f32;
                    }
                }
            }
        }
        // Histograms, idf, normalisation.
        let mut hist = DMatrix::<f32>::zeros(n, words);
        let labels: Vec<Vec<usize>> = per_image
            .par_iter()
            .map(|(data, w)| {
                if *w != dim || data.is_empty() {
                    Vec::new()
                } else {
                    assign(data, dim, &centres)
                }
            })
            .collect();
        for (i, labels) in labels.iter().enumerate() {
            for &l in labels {
                hist[(i, l)] += 1.0;
            }
        }
        let idf: Vec<f32> = (0..words)
            .map(|c| {
                let df = (0..n).filter(|&i| hist[(i, c)] > 0.0).count();
                if df > 0 {
                    (n as f32 / df as f32).ln()
                } else {
                    0.0
                }
            })
            .collect();
        for (c, &w) in idf.iter().enumerate() {
            for i in 0..n {
                hist[(i, c)] *= w;
            }
        }
        for i in 0..n {
            let norm = hist.row(i).norm();
            if norm > 0.0 {
                for c in 0..words {
                    hist[(i, c)] /= norm;
                }
            }
        }
        Some(Self {
            centres,
            idf,
            dim,
            per_image: options.per_image,
            histograms: hist,
        })
    }

    /// Images of the set.
    pub fn len(&self) -> usize {
        self.histograms.nrows()
    }

    /// Whether the set has no images.
    pub fn is_empty(&self) -> bool {
        self.histograms.nrows() == 0
    }

    /// The normalised histogram of image `i` of the set.
    pub fn histogram_of(&self, i: usize) -> Option<Vec<f32>> {
        (i < self.histograms.nrows()).then(|| self.histograms.row(i).iter().copied().collect())
    }

    /// The normalised histogram of other features (an image of the set extracted again, say)
    /// in this vocabulary and with the set's idf; zero when their descriptors do not fit it.
    pub fn histogram(&self, features: &ImageFeatures) -> Vec<f32> {
        let mut hist = vec![0.0f32; self.idf.len()];
        let (data, w) = float_rows(&features.descriptors, self.per_image);
        if w == self.dim && !data.is_empty() {
            for l in assign(&data, w, &self.centres) {
                hist[l] += 1.0;
            }
        }
        for (h, w) in hist.iter_mut().zip(&self.idf) {
            *h *= w;
        }
        let norm = hist.iter().map(|h| h * h).sum::<f32>().sqrt();
        if norm > 0.0 {
            for h in &mut hist {
                *h /= norm;
            }
        }
        hist
    }

    /// The images of the set for which `keep` holds, most similar to `histogram` first (cosine;
    /// ties by index), `k` at most.
    pub fn most_similar(
        &self,
        histogram: &[f32],
        k: usize,
        keep: impl Fn(usize) -> bool,
    ) -> Vec<usize> {
        let mut others: Vec<(usize, f32)> = (0..self.histograms.nrows())
            .filter(|&j| keep(j))
            .map(|j| {
                let row = self.histograms.row(j);
                (j, row.iter().zip(histogram).map(|(a, b)| a * b).sum())
            })
            .collect();
        others.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        others.into_iter().take(k).map(|(j, _)| j).collect()
    }

    /// For each image its `k` most similar others, as pairs `i < j`, sorted, without repeats.
    pub fn pairs(&self, k: usize) -> Vec<(usize, usize)> {
        let n = self.histograms.nrows();
        let similarity = &self.histograms * self.histograms.transpose();
        let mut pairs = Vec::new();
        for i in 0..n {
            let mut others: Vec<(usize, f32)> = (0..n)
                .filter(|&j| j != i)
                .map(|j| (j, similarity[(i, j)]))
                .collect();
            others.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
            for &(j, _) in others.iter().take(k) {
                pairs.push((i.min(j), i.max(j)));
            }
        }
        pairs.sort_unstable();
        pairs.dedup();
        pairs
    }
}

/// For each image its `k` most similar others by tf-idf bag-of-words cosine similarity
/// ([`BagOfWords`]), as pairs `i < j`.
pub fn retrieval_pairs(
    features: &[ImageFeatures],
    k: usize,
    options: &RetrievalOptions,
) -> Vec<(usize, usize)> {
    if features.len() < 2 || k == 0 {
        return Vec::new();
    }
    BagOfWords::build(features, options).map_or_else(Vec::new, |b| b.pairs(k))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use posediff_geometry::ImageSize;

    #[test]
    fn selections_parse_and_print() {
        let s: PairSelection = "sequential:10, retrieval:20".parse().unwrap();
        assert_eq!(
            s,
            PairSelection::Rules(vec![PairRule::Sequential(10), PairRule::Retrieval(20)])
        );
        assert_eq!(s.to_string(), "sequential:10,retrieval:20");
        assert_eq!(
            "auto".parse::<PairSelection>().unwrap(),
            PairSelection::Auto
        );
        for bad in ["sequential", "sequential:0", "retrieval:x", "nearest:3", ""] {
            assert!(bad.parse::<PairSelection>().is_err(), "{bad}");
        }
        assert_eq!(PairSelection::Auto.rules(10), vec![PairRule::Exhaustive]);
        assert!(PairSelection::Auto.needs_features(1000));
    }

    #[test]
    fn sequential_and_exhaustive_pairs() {
        let seq = select_pairs(5, &"sequential:2".parse().unwrap(), None).unwrap();
        assert_eq!(
            seq,
            vec![(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4)]
        );
        assert_eq!(
            select_pairs(5, &"exhaustive".parse().unwrap(), None)
                .unwrap()
                .len(),
            10
        );
        // Union without repeats.
        let both = select_pairs(5, &"sequential:2,exhaustive".parse().unwrap(), None).unwrap();
        assert_eq!(both.len(), 10);
        // Retrieval needs the features: an error, never silently fewer pairs.
        assert!(select_pairs(5, &"sequential:2,retrieval:3".parse().unwrap(), None).is_err());
    }

    /// Retrieval pairs each image of [`three_scenes`] with its twin.
    #[test]
    fn retrieval_finds_the_images_of_the_same_scene() {
        let (features, options) = three_scenes();
        let pairs = retrieval_pairs(&features, 1, &options);
        assert_eq!(pairs, vec![(0, 3), (1, 4), (2, 5)]);
    }

    /// A query by features outside the set (here copies of the set's images) lands in the set's
    /// histogram of the same image, and the most similar images respect the filter and `k`.
    #[test]
    fn queries_in_the_vocabulary_find_the_same_scene() {
        let (features, options) = three_scenes();
        let words = BagOfWords::build(&features, &options).unwrap();
        assert_eq!(words.len(), 6);
        for (i, f) in features.iter().enumerate() {
            let h = words.histogram(f);
            let own = words.histogram_of(i).unwrap();
            assert!(h.iter().zip(&own).all(|(a, b)| (a - b).abs() < 1e-6));
            assert_eq!(words.most_similar(&h, 1, |j| j != i), vec![(i + 3) % 6]);
            let others = words.most_similar(&h, 3, |j| j % 3 != i % 3);
            assert_eq!(others.len(), 3);
            assert!(others.iter().all(|j| j % 3 != i % 3), "{others:?}");
        }
        assert!(words.histogram_of(6).is_none());
    }

    /// Three "scenes" of two images each (descriptors drawn around scene-specific centres),
    /// with a vocabulary small enough for them.
    fn three_scenes() -> (Vec<ImageFeatures>, RetrievalOptions) {
        let mut seed = 7u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let scenes: Vec<Vec<f32>> = (0..3)
            .map(|_| (0..20 * 8).map(|_| rnd() * 10.0).collect())
            .collect();
        let features: Vec<ImageFeatures> = (0..6)
            .map(|i| {
                let centres = &scenes[i % 3];
                let mut data = Vec::new();
                for r in 0..200 {
                    let c = &centres[(r % 20) * 8..(r % 20 + 1) * 8];
                    data.extend(c.iter().map(|v| v + 0.1 * rnd()));
                }
                ImageFeatures {
                    image_size: ImageSize::new(10, 10).unwrap(),
                    keypoints: vec![[0.0, 0.0]; 200],
                    descriptors: Descriptors::Float { data, dim: 8 },
                    half_turned: false,
                }
            })
            .collect();
        let options = RetrievalOptions {
            words: 60,
            ..RetrievalOptions::default()
        };
        (features, options)
    }
}
