//! Test support for the posediff workspace: locating and reading the parity fixtures produced by
//! the official PoseDiffusion code, and tolerance checks that report the worst error.
//!
//! Fixtures live in two places: small ones are copied into the workspace's `fixtures/` folder;
//! large ones (checkpoints) are read from `../shared/reference` beside the checkout (override with
//! `POSEDIFF_SHARED`). A missing fixture is a test failure with a message saying where it was
//! looked for, never a skipped test.
//!
//! Functions here panic with a clear message on malformed fixtures: they run only in tests.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

use std::path::{Path, PathBuf};

pub use serde_json;

/// The workspace root (two levels above this crate).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// `<workspace>/fixtures/<relative>`, checked to exist.
#[track_caller]
pub fn fixture_path(relative: &str) -> PathBuf {
    let path = workspace_root().join("fixtures").join(relative);
    assert!(path.exists(), "fixture {} is missing", path.display());
    path
}

/// The shared material beside the checkout: `$POSEDIFF_SHARED` or `<workspace>/../shared`.
pub fn shared_dir() -> PathBuf {
    std::env::var_os("POSEDIFF_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("../shared"))
}

/// `<shared>/<relative>`, checked to exist.
#[track_caller]
pub fn shared_path(relative: &str) -> PathBuf {
    let path = shared_dir().join(relative);
    assert!(
        path.exists(),
        "{} is missing: the shared material must sit beside the checkout (or set POSEDIFF_SHARED)",
        path.display()
    );
    path
}

/// A fresh, empty folder for one test: `posediff-<tag>-<pid>` in the system's temporary
/// folder (an earlier run's is removed).
///
/// # Panics
/// When the folder cannot be made (the test cannot run).
#[allow(clippy::expect_used)] // test support: a failure is the test failing
pub fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("posediff-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("a temporary folder");
    d
}

/// A tensor read from a fixture, converted to `f64`, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    /// Shape.
    pub shape: Vec<usize>,
    /// Values, row-major.
    pub data: Vec<f64>,
}

impl Tensor {
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// True for a tensor without elements.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The values split into consecutive rows of `n` (e.g. `n = 9` for 3×3 matrices).
    #[track_caller]
    pub fn chunks(&self, n: usize) -> Vec<&[f64]> {
        assert_eq!(
            self.data.len() % n,
            0,
            "tensor of {:?} is not made of rows of {n}",
            self.shape
        );
        self.data.chunks(n).collect()
    }

    /// The single value of a one-element tensor.
    #[track_caller]
    pub fn scalar(&self) -> f64 {
        assert_eq!(
            self.data.len(),
            1,
            "tensor of {:?} is not a scalar",
            self.shape
        );
        self.data[0]
    }
}

/// A safetensors fixture file held in memory.
pub struct SafetensorsFixture {
    path: PathBuf,
    bytes: Vec<u8>,
}

impl SafetensorsFixture {
    /// Reads a whole safetensors file.
    #[track_caller]
    pub fn open(path: &Path) -> Self {
        let bytes = std::fs::read(path)
            .unwrap_or_else(|e| panic!("cannot read fixture {}: {e}", path.display()));
        Self {
            path: path.to_owned(),
            bytes,
        }
    }

    /// The names of the tensors in the file.
    #[track_caller]
    pub fn names(&self) -> Vec<String> {
        safetensors::SafeTensors::deserialize(&self.bytes)
            .unwrap_or_else(|e| panic!("{}: {e}", self.path.display()))
            .names()
            .into_iter()
            .map(|n| n.to_string())
            .collect()
    }

    /// Tensor `name` as `f64` (F16, F32, F64, I64, I32, U8 storage).
    #[track_caller]
    pub fn tensor(&self, name: &str) -> Tensor {
        let st = safetensors::SafeTensors::deserialize(&self.bytes)
            .unwrap_or_else(|e| panic!("{} is not a safetensors file: {e}", self.path.display()));
        let view = st
            .tensor(name)
            .unwrap_or_else(|e| panic!("{} has no tensor {name}: {e}", self.path.display()));
        let raw = view.data();
        use safetensors::Dtype;
        let data: Vec<f64> = match view.dtype() {
            Dtype::F64 => raw
                .chunks_exact(8)
                .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
                .collect(),
            Dtype::F32 => raw
                .chunks_exact(4)
                .map(|b| f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])))
                .collect(),
            Dtype::F16 => raw
                .chunks_exact(2)
                .map(|b| f16_to_f64(u16::from_le_bytes([b[0], b[1]])))
                .collect(),
            Dtype::I64 => raw
                .chunks_exact(8)
                .map(|b| {
                    i64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f64
                })
                .collect(),
            Dtype::I32 => raw
                .chunks_exact(4)
                .map(|b| f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])))
                .collect(),
            Dtype::U8 => raw.iter().map(|&b| f64::from(b)).collect(),
            other => panic!(
                "{}: tensor {name} has unsupported dtype {other:?}",
                self.path.display()
            ),
        };
        Tensor {
            shape: view.shape().to_vec(),
            data,
        }
    }
}

impl SafetensorsFixture {
    /// Tensor `name` as rows of `N` values (e.g. `N = 2` keypoints, `N = 9` pose encodings).
    #[track_caller]
    pub fn rows<const N: usize>(&self, name: &str) -> Vec<[f64; N]> {
        self.tensor(name)
            .chunks(N)
            .iter()
            .map(|c| {
                let mut row = [0.0; N];
                row.copy_from_slice(c);
                row
            })
            .collect()
    }

