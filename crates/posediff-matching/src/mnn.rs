//! Exact mutual nearest-neighbour matching with an optional Lowe ratio test.
//!
//! Float descriptors (SIFT) use squared L2 distances computed as blocked matrix products,
//! `‖a‖² + ‖b‖² − 2 a·b` (nalgebra → matrixmultiply's SIMD sgemm), a block of query rows at a
//! time so memory stays small; binary descriptors (ORB) use Hamming distances by XOR + popcount
//! on 64-bit words. A pair `(i, j)` is kept when `j` is `i`'s nearest neighbour and `i` is `j`'s;
//! with a ratio `ρ`, also when `d₁ < ρ·d₂` (distances, not squared).

use nalgebra::DMatrix;

use crate::features::{Descriptors, byte_floats};

#[cfg(target_arch = "x86_64")]
mod vnni;

/// Query rows per block of the distance computation.
const BLOCK_ROWS: usize = 256;

/// Nearest and second-nearest of one row.
#[derive(Debug, Clone, Copy)]
struct RowBest {
    j: usize,
    d1: f32,
    d2: f32,
}

impl RowBest {
    const EMPTY: Self = Self {
        j: usize::MAX,
        d1: f32::INFINITY,
        d2: f32::INFINITY,
    };

    #[inline]
    fn offer(&mut self, j: usize, d: f32) {
        if d < self.d1 {
            self.d2 = self.d1;
            self.d1 = d;
            self.j = j;
        } else if d < self.d2 {
            self.d2 = d;
        }
    }
}

/// Index pairs `(i in a, j in b)` of mutual nearest neighbours. `ratio` applies Lowe's test.
/// Descriptors of different kinds or widths match nothing.
pub fn mutual_nearest_neighbours(
    a: &Descriptors,
    b: &Descriptors,
    ratio: Option<f32>,
) -> Vec<(usize, usize)> {
    let (rows, cols) = match (a, b) {
        (
            Descriptors::Float { data: da, dim },
            Descriptors::Float {
                data: db,
                dim: dim_b,
            },
        ) if dim == dim_b => l2_best_f32(da, db, *dim),
        (
            Descriptors::Bytes { data: da, dim },
            Descriptors::Bytes {
                data: db,
                dim: dim_b,
            },
        ) if dim == dim_b => l2_best_u8(da, db, *dim),
        (Descriptors::Float { .. }, Descriptors::Bytes { .. })
        | (Descriptors::Bytes { .. }, Descriptors::Float { .. }) => {
            match (a.floats(), b.floats()) {
                (Some((da, dim)), Some((db, dim_b))) if dim == dim_b => l2_best_f32(&da, &db, dim),
                _ => return Vec::new(),
            }
        }
        (
            Descriptors::Binary { data: da, words },
            Descriptors::Binary {
                data: db,
                words: wb,
            },
        ) if words == wb => hamming_best(da, db, *words),
        _ => return Vec::new(),
    };
    // With squared L2, the ratio test compares squared distances with ρ².
    let squared = matches!(a, Descriptors::Float { .. } | Descriptors::Bytes { .. });
    rows.iter()
        .enumerate()
        .filter(|(i, r)| r.j != usize::MAX && cols[r.j] == *i)
        .filter(|(_, r)| match ratio {
            None => true,
            Some(rho) => {
                let rho = if squared { rho * rho } else { rho };
                r.d1 < rho * r.d2
            }
        })
        .map(|(i, r)| (i, r.j))
        .collect()
}

/// [`l2_best_f32`] of byte descriptors (SIFT): the exact integer kernel where the CPU has it, the
/// F32 products of the same values otherwise (the same result: `the_byte_kernel_is_the_f32_path_exactly`).
fn l2_best_u8(a: &[u8], b: &[u8], dim: usize) -> (Vec<RowBest>, Vec<usize>) {
    #[cfg(target_arch = "x86_64")]
    if let Some(found) = l2_best_vnni(a, b, dim) {
        return found;
    }
    l2_best_f32(&byte_floats(a), &byte_floats(b), dim)
}

/// [`l2_best_f32`] of byte descriptors by the exact integer kernel ([`vnni`]) when the CPU has
/// AVX-512 VNNI; `None` otherwise.
#[cfg(target_arch = "x86_64")]
fn l2_best_vnni(a: &[u8], b: &[u8], dim: usize) -> Option<(Vec<RowBest>, Vec<usize>)> {
    let (rows, cols) = vnni::best(a, b, dim)?;
    let rows = rows
        .into_iter()
        .map(|(j, d1, d2)| RowBest {
            j: j as usize,
            d1: d1 as f32,
            d2: d2.map_or(f32::INFINITY, |d| d as f32),
        })
        .collect();
    Some((rows, cols.into_iter().map(|c| c as usize).collect()))
}

