//! Tile products against faer's F32 product on the shapes of LightGlue's layers, one thread:
//! `cargo run --profile ci -p posediff-amx --example amx_speed`.
#![allow(clippy::print_stdout, missing_docs)]

use std::time::Instant;

use faer::{Accum, MatMut, MatRef, Par};
use posediff_amx::{PackedA, PackedB, Split, available, matmul};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("AMX available: {}", available());
    let shapes = [
        ("attention scores, 32 rows", 32, 64, 2048),
        ("attention values, 32 rows", 32, 2048, 64),
        ("linear 2048 x 256 -> 768", 2048, 256, 768),
        ("linear 2048 x 512 -> 512", 2048, 512, 512),
    ];
    for (name, m, k, n) in shapes {
        let a: Vec<f32> = (0..m * k)
            .map(|i| ((i * 7919) % 1000) as f32 / 500.0 - 1.0)
            .collect();
        let b: Vec<f32> = (0..k * n)
            .map(|i| ((i * 104729) % 997) as f32 / 498.0 - 1.0)
            .collect();
        let flop = 2.0 * (m * k * n) as f64;
        let reps = (2e10 / flop).max(1.0) as usize;
        let mut c = vec![0f32; m * n];
        let t = Instant::now();
        for _ in 0..reps {
            let ct = MatMut::from_column_major_slice_mut(&mut c, n, m);
            let bt = MatRef::from_column_major_slice(&b, n, k);
            let at = MatRef::from_column_major_slice(&a, k, m);
            faer::linalg::matmul::matmul(ct, Accum::Replace, bt, at, 1.0, Par::Seq);
        }
        let f32_s = t.elapsed().as_secs_f64() / reps as f64;
        print!("{name}: faer F32 {:.0} GFLOP/s", flop / f32_s / 1e9);
        for sp in [Split::Two, Split::Three] {
            let (mut pa, mut pb) = (PackedA::new(sp), PackedB::new(sp));
            let t = Instant::now();
            for _ in 0..reps {
                pa.pack(&a, m, k, k)?;
            }
            let pack_a = t.elapsed().as_secs_f64() / reps as f64;
            let t = Instant::now();
            for _ in 0..reps {
                pb.pack(&b, k, n, n)?;
            }
            let pack_b = t.elapsed().as_secs_f64() / reps as f64;
            let t = Instant::now();
            for _ in 0..reps {
                matmul(&mut c, n, &pa, 0..m, &pb, false)?;
            }
            let mm = t.elapsed().as_secs_f64() / reps as f64;
            print!(
                "; {sp:?}: product {:.0} GFLOP/s ({:.1}x), pack A {:.0}%, pack B {:.0}% of F32's time",
                flop / mm / 1e9,
                f32_s / mm,
                100.0 * pack_a / f32_s,
                100.0 * pack_b / f32_s
            );
        }
        println!();
    }
    Ok(())
}
