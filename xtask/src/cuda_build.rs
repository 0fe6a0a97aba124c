//! `cargo xtask cuda-build [--compute-cap 90] [--out F]`: the `posediff` binary with
//! `--features cuda`, built on a machine without a GPU and run on one that has the NVIDIA
//! driver and the CUDA 13 runtime libraries (the GPU machine has them inside PyTorch's
//! `nvidia-*` wheels). Everything lives under `target/cuda-build/`:
//!
//! - `cuda/nvidia/cu13`: the CUDA 13.0 compiler, headers and the libraries the binary links
//!   against, from PyPI (`scripts/cuda-build-requirements.txt`, pinned by version and sha256).
//!   The driver library is not on PyPI: the link uses a stub `libcuda.so` (soname
//!   `libcuda.so.1`, like the CUDA toolkit's own `lib64/stubs/libcuda.so`) made from the
//!   driver functions cudarc binds; at run time the real driver is loaded by that name.
//! - `opencv`: OpenCV 4.6.0 (Debian's source, the version of the system bindings) built as
//!   static libraries with the eight modules posediff uses and no optional codec or back end
//!   (JPEG and PNG from the static system libraries), so the binary needs no OpenCV, GDAL or
//!   codec libraries where it runs: only glibc, libstdc++ and the CUDA libraries.
//! - `cargo`: the cargo target folder of this build (the workspace's own stays untouched).
//! - `posediff`: the stripped binary. Its size and the shared libraries it needs are printed.
//!
//! The CUDA libraries are found at run time through `LD_LIBRARY_PATH` (the binary has no
//! RUNPATH into a Python installation); `scripts/device_check.sh` sets it from the local
//! PyTorch's `nvidia/cu13/lib` and the driver's folder. The kernels are PTX for the chosen
//! compute capability (default 90, Hopper), JIT-compiled by the driver for that GPU and newer.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use crate::{output, run, workspace_root};

/// OpenCV's source: Debian's original tarball of the version the system bindings are made from.
const OPENCV_URL: &str =
    "http://deb.debian.org/debian/pool/main/o/opencv/opencv_4.6.0+dfsg.orig.tar.xz";
const OPENCV_SHA256: &str = "40a59ba7e5c18a43652de0a08733c9843a39bba619b1f3e26a5fac4a6f041423";
const OPENCV_DIR: &str = "opencv-4.6.0";
/// The modules posediff uses (and their dependencies among them), in static-link order.
/// `videoio` is built without FFmpeg here (no optional back end), so the CUDA binary reads
/// OpenCV's own MJPEG AVI only; `video` is the optical flow of the keyframe selection.
const OPENCV_MODULES: [&str; 8] = [
    "video",
    "calib3d",
    "features2d",
    "flann",
    "videoio",
    "imgcodecs",
    "imgproc",
    "core",
];
/// The system static libraries OpenCV's image codecs and core use (Debian's `-dev` packages),
/// in link order: the codecs and zlib, then LAPACK (core's decompositions, as in Debian's
/// build) on the reference BLAS, with the Fortran runtime it needs.
const SYSTEM_STATIC: [(&str, &str, &str); 7] = [
    ("png16", "libpng-dev", SYSTEM_LIB_DIR),
    ("jpeg", "libjpeg62-turbo-dev", SYSTEM_LIB_DIR),
    ("z", "zlib1g-dev", SYSTEM_LIB_DIR),
    ("lapack", "liblapack-dev", SYSTEM_LIB_DIR),
    ("blas", "libblas-dev", SYSTEM_LIB_DIR),
    ("gfortran", "libgfortran-12-dev", GCC_LIB_DIR),
    ("quadmath", "libgcc-12-dev", GCC_LIB_DIR),
];
/// Header-only or header packages the static OpenCV is configured with: Eigen (USAC's
/// essential-matrix and other minimal solvers need Eigen or LAPACK: without them
/// `findEssentialMat` throws "not implemented") and LAPACKE/CBLAS's headers.
const SYSTEM_HEADERS: [(&str, &str); 3] = [
    ("/usr/include/eigen3/Eigen/Core", "libeigen3-dev"),
    ("/usr/include/lapacke.h", "liblapacke-dev"),
    ("/usr/include/x86_64-linux-gnu/cblas.h", "libblas-dev"),
];
const SYSTEM_LIB_DIR: &str = "/usr/lib/x86_64-linux-gnu";
const GCC_LIB_DIR: &str = "/usr/lib/gcc/x86_64-linux-gnu/12";
/// Libraries that get an unversioned `.so` link for the linker (the wheels ship only sonames).
const CUDA_LINK_NAMES: [&str; 5] = [
    "libcudart.so.13",
    "libcublas.so.13",
    "libcublasLt.so.13",
    "libcurand.so.10",
    "libnvrtc.so.13",
];
/// The most that travels to the GPU machine in one call (its `run` limit, the tree included).
const SIZE_LIMIT: u64 = 64 << 20;

