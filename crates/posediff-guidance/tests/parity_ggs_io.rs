//! One whole official GGS call (`reference/full/ggs_io.safetensors`): the five phase outputs,
//! the final posterior mean and the 700-iteration loss and valid-count traces.
//!
//! What agreement is possible. The README expects "~1e-5 relative agreement of the outputs"
//! for this iterative SGD. An independent re-run of the same algorithm (numpy, float32 and
//! float64, same data) shows where that holds and where it cannot:
//!
//! - every step is clipped to `alpha·‖μ‖`, so float rounding in the gradient direction (the
//!   reference's float32 gradient carries ~1e-3 relative noise, see `parity_gradients.rs`)
//!   accumulates: the first ~60 loss values agree to 1e-5, later ones drift by 1e-4..1e-3;
//! - in phase 4 (translation only) one match sits exactly at the 10 px² drop threshold and the
//!   reference's valid count flips between 535 and 536 from one iteration to the next; which side
//!   it falls on is decided by rounding, so the loss jumps by ~0.018 at different iterations.
//!   float32 numpy deviates from the reference by 7.4e-4 there, float64 by 6.9e-4.
//!
//! Hence the checks: teacher-forced phases (each started from the reference's input to that
//! phase) at 2e-5 of max|μ| where the valid set is stable (phases 1, 2, 3, 5: measured 8.3e-6,
//! 1.3e-7, 3.3e-7, 1.7e-5) and at 3e-4 for phase 4 (measured 2.2e-4, float32 numpy 2.4e-4); the
//! first loss of every phase at 1e-5; the free-running call with identical valid counts through
//! phases 1 and 2 (the first difference comes at iteration 365), counts within ±2 after, the
//! first 50 losses at 1e-5, and the final mean at 3e-4 of max|μ| (measured 9.1e-5).

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff_fixtures::{SafetensorsFixture, assert_close, shared_path};
use posediff_geometry::PoseEncoding;
use posediff_guidance::{GgsConfig, GgsReport, GgsSolver, MatchSet, geometry_guided_sampling};

/// Phase outputs of the reference, in order, preceded by the input.
const STAGES: [&str; 6] = [
    "model_mean_in",
    "phase1_all_out",
    "phase2_fl_out",
    "phase3_R_out",
    "phase4_T_out",
    "phase5_all_out",
];

/// Teacher-forced tolerance per phase, relative to max|μ| (see the module docs).
const PHASE_TOLERANCE: [f64; 5] = [2e-5, 2e-5, 2e-5, 3e-4, 2e-5];

fn fixture() -> SafetensorsFixture {
    SafetensorsFixture::open(&shared_path("reference/full/ggs_io.safetensors"))
}

fn encodings(fx: &SafetensorsFixture, name: &str) -> Vec<PoseEncoding> {
    fx.rows::<9>(name).into_iter().map(PoseEncoding).collect()
}

fn matches(fx: &SafetensorsFixture) -> MatchSet {
    assert_eq!(fx.tensor("img_shape_NCHW").data, [5.0, 3.0, 224.0, 224.0]);
    MatchSet::new(
        5,
        &fx.rows::<2>("kp1"),
        &fx.rows::<2>("kp2"),
        &fx.index_pairs("i12"),
    )
    .unwrap()
}

fn flat(e: &[PoseEncoding]) -> Vec<f64> {
    e.iter().flat_map(|e| e.0).collect()
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |a, x| a.max(x.abs()))
}

#[test]
fn each_phase_teacher_forced_matches_the_official_phase() {
    let fx = fixture();
    let m = matches(&fx);
    let mut solver = GgsSolver::new(&m, GgsConfig::default()).unwrap();
    let loss_trace = fx.tensor("loss_trace").data;
    let mut start = 0;
    for (k, (mask, iterations)) in GgsConfig::default().phases().into_iter().enumerate() {
        let mut mean = encodings(&fx, STAGES[k]);
        let mut report = GgsReport::default();
        assert!(
            solver
                .optimize_phase(&mut mean, mask, iterations, k, Some(&mut report))
                .unwrap()
        );
        let first = report.iterations[0].evaluation.loss;
        assert_close(
            &format!("phase {} first loss", k + 1),
            &[first],
            &[loss_trace[start]],
            0.0,
            1e-5,
        );
        start += iterations;
        let expected = fx.tensor(STAGES[k + 1]).data;
        let atol = PHASE_TOLERANCE[k] * max_abs(&expected);
        assert_close(STAGES[k + 1], &flat(&mean), &expected, atol, 0.0);
    }
}

#[test]
fn phase_four_chatters_at_the_drop_threshold_in_the_reference() {
    // The reason phase 4 gets a wider tolerance: its valid count alternates.
    let fx = fixture();
    let valid = fx.tensor("n_valid_trace").data;
    let flips = valid[400..500].windows(2).filter(|w| w[0] != w[1]).count();
    assert!(flips >= 20, "only {flips} flips");
}

#[test]
fn the_whole_call_follows_the_official_trajectory() {
    let fx = fixture();
    let m = matches(&fx);
    let mut mean = encodings(&fx, "model_mean_in");
    let report = geometry_guided_sampling(&mut mean, &m, GgsConfig::default()).unwrap();
    assert!(report.stopped_phases.is_empty());
    assert_eq!(report.iterations.len(), 700);
    assert_eq!(report.phase_outputs.len(), 5);

    let n_valid: Vec<f64> = report
        .iterations
        .iter()
        .map(|r| r.evaluation.n_valid as f64)
        .collect();
    let expected_valid = fx.tensor("n_valid_trace").data;
    assert_eq!(
        n_valid[..300],
        expected_valid[..300],
        "valid counts through phase 2"
    );
    for (k, (a, b)) in n_valid.iter().zip(&expected_valid).enumerate() {
        assert!((a - b).abs() <= 2.0, "iteration {k}: {a} valid vs {b}");
    }
    let loss: Vec<f64> = report
        .iterations
        .iter()
        .map(|r| r.evaluation.loss)
        .collect();
    let print: Vec<f64> = report
        .iterations
        .iter()
        .map(|r| r.evaluation.print_mean)
        .collect();
    let loss_trace = fx.tensor("loss_trace").data;
    assert_close(
        "loss_trace[..50]",
        &loss[..50],
        &loss_trace[..50],
        0.0,
        1e-5,
    );
    assert_close(
        "sampson_print_trace[..50]",
        &print[..50],
        &fx.tensor("sampson_print_trace").data[..50],
        0.0,
        1e-5,
    );
    assert_close("final loss", &loss[699..], &loss_trace[699..], 0.0, 1e-3);
    let expected = fx.tensor("model_mean_out").data;
    assert_close(
        "model_mean_out",
        &flat(&mean),
        &expected,
        3e-4 * max_abs(&expected),
        0.0,
    );
    assert_eq!(flat(&report.phase_outputs[4]), flat(&mean));
}
