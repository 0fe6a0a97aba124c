//! Checkpoint loading: a `.pth` written by PyTorch (`torch.save` of the tiny fixture's state
//! dict with accelerate's `module.` prefix, `fixtures/torch/`), dtypes and strides of a small
//! PyTorch state dict, layout errors listing every problem, and the safetensors converter.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff_fixtures::tensors::values;

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use posediff_diffusion::checkpoint::{ModelDepths, read_tensors};
use posediff_diffusion::{Checkpoint, DiffusionError};
use posediff_fixtures::{fixture_path, shared_path};

fn tiny_safetensors() -> HashMap<String, Tensor> {
    read_tensors(&shared_path("reference/tiny/model_tiny.safetensors"))
        .unwrap()
        .into_iter()
        .collect()
}

#[test]
fn a_pth_written_by_pytorch_loads_like_the_safetensors() {
    let pth = Checkpoint::load(
        &fixture_path("torch/model_tiny_module_prefix.pth"),
        &Device::Cpu,
    )
    .unwrap();
    assert_eq!(
        pth.depths(),
        ModelDepths {
            vit_blocks: 2,
            trunk_layers: 2
        }
    );
    let reference = tiny_safetensors();
    assert_eq!(reference.len(), 79);
    for (key, t) in &reference {
        let ours = pth
            .get(key)
            .unwrap_or_else(|| panic!("{key} missing after stripping module."));
        assert_eq!(ours.dtype(), t.dtype(), "{key}");
        assert_eq!(ours.dims(), t.dims(), "{key}");
        assert_eq!(values(ours), values(t), "{key}");
    }
}

#[test]
fn pytorch_dtypes_and_transposed_storage_are_read_exactly() {
    let t: HashMap<String, Tensor> = read_tensors(&fixture_path("torch/small_state_dict.pth"))
        .unwrap()
        .into_iter()
        .collect();
    assert_eq!(
        values(&t["a.f32"]),
        (0..6)
            .map(|i| f64::from(i as f32 / 7.0))
            .collect::<Vec<_>>()
    );
    assert_eq!(t["b.f16"].dtype(), DType::F16);
    assert_eq!(values(&t["b.f16"]), vec![-1.5, -0.5, 0.5, 1.5]);
    assert_eq!(t["c.f64"].dtype(), DType::F64);
    assert_eq!(values(&t["c.f64"]), vec![1.0, -2.5, 3.25, 1e-9]);
    // (arange(6).reshape(2, 3) + 0.5).t(): shape (3, 2), saved with transposed strides.
    assert_eq!(t["d.transposed"].dims(), [3, 2]);
    assert_eq!(
        values(&t["d.transposed"]),
        vec![0.5, 3.5, 1.5, 4.5, 2.5, 5.5]
    );
}

#[test]
fn layout_errors_list_every_problem() {
    let mut tensors = tiny_safetensors();
    tensors.remove("diffuser.model._first.bias");
    tensors.insert(
        "diffuser.model._last.3.weight".into(),
        Tensor::zeros((8, 128), DType::F32, &Device::Cpu).unwrap(),
    );
    tensors.insert(
        "extra.weight".into(),
        Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
    );
    let err = Checkpoint::from_tensors(tensors).unwrap_err();
    let DiffusionError::CheckpointLayout { problems } = &err else {
        panic!("unexpected error {err}");
    };
    assert_eq!(problems.len(), 3, "{problems:?}");
    let text = err.to_string();
    assert!(
        text.contains("missing: diffuser.model._first.bias"),
        "{text}"
    );
    assert!(
        text.contains("wrong shape: diffuser.model._last.3.weight"),
        "{text}"
    );
    assert!(text.contains("unexpected: extra.weight"), "{text}");
}

#[test]
fn unreadable_and_foreign_files_are_clear_errors() {
    let dir = std::env::temp_dir().join(format!("posediff-ckpt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let text = dir.join("notes.pth");
    std::fs::write(&text, "not a checkpoint").unwrap();
    assert!(matches!(
        Checkpoint::load(&text, &Device::Cpu),
        Err(DiffusionError::UnknownFormat { .. })
    ));
    let missing = dir.join("missing.pth");
    assert!(matches!(
        Checkpoint::load(&missing, &Device::Cpu),
        Err(DiffusionError::CheckpointRead { .. })
    ));
    let small = Checkpoint::load(&fixture_path("torch/small_state_dict.pth"), &Device::Cpu);
    assert!(matches!(
        small,
        Err(DiffusionError::CheckpointLayout { .. })
    ));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn converting_pth_to_safetensors_keeps_every_tensor() {
    let pth = Checkpoint::load(
        &fixture_path("torch/model_tiny_module_prefix.pth"),
        &Device::Cpu,
    )
    .unwrap();
    let out = std::env::temp_dir().join(format!(
        "posediff-convert-{}.safetensors",
        std::process::id()
    ));
    pth.save_safetensors(&out).unwrap();
    let back = Checkpoint::load(&out, &Device::Cpu).unwrap();
    std::fs::remove_file(&out).unwrap();
    for (key, t) in tiny_safetensors() {
        let b = back.get(&key).unwrap();
        assert_eq!(b.dtype(), t.dtype(), "{key}");
        assert_eq!(values(b), values(&t), "{key}");
    }
}

/// The legacy (pre-zip) format of `torch.save(..., _use_new_zipfile_serialization=False)`, as
/// DISK's released weights are stored: the same tensors as the zip fixture, nested under
/// `extractor`, read exactly (dtypes and the transposed storage included).
#[test]
fn legacy_pytorch_files_are_read_exactly_with_nested_keys() {
    let zip: HashMap<String, Tensor> = read_tensors(&fixture_path("torch/small_state_dict.pth"))
        .unwrap()
        .into_iter()
        .collect();
    let legacy: HashMap<String, Tensor> =
        read_tensors(&fixture_path("torch/small_state_dict_legacy.pth"))
            .unwrap()
            .into_iter()
            .collect();
    assert_eq!(legacy.len(), zip.len());
    for (key, t) in &zip {
        let ours = &legacy[&format!("extractor.{key}")];
        assert_eq!(ours.dtype(), t.dtype(), "{key}");
        assert_eq!(ours.dims(), t.dims(), "{key}");
        assert_eq!(values(ours), values(t), "{key}");
    }
}

/// A legacy file cut short is an error naming the file, not a panic or a partial dict.
#[test]
fn a_truncated_legacy_file_is_an_error() {
    let bytes = std::fs::read(fixture_path("torch/small_state_dict_legacy.pth")).unwrap();
    let dir = posediff_fixtures::temp_dir("legacy-truncated");
    let path = dir.join("cut.pth");
    std::fs::write(&path, &bytes[..bytes.len() - 10]).unwrap();
    let e = read_tensors(&path).unwrap_err().to_string();
    assert!(e.contains("cut.pth"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}
