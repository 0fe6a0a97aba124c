//! Converts an official PoseDiffusion checkpoint (`.pth`, or safetensors) into a validated
//! safetensors file with the official keys (any `module.` prefix removed, dtypes kept):
//!
//! ```text
//! cargo xtask convert-checkpoint co3d_model_Apr16.pth co3d_model_Apr16.safetensors
//! ```
#![allow(clippy::print_stdout)]

use std::path::PathBuf;

use anyhow::{Context, bail};
use candle_core::Device;
use posediff_diffusion::Checkpoint;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output] = args.as_slice() else {
        bail!("usage: convert_checkpoint <input.pth|.safetensors> <output.safetensors>");
    };
    let (input, output) = (PathBuf::from(input), PathBuf::from(output));
    let ckpt = Checkpoint::load(&input, &Device::Cpu)
        .with_context(|| format!("loading {}", input.display()))?;
    ckpt.save_safetensors(&output)
        .with_context(|| format!("writing {}", output.display()))?;
    let d = ckpt.depths();
    println!(
        "{} -> {}: ViT {} blocks, denoiser {} layers, schedule buffers {}",
        input.display(),
        output.display(),
        d.vit_blocks,
        d.trunk_layers,
        if ckpt.has_schedule() {
            "stored"
        } else {
            "absent (computed)"
        }
    );
    Ok(())
}
