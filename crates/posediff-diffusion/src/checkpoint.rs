//! Loading official PoseDiffusion checkpoints: PyTorch `.pth` (zip + pickle, or the legacy
//! format of PyTorch < 1.6 that DISK's released weights use; the pickle is read without
//! executing code) or safetensors, keys as `model_keys.txt`, with or without a `module.` prefix,
//! F16/F32/F64 storage. The depths of the ViT and of the denoiser trunk are read from the keys.
//!
//! Every missing, unexpected or mis-shaped key is reported in one error.

use std::collections::{BTreeSet, HashMap};
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use crate::error::{DiffusionError, Result};

/// Prefix of the image feature extractor's ViT.
pub const VIT_PREFIX: &str = "image_feature_extractor._net";
/// Prefix of the denoiser.
pub const DENOISER_PREFIX: &str = "diffuser.model";
/// Prefix of the registered schedule buffers.
pub const SCHEDULE_PREFIX: &str = "diffuser";
/// The prefix `accelerate`/DDP adds to every key.
const DDP_PREFIX: &str = "module.";

/// ViT-S/16 width.
pub const VIT_DIM: usize = 384;
/// ViT MLP width.
pub const VIT_MLP_DIM: usize = 1536;
/// Positional-embedding table length (14×14 + CLS).
pub const VIT_POS_TOKENS: usize = 197;
/// Denoiser width.
pub const DENOISER_DIM: usize = 512;
/// Denoiser feed-forward width.
pub const DENOISER_FF_DIM: usize = 1024;
/// Input width of `_first`: 189 + 128 + 384 + 1.
pub const DENOISER_FEED_DIM: usize = 702;
/// Time-embedding sinusoid width.
pub const TIME_EMBED_DIM: usize = 256;
/// Diffusion steps of the official schedule.
pub const TIMESTEPS: usize = 100;

/// The names of the 13 registered schedule buffers.
pub const SCHEDULE_BUFFERS: [&str; 13] = [
    "betas",
    "alphas_cumprod",
    "alphas_cumprod_prev",
    "sqrt_alphas_cumprod",
    "sqrt_one_minus_alphas_cumprod",
    "log_one_minus_alphas_cumprod",
    "sqrt_recip_alphas_cumprod",
    "sqrt_recipm1_alphas_cumprod",
    "posterior_variance",
    "posterior_log_variance_clipped",
    "posterior_mean_coef1",
    "posterior_mean_coef2",
    "p2_loss_weight",
];

/// Depths read from a checkpoint's keys.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ModelDepths {
    /// Transformer blocks of the ViT (official 12).
    pub vit_blocks: usize,
    /// Encoder layers of the denoiser trunk (official 8).
    pub trunk_layers: usize,
}

impl ModelDepths {
    /// The official model.
    pub const OFFICIAL: Self = Self {
        vit_blocks: 12,
        trunk_layers: 8,
    };
}

