//! numpy's legacy global random generator, as the official `test.py` draws its frames:
//! `np.random.seed(0)` once, then `np.random.choice(n, k, replace=False)` per sequence,
//! consumed across categories and sequences.
//!
//! - MT19937 seeded like `mt19937_seed` (Knuth's 1812433253 recurrence), tempered 32-bit outputs;
//!   `next_uint64` is two 32-bit outputs, high word first.
//! - `choice(n, k, replace=False)` (legacy `RandomState`, no `p`) is `permutation(n)[:k]`, and
//!   `permutation` shuffles `arange(n)` with Fisher–Yates from the end: for `i = n−1 … 1`,
//!   `j = random_interval(i)`, swap `x[i]`, `x[j]`.
//! - `random_interval(max)` draws `next_uint32 & mask` (`next_uint64` above 2³²−1), `mask` the
//!   smallest all-ones number ≥ `max`, until the value is ≤ `max`.
//!
//! Checked against vectors produced by numpy (`fixtures/numpy/legacy_choice.json`,
//! `scripts/make_numpy_choice_vectors.py`).

use crate::error::{MetricsError, Result};

const N: usize = 624;
const M: usize = 397;
const MATRIX_A: u32 = 0x9908_b0df;
const UPPER_MASK: u32 = 0x8000_0000;
const LOWER_MASK: u32 = 0x7fff_ffff;

/// numpy's legacy `RandomState` (MT19937), enough of it for `choice` without replacement.
#[derive(Clone)]
pub struct LegacyRandomState {
    key: [u32; N],
    pos: usize,
}

impl std::fmt::Debug for LegacyRandomState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LegacyRandomState")
            .field("pos", &self.pos)
            .finish_non_exhaustive()
    }
}

impl LegacyRandomState {
    /// `np.random.seed(seed)` for an integer seed.
    pub fn new(seed: u32) -> Self {
        let mut key = [0u32; N];
        let mut s = seed;
        for (pos, k) in key.iter_mut().enumerate() {
            *k = s;
            s = 1_812_433_253u32
                .wrapping_mul(s ^ (s >> 30))
                .wrapping_add(pos as u32 + 1);
        }
        Self { key, pos: N }
    }

    fn generate(&mut self) {
        for i in 0..N {
            let y = (self.key[i] & UPPER_MASK) | (self.key[(i + 1) % N] & LOWER_MASK);
            let mag = if y & 1 == 1 { MATRIX_A } else { 0 };
            self.key[i] = self.key[(i + M) % N] ^ (y >> 1) ^ mag;
        }
        self.pos = 0;
    }

    /// The next tempered 32-bit output (`genrand_int32`).
    pub fn next_u32(&mut self) -> u32 {
        if self.pos == N {
            self.generate();
        }
        let mut y = self.key[self.pos];
        self.pos += 1;
        y ^= y >> 11;
        y ^= (y << 7) & 0x9d2c_5680;
        y ^= (y << 15) & 0xefc6_0000;
        y ^ (y >> 18)
    }

    /// numpy's `next_uint64` for MT19937: high word first.
    pub fn next_u64(&mut self) -> u64 {
        let hi = u64::from(self.next_u32());
        (hi << 32) | u64::from(self.next_u32())
    }

    /// numpy's `random_interval(max)`: uniform on `0..=max` by masked rejection.
    pub fn random_interval(&mut self, max: u64) -> u64 {
        if max == 0 {
            return 0;
        }
        let mut mask = max;
        for shift in [1, 2, 4, 8, 16, 32] {
            mask |= mask >> shift;
        }
        loop {
            let value = if max <= u64::from(u32::MAX) {
                u64::from(self.next_u32()) & mask
            } else {
                self.next_u64() & mask
            };
            if value <= max {
                return value;
            }
        }
    }

    /// `np.random.permutation(n)`.
    pub fn permutation(&mut self, n: usize) -> Vec<usize> {
        let mut x: Vec<usize> = (0..n).collect();
        for i in (1..n).rev() {
            let j = self.random_interval(i as u64) as usize;
            x.swap(i, j);
        }
        x
    }

    /// `np.random.choice(n, k, replace=False)`.
    ///
    /// # Errors
    /// `k > n` (numpy raises too).
    pub fn choice_without_replacement(&mut self, n: usize, k: usize) -> Result<Vec<usize>> {
        if k > n {
            return Err(MetricsError::TooFew {
                what: "frames to choose from",
                needed: k,
                got: n,
            });
        }
        let mut p = self.permutation(n);
        p.truncate(k);
        Ok(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_outputs_of_seed_5489_are_the_reference_ones() {
        // The MT19937 reference implementation's default seed.
        let mut r = LegacyRandomState::new(5489);
        assert_eq!(r.next_u32(), 3_499_211_612);
        assert_eq!(r.next_u32(), 581_869_302);
    }

    #[test]
    fn too_many_frames_is_an_error() {
        assert!(
            LegacyRandomState::new(0)
                .choice_without_replacement(3, 4)
                .is_err()
        );
        assert_eq!(
            LegacyRandomState::new(0)
                .choice_without_replacement(0, 0)
                .unwrap(),
            Vec::<usize>::new()
        );
    }
}
