//! F32 matrix products on Intel AMX tiles (Sapphire Rapids and later Xeons).
//!
//! AMX multiplies tiles of BF16 values into F32 accumulators: one `TDPBF16PS` is
//! 16 × 16 × 32 multiply-adds, and a core runs about 3.6 TFLOP/s of them, against about 0.2
//! TFLOP/s of F32 products on its two AVX-512 FMA ports. BF16 keeps 8 of F32's 24 significand
//! bits, so each F32 operand is split into BF16 terms, `x = x₀ + x₁ (+ x₂) + r`, each term the
//! rounding of what the previous ones left, and `c += a b` becomes the sum of the term products
//! up to the precision asked ([`Split`]):
//! - [`Split::Two`]: `a₁b₀ + a₀b₁ + a₀b₀`, three tile products. The dropped `a₁b₁` and the
//!   remainders are each below `2⁻¹⁸ |a b|`: about `2⁻¹⁶` relative to `Σ|aᵢ bᵢ|`, the accuracy of
//!   a 16-bit significand.
//! - [`Split::Three`]: six tile products (all `aᵢbⱼ` with `i + j ≤ 2`), about `2⁻²⁴`: F32's own.
//!
//! Term products are exact in F32 (8 × 8 bits) and accumulate in F32: [`matmul_emulated`] adds
//! the smallest term products first; the two-term tile kernel, per step of `k`, adds `a₁b₀`,
//! `a₀b₀`, then `a₀b₁` (so that each loaded tile serves two products). Both orders have the
//! accuracy above.
//!
//! Operands are packed once ([`PackedA`], [`PackedB`]) and can serve many products: the rows of
//! `A` row-major in blocks of 32, `B` in the pairwise-interleaved ("VNNI") layout the tile unit
//! reads, both zero-padded to multiples of 32, each packed row at an odd number of 64-byte
//! lines (so that a tile load's 16 rows do not share one L1 set). [`matmul`] runs 32 × 32 blocks of `C` in four
//! accumulator tiles.
//!
//! # Pitfalls
//! - **Permission.** Linux hands out the 8 KiB tile state only on request, once per process
//!   (`arch_prctl(ARCH_REQ_XCOMP_PERM)`); [`available`] asks and says whether it was granted.
//!   Without it a tile instruction is a fatal signal, so [`matmul`] refuses to run unless
//!   [`available`] is true. `POSEDIFF_NO_AMX=1` turns AMX off for the process.
//! - **Subnormals.** The tile unit treats subnormal BF16 inputs as zero and flushes subnormal
//!   results: the smallest terms of values below about `1e-33` are lost. Products of values of
//!   ordinary size are unaffected.
//! - **Range.** Inputs must be finite and below about `3.3e38` in magnitude (the BF16 rounding of
//!   the largest F32 values overflows).
//! - **Tile state is per thread.** Each [`matmul`] call configures the tiles and releases them;
//!   callers parallelise by giving each thread its own block rows.
#![deny(missing_docs)]
// The one crate of the workspace with unsafe code, because AMX is reached only through inline
// assembly (its intrinsics are not stable Rust), tile loads and stores take raw addresses, and
// the tile state needs the kernel's permission (a raw system call). Every unsafe block states
// the bounds it relies on; they are checked before any assembly runs.
#![allow(unsafe_code)]

use std::ops::Range;
use std::sync::OnceLock;

/// Rows and columns of one block of `C` (four 16 × 16 accumulator tiles), and the padding of
/// every packed dimension.
pub const BLOCK: usize = 32;

/// How many BF16 terms each F32 operand is split into.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    /// Two terms, three tile products: about 2⁻¹⁶ relative.
    Two,
    /// Three terms, six tile products: about 2⁻²⁴ relative (F32's rounding).
    Three,
}

impl Split {
    /// The number of BF16 terms of an operand.
    pub fn terms(self) -> usize {
        match self {
            Split::Two => 2,
            Split::Three => 3,
        }
    }

    /// The term products `(term of A, term of B)`, smallest first.
    fn products(self) -> &'static [(usize, usize)] {
        match self {
            Split::Two => &[(1, 0), (0, 1), (0, 0)],
            Split::Three => &[(2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0)],
        }
    }
}

/// What [`matmul`] refuses.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AmxError {
    /// The CPU has no AMX-BF16, the kernel refused the tile state, or `POSEDIFF_NO_AMX` is set.
    Unavailable,
    /// Operands or output that do not fit together.
    Shape(String),
}

impl std::fmt::Display for AmxError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            AmxError::Unavailable => write!(
                f,
                "AMX tiles are not usable here (no AMX-BF16, no permission from the kernel, or POSEDIFF_NO_AMX set)"
            ),
            AmxError::Shape(s) => write!(f, "AMX product: {s}"),
        }
    }
}

impl std::error::Error for AmxError {}

/// Whether this process can run AMX-BF16 tile products: the CPU has AMX-TILE and AMX-BF16,
/// the kernel granted the tile state, and `POSEDIFF_NO_AMX` is not set. Asked once per process.
pub fn available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    *AVAILABLE.get_or_init(|| std::env::var_os("POSEDIFF_NO_AMX").is_none() && detect())
}

#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
fn detect() -> bool {
    // CPUID leaf 7: EDX bit 22 AMX-BF16, bit 24 AMX-TILE.
    let max_leaf = std::arch::x86_64::__cpuid(0).eax;
    if max_leaf < 7 {
        return false;
    }
    let edx = std::arch::x86_64::__cpuid_count(7, 0).edx;
    if edx & (1 << 22) == 0 || edx & (1 << 24) == 0 {
        return false;
    }
    const ARCH_REQ_XCOMP_PERM: libc::c_ulong = 0x1023;
    const XFEATURE_XTILEDATA: libc::c_ulong = 18;
    // SAFETY: arch_prctl with ARCH_REQ_XCOMP_PERM takes two integers and touches no memory of
    // ours; it fails (non-zero) where the kernel does not support or enable the tile state.
    let granted = unsafe {
        libc::syscall(
            libc::SYS_arch_prctl,
            ARCH_REQ_XCOMP_PERM,
            XFEATURE_XTILEDATA,
        )
    };
    granted == 0
}

