//! Procedural solid noise: hashed-lattice value noise and its fractal sum. Solid (3-D) textures
//! need no texture coordinates and look the same from every view, which is what matching needs.

use nalgebra::Vector3;

/// A 64-bit mix of three lattice coordinates and a seed (splitmix64 finaliser).
fn hash(x: i64, y: i64, z: i64, seed: u64) -> u64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 30;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 27;
    h = h.wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^ (h >> 31)
}

fn lattice(x: i64, y: i64, z: i64, seed: u64) -> f64 {
    (hash(x, y, z, seed) >> 11) as f64 / (1u64 << 53) as f64
}

fn smooth(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// Value noise in `[0, 1]` at `p` (lattice spacing 1), smooth (quintic) interpolation.
pub fn value(p: &Vector3<f64>, seed: u64) -> f64 {
    let (fx, fy, fz) = (p.x.floor(), p.y.floor(), p.z.floor());
    let (ix, iy, iz) = (fx as i64, fy as i64, fz as i64);
    let (tx, ty, tz) = (smooth(p.x - fx), smooth(p.y - fy), smooth(p.z - fz));
    let mut acc = 0.0;
    for (dz, wz) in [(0, 1.0 - tz), (1, tz)] {
        for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
            for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                acc += wx * wy * wz * lattice(ix + dx, iy + dy, iz + dz, seed);
            }
        }
    }
    acc
}

/// Fractal sum of `octaves` value-noise octaves (frequency ×2, amplitude ×`gain`), in `[0, 1]`.
pub fn fbm(p: &Vector3<f64>, octaves: u32, gain: f64, seed: u64) -> f64 {
    let (mut sum, mut norm, mut amp, mut freq) = (0.0, 0.0, 1.0, 1.0);
    for o in 0..octaves {
        sum += amp * value(&(p * freq), seed.wrapping_add(u64::from(o)));
        norm += amp;
        amp *= gain;
        freq *= 2.0;
    }
    if norm > 0.0 { sum / norm } else { 0.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_deterministic_bounded_and_continuous() {
        let p = Vector3::new(1.3, -2.7, 0.4);
        assert_eq!(value(&p, 7), value(&p, 7));
        assert_ne!(value(&p, 7), value(&p, 8));
        for k in 0..200 {
            let q = Vector3::new(k as f64 * 0.37, -(k as f64) * 0.11, 0.5 * k as f64);
            let v = fbm(&q, 5, 0.5, 3);
            assert!((0.0..=1.0).contains(&v));
            let near = fbm(&(q + Vector3::new(1e-6, 0.0, 0.0)), 5, 0.5, 3);
            assert!((v - near).abs() < 1e-4);
        }
    }
}
