//! Features and verified matches kept between runs (COLMAP's `database.db`, written by the
//! umbrella's `io::database`): a [`FeatureStore`] is asked before anything is extracted or
//! matched, and [`Stored`] wraps a matcher so that it only works on what the store lacks, and
//! commits its work in chunks ([`crate::options::DatabaseOptions`]), so that a run killed
//! mid-way loses at most one chunk and the next run resumes.
//!
//! What a run uses is what the store holds: features come back from the store after they are
//! written (COLMAP keeps keypoints as 32-bit floats), so a first run and a resumed one see the
//! same numbers and give the same cameras.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use posediff_geometry::PairMatches;
use posediff_matching::ImageFeatures;

use crate::correspondences::{Correspondences, StepCounter};
use crate::error::Result;

/// A verification outcome as stored: the keypoint indices of each verified match (in the
/// pair's order, first image first), empty for a pair that verified too few.
pub type StoredMatches = Vec<(u32, u32)>;

/// Where features and verified matches are kept between runs. The images of a run are set by
/// [`Self::features`]; [`Self::matches`] and [`Self::put_matches`] name them by index into that
/// list.
pub trait FeatureStore: Send + Sync {
    /// The stored features of each of `images` (`None`: not stored), and `images` as the list
    /// later pair indices refer to.
    ///
    /// # Errors
    /// Images that are not the run's; unreadable records.
    fn features(&self, images: &[PathBuf]) -> Result<Vec<Option<ImageFeatures>>>;

    /// Stores the features of `images` in one commit; returns them as stored.
    ///
    /// # Errors
    /// Images that are not the run's; the store cannot be written.
    fn put_features(
        &self,
        images: &[&Path],
        features: Vec<ImageFeatures>,
    ) -> Result<Vec<ImageFeatures>>;

    /// The stored outcome of each pair (indices into the last [`Self::features`] list;
    /// `None`: never matched).
    ///
    /// # Errors
    /// Indices out of range; unreadable records.
    fn matches(&self, pairs: &[(usize, usize)]) -> Result<Vec<Option<StoredMatches>>>;

    /// Stores the verified matches of pairs in one commit (each `PairMatches` names its pair;
    /// an empty one records a pair that verified too few).
    ///
    /// # Errors
    /// Indices out of range; the store cannot be written.
    fn put_matches(&self, pairs: &[PairMatches]) -> Result<()>;

    /// [`Self::put_matches`] with each pair's matches before verification where the matcher
    /// kept them (`raw[k]` of `pairs[k]`; COLMAP's `matches` table holds them, its
    /// `two_view_geometries` the verified ones). A store without a place for them stores the
    /// verified ones only.
    ///
    /// # Errors
    /// As [`Self::put_matches`]; `raw` of another length than `pairs`.
    fn put_matches_with_raw(
        &self,
        pairs: &[PairMatches],
        raw: &[Option<PairMatches>],
    ) -> Result<()> {
        let _ = raw;
        self.put_matches(pairs)
    }

    /// How many images the last [`Self::features`] list has.
    fn images(&self) -> usize;

    /// The pairs to map instead of a selection (indices into the last [`Self::features`]
    /// list): `posediff map` maps the pairs its database holds, as COLMAP's mappers do.
    ///
    /// # Errors
    /// Unreadable records.
    fn fixed_pairs(&self) -> Result<Option<Vec<(usize, usize)>>> {
        Ok(None)
    }

    /// The pair selection stored under `rules` for exactly the last [`Self::features`] list
    /// (`None`: none, or one made for other images or another order), so that the workers of a
    /// distributed run match the driver's selection instead of each making it again.
    ///
    /// # Errors
    /// Unreadable records.
    fn selection(&self, rules: &str) -> Result<Option<Vec<(usize, usize)>>> {
        let _ = rules;
        Ok(None)
    }

    /// Stores `pairs`, the selection `rules` made for the last [`Self::features`] list.
    ///
    /// # Errors
    /// The store cannot be written.
    fn put_selection(&self, rules: &str, pairs: &[(usize, usize)]) -> Result<()> {
        let _ = (rules, pairs);
        Ok(())
    }
}