/// Which static OpenCV.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Flavour {
    /// For an executable (the CUDA binary): the system's static codecs and reference LAPACK,
    /// configured as Debian's build, so the numbers are the system build's.
    System,
    /// For a shared library (the portable wheel): Debian's static archives are not
    /// position-independent (and libgfortran's TLS cannot go into a shared object), and its
    /// OpenCV source has no bundled codecs (`+dfsg`), so the codecs are the system's shared
    /// zlib, libjpeg and libpng (which the wheel carries: auditwheel's repair), and the
    /// decompositions OpenCV's own (Eigen for USAC's minimal solvers, no LAPACK).
    Portable,
}

/// The static OpenCV of [`static_opencv`] (with its CMake and Ninja venv in
/// `target/cuda-build/tools`), built when missing or when its options changed: `System` in
/// `target/cuda-build/opencv` (the CUDA binary), `Portable` in `target/portable-wheel/opencv`
/// (`cargo xtask wheel --portable`).
pub(crate) fn shared_static_opencv(flavour: Flavour) -> Result<PathBuf> {
    let tools_base = workspace_root().join("target/cuda-build");
    let base = match flavour {
        Flavour::System => tools_base.clone(),
        Flavour::Portable => workspace_root().join("target/portable-wheel"),
    };
    std::fs::create_dir_all(&base).with_context(|| format!("creating {}", base.display()))?;
    check_system_libraries()?;
    let tools = tools_venv(&tools_base)?;
    static_opencv(&base, &tools, flavour)
}

/// The system's shared codecs the portable build links, in link order.
const SHARED_CODECS: [&str; 3] = ["png16", "jpeg", "z"];

/// The environment of the `opencv` crate's build script that links the static OpenCV at
/// `opencv` (its modules, then the codecs and LAPACK of `flavour`) instead of probing for the
/// system's shared one.
pub(crate) fn static_opencv_env(opencv: &Path, flavour: Flavour) -> Vec<(&'static str, String)> {
    let mut link_libs: Vec<String> = OPENCV_MODULES
        .iter()
        .map(|m| format!("static=opencv_{m}"))
        .collect();
    let paths = match flavour {
        Flavour::System => {
            link_libs.extend(SYSTEM_STATIC.iter().map(|(l, _, _)| format!("static={l}")));
            format!(
                "{},{SYSTEM_LIB_DIR},{GCC_LIB_DIR}",
                opencv.join("lib").display()
            )
        }
        Flavour::Portable => {
            link_libs.extend(SHARED_CODECS.iter().map(|l| (*l).to_owned()));
            format!("{},{SYSTEM_LIB_DIR}", opencv.join("lib").display())
        }
    };
    vec![
        ("OPENCV_LINK_LIBS", link_libs.join(",")),
        ("OPENCV_LINK_PATHS", paths),
        (
            "OPENCV_INCLUDE_PATHS",
            opencv
                .join("include/opencv4")
                .to_string_lossy()
                .into_owned(),
        ),
        (
            "OPENCV_DISABLE_PROBES",
            "pkg_config,cmake,vcpkg_cmake,vcpkg".to_owned(),
        ),
    ]
}