#[cfg(not(all(target_arch = "x86_64", target_os = "linux")))]
fn detect() -> bool {
    false
}

/// Round to the nearest BF16, ties to even (finite inputs).
#[inline(always)]
fn bf16(x: f32) -> u16 {
    let b = x.to_bits();
    (b.wrapping_add(0x7fff + ((b >> 16) & 1)) >> 16) as u16
}

/// The F32 value of a BF16.
#[inline(always)]
fn widen(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}

/// `x` as [`Split::Two`]'s two BF16 values `(high, low)`, for callers that pack their own
/// values (through [`PackedA::two_terms_mut`], [`PackedB::two_term_pairs_mut`]).
#[inline(always)]
pub fn split_two(x: f32) -> (u16, u16) {
    let h = bf16(x);
    (h, bf16(x - widen(h)))
}

/// `x` as `terms` BF16 values, each the rounding of what the previous ones left.
#[inline(always)]
fn split(x: f32, out: &mut [u16; 3], terms: usize) {
    let mut r = x;
    for t in out.iter_mut().take(terms) {
        *t = bf16(r);
        r -= widen(*t);
    }
}

/// `A` (`m × k`) split into BF16 terms, row-major, padded with zeros to `BLOCK` multiples.
#[derive(Clone)]
pub struct PackedA {
    split: Split,
    m: usize,
    k: usize,
    mp: usize,
    kp: usize,
    /// Row stride of a term, [`row_stride`] of `kp` (`u16`s).
    lda: usize,
    /// Term `t` is `data[t·mp·lda ..]`, `mp` rows of `kp` at stride `lda`.
    data: Vec<u16>,
    /// [`PackedA::pack_transposed`]'s row-major copy of its input, kept between calls.
    transposed: Vec<f32>,
}

impl std::fmt::Debug for PackedA {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PackedA({} × {}, {:?})", self.m, self.k, self.split)
    }
}

/// The caller-filled operands are [`Split::Two`]'s.
fn two_terms(split: Split) -> Result<(), AmxError> {
    if split == Split::Two {
        Ok(())
    } else {
        Err(AmxError::Shape(format!(
            "two terms asked of a {split:?} operand"
        )))
    }
}

fn padded(x: usize) -> usize {
    x.div_ceil(BLOCK).max(1) * BLOCK
}

/// `out` (`cols × rows`, row-major) = the transpose of the `rows × cols` matrix `x` whose row
/// `r` starts at `x[r·ld]`: strided reads, contiguous writes.
fn transpose_into(x: &[f32], rows: usize, cols: usize, ld: usize, out: &mut Vec<f32>) {
    out.clear();
    out.extend((0..cols).flat_map(|c| (0..rows).map(move |r| x[r * ld + c])));
}

/// The row stride in bytes for rows of `bytes` (a multiple of 64): an odd number of 64-byte
/// lines. A tile load reads 16 rows at this stride; at a power-of-two stride of 4 KiB or more
/// (`k` = 2048 of the attention's values) all 16 fall into one set of the 12-way L1 and evict
/// each other, and the tile loads ran at a fraction of their speed. With an odd count of lines
/// the 16 rows fall into 16 different sets.
fn row_stride(bytes: usize) -> usize {
    let lines = bytes.div_ceil(64);
    (lines | 1) * 64
}

impl PackedA {
    /// An empty operand whose buffers [`PackedA::pack`] fills and reuses.
    pub fn new(split: Split) -> Self {
        Self {
            split,
            m: 0,
            k: 0,
            mp: 0,
            kp: 0,
            lda: 0,
            data: Vec::new(),
            transposed: Vec::new(),
        }
    }

    /// Sizes the buffers for `m × k`. They are cleared only when the shape changes: a pack of
    /// the same shape writes the same entries, so the padding stays zero.
    fn reset(&mut self, m: usize, k: usize) {
        if (m, k) == (self.m, self.k) && !self.data.is_empty() {
            return;
        }
        let (mp, kp) = (padded(m), padded(k));
        self.m = m;
        self.k = k;
        self.mp = mp;
        self.kp = kp;
        self.lda = row_stride(kp * 2) / 2;
        self.data.clear();
        self.data.resize(self.split.terms() * mp * self.lda, 0);
    }

    /// Packs the row-major `m × k` matrix whose row `i` starts at `a[i·lda]`.
    ///
    /// # Errors
    /// `lda < k` or `a` too short.
    pub fn pack(&mut self, a: &[f32], m: usize, k: usize, lda: usize) -> Result<(), AmxError> {
        if lda < k || (m > 0 && a.len() < (m - 1) * lda + k) {
            return Err(AmxError::Shape(format!(
                "A of {} values cannot hold {m} rows of {k} at stride {lda}",
                a.len()
            )));
        }
        self.reset(m, k);
        let (stride, terms) = (self.lda, self.split.terms());
        let plane = self.mp * stride;
        pulp::Arch::new().dispatch(PackRows {
            a,
            lda,
            m,
            k,
            stride,
            plane,
            terms,
            out: &mut self.data,
        });
        Ok(())
    }

    /// Packs `A` given as its transpose: `k` rows of `m` (row `p` at `at[p·ld]`), e.g. the
    /// attention weights read column-wise.
    ///
    /// # Errors
    /// `ld < m` or `at` too short.
    pub fn pack_transposed(
        &mut self,
        at: &[f32],
        m: usize,
        k: usize,
        ld: usize,
    ) -> Result<(), AmxError> {
        if ld < m || (k > 0 && at.len() < (k - 1) * ld + m) {
            return Err(AmxError::Shape(format!(
                "Aᵀ of {} values cannot hold {k} rows of {m} at stride {ld}",
                at.len()
            )));
        }
        // Transposed into a reused buffer, then packed as rows: the splitting stays one loop.
        let mut rows = std::mem::take(&mut self.transposed);
        transpose_into(at, k, m, ld, &mut rows);
        let packed = self.pack(&rows, m, k, k);
        self.transposed = rows;
        packed
    }

