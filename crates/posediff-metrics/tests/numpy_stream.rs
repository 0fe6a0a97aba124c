//! The re-created numpy legacy stream against vectors produced by numpy itself
//! (`fixtures/numpy/legacy_choice.json`): raw outputs after `np.random.seed(0)`, and
//! `np.random.choice(n, k, replace=False)` sequences for several seeds, consumed in order.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff_fixtures::{fixture_path, read_json};
use posediff_metrics::numpy_rng::LegacyRandomState;

#[test]
fn matches_numpy_for_several_seeds_and_multi_sequence_runs() {
    let v = read_json(&fixture_path("numpy/legacy_choice.json"));
    let mut r = LegacyRandomState::new(0);
    let raw: Vec<u64> = v["seed0_first_uint32"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_u64().unwrap())
        .collect();
    let ours: Vec<u64> = (0..raw.len()).map(|_| u64::from(r.next_u32())).collect();
    assert_eq!(ours, raw);
    let cases = v["choice_cases"].as_array().unwrap();
    assert!(cases.len() >= 4);
    for case in cases {
        let seed = case["seed"].as_u64().unwrap() as u32;
        let mut rng = LegacyRandomState::new(seed);
        for (call, expected) in case["calls"]
            .as_array()
            .unwrap()
            .iter()
            .zip(case["choices"].as_array().unwrap())
        {
            let n = call[0].as_u64().unwrap() as usize;
            let k = call[1].as_u64().unwrap() as usize;
            let expected: Vec<usize> = expected
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap() as usize)
                .collect();
            assert_eq!(
                rng.choice_without_replacement(n, k).unwrap(),
                expected,
                "seed {seed}, choice({n}, {k})"
            );
        }
    }
}