/// The shared libraries an ELF file needs (`readelf -d`'s NEEDED entries).
pub(crate) fn needed_libraries(file: &Path) -> Result<Vec<String>> {
    let dynamic = output("readelf", &["-d", &file.to_string_lossy()])?;
    Ok(dynamic
        .lines()
        .filter(|l| l.contains("(NEEDED)"))
        .filter_map(|l| l.split('[').nth(1))
        .map(|l| l.trim_end_matches(']').to_owned())
        .collect())
}

/// `cargo xtask cuda-build`.
pub fn cuda_build(args: &[String]) -> Result<()> {
    let root = workspace_root();
    let mut compute_cap = "90".to_owned();
    let mut out = root.join("target/cuda-build/posediff");
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--compute-cap" => compute_cap = value()?.clone(),
            "--out" => out = std::env::current_dir()?.join(value()?),
            other => bail!("cuda-build: unknown argument {other:?} (--compute-cap N, --out F)"),
        }
    }
    if !compute_cap.chars().all(|c| c.is_ascii_digit()) || compute_cap.len() < 2 {
        bail!("--compute-cap {compute_cap}: expected digits such as 90 (Hopper) or 80 (Ampere)");
    }
    let base = root.join("target/cuda-build");
    let opencv = shared_static_opencv(Flavour::System)?;
    let tools = tools_venv(&base)?;
    let cuda = cuda_toolkit(&base, &tools)?;
    build(&base, &cuda, &opencv, &compute_cap, &out)
}

/// The static libraries of [`SYSTEM_STATIC`] and the headers of [`SYSTEM_HEADERS`] are there:
/// installed with apt when missing and running as root, else a clear error naming the packages.
fn check_system_libraries() -> Result<()> {
    let mut missing: Vec<&str> = SYSTEM_STATIC
        .iter()
        .filter(|(lib, _, dir)| !Path::new(dir).join(format!("lib{lib}.a")).is_file())
        .map(|(_, package, _)| *package)
        .collect();
    missing.extend(
        SYSTEM_HEADERS
            .iter()
            .filter(|(file, _)| !Path::new(file).is_file())
            .map(|(_, package)| *package),
    );
    missing.sort_unstable();
    missing.dedup();
    if !missing.is_empty() {
        crate::apt_install(&missing, "the static OpenCV")?;
    }
    for tool in ["cc", "c++", "curl", "tar", "readelf"] {
        if output("sh", &["-c", &format!("command -v {tool}")]).is_err() {
            bail!(
                "the static OpenCV needs `{tool}` on the PATH (Debian: build-essential, curl, binutils)"
            );
        }
    }
    Ok(())
}

/// Skips `make` when `stamp` holds `key`, else runs it and writes the stamp.
fn stamped(stamp: &Path, key: &str, make: impl FnOnce() -> Result<()>) -> Result<()> {
    if std::fs::read_to_string(stamp).is_ok_and(|s| s == key) {
        eprintln!("up to date: {}", stamp.parent().unwrap_or(stamp).display());
        return Ok(());
    }
    make()?;
    std::fs::write(stamp, key).with_context(|| format!("writing {}", stamp.display()))
}

/// `target/cuda-build/tools`: a venv with the pinned CMake and Ninja; returns its `bin`.
fn tools_venv(base: &Path) -> Result<PathBuf> {
    let root = workspace_root();
    let venv = base.join("tools");
    let requirements = root.join("scripts/cuda-build-tools.txt");
    let key = std::fs::read_to_string(&requirements)
        .with_context(|| format!("reading {}", requirements.display()))?;
    let python = venv.join("bin/python");
    stamped(&venv.join("requirements.stamp"), &key, || {
        if !python.is_file() {
            run("python3", &["-m", "venv", &venv.to_string_lossy()], &[])?;
        }
        run(
            &python.to_string_lossy(),
            &[
                "-m",
                "pip",
                "install",
                "-q",
                "--require-hashes",
                "-r",
                &requirements.to_string_lossy(),
            ],
            &[("PIP_DISABLE_PIP_VERSION_CHECK", "1")],
        )
    })?;
    Ok(venv.join("bin"))
}