/// One of `count` parts of a run's work (`--shard K/N`), for extraction and matching spread
/// over processes or machines that each fill their own copy of the store: images are split
/// into `count` contiguous runs, the selected pairs every `count`-th from `index`. The parts
/// together are exactly the whole run's work, each piece in one part.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    /// This part, `0..count`.
    pub index: usize,
    /// How many parts.
    pub count: usize,
}

impl Shard {
    /// `K/N`, with `K < N`.
    ///
    /// # Errors
    /// Anything else, named.
    pub fn parse(text: &str) -> Result<Self> {
        let bad = || {
            crate::error::PosediffError::InvalidArgument(format!(
                "shard {text:?}: give K/N with 0 <= K < N (e.g. 0/4)"
            ))
        };
        let (k, n) = text.split_once('/').ok_or_else(bad)?;
        let (index, count) = (
            k.trim().parse::<usize>().map_err(|_| bad())?,
            n.trim().parse::<usize>().map_err(|_| bad())?,
        );
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Self { index, count })
    }

    /// This part's images of `len`: a contiguous range (empty when there are more parts than
    /// images).
    pub fn images(&self, len: usize) -> std::ops::Range<usize> {
        (self.index * len / self.count)..((self.index + 1) * len / self.count)
    }

    /// This part's pairs of `pairs` (the whole run's selection, in its order).
    pub fn pairs(&self, pairs: &[(usize, usize)]) -> Vec<(usize, usize)> {
        pairs
            .iter()
            .skip(self.index)
            .step_by(self.count)
            .copied()
            .collect()
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// A store shared by the configurations that use it (equal when it is the same store).
#[derive(Clone)]
pub struct SharedStore(pub Arc<dyn FeatureStore>);

impl std::fmt::Debug for SharedStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SharedStore")
    }
}

impl PartialEq for SharedStore {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// A matcher that asks `store` first and stores what it computes, `images_per_commit` images
/// and `pairs_per_commit` pairs at a time. Turned features (the orientation check's) and
/// feature lists that are not the run's pass through unstored.
pub struct Stored<'a> {
    /// The matcher (with its masks applied: the store holds the features the matches index).
    pub inner: Box<dyn Correspondences + 'a>,
    /// The store.
    pub store: &'a dyn FeatureStore,
    /// Images extracted per commit.
    pub images_per_commit: usize,
    /// Pairs matched per commit.
    pub pairs_per_commit: usize,
}

/// Forwards nothing: the chunks of [`Stored`] are counted by it, not by the inner matcher.
struct Quiet;
impl StepCounter for Quiet {}

/// The matches `stored` of pair `(i, j)` with the keypoints of `features`.
fn rebuild(
    features: &[ImageFeatures],
    (i, j): (usize, usize),
    stored: &StoredMatches,
) -> Result<PairMatches> {
    let (a, b) = (&features[i], &features[j]);
    let mut m = PairMatches {
        first: i,
        second: j,
        ..PairMatches::default()
    };
    for &(k, l) in stored {
        let (Some(&p), Some(&q)) = (a.keypoints.get(k as usize), b.keypoints.get(l as usize))
        else {
            return Err(crate::error::PosediffError::InvalidArgument(format!(
                "stored match ({k}, {l}) of images {i} and {j} names a keypoint beyond their {} and {}",
                a.keypoints.len(),
                b.keypoints.len()
            )));
        };
        m.kp1.push(p);
        m.kp2.push(q);
        m.idx1.push(k);
        m.idx2.push(l);
    }
    Ok(m)
}