/// Row bests and column argmins of squared L2 distances, by F32 matrix products (any
/// descriptor values: float descriptors are never bytes here, `Descriptors::from_floats`
/// decided that once per image).
///
/// The product of a block of query rows with Bᵀ is column-major (`rb × m`), so the scan walks
/// it column by column: each column's `rb` distances are contiguous, the block's row bests are
/// kept as arrays (nearest, second, index) updated by selects, and both loops vectorise. The
/// order of the comparisons is the plain row-by-row scan's (strict `<`: the first of equal
/// distances wins, in rows and in columns), so the result is the same.
fn l2_best_f32(a: &[f32], b: &[f32], dim: usize) -> (Vec<RowBest>, Vec<usize>) {
    let (n, m) = (a.len() / dim, b.len() / dim);
    let mut rows = vec![RowBest::EMPTY; n];
    let mut col_best = vec![(f32::INFINITY, usize::MAX); m];
    if n == 0 || m == 0 {
        return (rows, vec![usize::MAX; m]);
    }
    let norm = |v: &[f32]| v.iter().map(|x| x * x).sum::<f32>();
    let b_norms: Vec<f32> = b.chunks(dim).map(norm).collect();
    // Bᵀ (dim × m, column-major) is B's row-major storage as it is.
    let bt = DMatrix::from_column_slice(dim, m, b);
    let mut dist = vec![0.0f32; BLOCK_ROWS];
    let (mut d1, mut d2, mut jbest) = (
        vec![0.0f32; BLOCK_ROWS],
        vec![0.0f32; BLOCK_ROWS],
        vec![0u32; BLOCK_ROWS],
    );
    for start in (0..n).step_by(BLOCK_ROWS) {
        let rb = BLOCK_ROWS.min(n - start);
        let block = &a[start * dim..(start + rb) * dim];
        let d = DMatrix::from_row_slice(rb, dim, block) * &bt;
        let a_norms: Vec<f32> = block.chunks(dim).map(norm).collect();
        let (dist, d1, d2, jbest) = (
            &mut dist[..rb],
            &mut d1[..rb],
            &mut d2[..rb],
            &mut jbest[..rb],
        );
        d1.fill(f32::INFINITY);
        d2.fill(f32::INFINITY);
        jbest.fill(u32::MAX);
        for (j, ((column, &bn), cb)) in d
            .as_slice()
            .chunks_exact(rb)
            .zip(&b_norms)
            .zip(col_best.iter_mut())
            .enumerate()
        {
            for ((x, &an), &dot) in dist.iter_mut().zip(&a_norms).zip(column) {
                *x = (an + bn - 2.0 * dot).max(0.0);
            }
            // Row bests: the nearest so far moves to second when beaten.
            let ju = j as u32;
            for (((&x, n1), n2), jb) in dist
                .iter()
                .zip(d1.iter_mut())
                .zip(d2.iter_mut())
                .zip(jbest.iter_mut())
            {
                let closer = x < *n1;
                *n2 = if closer { *n1 } else { n2.min(x) };
                *jb = if closer { ju } else { *jb };
                *n1 = if closer { x } else { *n1 };
            }
            // The column's nearest row of this block (the first of equals), kept when it beats
            // the earlier blocks'.
            let low = dist.iter().copied().fold(f32::INFINITY, f32::min);
            if low < cb.0
                && let Some(r) = dist.iter().position(|&x| x == low)
            {
                *cb = (low, start + r);
            }
        }
        for (r, best) in rows[start..start + rb].iter_mut().enumerate() {
            if jbest[r] != u32::MAX {
                *best = RowBest {
                    j: jbest[r] as usize,
                    d1: d1[r],
                    d2: d2[r],
                };
            }
        }
    }
    (rows, col_best.into_iter().map(|c| c.1).collect())
}