/// Every parameter key of a model of the given depths, with its shape (`model_keys.txt`).
pub fn expected_parameters(depths: ModelDepths) -> Vec<(String, Vec<usize>)> {
    let v = VIT_PREFIX;
    let mut keys: Vec<(String, Vec<usize>)> = vec![
        (format!("{v}.cls_token"), vec![1, 1, VIT_DIM]),
        (format!("{v}.pos_embed"), vec![1, VIT_POS_TOKENS, VIT_DIM]),
        (
            format!("{v}.patch_embed.proj.weight"),
            vec![VIT_DIM, 3, 16, 16],
        ),
        (format!("{v}.patch_embed.proj.bias"), vec![VIT_DIM]),
    ];
    for b in 0..depths.vit_blocks {
        let p = format!("{v}.blocks.{b}");
        for (name, shape) in [
            ("norm1.weight", vec![VIT_DIM]),
            ("norm1.bias", vec![VIT_DIM]),
            ("attn.qkv.weight", vec![3 * VIT_DIM, VIT_DIM]),
            ("attn.qkv.bias", vec![3 * VIT_DIM]),
            ("attn.proj.weight", vec![VIT_DIM, VIT_DIM]),
            ("attn.proj.bias", vec![VIT_DIM]),
            ("norm2.weight", vec![VIT_DIM]),
            ("norm2.bias", vec![VIT_DIM]),
            ("mlp.fc1.weight", vec![VIT_MLP_DIM, VIT_DIM]),
            ("mlp.fc1.bias", vec![VIT_MLP_DIM]),
            ("mlp.fc2.weight", vec![VIT_DIM, VIT_MLP_DIM]),
            ("mlp.fc2.bias", vec![VIT_DIM]),
        ] {
            keys.push((format!("{p}.{name}"), shape));
        }
    }
    keys.push((format!("{v}.norm.weight"), vec![VIT_DIM]));
    keys.push((format!("{v}.norm.bias"), vec![VIT_DIM]));
    let d = DENOISER_PREFIX;
    let half = TIME_EMBED_DIM / 2;
    for (name, shape) in [
        ("time_embed.linear.0.weight", vec![half, TIME_EMBED_DIM]),
        ("time_embed.linear.0.bias", vec![half]),
        ("time_embed.linear.2.weight", vec![half, half]),
        ("time_embed.linear.2.bias", vec![half]),
        ("_first.weight", vec![DENOISER_DIM, DENOISER_FEED_DIM]),
        ("_first.bias", vec![DENOISER_DIM]),
    ] {
        keys.push((format!("{d}.{name}"), shape));
    }
    for l in 0..depths.trunk_layers {
        let p = format!("{d}._trunk.layers.{l}");
        for (name, shape) in [
            (
                "self_attn.in_proj_weight",
                vec![3 * DENOISER_DIM, DENOISER_DIM],
            ),
            ("self_attn.in_proj_bias", vec![3 * DENOISER_DIM]),
            (
                "self_attn.out_proj.weight",
                vec![DENOISER_DIM, DENOISER_DIM],
            ),
            ("self_attn.out_proj.bias", vec![DENOISER_DIM]),
            ("linear1.weight", vec![DENOISER_FF_DIM, DENOISER_DIM]),
            ("linear1.bias", vec![DENOISER_FF_DIM]),
            ("linear2.weight", vec![DENOISER_DIM, DENOISER_FF_DIM]),
            ("linear2.bias", vec![DENOISER_DIM]),
            ("norm1.weight", vec![DENOISER_DIM]),
            ("norm1.bias", vec![DENOISER_DIM]),
            ("norm2.weight", vec![DENOISER_DIM]),
            ("norm2.bias", vec![DENOISER_DIM]),
        ] {
            keys.push((format!("{p}.{name}"), shape));
        }
    }
    for (name, shape) in [
        ("_last.0.weight", vec![half, DENOISER_DIM]),
        ("_last.0.bias", vec![half]),
        ("_last.1.weight", vec![half]),
        ("_last.1.bias", vec![half]),
        ("_last.3.weight", vec![9, half]),
        ("_last.3.bias", vec![9]),
    ] {
        keys.push((format!("{d}.{name}"), shape));
    }
    keys
}