    /// For a caller that computes and splits its own values ([`split_two`]): sizes the operand
    /// for `m × k` and returns the high and low term planes and their row stride. The caller
    /// writes entry `(i, p)` at `i·stride + p` of both for every `i < m`, `p < k`, and nothing
    /// else (the padding stays zero).
    ///
    /// # Errors
    /// An operand split other than [`Split::Two`].
    pub fn two_terms_mut(
        &mut self,
        m: usize,
        k: usize,
    ) -> Result<(&mut [u16], &mut [u16], usize), AmxError> {
        two_terms(self.split)?;
        self.reset(m, k);
        let plane = self.mp * self.lda;
        let (hi, lo) = self.data.split_at_mut(plane);
        Ok((hi, lo, self.lda))
    }

    /// Rows of `A`.
    pub fn rows(&self) -> usize {
        self.m
    }

    /// Columns of `A`.
    pub fn cols(&self) -> usize {
        self.k
    }
}

struct PackRows<'a> {
    a: &'a [f32],
    lda: usize,
    m: usize,
    k: usize,
    stride: usize,
    plane: usize,
    terms: usize,
    out: &'a mut [u16],
}

impl pulp::WithSimd for PackRows<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let Self {
            a,
            lda,
            m,
            k,
            stride,
            plane,
            terms,
            out,
        } = self;
        let (t0, rest) = out.split_at_mut(plane);
        let (t1, t2) = rest.split_at_mut(plane);
        for i in 0..m {
            let src = &a[i * lda..i * lda + k];
            let d0 = &mut t0[i * stride..i * stride + k];
            let d1 = &mut t1[i * stride..i * stride + k];
            if terms == 2 {
                for ((x, h), l) in src.iter().zip(d0.iter_mut()).zip(d1.iter_mut()) {
                    (*h, *l) = split_two(*x);
                }
            } else {
                let d2 = &mut t2[i * stride..i * stride + k];
                let mut parts = [0u16; 3];
                for (((x, h), l), s) in src
                    .iter()
                    .zip(d0.iter_mut())
                    .zip(d1.iter_mut())
                    .zip(d2.iter_mut())
                {
                    split(*x, &mut parts, 3);
                    [*h, *l, *s] = parts;
                }
            }
        }
    }
}

struct PackPairs<'a> {
    b: &'a [f32],
    ldb: usize,
    k: usize,
    n: usize,
    stride: usize,
    plane: usize,
    terms: usize,
    out: &'a mut [u32],
}

impl pulp::WithSimd for PackPairs<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let Self {
            b,
            ldb,
            k,
            n,
            stride,
            plane,
            terms,
            out,
        } = self;
        let zeros = vec![0f32; n];
        let (t0, rest) = out.split_at_mut(plane);
        let (t1, t2) = rest.split_at_mut(plane);
        for r in 0..k.div_ceil(2) {
            let even = &b[2 * r * ldb..2 * r * ldb + n];
            let odd = if 2 * r + 1 < k {
                &b[(2 * r + 1) * ldb..(2 * r + 1) * ldb + n]
            } else {
                &zeros[..]
            };
            let d0 = &mut t0[r * stride..r * stride + n];
            let d1 = &mut t1[r * stride..r * stride + n];
            if terms == 2 {
                for (((x, y), h), l) in even.iter().zip(odd).zip(d0.iter_mut()).zip(d1.iter_mut()) {
                    let ((hx, lx), (hy, ly)) = (split_two(*x), split_two(*y));
                    *h = hx as u32 | (hy as u32) << 16;
                    *l = lx as u32 | (ly as u32) << 16;
                }
            } else {
                let d2 = &mut t2[r * stride..r * stride + n];
                for ((((x, y), h), l), s) in even
                    .iter()
                    .zip(odd)
                    .zip(d0.iter_mut())
                    .zip(d1.iter_mut())
                    .zip(d2.iter_mut())
                {
                    let (mut px, mut py) = ([0u16; 3], [0u16; 3]);
                    split(*x, &mut px, 3);
                    split(*y, &mut py, 3);
                    *h = px[0] as u32 | (py[0] as u32) << 16;
                    *l = px[1] as u32 | (py[1] as u32) << 16;
                    *s = px[2] as u32 | (py[2] as u32) << 16;
                }
            }
        }
    }
}

/// `B` (`k × n`) split into BF16 terms in the tile unit's pairwise layout: row `r` of the packed
/// term holds, for every column `j`, `B[2r][j]` and `B[2r + 1][j]` side by side (one `u32`, the
/// even row in the low half). Padded with zeros to `BLOCK` multiples.
#[derive(Clone)]
pub struct PackedB {
    split: Split,
    k: usize,
    n: usize,
    kp: usize,
    np: usize,
    /// Row stride of a term, [`row_stride`] of `np` pairs (`u32`s).
    ldb: usize,
    /// Term `t` is `data[t·kp·ldb / 2 ..]`: `kp / 2` rows of `np` pairs at stride `ldb`.
    data: Vec<u32>,
    /// [`PackedB::pack_transposed`]'s row-major copy of its input, kept between calls.
    transposed: Vec<f32>,
}

impl std::fmt::Debug for PackedB {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PackedB({} × {}, {:?})", self.k, self.n, self.split)
    }
}

impl PackedB {
    /// An empty operand whose buffers the pack methods fill and reuse.
    pub fn new(split: Split) -> Self {
        Self {
            split,
            k: 0,
            n: 0,
            kp: 0,
            np: 0,
            ldb: 0,
            data: Vec::new(),
            transposed: Vec::new(),
        }
    }