/// `target/cuda-build/cuda/nvidia/cu13` with the pinned wheels, unversioned link names and the
/// driver stub; returns that folder (the `CUDA_HOME` of the build).
fn cuda_toolkit(base: &Path, tools: &Path) -> Result<PathBuf> {
    let root = workspace_root();
    let target = base.join("cuda");
    let requirements = root.join("scripts/cuda-build-requirements.txt");
    let key = std::fs::read_to_string(&requirements)
        .with_context(|| format!("reading {}", requirements.display()))?;
    std::fs::create_dir_all(&target)?;
    stamped(&target.join("requirements.stamp"), &key, || {
        // The tools venv's pip: no system Python policy (PEP 668) in the way.
        run(
            &tools.join("python").to_string_lossy(),
            &[
                "-m",
                "pip",
                "install",
                "-q",
                "--upgrade",
                "--no-deps",
                "--require-hashes",
                "--only-binary=:all:",
                "--target",
                &target.to_string_lossy(),
                "-r",
                &requirements.to_string_lossy(),
            ],
            &[("PIP_DISABLE_PIP_VERSION_CHECK", "1")],
        )
    })?;
    let home = target.join("nvidia/cu13");
    let lib = home.join("lib");
    for soname in CUDA_LINK_NAMES {
        let plain = soname.split(".so").next().unwrap_or(soname).to_owned() + ".so";
        let link = lib.join(&plain);
        if !lib.join(soname).is_file() {
            bail!(
                "{}: {soname} is missing (remove {} and run again)",
                lib.display(),
                target.join("requirements.stamp").display()
            );
        }
        if !link.exists() {
            std::os::unix::fs::symlink(soname, &link)
                .with_context(|| format!("linking {}", link.display()))?;
        }
    }
    driver_stub(&lib.join("stubs"))?;
    Ok(home)
}

/// `stubs/libcuda.so`: every driver function cudarc binds, as empty functions, in a library
/// named `libcuda.so.1` (what the linker records, so the real driver is loaded at run time).
/// Only for linking: it is never on the run-time library path.
fn driver_stub(dir: &Path) -> Result<()> {
    let stub = dir.join("libcuda.so");
    if stub.is_file() {
        return Ok(());
    }
    std::fs::create_dir_all(dir)?;
    run("cargo", &["fetch", "--quiet"], &[])?;
    let bindings = cudarc_source()?.join("src/driver/sys/mod.rs");
    let text = std::fs::read_to_string(&bindings)
        .with_context(|| format!("reading {}", bindings.display()))?;
    let mut names: Vec<&str> = text
        .lines()
        .filter_map(|l| l.strip_prefix("pub unsafe fn "))
        .filter_map(|l| l.split('(').next())
        .filter(|n| n.starts_with("cu"))
        .collect();
    names.sort_unstable();
    names.dedup();
    if names.len() < 100 || !names.contains(&"cuInit") {
        bail!(
            "{}: found {} driver functions, expected the driver API (cuInit, …)",
            bindings.display(),
            names.len()
        );
    }
    let source = dir.join("libcuda_stub.c");
    let body: String = names
        .iter()
        .map(|n| format!("int {n}(void) {{ return 999; }}\n"))
        .collect();
    std::fs::write(
        &source,
        format!("/* Link stub of the CUDA driver (cargo xtask cuda-build). */\n{body}"),
    )?;
    run(
        "cc",
        &[
            "-shared",
            "-fPIC",
            "-Wl,-soname,libcuda.so.1",
            "-o",
            &stub.to_string_lossy(),
            &source.to_string_lossy(),
        ],
        &[],
    )?;
    eprintln!("driver link stub: {} functions", names.len());
    Ok(())
}

/// The registry source of the cudarc version in `Cargo.lock`.
fn cudarc_source() -> Result<PathBuf> {
    let root = workspace_root();
    let lock = std::fs::read_to_string(root.join("Cargo.lock"))?;
    let version = lock
        .split("[[package]]")
        .find(|p| p.contains("name = \"cudarc\""))
        .and_then(|p| p.lines().find_map(|l| l.strip_prefix("version = ")))
        .map(|v| v.trim_matches('"').to_owned())
        .context("Cargo.lock has no cudarc (the `cuda` feature's dependency)")?;
    let cargo_home = std::env::var_os("CARGO_HOME").map_or_else(
        || PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cargo"),
        PathBuf::from,
    );
    let registry = cargo_home.join("registry/src");
    let entries = std::fs::read_dir(&registry)
        .with_context(|| format!("reading {} (run `cargo fetch`)", registry.display()))?;
    for entry in entries.flatten() {
        let candidate = entry.path().join(format!("cudarc-{version}"));
        if candidate.is_dir() {
            return Ok(candidate);
        }
    }
    bail!("cudarc-{version} is not in {}", registry.display())
}

