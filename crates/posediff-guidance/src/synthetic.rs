//! Synthetic GGS problems with known cameras, for benchmarks, examples and tests: cameras on a
//! ring around the origin looking at it (official pose encodings at the 224 crop), random points
//! near the origin, their projections as matches for every pair `i < j` with pixel noise, and a
//! perturbed initial posterior mean.
//!
//! Deterministic for a seed (a small xorshift generator: no dependency on `rand`).

use nalgebra::{Matrix3, Point3, Vector3};
use posediff_geometry::{Camera, ImageSize, Intrinsics, Pose, PoseEncoding, QuaternionSign};

use crate::error::Result;
use crate::matches::MatchSet;

/// A synthetic problem: ground truth, matches and a perturbed start.
#[derive(Debug, Clone)]
pub struct SyntheticProblem {
    /// Ground-truth encodings (224 crop, NDC focal 2.0).
    pub ground_truth: Vec<PoseEncoding>,
    /// The ground truth plus noise (σ 0.05 on T and q, 0.03 on log f).
    pub initial: Vec<PoseEncoding>,
    /// Matches of every pair `i < j`.
    pub matches: MatchSet,
}

/// xorshift64* — enough for reproducible synthetic data.
struct Rng(u64);

impl Rng {
    fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal by Box–Muller.
    fn normal(&mut self) -> f64 {
        let u = self.next_f64().max(1e-300);
        let v = self.next_f64();
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

fn look_at(center: Vector3<f64>) -> Pose {
    let z = (-center).normalize();
    let x = Vector3::z().cross(&z).normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    Pose::from_rotation_centre(r, center)
}

/// A ring of `n_frames` cameras (radius 3, varying height), `matches_per_pair` projected points
/// per pair `i < j` with `pixel_noise` px of noise on each side, seeded.
///
/// # Errors
/// Fewer than two frames.
pub fn ring_problem(
    n_frames: usize,
    matches_per_pair: usize,
    pixel_noise: f64,
    seed: u64,
) -> Result<SyntheticProblem> {
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let side = 224;
    let size = ImageSize::new(side, side)?;
    let focal_ndc = 2.0;
    let half = f64::from(side) / 2.0;
    let k = Intrinsics::new(focal_ndc * half, focal_ndc * half, half, half)?;
    let cameras: Vec<Camera> = (0..n_frames)
        .map(|i| {
            let a = std::f64::consts::TAU * i as f64 / n_frames as f64 * 0.7;
            let center = Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.5 + 0.3 * (3.0 * a).sin());
            Camera::new(k, look_at(center), size)
        })
        .collect();
    let ground_truth = cameras
        .iter()
        .map(|c| PoseEncoding::from_camera(c, QuaternionSign::LargestComponentPositive))
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let initial = ground_truth
        .iter()
        .map(|e| {
            let mut x = e.0;
            for (c, v) in x.iter_mut().enumerate() {
                *v += rng.normal() * if c < 7 { 0.05 } else { 0.03 };
            }
            PoseEncoding(x)
        })
        .collect();
    let (mut kp1, mut kp2, mut frames) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..n_frames {
        for j in i + 1..n_frames {
            let mut made = 0;
            while made < matches_per_pair {
                let x = Point3::new(rng.normal() * 0.6, rng.normal() * 0.6, rng.normal() * 0.6);
                let (Some(a), Some(b)) = (cameras[i].project(&x), cameras[j].project(&x)) else {
                    continue;
                };
                kp1.push([
                    a.x + pixel_noise * rng.normal(),
                    a.y + pixel_noise * rng.normal(),
                ]);
                kp2.push([
                    b.x + pixel_noise * rng.normal(),
                    b.y + pixel_noise * rng.normal(),
                ]);
                frames.push((i, j));
                made += 1;
            }
        }
    }
    Ok(SyntheticProblem {
        ground_truth,
        initial,
        matches: MatchSet::new(n_frames, &kp1, &kp2, &frames)?,
    })
}