impl Correspondences for Stored<'_> {
    fn extract(&self, images: &[PathBuf], counter: &dyn StepCounter) -> Result<Vec<ImageFeatures>> {
        let mut out = self.store.features(images)?;
        let missing: Vec<usize> = (0..images.len()).filter(|&i| out[i].is_none()).collect();
        log::info!(
            "features: {} of {} images from the database, {} to extract",
            images.len() - missing.len(),
            images.len(),
            missing.len()
        );
        counter.stage("features", missing.len() as u64);
        for chunk in missing.chunks(self.images_per_commit.max(1)) {
            let paths: Vec<PathBuf> = chunk.iter().map(|&i| images[i].clone()).collect();
            let fresh = self.inner.extract(&paths, &Quiet)?;
            let refs: Vec<&Path> = paths.iter().map(PathBuf::as_path).collect();
            for (&i, f) in chunk.iter().zip(self.store.put_features(&refs, fresh)?) {
                out[i] = Some(f);
                counter.step();
            }
        }
        Ok(out.into_iter().flatten().collect())
    }

    fn match_pairs(
        &self,
        features: &[ImageFeatures],
        pairs: &[(usize, usize)],
        (counter, name): (&dyn StepCounter, &str),
    ) -> Result<Vec<PairMatches>> {
        if features.len() != self.store.images() || features.iter().any(|f| f.half_turned) {
            return self.inner.match_pairs(features, pairs, (counter, name));
        }
        posediff_matching::check_pairs(features.len(), pairs)?;
        let stored = self.store.matches(pairs)?;
        let mut out: Vec<Option<PairMatches>> = vec![None; pairs.len()];
        let mut missing = Vec::new();
        for (k, s) in stored.iter().enumerate() {
            match s {
                Some(s) => out[k] = Some(rebuild(features, pairs[k], s)?),
                None => missing.push(k),
            }
        }
        log::info!(
            "{name}: {} of {} pairs from the database, {} to match",
            pairs.len() - missing.len(),
            pairs.len(),
            missing.len()
        );
        counter.stage(name, missing.len() as u64);
        for chunk in missing.chunks(self.pairs_per_commit.max(1)) {
            let list: Vec<(usize, usize)> = chunk.iter().map(|&k| pairs[k]).collect();
            let (raw, fresh): (Vec<Option<PairMatches>>, Vec<PairMatches>) = self
                .inner
                .match_pairs_with_raw(features, &list, (&Quiet, name))?
                .into_iter()
                .unzip();
            if fresh.len() != list.len()
                || fresh
                    .iter()
                    .zip(&list)
                    .any(|(m, &p)| (m.first, m.second) != p)
            {
                return Err(crate::error::PosediffError::InvalidArgument(format!(
                    "the matcher answered {} pairs for {} asked, or out of order",
                    fresh.len(),
                    list.len()
                )));
            }
            self.store.put_matches_with_raw(&fresh, &raw)?;
            drop(raw);
            for (&k, m) in chunk.iter().zip(fresh) {
                out[k] = Some(m);
                counter.step();
            }
            log::info!("{name}: stored {} pairs", chunk.len());
        }
        Ok(out.into_iter().flatten().collect())
    }

    fn depends_on_orientation(&self) -> bool {
        self.inner.depends_on_orientation()
    }

    fn extract_turned(
        &self,
        images: &[&Path],
        counter: &dyn StepCounter,
    ) -> Result<Option<Vec<ImageFeatures>>> {
        self.inner.extract_turned(images, counter)
    }
}

#[cfg(test)]
mod tests {
    use super::Shard;

    /// The parts cover every image and every pair exactly once.
    #[test]
    fn shards_partition_images_and_pairs() {
        let pairs: Vec<(usize, usize)> = (0..7)
            .flat_map(|i| (i + 1..7).map(move |j| (i, j)))
            .collect();
        for count in 1..=9 {
            let parts: Vec<Shard> = (0..count).map(|index| Shard { index, count }).collect();
            let mut images: Vec<usize> = parts.iter().flat_map(|s| s.images(7)).collect();
            images.sort_unstable();
            assert_eq!(images, (0..7).collect::<Vec<_>>(), "{count} parts");
            let mut all: Vec<(usize, usize)> = parts.iter().flat_map(|s| s.pairs(&pairs)).collect();
            all.sort_unstable();
            assert_eq!(all, pairs, "{count} parts");
        }
        assert_eq!(Shard::parse("1/3").unwrap(), Shard { index: 1, count: 3 });
        for bad in ["3/3", "1", "a/2", "0/0", "-1/2"] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
    }
}
