//! PyTorch's `F.interpolate` with a `scale_factor`, as separable interpolation matrices.
//!
//! With a scale factor `s` the output length is `floor(in · s)` and output index `d` samples the
//! source at `src = (d + 0.5)/s − 0.5` (not `in/out`): for `s = 1/3` on 224 px the stride is
//! exactly 3.0, not 224/74. Bilinear clamps `src` at 0 and the upper neighbour at `in − 1`;
//! bicubic (A = −0.75) does not clamp `src` but clamps each of its four taps to `[0, in − 1]`.
//! The matrices are `out × in`; an image is resized as `M_h · X · M_wᵀ`.

/// Output length of `F.interpolate(scale_factor = s)`.
pub fn scaled_len(len: usize, scale_factor: f64) -> usize {
    (len as f64 * scale_factor).floor() as usize
}

/// Bilinear (`align_corners=False`) interpolation matrix, row-major `out × in`.
pub fn bilinear_matrix(len_in: usize, len_out: usize, scale_factor: f64) -> Vec<f64> {
    let scale = 1.0 / scale_factor;
    let mut m = vec![0.0; len_out * len_in];
    for d in 0..len_out {
        let src = (scale * (d as f64 + 0.5) - 0.5).max(0.0);
        let i0 = (src.floor() as usize).min(len_in - 1);
        let i1 = (i0 + 1).min(len_in - 1);
        let l1 = src - i0 as f64;
        m[d * len_in + i0] += 1.0 - l1;
        m[d * len_in + i1] += l1;
    }
    m
}

/// The cubic convolution coefficient of PyTorch (`A = −0.75`) at distance `x`.
fn cubic_weight(x: f64) -> f64 {
    const A: f64 = -0.75;
    let x = x.abs();
    if x <= 1.0 {
        ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
    } else if x < 2.0 {
        ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A
    } else {
        0.0
    }
}

/// Bicubic (`align_corners=False`, A = −0.75, border-clamped taps) interpolation matrix,
/// row-major `out × in`.
pub fn bicubic_matrix(len_in: usize, len_out: usize, scale_factor: f64) -> Vec<f64> {
    let scale = 1.0 / scale_factor;
    let mut m = vec![0.0; len_out * len_in];
    let last = len_in as i64 - 1;
    for d in 0..len_out {
        let src = scale * (d as f64 + 0.5) - 0.5;
        let i = src.floor();
        let t = src - i;
        let weights = [
            cubic_weight(t + 1.0),
            cubic_weight(t),
            cubic_weight(1.0 - t),
            cubic_weight(2.0 - t),
        ];
        for (k, w) in weights.iter().enumerate() {
            let tap = (i as i64 - 1 + k as i64).clamp(0, last) as usize;
            m[d * len_in + tap] += w;
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_one_is_the_identity() {
        let m = bilinear_matrix(5, 5, 1.0);
        for i in 0..5 {
            for j in 0..5 {
                assert_eq!(m[i * 5 + j], if i == j { 1.0 } else { 0.0 });
            }
        }
    }

    #[test]
    fn a_third_samples_with_stride_three() {
        assert_eq!(scaled_len(224, 1.0 / 3.0), 74);
        let m = bilinear_matrix(224, 74, 1.0 / 3.0);
        // Output d samples source 3d + 1 exactly.
        for d in 0..74 {
            assert!((m[d * 224 + 3 * d + 1] - 1.0).abs() < 1e-12, "row {d}");
        }
    }

    #[test]
    fn rows_sum_to_one() {
        for m in [
            bicubic_matrix(14, 7, 7.1 / 14.0),
            bicubic_matrix(14, 4, 4.1 / 14.0),
            bilinear_matrix(224, 112, 0.5),
        ] {
            let n_in = if m.len() == 112 * 224 { 224 } else { 14 };
            for row in m.chunks(n_in) {
                assert!((row.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            }
        }
    }
}