    /// Sizes the buffers for `k × n`, cleared only when the shape changes (as [`PackedA`]).
    fn reset(&mut self, k: usize, n: usize) {
        if (k, n) == (self.k, self.n) && !self.data.is_empty() {
            return;
        }
        let (kp, np) = (padded(k), padded(n));
        self.k = k;
        self.n = n;
        self.kp = kp;
        self.np = np;
        self.ldb = row_stride(np * 4) / 4;
        self.data.clear();
        self.data.resize(self.split.terms() * self.plane(), 0);
    }

    /// The BF16 of term `t` at `(row, column)` of `B` (the emulation's view).
    fn at(&self, t: usize, row: usize, col: usize) -> u16 {
        let pair = self.data[t * self.plane() + (row / 2) * self.ldb + col];
        (pair >> (16 * (row % 2))) as u16
    }

    /// Packs `B` given as its transpose: `n` rows of `k` (row `j` at `bt[j·ldb]`), e.g. the keys
    /// of `Q Kᵀ` or the weight of a linear layer `x Wᵀ`.
    ///
    /// # Errors
    /// `ldb < k` or `bt` too short.
    pub fn pack_transposed(
        &mut self,
        bt: &[f32],
        n: usize,
        k: usize,
        ldb: usize,
    ) -> Result<(), AmxError> {
        if ldb < k || (n > 0 && bt.len() < (n - 1) * ldb + k) {
            return Err(AmxError::Shape(format!(
                "Bᵀ of {} values cannot hold {n} rows of {k} at stride {ldb}",
                bt.len()
            )));
        }
        // Transposed into a reused buffer, then packed as rows (as `PackedA::pack_transposed`).
        let mut rows = std::mem::take(&mut self.transposed);
        transpose_into(bt, n, k, ldb, &mut rows);
        let packed = self.pack(&rows, k, n, n);
        self.transposed = rows;
        packed
    }

    /// Packs the row-major `k × n` matrix whose row `r` starts at `b[r·ldb]`, e.g. the values of
    /// `P V`.
    ///
    /// # Errors
    /// `ldb < n` or `b` too short.
    pub fn pack(&mut self, b: &[f32], k: usize, n: usize, ldb: usize) -> Result<(), AmxError> {
        if ldb < n || (k > 0 && b.len() < (k - 1) * ldb + n) {
            return Err(AmxError::Shape(format!(
                "B of {} values cannot hold {k} rows of {n} at stride {ldb}",
                b.len()
            )));
        }
        self.reset(k, n);
        let (terms, stride, plane) = (self.split.terms(), self.ldb, self.plane());
        pulp::Arch::new().dispatch(PackPairs {
            b,
            ldb,
            k,
            n,
            stride,
            plane,
            terms,
            out: &mut self.data,
        });
        Ok(())
    }

    /// For a caller that computes and splits its own values ([`split_two`]): sizes the operand
    /// for `k × n` and returns the high and low term planes of pairs and their row stride. The
    /// caller writes the pair of rows `2r`, `2r + 1` of column `j` (the even row in the low
    /// half; zero for a missing odd row) at `r·stride + j` of both, for every `r < ⌈k/2⌉`,
    /// `j < n`, and nothing else.
    ///
    /// # Errors
    /// An operand split other than [`Split::Two`].
    pub fn two_term_pairs_mut(
        &mut self,
        k: usize,
        n: usize,
    ) -> Result<(&mut [u32], &mut [u32], usize), AmxError> {
        two_terms(self.split)?;
        self.reset(k, n);
        let plane = self.plane();
        let (hi, lo) = self.data.split_at_mut(plane);
        Ok((hi, lo, self.ldb))
    }

    /// Columns of `B`.
    pub fn cols(&self) -> usize {
        self.n
    }

    /// The `u32`s of one term: `kp / 2` rows at stride `ldb`.
    fn plane(&self) -> usize {
        self.kp / 2 * self.ldb
    }

    /// Rows of `B`.
    pub fn rows(&self) -> usize {
        self.k
    }
}

/// Checks that `a` and `b` multiply and that `c` holds the rows `rows` of the product at stride
/// `ldc` (`c[0]` is row `rows.start`).
fn check(
    c: &[f32],
    ldc: usize,
    a: &PackedA,
    rows: &Range<usize>,
    b: &PackedB,
) -> Result<(), AmxError> {
    if a.split != b.split {
        return Err(AmxError::Shape(format!(
            "A split {:?}, B split {:?}",
            a.split, b.split
        )));
    }
    if a.k != b.k {
        return Err(AmxError::Shape(format!(
            "A has {} columns, B {} rows",
            a.k, b.k
        )));
    }
    if !rows.start.is_multiple_of(BLOCK) || rows.end > a.m || rows.start > rows.end {
        return Err(AmxError::Shape(format!(
            "rows {rows:?} of A's {} (the start a multiple of {BLOCK})",
            a.m
        )));
    }
    let len = rows.len();
    if ldc < b.n || (len > 0 && b.n > 0 && c.len() < (len - 1) * ldc + b.n) {
        return Err(AmxError::Shape(format!(
            "C of {} values cannot hold {len} rows of {} at stride {ldc}",
            c.len(),
            b.n
        )));
    }
    Ok(())
}

/// `C[rows] = A[rows] B` (or `+=` with `accumulate`) on AMX tiles, with `C` row-major at stride
/// `ldc` and `c[0]` the first element of row `rows.start`. `rows.start` must be a multiple of
/// [`BLOCK`]. Runs on the calling thread.
///
/// # Errors
/// [`AmxError::Unavailable`] where [`available`] is false; shapes that do not fit together.
pub fn matmul(
    c: &mut [f32],
    ldc: usize,
    a: &PackedA,
    rows: Range<usize>,
    b: &PackedB,
    accumulate: bool,
) -> Result<(), AmxError> {
    check(c, ldc, a, &rows, b)?;
    if !available() {
        return Err(AmxError::Unavailable);
    }
    if rows.is_empty() || b.n == 0 {
        return Ok(());
    }
    #[cfg(target_arch = "x86_64")]
    tiles::matmul(c, ldc, a, rows, b, accumulate);
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (c, accumulate);
    Ok(())
}

