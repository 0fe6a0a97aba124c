//! Accuracy at thresholds and mean average accuracy, as the official `test.py` reports them.
//!
//! - RRA@τ / RTA@τ: the fraction of pairs whose rotation / translation error is **strictly**
//!   below τ (τ ∈ {5, 15, 30}°). `test.py` prints them ×100; here they are fractions.
//! - mAA(30) of `test.py` (`calculate_auc_np`): `e = max(rotation, translation)` per pair,
//!   `np.histogram(e, bins=[0, 1, …, 30])` (the last bin closed, `e > 30` dropped), divided by the
//!   number of pairs, `mean(cumsum)`. `train.py` uses `torch.histc` with 31 bins over `[0, 30]`
//!   instead, a different number ([`maa_train_py`]).
//! - Per category, the pairs of all sequences are pooled; the reported mean is the unweighted
//!   mean over categories ([`CategoryPool`]).

use std::collections::BTreeMap;

use crate::error::{MetricsError, Result};
use crate::relative::PairError;

/// The thresholds `test.py` reports, in degrees.
pub const THRESHOLDS_DEG: [f64; 3] = [5.0, 15.0, 30.0];

/// The mAA threshold of `test.py` (`max_threshold=30`).
pub const MAA_MAX_THRESHOLD_DEG: u32 = 30;

fn ensure_pairs(pairs: &[PairError]) -> Result<()> {
    if pairs.is_empty() {
        Err(MetricsError::TooFew {
            what: "pairs",
            needed: 1,
            got: 0,
        })
    } else {
        Ok(())
    }
}

/// Fraction of `errors_deg` strictly below `threshold_deg`.
pub fn fraction_below(errors_deg: impl ExactSizeIterator<Item = f64>, threshold_deg: f64) -> f64 {
    let n = errors_deg.len();
    if n == 0 {
        return 0.0;
    }
    errors_deg.filter(|&e| e < threshold_deg).count() as f64 / n as f64
}

/// `test.py`'s `calculate_auc_np(r, t, max_threshold)`: one-degree bins.
///
/// # Errors
/// No pairs.
pub fn maa_test_py(pairs: &[PairError], max_threshold_deg: u32) -> Result<f64> {
    ensure_pairs(pairs)?;
    let bins = max_threshold_deg as usize;
    let mut histogram = vec![0usize; bins];
    let top = f64::from(max_threshold_deg);
    for e in pairs.iter().map(PairError::max_deg) {
        if (0.0..top).contains(&e) {
            histogram[e.floor() as usize] += 1;
        } else if e == top && bins > 0 {
            histogram[bins - 1] += 1;
        }
    }
    Ok(mean_cumsum(&histogram, pairs.len()))
}

/// `train.py`'s `calculate_auc`: `torch.histc(e, bins=max+1, min=0, max=max)`.
///
/// # Errors
/// No pairs.
pub fn maa_train_py(pairs: &[PairError], max_threshold_deg: u32) -> Result<f64> {
    ensure_pairs(pairs)?;
    let bins = max_threshold_deg as usize + 1;
    let top = f64::from(max_threshold_deg);
    let mut histogram = vec![0usize; bins];
    for e in pairs.iter().map(PairError::max_deg) {
        if (0.0..=top).contains(&e) {
            let pos = ((e / top) * bins as f64) as usize;
            histogram[pos.min(bins - 1)] += 1;
        }
    }
    Ok(mean_cumsum(&histogram, pairs.len()))
}

fn mean_cumsum(histogram: &[usize], n_pairs: usize) -> f64 {
    let mut acc = 0.0;
    let mut sum = 0.0;
    for &h in histogram {
        acc += h as f64 / n_pairs as f64;
        sum += acc;
    }
    sum / histogram.len() as f64
}

/// The numbers `test.py` reports for a set of pairs (fractions, not percent).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseAccuracy {
    /// Relative rotation accuracy at 5°, 15°, 30°.
    pub rra: [f64; 3],
    /// Relative translation accuracy at 5°, 15°, 30°.
    pub rta: [f64; 3],
    /// mAA(30) as `test.py` computes it.
    pub maa_30: f64,
    /// Number of pairs behind the numbers.
    pub pairs: usize,
}

impl PoseAccuracy {
    /// The metrics of a pooled set of pairs.
    ///
    /// # Errors
    /// No pairs.
    pub fn from_pairs(pairs: &[PairError]) -> Result<Self> {
        ensure_pairs(pairs)?;
        let at = |f: fn(&PairError) -> f64| {
            THRESHOLDS_DEG.map(|t| fraction_below(pairs.iter().map(f), t))
        };
        Ok(Self {
            rra: at(|p| p.rotation_deg),
            rta: at(|p| p.translation_deg),
            maa_30: maa_test_py(pairs, MAA_MAX_THRESHOLD_DEG)?,
            pairs: pairs.len(),
        })
    }

