//! The sampler with the pipeline's GGS mean hook against the official run
//! (`reference/full/sampling_ggs_io.safetensors`: `iter_num 3`, `sampson_max 1e12`,
//! `min_matches 0`, GGS at t < 10, no noise there), teacher-forced per step: each of the last ten
//! steps starts from the reference's `pose_process[k]` and must land on `pose_process[k+1]`.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff_fixtures::tensors::tensor;

use candle_core::{DType, Device, IndexOp};
use posediff::GgsHook;
use posediff_diffusion::PoseDiffusionModel;
use posediff_diffusion::sampler::{MeanHook, denoise_step};
use posediff_fixtures::{SafetensorsFixture, assert_close, shared_path};
use posediff_guidance::{GgsConfig, MatchSet};

#[test]
fn ggs_steps_of_the_sampler_match_the_official_run() {
    let model = PoseDiffusionModel::load(
        &shared_path("reference/full/model_random.safetensors"),
        DType::F64,
        &Device::Cpu,
    )
    .unwrap();
    let run = SafetensorsFixture::open(&shared_path("reference/full/sampling_ggs_io.safetensors"));
    let io = SafetensorsFixture::open(&shared_path("reference/full/sampling_io.safetensors"));
    let ggs = SafetensorsFixture::open(&shared_path("reference/full/ggs_io.safetensors"));
    let matches = MatchSet::new(
        5,
        &ggs.rows::<2>("kp1"),
        &ggs.rows::<2>("kp2"),
        &ggs.index_pairs("i12"),
    )
    .unwrap();
    let config = GgsConfig {
        iter_num: 3,
        sampson_max: 1e12,
        min_matches: 0.0,
        ..GgsConfig::default()
    };
    let mut hook = GgsHook::new(&matches, config).unwrap();
    let z = tensor(&io, "z");
    let process = tensor(&run, "pose_process");
    for k in (100 - GgsConfig::default().start_step)..100 {
        let t = 99 - k;
        let step = denoise_step(
            &model.denoiser,
            &model.schedule,
            &process.i(k).unwrap(),
            t,
            &z,
        )
        .unwrap();
        let next = hook.replace_mean(&step.model_mean, t).unwrap();
        let ours: Vec<f64> = next.flatten_all().unwrap().to_vec1().unwrap();
        let expected: Vec<f64> = process
            .i(k + 1)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        // The per-step sampling tolerance of the fixture READMEs (1e-5 abs on x).
        assert_close(
            &format!("pose_process[{}] (GGS, t = {t})", k + 1),
            &ours,
            &expected,
            1e-5,
            0.0,
        );
    }
}
