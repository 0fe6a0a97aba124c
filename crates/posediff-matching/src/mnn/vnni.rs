//! Squared-L2 nearest neighbours of byte descriptors (SIFT) on AVX-512 VNNI, exact.
//!
//! OpenCV's SIFT values are whole numbers 0–255 (COLMAP stores them as bytes), so a dot
//! product of two descriptors is an integer, and `VPDPBUSD` (16 lanes, each four
//! unsigned-byte × signed-byte products added to an `i32`) computes 64 of its terms per
//! instruction, four times the F32 FMAs' 16. The signed operand is `b − 128`, whose
//! products are put back by `a·b = a·(b − 128) + 128 Σa`. Distances `‖a‖² + ‖b‖² − 2 a·b`
//! are then exact `i32`s; the F32 path computes the same integers (every partial sum of a
//! SIFT dot product is below 2²⁴), so both give the same matches.
//!
//! The distance block is never stored: an 8-row × 32-column tile of dot products stays in
//! sixteen registers, and the row bests (per lane: nearest, second, column) and column bests
//! (nearest row) are updated from it with the scalar scan's order of comparisons (strict
//! `<`, the first of equal distances wins), then the sixteen lanes of each row are reduced.
//!
//! `B` is packed once per pair: for each tile of 32 columns and each group of four bytes,
//! two 64-byte vectors whose lane `l` holds column `l`'s (and `16 + l`'s) four bytes.
// The only unsafe code of the crate: 64-byte loads from the packed buffers (bounds checked
// before the loops) inside functions compiled for AVX-512, called after runtime detection.
#![allow(unsafe_code)]

use std::arch::x86_64::{
    __m512i, _mm512_add_epi32, _mm512_cmplt_epi32_mask, _mm512_dpbusd_epi32, _mm512_loadu_si512,
    _mm512_mask_blend_epi32, _mm512_min_epi32, _mm512_set1_epi32, _mm512_setr_epi32,
    _mm512_setzero_si512, _mm512_slli_epi32, _mm512_storeu_si512, _mm512_sub_epi32,
};
use std::sync::OnceLock;

/// Rows of `A` per tile.
const ROWS: usize = 8;
/// Columns of `B` per tile (two vectors of 16 lanes).
const COLS: usize = 32;
/// Added to the distances of padding rows and columns: twice it still fits an `i32`.
const FAR: i32 = 1 << 29;
/// Every real distance is below this (at most `‖a‖² + ‖b‖² ≤ 2·dim·255² < 2²⁸` for
/// `dim ≤ MAX_DIM`), every distance to a padding row or column above it (at least
/// `FAR − 256·dim·255 > 2²⁸`).
const REAL_BELOW: i32 = FAR / 2;
/// The widest descriptors the kernel takes (wider ones go to the F32 path).
const MAX_DIM: usize = 2048;

/// Whether this CPU runs the kernel (AVX-512 F, BW and VNNI) and `POSEDIFF_NO_VNNI` is
/// unset. Asked once per process.
pub(super) fn available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    *AVAILABLE.get_or_init(|| {
        std::env::var_os("POSEDIFF_NO_VNNI").is_none()
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vnni")
    })
}

/// Per row of `a`: `(column, nearest, second)` as squared distances (`None`: no second
/// column).
pub(super) type RowBests = Vec<(u32, i32, Option<i32>)>;

/// The row bests and each column's nearest row of `a` (`n × dim` bytes) against `b`
/// (`m × dim`); `None` when the CPU lacks the instructions, `dim` is 0 or above `MAX_DIM`, or
/// either side is empty.
pub(super) fn best(a: &[u8], b: &[u8], dim: usize) -> Option<(RowBests, Vec<u32>)> {
    if !available() || dim == 0 || dim > MAX_DIM || a.len() < dim || b.len() < dim {
        return None;
    }
    // SAFETY: the features `best_avx512` is compiled for were detected by `available`.
    Some(unsafe { best_avx512(a, b, dim) })
}