/// What [`matmul`] computes, in software, in the order of the instruction's documented
/// pseudo-code: for every term product (smallest first) and every pair of `k`,
/// `c += a[2p+1] b[2p+1]`, then `c += a[2p] b[2p]`, each an exact product rounded once when
/// added (F32, ties to even), subnormal terms as zero. The tile unit groups its additions
/// differently (measured on a Sapphire Rapids core: results differ by a few F32 roundings of
/// the accumulated magnitude), so the two agree to the accumulation's error, not bit for bit.
///
/// # Errors
/// Shapes that do not fit together.
pub fn matmul_emulated(
    c: &mut [f32],
    ldc: usize,
    a: &PackedA,
    rows: Range<usize>,
    b: &PackedB,
    accumulate: bool,
) -> Result<(), AmxError> {
    check(c, ldc, a, &rows, b)?;
    let flush = |h: u16| if h & 0x7f80 == 0 { 0.0 } else { widen(h) };
    let aplane = a.mp * a.lda;
    for (ci, i) in rows.enumerate() {
        for j in 0..b.n {
            let mut acc = if accumulate { c[ci * ldc + j] } else { 0.0 };
            for &(ta, tb) in a.split.products() {
                for p in 0..a.kp / 2 {
                    for e in [1, 0] {
                        let x = flush(a.data[ta * aplane + i * a.lda + 2 * p + e]);
                        let y = flush(b.at(tb, 2 * p + e, j));
                        acc += x * y;
                    }
                }
            }
            c[ci * ldc + j] = acc;
        }
    }
    Ok(())
}

#[cfg(target_arch = "x86_64")]
mod tiles {
    use std::arch::asm;
    use std::ops::Range;

    use super::{BLOCK, PackedA, PackedB};

    /// The tile configuration (palette 1): eight tiles of 16 rows × 64 bytes.
    #[repr(C, align(64))]
    struct Config {
        palette: u8,
        start_row: u8,
        reserved: [u8; 14],
        colsb: [u16; 16],
        rows: [u8; 16],
    }

    const CONFIG: Config = Config {
        palette: 1,
        start_row: 0,
        reserved: [0; 14],
        colsb: [64, 64, 64, 64, 64, 64, 64, 64, 0, 0, 0, 0, 0, 0, 0, 0],
        rows: [16, 16, 16, 16, 16, 16, 16, 16, 0, 0, 0, 0, 0, 0, 0, 0],
    };

    /// The tiles configured for this thread; released when dropped.
    struct Tiles;

    impl Tiles {
        fn configure() -> Self {
            let cfg = &CONFIG;
            // SAFETY: only called after `available()` granted the tile state; `cfg` is a valid,
            // 64-byte aligned palette-1 configuration.
            unsafe { asm!("ldtilecfg [{}]", in(reg) cfg, options(nostack, readonly)) };
            Tiles
        }
    }

    impl Drop for Tiles {
        fn drop(&mut self) {
            // SAFETY: releases the state `configure` set up on this thread.
            unsafe { asm!("tilerelease", options(nostack, nomem)) };
        }
    }

    /// A 32 × 32 block of `C` in a 64-byte aligned scratch, for blocks at the edges.
    #[repr(C, align(64))]
    struct Edge([f32; BLOCK * BLOCK]);

    pub(super) fn matmul(
        c: &mut [f32],
        ldc: usize,
        a: &PackedA,
        rows: Range<usize>,
        b: &PackedB,
        accumulate: bool,
    ) {
        let _tiles = Tiles::configure();
        let mut edge = Edge([0.0; BLOCK * BLOCK]);
        // Columns in chunks whose packed B stays in L2 while the rows pass over it.
        let chunk = (128 * 1024 / (b.kp * 2 * a.split.terms()) / BLOCK).max(1) * BLOCK;
        for n0 in (0..b.n).step_by(chunk) {
            let n1 = (n0 + chunk).min(b.n);
            for i0 in rows.clone().step_by(BLOCK) {
                let ci = i0 - rows.start;
                let h = BLOCK.min(rows.end - i0);
                for j0 in (n0..n1).step_by(BLOCK) {
                    let w = BLOCK.min(b.n - j0);
                    if h == BLOCK && w == BLOCK {
                        let at = ci * ldc + j0;
                        let dst = &mut c[at..at + (BLOCK - 1) * ldc + BLOCK];
                        // SAFETY: `dst` holds 32 rows of 32 at stride `ldc` (checked by its
                        // slicing above); the packed operands cover block rows `i0..i0+32`
                        // and columns `j0..j0+32` (padded to multiples of 32).
                        unsafe { block(dst.as_mut_ptr(), ldc, accumulate, a, i0, b, j0) };
                    } else {
                        let e = &mut edge.0;
                        e.fill(0.0);
                        if accumulate {
                            for r in 0..h {
                                e[r * BLOCK..r * BLOCK + w].copy_from_slice(
                                    &c[(ci + r) * ldc + j0..(ci + r) * ldc + j0 + w],
                                );
                            }
                        }
                        // SAFETY: `e` is a 32 × 32 block at stride 32, the operands as above.
                        unsafe { block(e.as_mut_ptr(), BLOCK, true, a, i0, b, j0) };
                        for r in 0..h {
                            c[(ci + r) * ldc + j0..(ci + r) * ldc + j0 + w]
                                .copy_from_slice(&e[r * BLOCK..r * BLOCK + w]);
                        }
                    }
                }
            }
        }
    }