    /// The unweighted mean of several results (the "mean" row of `test.py` over categories);
    /// `pairs` is the total.
    ///
    /// # Errors
    /// An empty list.
    pub fn mean(results: &[Self]) -> Result<Self> {
        if results.is_empty() {
            return Err(MetricsError::TooFew {
                what: "results to average",
                needed: 1,
                got: 0,
            });
        }
        let n = results.len() as f64;
        let avg3 = |f: fn(&Self) -> [f64; 3]| {
            [0, 1, 2].map(|k| results.iter().map(|r| f(r)[k]).sum::<f64>() / n)
        };
        Ok(Self {
            rra: avg3(|r| r.rra),
            rta: avg3(|r| r.rta),
            maa_30: results.iter().map(|r| r.maa_30).sum::<f64>() / n,
            pairs: results.iter().map(|r| r.pairs).sum(),
        })
    }
}

/// Pairs pooled per category, in sorted category order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CategoryPool {
    pairs: BTreeMap<String, Vec<PairError>>,
}

/// Per-category results and their unweighted mean.
#[derive(Debug, Clone, PartialEq)]
pub struct CategoryReport {
    /// Metrics of each category (all pairs of all its sequences pooled), sorted by name.
    pub per_category: BTreeMap<String, PoseAccuracy>,
    /// Unweighted mean over categories.
    pub mean: PoseAccuracy,
}

impl CategoryPool {
    /// An empty pool.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds the pairs of one sequence of `category`.
    pub fn add(&mut self, category: &str, pairs: &[PairError]) {
        self.pairs
            .entry(category.to_owned())
            .or_default()
            .extend_from_slice(pairs);
    }

    /// Metrics per category and their mean.
    ///
    /// # Errors
    /// An empty pool or a category without pairs.
    pub fn report(&self) -> Result<CategoryReport> {
        let per_category = self
            .pairs
            .iter()
            .map(|(c, p)| Ok((c.clone(), PoseAccuracy::from_pairs(p)?)))
            .collect::<Result<BTreeMap<_, _>>>()?;
        let all: Vec<PoseAccuracy> = per_category.values().copied().collect();
        Ok(CategoryReport {
            mean: PoseAccuracy::mean(&all)?,
            per_category,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair(r: f64, t: f64) -> PairError {
        PairError {
            i: 0,
            j: 1,
            rotation_deg: r,
            translation_deg: t,
        }
    }

    #[test]
    fn thresholds_are_strict() {
        let pairs = [pair(5.0, 0.0), pair(4.999, 15.0), pair(31.0, 30.0)];
        let a = PoseAccuracy::from_pairs(&pairs).unwrap();
        assert_eq!(a.rra, [1.0 / 3.0, 2.0 / 3.0, 2.0 / 3.0]);
        assert_eq!(a.rta, [1.0 / 3.0, 1.0 / 3.0, 2.0 / 3.0]);
    }

    #[test]
    fn maa_of_perfect_and_failed_pairs() {
        assert_eq!(maa_test_py(&[pair(0.0, 0.0)], 30).unwrap(), 1.0);
        assert_eq!(maa_test_py(&[pair(180.0, 90.0)], 30).unwrap(), 0.0);
        // e = 30 lands in the last, closed bin: counted once, in the final cumsum entry.
        assert!((maa_test_py(&[pair(30.0, 0.0)], 30).unwrap() - 1.0 / 30.0).abs() < 1e-15);
        // e = 2.5 is below thresholds 3..30: 28 of 30 entries.
        assert!((maa_test_py(&[pair(2.5, 1.0)], 30).unwrap() - 28.0 / 30.0).abs() < 1e-15);
        assert!(maa_test_py(&[], 30).is_err());
    }

    #[test]
    fn category_mean_is_unweighted() {
        let mut pool = CategoryPool::new();
        pool.add("b", &[pair(1.0, 1.0)]);
        pool.add("a", &[pair(100.0, 1.0), pair(100.0, 1.0), pair(100.0, 1.0)]);
        let r = pool.report().unwrap();
        assert_eq!(r.per_category.keys().collect::<Vec<_>>(), ["a", "b"]);
        assert_eq!(r.mean.rra[0], 0.5);
        assert_eq!(r.mean.pairs, 4);
    }
}