/// Row bests and column argmins of Hamming distances.
fn hamming_best(a: &[u64], b: &[u64], words: usize) -> (Vec<RowBest>, Vec<usize>) {
    let (n, m) = (a.len() / words, b.len() / words);
    let mut rows = vec![RowBest::EMPTY; n];
    let mut col_best = vec![(u32::MAX, usize::MAX); m];
    for (i, da) in a.chunks(words).enumerate() {
        let best = &mut rows[i];
        for (j, (db, cb)) in b.chunks(words).zip(col_best.iter_mut()).enumerate() {
            let dist: u32 = da.iter().zip(db).map(|(x, y)| (x ^ y).count_ones()).sum();
            best.offer(j, dist as f32);
            if dist < cb.0 {
                *cb = (dist, i);
            }
        }
    }
    (rows, col_best.into_iter().map(|c| c.1).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute-force reference with plain loops.
    fn brute(a: &[f32], b: &[f32], dim: usize) -> Vec<(usize, usize)> {
        let d = |x: &[f32], y: &[f32]| x.iter().zip(y).map(|(p, q)| (p - q) * (p - q)).sum::<f32>();
        let (n, m) = (a.len() / dim, b.len() / dim);
        let argmin = |f: &dyn Fn(usize) -> f32, k: usize| {
            (0..k)
                .min_by(|x, y| f(*x).total_cmp(&f(*y)))
                .unwrap_or(usize::MAX)
        };
        (0..n)
            .filter_map(|i| {
                let j = argmin(
                    &|j| d(&a[i * dim..(i + 1) * dim], &b[j * dim..(j + 1) * dim]),
                    m,
                );
                let back = argmin(
                    &|k| d(&a[k * dim..(k + 1) * dim], &b[j * dim..(j + 1) * dim]),
                    n,
                );
                (back == i).then_some((i, j))
            })
            .collect()
    }

    fn pseudo_random(n: usize, seed: u32) -> Vec<f32> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                (s >> 8) as f32 / (1u32 << 24) as f32
            })
            .collect()
    }

    /// Row bests and column argmins by plain loops, strict `<` (the first of equals wins).
    fn plain_best(a: &[f32], b: &[f32], dim: usize) -> (Vec<(usize, f32, f32)>, Vec<usize>) {
        let norm = |v: &[f32]| v.iter().map(|x| x * x).sum::<f32>();
        let (n, m) = (a.len() / dim, b.len() / dim);
        let mut cols = vec![(f32::INFINITY, usize::MAX); m];
        let rows = (0..n)
            .map(|i| {
                let ai = &a[i * dim..(i + 1) * dim];
                let mut best = RowBest::EMPTY;
                for (j, col) in cols.iter_mut().enumerate() {
                    let bj = &b[j * dim..(j + 1) * dim];
                    let dot: f32 = ai.iter().zip(bj).map(|(x, y)| x * y).sum();
                    let d = (norm(ai) + norm(bj) - 2.0 * dot).max(0.0);
                    best.offer(j, d);
                    if d < col.0 {
                        *col = (d, i);
                    }
                }
                (best.j, best.d1, best.d2)
            })
            .collect();
        (rows, cols.into_iter().map(|c| c.1).collect())
    }

    #[test]
    fn equal_distances_go_to_the_first_row_and_column_across_blocks() {
        // Small integers: every dot product is exact, so equal descriptors give equal
        // distances whatever the summation order, and ties are real.
        let dim = 8;
        // Code k: its base-3 digits, distinct for k < 3⁸.
        let code = |k: usize| {
            (0..dim as u32)
                .map(|c| ((k / 3usize.pow(c)) % 3) as f32)
                .collect::<Vec<_>>()
        };
        // 700 query rows (three blocks) repeating 40 codes; 90 columns repeating 30 codes.
        let a: Vec<f32> = (0..700).flat_map(|i| code(i % 40)).collect();
        let b: Vec<f32> = (0..90).flat_map(|j| code(j % 30)).collect();
        let (rows, cols) = l2_best_f32(&a, &b, dim);
        let (want_rows, want_cols) = plain_best(&a, &b, dim);
        assert_eq!(cols, want_cols);
        for (r, w) in rows.iter().zip(&want_rows) {
            assert_eq!((r.j, r.d1, r.d2), *w);
        }
        // Code k < 30 is nearest to column k (its first copy) at distance 0.
        assert_eq!((rows[5].j, rows[5].d1), (5, 0.0));
        assert_eq!(
            cols[35], 5,
            "column 35 (code 5) goes to the first row with code 5"
        );
    }

    #[test]
    fn blocked_l2_matches_brute_force() {
        let dim = 16;
        let a = pseudo_random(300 * dim, 1);
        let mut b = pseudo_random(280 * dim, 2);
        // Plant exact correspondences: b[k] = a[3k] + tiny noise.
        for k in 0..90 {
            for c in 0..dim {
                b[k * dim + c] = a[3 * k * dim + c] + 1e-3 * (c as f32);
            }
        }
        let fa = Descriptors::Float {
            data: a.clone(),
            dim,
        };
        let fb = Descriptors::Float {
            data: b.clone(),
            dim,
        };
        let ours = mutual_nearest_neighbours(&fa, &fb, None);
        assert_eq!(ours, brute(&a, &b, dim));
        for k in 0..90 {
            assert!(ours.contains(&(3 * k, k)), "planted pair {k}");
        }
        // A strict ratio keeps only the planted, unambiguous pairs.
        let strict = mutual_nearest_neighbours(&fa, &fb, Some(0.5));
        assert!(strict.iter().all(|&(i, j)| i == 3 * j));
        assert!(strict.len() >= 80);
    }

    #[test]
    fn hamming_and_empty_inputs() {
        let a = Descriptors::Binary {
            data: vec![0b1011, 0, u64::MAX, 7],
            words: 2,
        };
        let b = Descriptors::Binary {
            data: vec![u64::MAX, 7, 0b1001, 0],
            words: 2,
        };
        assert_eq!(
            mutual_nearest_neighbours(&a, &b, None),
            vec![(0, 1), (1, 0)]
        );
        let empty = Descriptors::Float {
            data: vec![],
            dim: 128,
        };
        let one = Descriptors::Float {
            data: vec![0.0; 128],
            dim: 128,
        };
        assert!(mutual_nearest_neighbours(&empty, &one, None).is_empty());
        assert!(mutual_nearest_neighbours(&one, &empty, None).is_empty());
        assert!(mutual_nearest_neighbours(&one, &a, None).is_empty());
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod bytes {
    use super::*;
    use crate::features::whole_bytes;

    /// Byte-valued descriptors (SIFT-like: sparse, whole numbers 0–255), with repeats so that
    /// equal distances (ties) occur in rows and in columns.
    fn byte_descriptors(n: usize, dim: usize, seed: u64, repeat: usize) -> Vec<f32> {
        let mut s = seed;
        let mut next = || {
            s = s
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (s >> 33) as u32
        };
        let distinct: Vec<Vec<f32>> = (0..n.div_ceil(repeat))
            .map(|_| {
                (0..dim)
                    .map(|_| {
                        let v = next();
                        if v % 3 == 0 { 0.0 } else { (v % 256) as f32 }
                    })
                    .collect()
            })
            .collect();
        (0..n)
            .flat_map(|i| distinct[i % distinct.len()].clone())
            .collect()
    }

    /// The VNNI kernel gives exactly the F32 path's row bests (column, nearest, second) and
    /// column bests, ties included, for sizes that are not multiples of its tiles and widths
    /// that are not multiples of four. Reported as skipped (ignored) on hosts without AVX-512
    /// VNNI, where the kernel cannot run.
    #[test]
    #[cfg_attr(
        not(vnni_host),
        ignore = "needs a CPU with AVX-512 VNNI (e.g. Intel Ice Lake or later, AMD Zen 4)"
    )]
    fn the_byte_kernel_is_the_f32_path_exactly() {
        assert!(
            vnni::available(),
            "the CPU has AVX-512 VNNI but it was not detected"
        );
        for (n, m, dim, repeat) in [
            (1, 1, 128, 1),
            (9, 33, 128, 1),
            (300, 517, 128, 7),
            (517, 300, 128, 1),
            (64, 70, 6, 5),
            (20, 3, 130, 2),
        ] {
            let a = byte_descriptors(n, dim, 11 + n as u64, repeat);
            let mut b = byte_descriptors(m, dim, 5 + m as u64, repeat);
            // Some columns are copies of rows: distance 0, and ties between the copies.
            for k in 0..m.min(n) / 4 {
                b[k * dim..(k + 1) * dim].copy_from_slice(&a[2 * k * dim..(2 * k + 1) * dim]);
            }
            let (Some(ab), Some(bb)) = (whole_bytes(&a), whole_bytes(&b)) else {
                panic!("{n}×{m}×{dim}: byte values not taken as bytes");
            };
            let Some((rows, cols)) = l2_best_vnni(&ab, &bb, dim) else {
                panic!("the byte path refused {n}×{m}×{dim}");
            };
            let (want_rows, want_cols) = l2_best_f32(&a, &b, dim);
            assert_eq!(cols, want_cols, "{n}×{m}×{dim}: column bests");
            for (i, (r, w)) in rows.iter().zip(&want_rows).enumerate() {
                assert_eq!(
                    (r.j, r.d1, r.d2),
                    (w.j, w.d1, w.d2),
                    "{n}×{m}×{dim}: row {i}"
                );
            }
            assert_eq!(rows.len(), n);
        }
        // Values that are not bytes go to the F32 path.
        assert!(whole_bytes(&[0.5; 128]).is_none());
        assert!(whole_bytes(&[256.0; 128]).is_none());
        assert!(whole_bytes(&[-1.0; 128]).is_none());
        // Too wide for the kernel's i32 distances to stay below its padding's.
        assert!(l2_best_vnni(&[1; 4096], &[1; 4096], 4096).is_none());
    }
}