/// Every tensor of a PyTorch `.pth` (zip archive; the pickle is read, never executed) or
/// safetensors file, on the CPU, in its stored dtype, keys as stored.
///
/// # Errors
/// Unreadable files, unknown formats.
pub fn read_tensors(path: &Path) -> Result<Vec<(String, Tensor)>> {
    let read_err = |source| DiffusionError::CheckpointRead {
        path: path.to_owned(),
        source,
    };
    let mut magic = [0u8; 2];
    {
        use std::io::Read;
        let mut f = std::fs::File::open(path).map_err(|e| read_err(e.into()))?;
        f.read_exact(&mut magic).map_err(|e| read_err(e.into()))?;
    }
    // PyTorch ≥ 1.6 writes a zip archive ("PK"), older versions a run of pickles (protocol 2,
    // `\x80\x02`); anything else must parse as safetensors.
    if magic == [0x80, 0x02] {
        let p = path.to_owned();
        match std::panic::catch_unwind(move || read_legacy(&p)) {
            Ok(r) => r.map_err(read_err),
            Err(_) => Err(DiffusionError::MalformedCheckpoint {
                path: path.to_owned(),
            }),
        }
    } else if &magic == b"PK" {
        // candle's pickle reader panics on some malformed pickles (found by the `checkpoint`
        // fuzz target: an index out of bounds in its stack handling); a broken file is an
        // error, not a crash.
        let p = path.to_owned();
        match std::panic::catch_unwind(move || candle_core::pickle::read_all(&p)) {
            Ok(r) => r.map_err(read_err),
            Err(_) => Err(DiffusionError::MalformedCheckpoint {
                path: path.to_owned(),
            }),
        }
    } else {
        Ok(candle_core::safetensors::load(path, &Device::Cpu)
            .map_err(|_| DiffusionError::UnknownFormat {
                path: path.to_owned(),
            })?
            .into_iter()
            .collect())
    }
}

/// The first two pickles of PyTorch's legacy (pre-zip) serialisation, byte for byte: the magic
/// number `0x1950a86a20f9469cfc6c` (an 80-bit LONG1, read here as bytes: it does not fit an
/// i64) and the protocol version 1001 (BININT2).
const LEGACY_HEADER: [u8; 21] = [
    0x80, 0x02, 0x8a, 0x0a, 0x6c, 0xfc, 0x9c, 0x46, 0xf9, 0x20, 0x6a, 0xa8, 0x50, 0x19, 0x2e, 0x80,
    0x02, 0x4d, 0xe9, 0x03, 0x2e,
];

/// The tensors of a legacy `.pth` (`torch.save` before PyTorch 1.6, `_legacy_save`): three
/// small pickles (magic number, protocol version, system info), the object's pickle whose
/// tensors name their storages by key (persistent ids), a pickle of the storage keys, then per
/// key its element count (u64, little endian) and raw bytes. Nested dicts are flattened with
/// `.` (DISK's `{"extractor": state_dict}` gives `extractor.unet.…`).
fn read_legacy(path: &Path) -> candle_core::Result<Vec<(String, Tensor)>> {
    use candle_core::pickle::{Object, Stack, TensorInfo};
    use std::io::Read;
    let bad = |what: String| candle_core::Error::Msg(format!("legacy PyTorch file: {what}"));
    let mut r = std::io::BufReader::new(std::fs::File::open(path)?);
    let pickle = |r: &mut std::io::BufReader<std::fs::File>| -> candle_core::Result<Object> {
        let mut stack = Stack::empty();
        stack.read_loop(r)?;
        stack.finalize()
    };
    let mut header = [0u8; LEGACY_HEADER.len()];
    r.read_exact(&mut header)?;
    if header != LEGACY_HEADER {
        return Err(bad("no magic number and protocol 1001".into()));
    }
    let _system = pickle(&mut r)?;
    let object = pickle(&mut r)?;
    fn collect(obj: Object, prefix: &str, out: &mut Vec<TensorInfo>) -> candle_core::Result<()> {
        let Object::Dict(entries) = obj else {
            return Ok(());
        };
        for (k, v) in entries {
            let Object::Unicode(name) = k else { continue };
            let full = if prefix.is_empty() {
                name
            } else {
                format!("{prefix}.{name}")
            };
            if matches!(v, Object::Dict(_)) {
                collect(v, &full, out)?;
            } else if let Some(info) =
                v.into_tensor_info(Object::Unicode(full), Path::new("legacy"))?
            {
                out.push(info);
            }
        }
        Ok(())
    }
    let mut infos = Vec::new();
    collect(object, "", &mut infos)?;
    let keys = match pickle(&mut r)? {
        Object::List(keys) => keys
            .into_iter()
            .map(|k| match k {
                Object::Unicode(k) => Ok(k),
                other => Err(bad(format!("storage key {other:?}"))),
            })
            .collect::<candle_core::Result<Vec<_>>>()?,
        other => return Err(bad(format!("storage keys {other:?}"))),
    };
    let storage_key = |info: &TensorInfo| info.path.strip_prefix("legacy/").map(str::to_owned);
    let mut storages: HashMap<String, Vec<u8>> = HashMap::new();
    for key in keys {
        let info = infos
            .iter()
            .find(|i| storage_key(i).as_deref() == Some(key.as_str()))
            .ok_or_else(|| bad(format!("storage {key} belongs to no tensor")))?;
        let mut count = [0u8; 8];
        r.read_exact(&mut count)?;
        let bytes = usize::try_from(u64::from_le_bytes(count))
            .ok()
            .and_then(|n| n.checked_mul(info.dtype.size_in_bytes()))
            .filter(|&b| b <= 1 << 34)
            .ok_or_else(|| bad(format!("storage {key} of implausible size")))?;
        let mut data = vec![0u8; bytes];
        r.read_exact(&mut data)?;
        storages.insert(key, data);
    }
    infos
        .into_iter()
        .map(|info| {
            let key = storage_key(&info).unwrap_or_default();
            let data = storages
                .get(&key)
                .ok_or_else(|| bad(format!("no storage {key} for {}", info.name)))?;
            let layout = &info.layout;
            let size = info.dtype.size_in_bytes();
            let dims = layout.dims();
            let strides = layout.stride();
            // The elements in C order, gathered through the stored strides (a transposed
            // tensor keeps its storage's order on disk).
            let count = layout.shape().elem_count();
            let mut bytes = Vec::with_capacity(count * size);
            let mut index = vec![0usize; dims.len()];
            for _ in 0..count {
                let at = layout.start_offset()
                    + index.iter().zip(strides).map(|(i, s)| i * s).sum::<usize>() * size;
                let element = data
                    .get(at..at + size)
                    .ok_or_else(|| bad(format!("{}: a stride runs past its storage", info.name)))?;
                bytes.extend_from_slice(element);
                for d in (0..dims.len()).rev() {
                    index[d] += 1;
                    if index[d] < dims[d] {
                        break;
                    }
                    index[d] = 0;
                }
            }
            let t = Tensor::from_raw_buffer(&bytes, info.dtype, dims, &Device::Cpu)?;
            Ok((info.name, t))
        })
        .collect()
}