/// The CMake options of the static OpenCV: the modules of [`OPENCV_MODULES`]; what changes
/// numbers configured as Debian's `libopencv-dev` is (so SIFT, MAGSAC and the decompositions
/// give the system build's results): Eigen, reference LAPACK/BLAS, the SSE2 baseline with the
/// same dispatched kernels, `-O2`; no optional back end that only changes speed or I/O (IPP,
/// TBB, OpenMP, OpenCL), no codec beyond JPEG and PNG (plus OpenCV's own PNM/HDR), and the
/// system's static zlib, libjpeg and libpng.
fn opencv_options(prefix: &Path, flavour: Flavour) -> Vec<String> {
    let lib = |name: &str| format!("{SYSTEM_LIB_DIR}/lib{name}.a");
    let lapack = ["lapack", "blas"]
        .iter()
        .map(|l| lib(l))
        .chain(
            ["gfortran", "quadmath"]
                .iter()
                .map(|l| format!("{GCC_LIB_DIR}/lib{l}.a")),
        )
        .collect::<Vec<_>>()
        .join(";");
    let mut options = vec![
        "-DCMAKE_BUILD_TYPE=Release".to_owned(),
        format!("-DCMAKE_INSTALL_PREFIX={}", prefix.display()),
        "-DBUILD_SHARED_LIBS=OFF".to_owned(),
        "-DCMAKE_POSITION_INDEPENDENT_CODE=ON".to_owned(),
        format!("-DBUILD_LIST={}", OPENCV_MODULES.join(",")),
        format!("-DZLIB_LIBRARY={}", lib("z")),
        format!("-DJPEG_LIBRARY={}", lib("jpeg")),
        format!("-DPNG_LIBRARY={}", lib("png16")),
        format!("-DPNG_LIBRARY_RELEASE={}", lib("png16")),
        "-DWITH_PTHREADS_PF=ON".to_owned(),
        "-DWITH_EIGEN=ON".to_owned(),
        "-DEIGEN_INCLUDE_PATH=/usr/include/eigen3".to_owned(),
        "-DWITH_LAPACK=ON".to_owned(),
        format!("-DLAPACK_LIBRARIES={lapack}"),
        "-DLAPACK_INCLUDE_DIR=/usr/include;/usr/include/x86_64-linux-gnu".to_owned(),
        "-DLAPACK_CBLAS_H=cblas.h".to_owned(),
        "-DLAPACK_LAPACKE_H=lapacke.h".to_owned(),
        "-DLAPACK_IMPL=LAPACK/Generic".to_owned(),
        "-DCPU_BASELINE=SSE2".to_owned(),
        "-DCPU_BASELINE_DISABLE=SSE3".to_owned(),
        "-DCMAKE_C_FLAGS_RELEASE=-O2 -DNDEBUG".to_owned(),
        "-DCMAKE_CXX_FLAGS_RELEASE=-O2 -DNDEBUG".to_owned(),
        "-DWITH_IMGCODEC_HDR=ON".to_owned(),
        "-DWITH_IMGCODEC_PXM=ON".to_owned(),
    ];
    let off = [
        "BUILD_TESTS",
        "BUILD_PERF_TESTS",
        "BUILD_EXAMPLES",
        "BUILD_opencv_apps",
        "BUILD_DOCS",
        "BUILD_JAVA",
        "BUILD_opencv_python2",
        "BUILD_opencv_python3",
        "BUILD_ZLIB",
        "BUILD_JPEG",
        "BUILD_PNG",
        "WITH_IPP",
        "WITH_ITT",
        "WITH_TBB",
        "WITH_OPENMP",
        "WITH_OPENCL",
        "WITH_CUDA",
        "WITH_GDAL",
        "WITH_GDCM",
        "WITH_OPENEXR",
        "WITH_TIFF",
        "WITH_WEBP",
        "WITH_JASPER",
        "WITH_OPENJPEG",
        "WITH_IMGCODEC_SUNRASTER",
        "WITH_IMGCODEC_PFM",
        "WITH_FFMPEG",
        "WITH_GSTREAMER",
        "WITH_V4L",
        "WITH_GTK",
        "WITH_QT",
        "WITH_PROTOBUF",
        "WITH_QUIRC",
        "WITH_ADE",
        "WITH_VA",
        "WITH_1394",
        "WITH_AVIF",
        "WITH_VTK",
    ];
    options.extend(off.iter().map(|o| format!("-D{o}=OFF")));
    if flavour == Flavour::Portable {
        // The system's shared codecs (CMake finds them by default), no LAPACK.
        let system_static = [
            "-DZLIB_LIBRARY=",
            "-DJPEG_LIBRARY=",
            "-DPNG_LIBRARY",
            "-DWITH_LAPACK=",
            "-DLAPACK_",
        ];
        options.retain(|o| !system_static.iter().any(|p| o.starts_with(p)));
        options.push("-DWITH_LAPACK=OFF".to_owned());
    }
    options
}

