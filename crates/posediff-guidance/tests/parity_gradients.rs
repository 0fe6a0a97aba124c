//! The GGS objective and its analytic gradient against the official autograd
//! (`reference/full/geometry_io.safetensors`: losses and gradients of all four update modes,
//! the first iteration's clip norms and one clipped SGD step) and against central finite
//! differences, including frames whose focal is clamped.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff_fixtures::{SafetensorsFixture, assert_close, fixture_path};
use posediff_geometry::{ImageSize, PoseEncoding};
use posediff_guidance::{GgsConfig, GgsSolver, MatchSet, SampsonObjective, UpdateMask};

fn fixture() -> SafetensorsFixture {
    SafetensorsFixture::open(&fixture_path("reference/full/geometry_io.safetensors"))
}

fn encodings(fx: &SafetensorsFixture, name: &str) -> Vec<PoseEncoding> {
    fx.rows::<9>(name).into_iter().map(PoseEncoding).collect()
}

fn matches(fx: &SafetensorsFixture) -> MatchSet {
    MatchSet::new(
        6,
        &fx.rows::<2>("kp1"),
        &fx.rows::<2>("kp2"),
        &fx.index_pairs("i12"),
    )
    .unwrap()
}

fn size224() -> ImageSize {
    ImageSize::new(224, 224).unwrap()
}

/// Twice the measured float32 noise floor of the reference gradients, relative to their
/// largest entry (see `losses_and_gradients_match_official_autograd`).
const F32_GRADIENT_NOISE: f64 = 2e-3;

const MODES: [(&str, UpdateMask); 4] = [
    ("all", UpdateMask::ALL),
    ("R_only", UpdateMask::ROTATION),
    ("T_only", UpdateMask::TRANSLATION),
    ("FL_only", UpdateMask::FOCAL),
];

#[test]
fn losses_and_gradients_match_official_autograd() {
    let fx = fixture();
    let m = matches(&fx);
    let enc = encodings(&fx, "pose_encoding");
    let mut obj = SampsonObjective::new(&m, size224(), 10.0).unwrap();
    let eval = obj.evaluate(&enc).unwrap();
    assert_eq!(eval.n_valid, fx.tensor("sampson_valid_lt10").len());
    let mut grad = vec![[0.0; 9]; 6];
    // Every mode's gradient is a block of the full one (the others are detached), so the noise
    // scale is the full gradient's largest entry.
    let scale = fx
        .tensor("grad_all")
        .data
        .iter()
        .fold(0.0f64, |a, v| a.max(v.abs()));
    for (name, mask) in MODES {
        assert_close(
            &format!("loss_{name}"),
            &[eval.loss],
            &fx.tensor(&format!("loss_{name}")).data,
            0.0,
            1e-4,
        );
        obj.gradient(mask, &mut grad).unwrap();
        let ours: Vec<f64> = grad.iter().flatten().copied().collect();
        let expected = fx.tensor(&format!("grad_{name}"));
        // The reference is float32 autograd. Inlier matches have x2ᵀ F x1 at the float32
        // cancellation level, and their gradient is proportional to it: the same formulas
        // evaluated in float32 and float64 (numpy, same data) differ by up to 1.04e-3 of the
        // largest gradient entry (grad_all frame 3, q_z: −3.681 in float32, −3.709 in float64,
        // reference −3.680). Compare at twice that noise floor, and exactly where autograd
        // gives exact zeros (masks, clamped focals).
        assert_close(
            &format!("grad_{name}"),
            &ours,
            &expected.data,
            F32_GRADIENT_NOISE * scale,
            0.0,
        );
        for (k, (o, e)) in ours.iter().zip(&expected.data).enumerate() {
            assert_eq!(
                *e == 0.0,
                *o == 0.0,
                "grad_{name}[{k}]: zero pattern differs ({o} vs {e})"
            );
        }
    }
}

#[test]
fn first_iteration_clip_norms_and_sgd_step_match_official() {
    let fx = fixture();
    let m = matches(&fx);
    let mut enc = encodings(&fx, "pose_encoding");
    let mut solver = GgsSolver::new(&m, GgsConfig::default()).unwrap();
    let mut report = posediff_guidance::GgsReport::default();
    solver
        .optimize_phase(&mut enc, UpdateMask::ALL, 1, 0, Some(&mut report))
        .unwrap();
    let it = report.iterations[0];
    assert_close(
        "clip_max_norm",
        &[it.max_norm],
        &fx.tensor("clip_max_norm").data,
        0.0,
        1e-6,
    );
    // The norm of the reference gradient carries its float32 noise (2.7e-4 relative here).
    assert_close(
        "clip_total_norm",
        &[it.grad_norm],
        &fx.tensor("clip_total_norm").data,
        0.0,
        F32_GRADIENT_NOISE,
    );
    let after: Vec<f64> = enc.iter().flat_map(|e| e.0).collect();
    assert_close(
        "after_one_sgd_step",
        &after,
        &fx.tensor("after_one_sgd_step").data,
        1e-6,
        0.0,
    );
}

/// Central finite differences of the loss with the valid set frozen at the evaluation point.
fn finite_difference_check(enc: &[PoseEncoding], m: &MatchSet, mask: UpdateMask, sampson_max: f64) {
    let mut obj = SampsonObjective::new(m, size224(), sampson_max).unwrap();
    let base = obj.evaluate(enc).unwrap();
    let mut grad = vec![[0.0; 9]; enc.len()];
    obj.gradient(mask, &mut grad).unwrap();
    let h = 1e-6;
    for (i, row) in grad.iter().enumerate() {
        for (c, &g) in row.iter().enumerate() {
            let active = match c {
                0..=2 => mask.translation,
                3..=6 => mask.rotation,
                _ => mask.focal,
            };
            let mut plus = enc.to_vec();
            let mut minus = enc.to_vec();
            plus[i].0[c] += h;
            minus[i].0[c] -= h;
            let lp = obj.evaluate(&plus).unwrap();
            let lm = obj.evaluate(&minus).unwrap();
            // The dropped set must not change across the stencil for the difference to hold.
            assert_eq!((lp.n_valid, lm.n_valid), (base.n_valid, base.n_valid));
            let fd = if active {
                (lp.loss - lm.loss) / (2.0 * h)
            } else {
                0.0
            };
            assert!(
                (g - fd).abs() <= 1e-5 * (1.0 + fd.abs()),
                "frame {i} entry {c} ({mask:?}): analytic {g}, finite difference {fd}"
            );
        }
    }
}

#[test]
fn gradients_match_central_finite_differences_in_every_mode() {
    let fx = fixture();
    let m = matches(&fx);
    // Frames 4 and 5 of the fixture have clamped focals (zero focal gradient).
    let enc = encodings(&fx, "pose_encoding");
    for (_, mask) in MODES {
        finite_difference_check(&enc, &m, mask, 10.0);
        // And with every match valid (no dropping).
        finite_difference_check(&enc, &m, mask, f64::INFINITY);
    }
}

#[test]
fn unmatched_or_invalid_input_is_an_error_not_nan() {
    let fx = fixture();
    let m = matches(&fx);
    let mut obj = SampsonObjective::new(&m, size224(), 10.0).unwrap();
    let mut enc = encodings(&fx, "pose_encoding");
    assert!(obj.evaluate(&enc[..5]).is_err());
    enc[2].0[3..7].copy_from_slice(&[0.0; 4]);
    assert!(obj.evaluate(&enc).is_err());
    enc[2].0[3] = f64::NAN;
    assert!(obj.evaluate(&enc).is_err());
    assert!(SampsonObjective::new(&m, size224(), 0.0).is_err());
}