/// Counts `prefix.{i}.` indices among the keys: `max + 1`, or 0.
fn count_indexed(keys: &BTreeSet<String>, prefix: &str) -> usize {
    keys.iter()
        .filter_map(|k| {
            k.strip_prefix(prefix)?
                .split('.')
                .next()?
                .parse::<usize>()
                .ok()
        })
        .map(|i| i + 1)
        .max()
        .unwrap_or(0)
}

/// A checkpoint's tensors, validated against the PoseDiffusion layout.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    pub(crate) tensors: HashMap<String, Tensor>,
    depths: ModelDepths,
}

impl Checkpoint {
    /// Reads a `.pth` (zip) or safetensors file (detected from its first bytes) onto `device`
    /// and validates it.
    ///
    /// # Errors
    /// Unreadable files, unknown formats, keys or shapes that do not match the layout.
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let tensors = read_tensors(path)?
            .into_iter()
            .map(|(k, t)| Ok((k, t.to_device(device)?)))
            .collect::<Result<Vec<_>>>()?;
        Self::from_tensors(tensors)
    }

    /// Validates named tensors (e.g. a state dict already in memory).
    ///
    /// # Errors
    /// Missing, unexpected or mis-shaped keys, all listed in one error.
    pub fn from_tensors(tensors: impl IntoIterator<Item = (String, Tensor)>) -> Result<Self> {
        let tensors: HashMap<String, Tensor> = tensors
            .into_iter()
            .map(|(k, t)| {
                (
                    k.strip_prefix(DDP_PREFIX).map(str::to_owned).unwrap_or(k),
                    t,
                )
            })
            .collect();
        let keys: BTreeSet<String> = tensors.keys().cloned().collect();
        let depths = ModelDepths {
            vit_blocks: count_indexed(&keys, &format!("{VIT_PREFIX}.blocks.")),
            trunk_layers: count_indexed(&keys, &format!("{DENOISER_PREFIX}._trunk.layers.")),
        };
        let mut problems = Vec::new();
        if depths.vit_blocks == 0 {
            problems.push(format!("no ViT blocks ({VIT_PREFIX}.blocks.*)"));
        }
        if depths.trunk_layers == 0 {
            problems.push(format!(
                "no denoiser layers ({DENOISER_PREFIX}._trunk.layers.*)"
            ));
        }
        let mut expected: HashMap<String, Vec<usize>> =
            expected_parameters(depths).into_iter().collect();
        let buffers: Vec<String> = SCHEDULE_BUFFERS
            .iter()
            .map(|b| format!("{SCHEDULE_PREFIX}.{b}"))
            .collect();
        let buffers_present = buffers.iter().filter(|b| keys.contains(*b)).count();
        if buffers_present > 0 {
            for b in &buffers {
                expected.insert(b.clone(), vec![TIMESTEPS]);
            }
        }
        let mut sorted: Vec<_> = expected.iter().collect();
        sorted.sort();
        for (key, shape) in sorted {
            match tensors.get(key) {
                None => problems.push(format!("missing: {key} {shape:?}")),
                Some(t) if t.dims() != shape.as_slice() => {
                    problems.push(format!(
                        "wrong shape: {key} is {:?}, expected {shape:?}",
                        t.dims()
                    ));
                }
                Some(t)
                    if !matches!(
                        t.dtype(),
                        DType::F16 | DType::BF16 | DType::F32 | DType::F64
                    ) =>
                {
                    problems.push(format!("wrong dtype: {key} is {:?}", t.dtype()));
                }
                Some(_) => {}
            }
        }
        for key in &keys {
            if !expected.contains_key(key) {
                problems.push(format!("unexpected: {key} {:?}", tensors[key].dims()));
            }
        }
        if !problems.is_empty() {
            return Err(DiffusionError::CheckpointLayout { problems });
        }
        let mut bad: Vec<String> = Vec::new();
        let mut sorted: Vec<&String> = tensors.keys().collect();
        sorted.sort();
        for key in sorted {
            let t = &tensors[key];
            if !crate::finite::all_finite(t)? {
                let values: Vec<f64> = t.flatten_all()?.to_dtype(DType::F64)?.to_vec1()?;
                let n = values.iter().filter(|v| !v.is_finite()).count();
                bad.push(format!("{key} ({n} of {})", values.len()));
            }
        }
        if !bad.is_empty() {
            return Err(DiffusionError::NonFiniteWeights { keys: bad });
        }
        Ok(Self { tensors, depths })
    }

    /// The depths read from the keys.
    pub fn depths(&self) -> ModelDepths {
        self.depths
    }

    /// A tensor by its (un-prefixed) key.
    pub fn get(&self, key: &str) -> Option<&Tensor> {
        self.tensors.get(key)
    }

    /// Whether the schedule buffers are stored.
    pub fn has_schedule(&self) -> bool {
        self.tensors
            .contains_key(&format!("{SCHEDULE_PREFIX}.betas"))
    }

    /// A `VarBuilder` over the tensors, converting to `dtype` on `device`.
    pub fn var_builder(&self, dtype: DType, device: &Device) -> VarBuilder<'static> {
        VarBuilder::from_tensors(self.tensors.clone(), dtype, device)
    }

    /// The tensors by official key (un-prefixed).
    pub fn tensor_map(&self) -> &HashMap<String, Tensor> {
        &self.tensors
    }

    /// Writes the tensors (un-prefixed keys, stored dtypes) as safetensors: the `.pth` →
    /// safetensors converter, and the trainer's checkpoints.
    ///
    /// # Errors
    /// I/O errors.
    pub fn save_safetensors(&self, path: &Path) -> Result<()> {
        candle_core::safetensors::save(&self.tensors, path)?;
        Ok(())
    }
}