#[cfg(test)]
mod odd_sizes {
    use super::*;

    /// SIFT's whole-number floats are kept as bytes, anything else as floats, and bytes match
    /// exactly as the same values in floats do (on every host: the integer kernel where the
    /// CPU has it, the F32 products otherwise), also against floats, with the ratio test.
    #[test]
    fn byte_descriptors_match_as_their_floats() {
        let whole = |n: usize, seed: u64| -> Vec<f32> {
            let mut s = seed;
            (0..n * 128)
                .map(|_| {
                    s = s
                        .wrapping_mul(6_364_136_223_846_793_005)
                        .wrapping_add(1_442_695_040_888_963_407);
                    let v = (s >> 33) as u32;
                    if v.is_multiple_of(3) {
                        0.0
                    } else {
                        (v % 256) as f32
                    }
                })
                .collect()
        };
        let (a, mut b) = (whole(300, 1), whole(517, 5));
        // A hundred columns are rows of `a` moved a little: mutual nearest neighbours that
        // pass the ratio test.
        for k in 0..100 {
            let row = &a[2 * k * 128..(2 * k + 1) * 128];
            for (d, (bv, av)) in b[k * 128..(k + 1) * 128].iter_mut().zip(row).enumerate() {
                *bv = if d % 17 == 0 {
                    (av + 1.0).min(255.0)
                } else {
                    *av
                };
            }
        }
        let (fa, fb) = (
            Descriptors::Float {
                data: a.clone(),
                dim: 128,
            },
            Descriptors::Float {
                data: b.clone(),
                dim: 128,
            },
        );
        let (ba, bb) = (
            Descriptors::from_floats(a, 128),
            Descriptors::from_floats(b, 128),
        );
        assert!(matches!(ba, Descriptors::Bytes { dim: 128, .. }));
        assert_eq!(ba.len(), 300);
        for ratio in [None, Some(0.9)] {
            let want = mutual_nearest_neighbours(&fa, &fb, ratio);
            assert!(!want.is_empty());
            assert_eq!(mutual_nearest_neighbours(&ba, &bb, ratio), want);
            assert_eq!(mutual_nearest_neighbours(&ba, &fb, ratio), want);
            assert_eq!(mutual_nearest_neighbours(&fa, &bb, ratio), want);
        }
        for not_bytes in [0.5, 256.0, -1.0, f32::NAN] {
            let mut v = vec![3.0; 128];
            v[77] = not_bytes;
            assert!(
                matches!(Descriptors::from_floats(v, 128), Descriptors::Float { .. }),
                "{not_bytes} kept as a byte"
            );
        }
        let (Some((floats, 128)), None) = (
            ba.floats(),
            Descriptors::Binary {
                data: vec![1],
                words: 1,
            }
            .floats(),
        ) else {
            panic!("floats of bytes and of binary descriptors");
        };
        assert_eq!(
            &floats[..],
            &fa.floats().map(|(f, _)| f.into_owned()).unwrap_or_default()[..]
        );
    }

    #[test]
    fn partial_last_block() {
        for (n, m) in [(516usize, 303usize), (257, 5), (4, 300)] {
            let a: Vec<f32> = (0..n * 128).map(|k| ((k * 7919) % 1000) as f32).collect();
            let b: Vec<f32> = (0..m * 128).map(|k| ((k * 104_729) % 997) as f32).collect();
            let fa = Descriptors::Float { data: a, dim: 128 };
            let fb = Descriptors::Float { data: b, dim: 128 };
            let _ = mutual_nearest_neighbours(&fa, &fb, None);
        }
    }
}