    /// Tensor `name` (`M × 2` integers) as index pairs, e.g. the frames `i12` of matches.
    #[track_caller]
    pub fn index_pairs(&self, name: &str) -> Vec<(usize, usize)> {
        self.rows::<2>(name)
            .iter()
            .map(|r| (r[0] as usize, r[1] as usize))
            .collect()
    }
}

/// Candle conversions (feature `candle`).
#[cfg(feature = "candle")]
pub mod tensors {
    use candle_core::{DType, Device, Tensor};

    use crate::SafetensorsFixture;

    /// A fixture tensor as an F64 candle tensor on the CPU.
    #[track_caller]
    pub fn tensor(fx: &SafetensorsFixture, name: &str) -> Tensor {
        let t = fx.tensor(name);
        Tensor::from_vec(t.data, t.shape, &Device::Cpu).unwrap_or_else(|e| panic!("{name}: {e}"))
    }

    /// A tensor's values as f64, row-major.
    #[track_caller]
    pub fn values(t: &Tensor) -> Vec<f64> {
        t.flatten_all()
            .and_then(|t| t.to_dtype(DType::F64))
            .and_then(|t| t.to_vec1())
            .unwrap_or_else(|e| panic!("tensor values: {e}"))
    }
}

/// IEEE half precision to f64.
fn f16_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = i32::from((h >> 10) & 0x1f);
    let frac = f64::from(h & 0x3ff);
    match exp {
        0 => sign * frac * 2f64.powi(-24),
        31 if frac == 0.0 => sign * f64::INFINITY,
        31 => f64::NAN,
        _ => sign * (1.0 + frac / 1024.0) * 2f64.powi(exp - 15),
    }
}

/// Reads a JSON fixture.
#[track_caller]
pub fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("cannot read fixture {}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{} is not JSON: {e}", path.display()))
}

/// Flattens a JSON number or nested array of numbers.
#[track_caller]
pub fn json_f64s(value: &serde_json::Value) -> Vec<f64> {
    match value {
        serde_json::Value::Number(n) => vec![n.as_f64().unwrap_or(f64::NAN)],
        serde_json::Value::Array(items) => items.iter().flat_map(json_f64s).collect(),
        other => panic!("expected numbers, found {other}"),
    }
}

/// Concatenates fixed-size rows (vectors, encodings) into one row-major list.
pub fn flat<const N: usize>(rows: impl IntoIterator<Item = [f64; N]>) -> Vec<f64> {
    rows.into_iter().flatten().collect()
}

/// The mean of some values (NaN for none).
pub fn mean(values: impl IntoIterator<Item = f64>) -> f64 {
    let (sum, n) = values
        .into_iter()
        .fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    sum / n as f64
}

/// The worst element-wise error of `actual` against `expected` under `|a − e| ≤ atol + rtol·|e|`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorstError {
    /// Largest `|a − e|`.
    pub max_abs: f64,
    /// Largest `|a − e| / |e|` over elements with `e ≠ 0`.
    pub max_rel: f64,
    /// Largest `|a − e| / (atol + rtol·|e|)`: at most 1 when the check passes.
    pub max_ratio: f64,
}

/// Asserts `|a − e| ≤ atol + rtol·|e|` element-wise and returns the worst errors. The message
/// names the first failing index. NaN never passes.
#[track_caller]
pub fn assert_close(
    what: &str,
    actual: &[f64],
    expected: &[f64],
    atol: f64,
    rtol: f64,
) -> WorstError {
    assert_eq!(
        actual.len(),
        expected.len(),
        "{what}: {} values, expected {}",
        actual.len(),
        expected.len()
    );
    let mut worst = WorstError {
        max_abs: 0.0,
        max_rel: 0.0,
        max_ratio: 0.0,
    };
    for (i, (&a, &e)) in actual.iter().zip(expected).enumerate() {
        let err = (a - e).abs();
        let bound = atol + rtol * e.abs();
        assert!(
            err <= bound,
            "{what}[{i}]: got {a}, expected {e} (|diff| {err:e} > {bound:e})"
        );
        worst.max_abs = worst.max_abs.max(err);
        if e != 0.0 {
            worst.max_rel = worst.max_rel.max(err / e.abs());
        }
        if bound > 0.0 {
            worst.max_ratio = worst.max_ratio.max(err / bound);
        }
    }
    eprintln!(
        "{what}: max abs err {:.3e}, max rel err {:.3e} (atol {atol:e}, rtol {rtol:e})",
        worst.max_abs, worst.max_rel
    );
    worst
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_precision_decodes() {
        assert_eq!(f16_to_f64(0x3c00), 1.0);
        assert_eq!(f16_to_f64(0xc000), -2.0);
        assert_eq!(f16_to_f64(0x0001), 2f64.powi(-24));
        assert_eq!(f16_to_f64(0x3555), 0.333_251_953_125);
    }

    #[test]
    fn assert_close_reports_the_worst_error() {
        let w = assert_close("x", &[1.0, 2.001], &[1.0, 2.0], 0.0, 1e-3);
        assert!((w.max_abs - 0.001).abs() < 1e-12);
        assert!(w.max_ratio <= 1.0 + 1e-9);
    }

    #[test]
    fn assert_close_rejects_nan() {
        let r = std::panic::catch_unwind(|| assert_close("x", &[f64::NAN], &[1.0], 1.0, 1.0));
        assert!(r.is_err());
    }

    #[test]
    fn copied_fixtures_are_present() {
        for f in [
            "geometry_io.safetensors",
            "normalize_io.safetensors",
            "metrics_io.json",
        ] {
            assert!(fixture_path(&format!("reference/full/{f}")).is_file());
        }
    }
}