/// `target/cuda-build/opencv`: the static OpenCV, downloaded, checked and built when missing.
fn static_opencv(base: &Path, tools: &Path, flavour: Flavour) -> Result<PathBuf> {
    let prefix = base.join("opencv");
    let options = opencv_options(&prefix, flavour);
    let key = format!("{OPENCV_URL} {OPENCV_SHA256}\n{}", options.join("\n"));
    let tarball = base.join("opencv.tar.xz");
    let source = base.join(OPENCV_DIR);
    let build_dir = base.join("opencv-build");
    std::fs::create_dir_all(&prefix)?;
    stamped(&prefix.join("build.stamp"), &key, || {
        if !tarball.is_file() {
            run(
                "curl",
                &["-sSfL", "-o", &tarball.to_string_lossy(), OPENCV_URL],
                &[],
            )?;
        }
        crate::check_sha256(&tarball, OPENCV_SHA256, true)?;
        if !source.join("CMakeLists.txt").is_file() {
            run(
                "tar",
                &[
                    "-xJf",
                    &tarball.to_string_lossy(),
                    "-C",
                    &base.to_string_lossy(),
                ],
                &[],
            )?;
        }
        let path = format!(
            "{}:{}",
            tools.display(),
            std::env::var("PATH").unwrap_or_default()
        );
        let mut configure = vec![
            "-S".to_owned(),
            source.to_string_lossy().into_owned(),
            "-B".to_owned(),
            build_dir.to_string_lossy().into_owned(),
            "-G".to_owned(),
            "Ninja".to_owned(),
        ];
        configure.extend(options.iter().cloned());
        let configure: Vec<&str> = configure.iter().map(String::as_str).collect();
        let cmake = tools.join("cmake");
        run(&cmake.to_string_lossy(), &configure, &[("PATH", &path)])?;
        run(
            &cmake.to_string_lossy(),
            &[
                "--build",
                &build_dir.to_string_lossy(),
                "--target",
                "install",
            ],
            &[("PATH", &path)],
        )
    })?;
    for module in OPENCV_MODULES {
        let lib = prefix.join(format!("lib/libopencv_{module}.a"));
        if !lib.is_file() {
            bail!(
                "{} is missing after the OpenCV build (see {})",
                lib.display(),
                build_dir.display()
            );
        }
    }
    Ok(prefix)
}