    /// One 32 × 32 block of `C` at `c` (stride `ldc` floats): rows `i0..i0+32` of `A` times
    /// columns `j0..j0+32` of `B`, every term product, all of `k`.
    ///
    /// # Safety
    /// Tiles configured on this thread; `c` valid for 32 rows of 32 floats at stride `ldc`;
    /// `i0 + 32 ≤ a.mp`, `j0 + 32 ≤ b.np`, `a.kp == b.kp`.
    #[allow(clippy::too_many_arguments)]
    unsafe fn block(
        c: *mut f32,
        ldc: usize,
        accumulate: bool,
        a: &PackedA,
        i0: usize,
        b: &PackedB,
        j0: usize,
    ) {
        let sc = ldc * 4;
        let c1 = c.wrapping_add(16 * ldc);
        // SAFETY (all blocks below): the addresses are inside `c` and the packed buffers by the
        // function's contract; each tile row is 64 bytes at the given stride.
        unsafe {
            if accumulate {
                asm!(
                    "tileloadd tmm0, [{c0} + {sc}]",
                    "tileloadd tmm1, [{c0} + {sc} + 64]",
                    "tileloadd tmm2, [{c1} + {sc}]",
                    "tileloadd tmm3, [{c1} + {sc} + 64]",
                    c0 = in(reg) c, c1 = in(reg) c1, sc = in(reg) sc,
                    options(nostack, readonly)
                );
            } else {
                asm!(
                    "tilezero tmm0",
                    "tilezero tmm1",
                    "tilezero tmm2",
                    "tilezero tmm3",
                    options(nostack, nomem)
                );
            }
        }
        let (kp, lda, ldb) = (a.kp, a.lda, b.ldb);
        let (aplane, bplane) = (a.mp * lda, b.plane());
        if a.split == super::Split::Two {
            // Per step of k: A's low terms with B's high, A's high with B's high, A's high with
            // B's low; eight tile loads for twelve products.
            let a0h = a.data[i0 * lda..].as_ptr();
            let a1h = a.data[(i0 + 16) * lda..].as_ptr();
            let a0l = a.data[aplane + i0 * lda..].as_ptr();
            let a1l = a.data[aplane + (i0 + 16) * lda..].as_ptr();
            let b0h = b.data[j0..].as_ptr();
            let b0l = b.data[bplane + j0..].as_ptr();
            // SAFETY: see above; kp / 32 steps along k of A's two row tiles and B's two column
            // tiles, both terms.
            unsafe {
                asm!(
                    "2:",
                    "tileloadd tmm4, [{a0l} + {sa}]",
                    "tileloadd tmm6, [{b0h} + {sb}]",
                    "tileloadd tmm7, [{b0h} + {sb} + 64]",
                    "tdpbf16ps tmm0, tmm4, tmm6",
                    "tileloadd tmm5, [{a1l} + {sa}]",
                    "tdpbf16ps tmm1, tmm4, tmm7",
                    "tileloadd tmm4, [{a0h} + {sa}]",
                    "tdpbf16ps tmm2, tmm5, tmm6",
                    "tdpbf16ps tmm3, tmm5, tmm7",
                    "tileloadd tmm5, [{a1h} + {sa}]",
                    "tdpbf16ps tmm0, tmm4, tmm6",
                    "tdpbf16ps tmm1, tmm4, tmm7",
                    "tdpbf16ps tmm2, tmm5, tmm6",
                    "tileloadd tmm6, [{b0l} + {sb}]",
                    "tdpbf16ps tmm3, tmm5, tmm7",
                    "tileloadd tmm7, [{b0l} + {sb} + 64]",
                    "tdpbf16ps tmm0, tmm4, tmm6",
                    "tdpbf16ps tmm2, tmm5, tmm6",
                    "tdpbf16ps tmm1, tmm4, tmm7",
                    "tdpbf16ps tmm3, tmm5, tmm7",
                    "add {a0h}, 64",
                    "add {a1h}, 64",
                    "add {a0l}, 64",
                    "add {a1l}, 64",
                    "add {b0h}, {bstep}",
                    "add {b0l}, {bstep}",
                    "dec {n}",
                    "jnz 2b",
                    a0h = inout(reg) a0h => _,
                    a1h = inout(reg) a1h => _,
                    a0l = inout(reg) a0l => _,
                    a1l = inout(reg) a1l => _,
                    b0h = inout(reg) b0h => _,
                    b0l = inout(reg) b0l => _,
                    sa = in(reg) lda * 2,
                    sb = in(reg) ldb * 4,
                    bstep = in(reg) 16 * ldb * 4,
                    n = inout(reg) kp / 32 => _,
                    options(nostack, readonly)
                );
            }
        } else {
            for &(ta, tb) in a.split.products() {
                let a0 = a.data[ta * aplane + i0 * lda..].as_ptr();
                let a1 = a.data[ta * aplane + (i0 + 16) * lda..].as_ptr();
                let b0 = b.data[tb * bplane + j0..].as_ptr();
                // SAFETY: see above; the loop reads kp / 32 tiles along k from each of A's two
                // row tiles and B's two column tiles.
                unsafe {
                    asm!(
                        "2:",
                        "tileloadd tmm4, [{a0} + {sa}]",
                        "tileloadd tmm6, [{b0} + {sb}]",
                        "tileloadd tmm7, [{b0} + {sb} + 64]",
                        "tdpbf16ps tmm0, tmm4, tmm6",
                        "tileloadd tmm5, [{a1} + {sa}]",
                        "tdpbf16ps tmm1, tmm4, tmm7",
                        "tdpbf16ps tmm2, tmm5, tmm6",
                        "tdpbf16ps tmm3, tmm5, tmm7",
                        "add {a0}, 64",
                        "add {a1}, 64",
                        "add {b0}, {bstep}",
                        "dec {n}",
                        "jnz 2b",
                        a0 = inout(reg) a0 => _,
                        a1 = inout(reg) a1 => _,
                        b0 = inout(reg) b0 => _,
                        sa = in(reg) lda * 2,
                        sb = in(reg) ldb * 4,
                        bstep = in(reg) 16 * ldb * 4,
                        n = inout(reg) kp / 32 => _,
                        options(nostack, readonly)
                    );
                }
            }
        }
        // SAFETY: see above.
        unsafe {
            asm!(
                "tilestored [{c0} + {sc}], tmm0",
                "tilestored [{c0} + {sc} + 64], tmm1",
                "tilestored [{c1} + {sc}], tmm2",
                "tilestored [{c1} + {sc} + 64], tmm3",
                c0 = in(reg) c, c1 = in(reg) c1, sc = in(reg) sc,
                options(nostack)
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng, rngs::StdRng};

    use super::*;

    fn random(len: usize, rng: &mut StdRng, scale: f32) -> Vec<f32> {
        (0..len)
            .map(|_| rng.random_range(-1.0f32..1.0) * scale)
            .collect()
    }

    /// `A B` in F64 and `Σ|aᵢ bᵢ|` per entry.
    fn reference(a: &[f32], b: &[f32], m: usize, k: usize, n: usize) -> (Vec<f64>, Vec<f64>) {
        let mut c = vec![0f64; m * n];
        let mut abs = vec![0f64; m * n];
        for i in 0..m {
            for j in 0..n {
                for p in 0..k {
                    let t = a[i * k + p] as f64 * b[p * n + j] as f64;
                    c[i * n + j] += t;
                    abs[i * n + j] += t.abs();
                }
            }
        }
        (c, abs)
    }

    fn transpose(b: &[f32], k: usize, n: usize) -> Vec<f32> {
        let mut t = vec![0f32; k * n];
        for p in 0..k {
            for j in 0..n {
                t[j * k + p] = b[p * n + j];
            }
        }
        t
    }

    /// A tile load reads 16 rows at the operand's stride: each row must land in its own set of
    /// the L1 (64 sets of 64-byte lines), whatever the row length.
    #[test]
    fn a_tiles_rows_fall_into_different_cache_sets() -> Result<(), AmxError> {
        for k in [32usize, 64, 96, 256, 1024, 2048, 4096] {
            for bytes in [k * 2, k * 4] {
                let stride = row_stride(bytes);
                assert!(
                    stride >= bytes && stride.is_multiple_of(64),
                    "{bytes} → {stride}"
                );
                assert!(
                    stride < bytes + 128,
                    "{bytes} → {stride}: more than one line added"
                );
                let sets: std::collections::HashSet<usize> =
                    (0..16).map(|r| (r * stride / 64) % 64).collect();
                assert_eq!(sets.len(), 16, "rows of {bytes} bytes at stride {stride}");
            }
        }
        let mut a = PackedA::new(Split::Two);
        let (_, _, lda) = a.two_terms_mut(40, 2048)?;
        assert_eq!(lda, 2048 + 32);
        let mut b = PackedB::new(Split::Two);
        let (_, _, ldb) = b.two_term_pairs_mut(64, 2048)?;
        assert_eq!(ldb, 2048 + 16);
        Ok(())
    }

    #[test]
    fn splitting_recovers_the_value_to_the_terms_precision() {
        let mut rng = StdRng::seed_from_u64(1);
        for x in random(10_000, &mut rng, 100.0) {
            let mut t = [0u16; 3];
            split(x, &mut t, 3);
            let two = widen(t[0]) as f64 + widen(t[1]) as f64;
            let three = two + widen(t[2]) as f64;
            let x = x as f64;
            assert!((two - x).abs() <= x.abs() * 2f64.powi(-17), "{x} {two}");
            assert!((three - x).abs() <= x.abs() * 2f64.powi(-24), "{x} {three}");
        }
    }

    #[test]
    fn emulated_products_have_the_splits_accuracy_at_odd_shapes() -> Result<(), AmxError> {
        let mut rng = StdRng::seed_from_u64(2);
        for (m, k, n) in [(1, 1, 1), (37, 70, 45), (64, 256, 33), (5, 2048, 64)] {
            let a = random(m * k, &mut rng, 3.0);
            let b = random(k * n, &mut rng, 0.5);
            let (exact, abs) = reference(&a, &b, m, k, n);
            for (sp, bound) in [(Split::Two, 2f64.powi(-15)), (Split::Three, 2f64.powi(-21))] {
                let mut pa = PackedA::new(sp);
                pa.pack(&a, m, k, k)?;
                // Both ways of packing A, and of B, give the same operand.
                let mut pat = PackedA::new(sp);
                let mut at = vec![0f32; k * m];
                for i in 0..m {
                    for p in 0..k {
                        at[p * m + i] = a[i * k + p];
                    }
                }
                pat.pack_transposed(&at, m, k, m)?;
                assert_eq!(pa.data, pat.data);
                let mut pb = PackedB::new(sp);
                pb.pack(&b, k, n, n)?;
                let mut pbt = PackedB::new(sp);
                pbt.pack_transposed(&transpose(&b, k, n), n, k, k)?;
                assert_eq!(pb.data, pbt.data);
                let mut c = vec![0f32; m * n];
                matmul_emulated(&mut c, n, &pa, 0..m, &pb, false)?;
                for ((x, e), s) in c.iter().zip(&exact).zip(&abs) {
                    // F32 accumulation adds about k · 2⁻²⁴ of Σ|ab| on top of the split's error.
                    let tol = s * (bound + k as f64 * 2f64.powi(-24));
                    assert!((*x as f64 - e).abs() <= tol, "{sp:?} {m}x{k}x{n}: {x} {e}");
                }
            }
        }
        Ok(())
    }

    #[test]
    fn operands_filled_by_the_caller_equal_the_packed_ones() -> Result<(), AmxError> {
        let mut rng = StdRng::seed_from_u64(4);
        let (m, k, n) = (37, 45, 29);
        let a = random(m * k, &mut rng, 3.0);
        let b = random(k * n, &mut rng, 3.0);
        let mut pa = PackedA::new(Split::Two);
        pa.pack(&a, m, k, k)?;
        let mut fa = PackedA::new(Split::Two);
        // A larger shape first: its entries must not survive as padding.
        fa.pack(&random(64 * 64, &mut rng, 1.0), 64, 64, 64)?;
        let (hi, lo, stride) = fa.two_terms_mut(m, k)?;
        for i in 0..m {
            for p in 0..k {
                (hi[i * stride + p], lo[i * stride + p]) = split_two(a[i * k + p]);
            }
        }
        assert_eq!(pa.data, fa.data);
        let mut pb = PackedB::new(Split::Two);
        pb.pack(&b, k, n, n)?;
        let mut fb = PackedB::new(Split::Two);
        let (hi, lo, stride) = fb.two_term_pairs_mut(k, n)?;
        for r in 0..k.div_ceil(2) {
            for j in 0..n {
                let (eh, el) = split_two(b[2 * r * n + j]);
                let (oh, ol) = if 2 * r + 1 < k {
                    split_two(b[(2 * r + 1) * n + j])
                } else {
                    (0, 0)
                };
                hi[r * stride + j] = eh as u32 | (oh as u32) << 16;
                lo[r * stride + j] = el as u32 | (ol as u32) << 16;
            }
        }
        assert_eq!(pb.data, fb.data);
        assert!(PackedA::new(Split::Three).two_terms_mut(2, 2).is_err());
        Ok(())
    }

    #[test]
    fn shapes_that_do_not_fit_are_errors() -> Result<(), AmxError> {
        let mut pa = PackedA::new(Split::Two);
        assert!(pa.pack(&[0.0; 5], 2, 3, 3).is_err());
        pa.pack(&[0.0; 6], 2, 3, 3)?;
        let mut pb = PackedB::new(Split::Two);
        pb.pack(&[0.0; 8], 4, 2, 2)?;
        let mut c = [0f32; 4];
        // k 3 against 4.
        assert!(matmul_emulated(&mut c, 2, &pa, 0..2, &pb, false).is_err());
        let mut pb3 = PackedB::new(Split::Three);
        pb3.pack(&[0.0; 6], 3, 2, 2)?;
        assert!(matmul_emulated(&mut c, 2, &pa, 0..2, &pb3, false).is_err());
        pb.pack(&[0.0; 6], 3, 2, 2)?;
        // C too short, a row range beyond A.
        assert!(matmul_emulated(&mut c[..3], 2, &pa, 0..2, &pb, false).is_err());
        assert!(matmul_emulated(&mut c, 2, &pa, 0..3, &pb, false).is_err());
        matmul_emulated(&mut c, 2, &pa, 0..2, &pb, false)
    }

    /// Without AMX (this build's host: `cfg(amx_host)` from build.rs) `available()` is false
    /// and `matmul` refuses with `Unavailable`, touching nothing.
    #[test]
    #[cfg_attr(
        amx_host,
        ignore = "this host has AMX: the tile test below runs instead"
    )]
    fn without_amx_matmul_refuses() -> Result<(), AmxError> {
        assert!(!available());
        let (mut pa, mut pb) = (PackedA::new(Split::Two), PackedB::new(Split::Two));
        pa.pack(&[1.0; 6], 2, 3, 3)?;
        pb.pack(&[1.0; 6], 3, 2, 2)?;
        let mut c = [7f32; 4];
        assert!(matches!(
            matmul(&mut c, 2, &pa, 0..2, &pb, false),
            Err(AmxError::Unavailable)
        ));
        assert_eq!(c, [7.0; 4]);
        Ok(())
    }

