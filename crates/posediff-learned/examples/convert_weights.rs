//! `convert_weights IN OUT`: a released `.pth` state dict (ALIKED, DISK or LightGlue) to safetensors,
//! checked to load as its network first. Used by `cargo xtask weights`.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use candle_core::Device;
use posediff_learned::weights::convert_to_safetensors;
use posediff_learned::{Aliked, Disk, LightGlue};

fn main() -> Result<()> {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [src, dst] = args.as_slice() else {
        bail!("usage: convert_weights IN.pth OUT.safetensors");
    };
    let n = convert_to_safetensors(src, dst)
        .with_context(|| format!("converting {}", src.display()))?;
    // The output must load as the network its name says.
    let name = dst
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    if name.contains("lightglue") {
        LightGlue::load(dst, &Device::Cpu)?;
    } else if name.starts_with("disk") {
        Disk::load(dst)?;
    } else {
        Aliked::load(dst, &Device::Cpu)?;
    }
    eprintln!("{} -> {} ({n} tensors)", src.display(), dst.display());
    Ok(())
}
