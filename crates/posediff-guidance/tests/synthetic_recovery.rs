//! GGS does what it is for: on a synthetic ring with exact matches it lowers the Sampson loss and
//! brings the relative poses closer to the truth, whatever the seed.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff_geometry::{ImageSize, Pose, PoseEncoding};
use posediff_guidance::synthetic::ring_problem;
use posediff_guidance::{GgsConfig, GgsSolver};
use posediff_metrics::relative_pose_errors;

fn poses(enc: &[PoseEncoding]) -> Vec<Pose> {
    let size = ImageSize::new(224, 224).unwrap();
    enc.iter()
        .map(|e| e.to_camera(size).unwrap().cam_from_world)
        .collect()
}

fn mean_rotation_error(gt: &[PoseEncoding], est: &[PoseEncoding]) -> f64 {
    let pairs = relative_pose_errors(&poses(gt), &poses(est)).unwrap();
    pairs.iter().map(|p| p.rotation_deg).sum::<f64>() / pairs.len() as f64
}

#[test]
fn ten_ggs_steps_reduce_loss_and_pose_error() {
    for seed in [1, 2, 3] {
        let problem = ring_problem(8, 80, 0.3, seed).unwrap();
        let mut solver = GgsSolver::new(&problem.matches, GgsConfig::default()).unwrap();
        let mut mean = problem.initial.clone();
        let before = solver.objective().evaluate(&mean).unwrap();
        let err_before = mean_rotation_error(&problem.ground_truth, &mean);
        for _ in 0..10 {
            solver.run(&mut mean, None).unwrap();
        }
        let after = solver.objective().evaluate(&mean).unwrap();
        let err_after = mean_rotation_error(&problem.ground_truth, &mean);
        assert!(
            after.loss < 0.5 * before.loss,
            "seed {seed}: loss {} -> {}",
            before.loss,
            after.loss
        );
        assert!(after.n_valid >= before.n_valid, "seed {seed}");
        assert!(
            err_after < err_before,
            "seed {seed}: rotation error {err_before} -> {err_after}"
        );
        assert!(mean.iter().flat_map(|e| e.0).all(f64::is_finite));
    }
}