/// Descriptors padded to a multiple of four bytes and of `ROWS` rows, with `‖a‖² − 256 Σa`
/// per row (`FAR` for padding rows).
fn pack_a(a: &[u8], dim: usize) -> (Vec<u8>, Vec<i32>, usize) {
    let n = a.len() / dim;
    let width = dim.next_multiple_of(4);
    let rows = n.next_multiple_of(ROWS);
    let mut packed = vec![0u8; rows * width];
    let mut bias = vec![FAR; rows];
    for (i, row) in a.chunks_exact(dim).enumerate() {
        packed[i * width..i * width + dim].copy_from_slice(row);
        let (norm, sum) = row.iter().fold((0i32, 0i32), |(n, s), &x| {
            (n + i32::from(x) * i32::from(x), s + i32::from(x))
        });
        bias[i] = norm - 256 * sum;
    }
    (packed, bias, width)
}

/// `B − 128` as signed bytes in the tile layout, and `‖b‖²` per column (`FAR` for padding).
fn pack_b(b: &[u8], dim: usize, width: usize) -> (Vec<u8>, Vec<i32>) {
    let m = b.len() / dim;
    let tiles = m.div_ceil(COLS);
    let groups = width / 4;
    // Padding bytes are 0, i.e. `b = 128`; a padding column's `FAR` puts its distances above
    // `REAL_BELOW`, so it is never a real row's nearest and never a second.
    let mut packed = vec![0u8; tiles * groups * COLS * 4];
    let mut norms = vec![FAR; tiles * COLS];
    let mut word = vec![0u8; width];
    for (j, col) in b.chunks_exact(dim).enumerate() {
        let (t, c) = (j / COLS, j % COLS);
        word[..dim].copy_from_slice(col);
        for (g, four) in word.chunks_exact(4).enumerate() {
            let at = ((t * groups + g) * COLS + c) * 4;
            let shifted = u32::from_le_bytes([four[0], four[1], four[2], four[3]]) ^ 0x8080_8080;
            packed[at..at + 4].copy_from_slice(&shifted.to_le_bytes());
        }
        norms[j] = col.iter().map(|&x| i32::from(x) * i32::from(x)).sum();
    }
    (packed, norms)
}

#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
fn best_avx512(a: &[u8], b: &[u8], dim: usize) -> (RowBests, Vec<u32>) {
    let (n, m) = (a.len() / dim, b.len() / dim);
    let (pa, bias, width) = pack_a(a, dim);
    let (pb, norms) = pack_b(b, dim, width);
    let groups = width / 4;
    let tiles = m.div_ceil(COLS);
    assert!(pb.len() >= tiles * groups * COLS * 4 && norms.len() >= tiles * COLS);
    let mut col_d = vec![i32::MAX; tiles * COLS];
    let mut col_i = vec![u32::MAX; tiles * COLS];
    let mut rows = Vec::with_capacity(n);
    let iota = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let (mut d1, mut d2, mut jb) = ([iota; ROWS], [iota; ROWS], [iota; ROWS]);
    let mut words: Vec<[i32; ROWS]> = vec![[0; ROWS]; groups];
    for i0 in (0..n).step_by(ROWS) {
        // The four bytes of each group of the block's rows, as broadcastable i32s.
        for (g, w) in words.iter_mut().enumerate() {
            *w = std::array::from_fn(|r| {
                let at = (i0 + r) * width + 4 * g;
                i32::from_le_bytes([pa[at], pa[at + 1], pa[at + 2], pa[at + 3]])
            });
        }
        for r in 0..ROWS {
            d1[r] = _mm512_set1_epi32(i32::MAX);
            d2[r] = _mm512_set1_epi32(i32::MAX);
            jb[r] = _mm512_set1_epi32(-1);
        }
        for t in 0..tiles {
            let tile = &pb[t * groups * COLS * 4..(t + 1) * groups * COLS * 4];
            let acc = dots(&words, tile);
            for (c, half) in [0usize, 1].into_iter().zip([0i32, 16]) {
                let j0 = t * COLS + 16 * c;
                // SAFETY: `j0 + 16 ≤ tiles·COLS`, the length of `norms`, `col_d` and `col_i`.
                let (norm, mut cd, mut ci) = unsafe {
                    (
                        _mm512_loadu_si512(norms.as_ptr().add(j0).cast()),
                        _mm512_loadu_si512(col_d.as_ptr().add(j0).cast()),
                        _mm512_loadu_si512(col_i.as_ptr().add(j0).cast()),
                    )
                };
                let jv = _mm512_add_epi32(iota, _mm512_set1_epi32(t as i32 * COLS as i32 + half));
                for r in 0..ROWS {
                    // ‖a‖² + ‖b‖² − 2(acc + 128 Σa) = (‖a‖² − 256 Σa) + ‖b‖² − 2 acc.
                    let x = _mm512_sub_epi32(
                        _mm512_add_epi32(_mm512_set1_epi32(bias[i0 + r]), norm),
                        _mm512_slli_epi32::<1>(acc[r][c]),
                    );
                    let closer = _mm512_cmplt_epi32_mask(x, d1[r]);
                    d2[r] = _mm512_mask_blend_epi32(closer, _mm512_min_epi32(d2[r], x), d1[r]);
                    jb[r] = _mm512_mask_blend_epi32(closer, jb[r], jv);
                    d1[r] = _mm512_mask_blend_epi32(closer, d1[r], x);
                    let nearer = _mm512_cmplt_epi32_mask(x, cd);
                    cd = _mm512_mask_blend_epi32(nearer, cd, x);
                    ci = _mm512_mask_blend_epi32(nearer, ci, _mm512_set1_epi32((i0 + r) as i32));
                }
                // SAFETY: as for the loads above.
                unsafe {
                    _mm512_storeu_si512(col_d.as_mut_ptr().add(j0).cast(), cd);
                    _mm512_storeu_si512(col_i.as_mut_ptr().add(j0).cast(), ci);
                }
            }
        }
        for r in 0..ROWS.min(n - i0) {
            rows.push(reduce(lanes(d1[r]), lanes(d2[r]), lanes(jb[r])));
        }
    }
    col_i.truncate(m);
    (rows, col_i)
}