/// The cargo build of `posediff --features cuda` against the toolkit and the static OpenCV,
/// then the stripped binary at `out` with its size and needed libraries.
fn build(base: &Path, cuda: &Path, opencv: &Path, compute_cap: &str, out: &Path) -> Result<()> {
    let path = format!(
        "{}:{}",
        cuda.join("bin").display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let opencv_env = static_opencv_env(opencv, Flavour::System);
    let cuda_home = cuda.to_string_lossy().into_owned();
    let target_dir = base.join("cargo").to_string_lossy().into_owned();
    let envs = [
        ("PATH", path.as_str()),
        ("CUDA_HOME", cuda_home.as_str()),
        ("CUDA_COMPUTE_CAP", compute_cap),
        ("CARGO_TARGET_DIR", target_dir.as_str()),
        ("CARGO_PROFILE_RELEASE_STRIP", "symbols"),
        // Whole-program LTO drops candle's quantized CUDA paths posediff never calls, and with
        // them the references that would pull candle-kernels' 33 MB of MoE/GGUF machine code
        // (`.nv_fatbin`) out of its static library.
        ("CARGO_PROFILE_RELEASE_LTO", "fat"),
    ];
    let envs: Vec<(&str, &str)> = envs
        .into_iter()
        .chain(opencv_env.iter().map(|(k, v)| (*k, v.as_str())))
        .collect();
    run(
        "cargo",
        &[
            "build",
            "--release",
            "--locked",
            "-p",
            "posediff",
            "--bin",
            "posediff",
            "--features",
            "cuda",
        ],
        &envs,
    )?;
    let built = base.join("cargo/release/posediff");
    if let Some(parent) = out.parent() {
        std::fs::create_dir_all(parent)?;
    }
    if built != out {
        std::fs::copy(&built, out)
            .with_context(|| format!("copying {} to {}", built.display(), out.display()))?;
    }
    let size = std::fs::metadata(out)?.len();
    let needed = needed_libraries(out)?;
    eprintln!(
        "\n{}: {:.1} MiB (limit {} MiB), compute capability {compute_cap}\nneeds: {}",
        out.display(),
        size as f64 / f64::from(1 << 20),
        SIZE_LIMIT >> 20,
        needed.join(" ")
    );
    if needed.iter().any(|n| n.starts_with("libopencv")) {
        bail!("the binary still needs shared OpenCV libraries: the static OpenCV was not used");
    }
    if size > SIZE_LIMIT {
        bail!(
            "{} is {size} bytes, over the {} MiB that travel",
            out.display(),
            SIZE_LIMIT >> 20
        );
    }
    eprintln!(
        "run it with the CUDA 13 libraries on LD_LIBRARY_PATH, e.g. \
         LD_LIBRARY_PATH=$(python3 -c 'import nvidia, os; print(os.path.join(list(nvidia.__path__)[0], \"cu13/lib\"))') \
         {} estimate … --device cuda (scripts/device_check.sh does this)",
        out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_portable_opencv_links_nothing_static_from_the_system() {
        let prefix = Path::new("/tmp/opencv");
        let system = opencv_options(prefix, Flavour::System);
        let portable = opencv_options(prefix, Flavour::Portable);
        // The executable's build takes Debian's static archives and LAPACK …
        assert!(system.iter().any(|o| o.ends_with("libz.a")));
        assert!(system.contains(&"-DWITH_LAPACK=ON".to_owned()));
        // … the shared library's none of them (not position-independent), and no LAPACK.
        assert!(
            portable
                .iter()
                .all(|o| !o.contains(".a;") && !o.ends_with(".a"))
        );
        assert!(portable.contains(&"-DWITH_LAPACK=OFF".to_owned()));
        assert!(!portable.contains(&"-DWITH_LAPACK=ON".to_owned()));
        assert!(portable.contains(&"-DWITH_EIGEN=ON".to_owned()));
        // Everything else is configured alike.
        let common = |o: &&String| !o.contains("LAPACK") && !o.contains("_LIBRARY");
        assert_eq!(
            system.iter().filter(common).collect::<Vec<_>>(),
            portable.iter().filter(common).collect::<Vec<_>>()
        );
        let env = static_opencv_env(prefix, Flavour::Portable);
        let libs = &env
            .iter()
            .find(|(k, _)| *k == "OPENCV_LINK_LIBS")
            .unwrap()
            .1;
        assert!(libs.starts_with("static=opencv_video,"));
        assert!(libs.ends_with(",png16,jpeg,z"), "{libs}");
        assert!(!libs.contains("lapack") && !libs.contains("gfortran"));
    }
}