    /// On a host with AMX the tiles have the split's accuracy, touch nothing outside `C`'s
    /// rows and columns, and agree with the emulation. Reported as skipped (ignored) on hosts
    /// without AMX, where it cannot run.
    #[test]
    #[cfg_attr(
        not(amx_host),
        ignore = "needs a CPU with AMX-TILE and AMX-BF16 (Intel Sapphire Rapids or later)"
    )]
    fn tiles_have_the_accuracy_of_the_emulation() -> Result<(), AmxError> {
        assert!(
            available(),
            "the CPU has AMX but the kernel did not grant the tiles"
        );
        let mut rng = StdRng::seed_from_u64(3);
        for (m, k, n, rows) in [
            (64, 64, 2048, 0..64),
            (70, 96, 50, 32..70),
            (33, 512, 256, 0..33),
            (3, 5, 7, 0..3),
        ] {
            for (sp, bound) in [(Split::Two, 2f64.powi(-15)), (Split::Three, 2f64.powi(-21))] {
                let a = random(m * k, &mut rng, 2.0);
                let b = random(k * n, &mut rng, 1.0);
                let (exact, abs) = reference(&a, &b, m, k, n);
                let (mut pa, mut pb) = (PackedA::new(sp), PackedB::new(sp));
                pa.pack(&a, m, k, k)?;
                pb.pack(&b, k, n, n)?;
                let ldc = n + 3;
                let init = random(rows.len() * ldc, &mut rng, 1.0);
                for accumulate in [false, true] {
                    let mut emulated = init.clone();
                    matmul_emulated(&mut emulated, ldc, &pa, rows.clone(), &pb, accumulate)?;
                    let mut got = init.clone();
                    matmul(&mut got, ldc, &pa, rows.clone(), &pb, accumulate)?;
                    for (r, i) in rows.clone().enumerate() {
                        for j in 0..ldc {
                            let (x, e, c0) =
                                (got[r * ldc + j], emulated[r * ldc + j], init[r * ldc + j]);
                            if j >= n {
                                assert_eq!(x, c0, "the stride's gap at ({i}, {j})");
                                continue;
                            }
                            let base = if accumulate { c0 as f64 } else { 0.0 };
                            let want = base + exact[i * n + j];
                            let scale = base.abs() + abs[i * n + j];
                            let tol = scale * (bound + k as f64 * 2f64.powi(-24));
                            assert!(
                                (x as f64 - want).abs() <= tol,
                                "{sp:?} {m}x{k}x{n} ({i}, {j}) {accumulate}: {x} against {want}"
                            );
                            assert!(
                                ((x - e) as f64).abs() <= scale * k as f64 * 2f64.powi(-23),
                                "{sp:?} ({i}, {j}): tiles {x}, emulation {e}"
                            );
                        }
                    }
                }
            }
        }
        Ok(())
    }
}