/// The dot products (less `128 Σa`) of a block's rows with one tile's 32 columns: `words[g]`
/// holds the rows' bytes `4g..4g + 4`, `tile` the columns' in the packed layout. Kept out of
/// line so that its sixteen accumulators stay in registers (inlined into the scan, whose row
/// bests need 24 more, they were spilled to the stack on every step).
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline(never)]
fn dots(words: &[[i32; ROWS]], tile: &[u8]) -> [[__m512i; 2]; ROWS] {
    let mut acc = [[_mm512_setzero_si512(); 2]; ROWS];
    for (w, b) in words.iter().zip(tile.chunks_exact(COLS * 4)) {
        // SAFETY: `b` is `COLS·4 = 128` bytes: two 64-byte loads.
        let (b0, b1) = unsafe {
            (
                _mm512_loadu_si512(b.as_ptr().cast()),
                _mm512_loadu_si512(b.as_ptr().add(64).cast()),
            )
        };
        for r in 0..ROWS {
            let x = _mm512_set1_epi32(w[r]);
            acc[r][0] = _mm512_dpbusd_epi32(acc[r][0], x, b0);
            acc[r][1] = _mm512_dpbusd_epi32(acc[r][1], x, b1);
        }
    }
    acc
}

/// The sixteen `i32` lanes of `v`.
#[target_feature(enable = "avx512f")]
fn lanes(v: __m512i) -> [i32; 16] {
    let mut out = [0i32; 16];
    // SAFETY: `out` is 64 bytes.
    unsafe { _mm512_storeu_si512(out.as_mut_ptr().cast(), v) };
    out
}

/// One row's bests from its lanes (each lane saw its columns in increasing order): the
/// nearest of all lanes, the first column among equals; the second is the nearest lane's
/// second or another lane's nearest.
fn reduce(d1: [i32; 16], d2: [i32; 16], jb: [i32; 16]) -> (u32, i32, Option<i32>) {
    let mut best = 0;
    for l in 1..16 {
        if (d1[l], jb[l] as u32) < (d1[best], jb[best] as u32) {
            best = l;
        }
    }
    let second = (0..16)
        .filter(|&l| l != best)
        .map(|l| d1[l])
        .fold(d2[best], i32::min);
    (
        jb[best] as u32,
        d1[best],
        (second < REAL_BELOW).then_some(second),
    )
}
