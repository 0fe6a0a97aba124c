//! The linear layers' matrix products on this CPU: candle's matmul (the `gemm` crate) against
//! faer's product with the weight row-major (as PyTorch stores it) and column-major (as
//! `posediff_diffusion::linear::Linear` keeps it), for the ViT's and the denoiser's shapes
//! (`rows × in → out`; ViT rows = 197 tokens × images, denoiser rows = frames).
//!
//! `cargo run --release -p posediff-diffusion --example gemm_probe`

use std::time::Instant;

use candle_core::{Device, Tensor};
use faer::{Accum, Mat, MatRef, Par};

/// Seconds per call of `f`, after one warm-up call.
fn per_call(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    let start = Instant::now();
    for _ in 0..reps {
        f();
    }
    start.elapsed().as_secs_f64() / reps as f64
}

fn main() -> anyhow::Result<()> {
    let shapes = [
        (788usize, 384usize, 1152usize),
        (788, 384, 1536),
        (788, 1536, 384),
        (788, 384, 384),
        (3940, 384, 1536),
        (20, 512, 1536),
        (20, 512, 1024),
        (20, 1024, 512),
        (100, 512, 1536),
        (100, 1024, 512),
    ];
    let threads = posediff_diffusion::threads();
    eprintln!(
        "| rows × in → out | candle | faer, W row-major | faer, W column-major | GFLOP/s (best) |"
    );
    eprintln!("|---|---:|---:|---:|---:|");
    for (m, k, n) in shapes {
        let x = Tensor::randn(0f32, 1f32, (m, k), &Device::Cpu)?;
        let w = Tensor::randn(0f32, 1f32, (n, k), &Device::Cpu)?;
        let wt = w.t()?;
        let reps = (2e10 / (2.0 * (m * k * n) as f64)).clamp(3.0, 2000.0) as usize;
        let candle = per_call(reps, || {
            let _ = x.matmul(&wt);
        });
        let xv: Vec<f32> = x.flatten_all()?.to_vec1()?;
        let wv: Vec<f32> = w.flatten_all()?.to_vec1()?;
        let wtv: Vec<f32> = wt.contiguous()?.flatten_all()?.to_vec1()?;
        // outᵀ (n × m, column-major) = W (n × k) · xᵀ (k × m, column-major).
        let xr = MatRef::from_column_major_slice(&xv, k, m);
        let mut out = Mat::<f32>::zeros(n, m);
        let mut faer_with = |lhs: MatRef<'_, f32>| {
            per_call(reps, || {
                faer::linalg::matmul::matmul(
                    out.as_mut(),
                    Accum::Replace,
                    lhs,
                    xr,
                    1.0,
                    Par::rayon(threads),
                );
            })
        };
        let row = faer_with(MatRef::from_row_major_slice(&wv, n, k));
        let col = faer_with(MatRef::from_column_major_slice(&wtv, n, k));
        let best = candle.min(row).min(col);
        eprintln!(
            "| {m} × {k} → {n} | {:.3} ms | {:.3} ms | {:.3} ms | {:.0} |",
            candle * 1e3,
            row * 1e3,
            col * 1e3,
            2.0 * (m * k * n) as f64 / best / 1e9
        );
    }
    Ok(())
}
