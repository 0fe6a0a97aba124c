//! `posediff._native`: the extension module under the Python package `posediff`
//! (`python/posediff/__init__.py` re-exports it and adds tqdm progress).
//!
//! Every estimation goes through [`posediff::estimate::run::run`], the function the CLI calls, so the
//! files `Reconstruction.write` writes are the CLI's byte for byte. The GIL is released
//! while it runs; progress comes back through a Python callable, called with the GIL held.
//! Cameras speak OpenCV (`x_cam = R x_world + t`, pixels); the PyTorch3D conversions are the
//! geometry crate's (`posediff_geometry::pytorch3d`), with PyTorch3D's `image_size = (H, W)`.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector2, Vector3};
use numpy::PyReadonlyArray3;
use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2};
use posediff::PosediffError;
use posediff::correspondences::StepCounter;
use posediff::estimate::run::{
    InitSource, Inputs, IntrinsicsSource, Network, RefineMode, Run, RunOptions, load_estimator, run,
};
use posediff::io::colmap::ColmapFormat;
use posediff::io::export::ImageCamera;
use posediff::io::outputs::{ImagesMode, OutputOptions, prepare_output_dir};
use posediff::{Estimator, Progress};
use posediff_geometry::pytorch3d::{NdcIntrinsics, Pytorch3dCamera};
use posediff_geometry::{Camera, ImageSize, Intrinsics, Pose, PoseEncoding};
use pyo3::exceptions::{PyException, PyFileNotFoundError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

/// The CLI's allocator (see `crates/posediff/src/main.rs`): the networks allocate and free tensors
/// of tens of megabytes per layer, which glibc's allocator hands back to the kernel each time.
/// Only this module's Rust allocations use it; arrays handed to numpy are freed by Rust too.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

pyo3::create_exception!(
    posediff,
    Error,
    PyException,
    "An estimation that failed on valid input (no overlapping images, a degenerate solve, a \
     model error); the message is posediff's."
);

/// A posediff error as the Python exception a caller would catch: `FileNotFoundError` for a
/// missing path, `ValueError` for an input or option that is wrong, `posediff.Error` for the
/// rest. The message is the whole Rust message.
fn py_err(e: PosediffError) -> PyErr {
    let message = e.to_string();
    match e.root() {
        PosediffError::NotFound(_) => PyFileNotFoundError::new_err(message),
        PosediffError::Read { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(message)
        }
        PosediffError::Learned(l)
            if matches!(**l, posediff_learned::LearnedError::MissingWeights { .. }) =>
        {
            PyFileNotFoundError::new_err(message)
        }
        PosediffError::InvalidArgument(_)
        | PosediffError::InvalidFile { .. }
        | PosediffError::NoImages(_)
        | PosediffError::TooFewImages { .. }
        | PosediffError::UnreadableImage(_)
        | PosediffError::Matching(posediff_matching::MatchingError::CorruptImage { .. })
        | PosediffError::Geometry(_) => PyValueError::new_err(message),
        _ => Error::new_err(message),
    }
}

fn value_err(message: impl Into<String>) -> PyErr {
    PyValueError::new_err(message.into())
}

/// Progress reported to a Python callable `callback(stage, done, total, finished)`. Steps of
/// the geometric path finish on worker threads ([`StepCounter`]), so the state sits behind a
/// lock; the callback runs with the GIL held, one call at a time.
struct PyProgress {
    callback: Option<Py<PyAny>>,
    state: std::sync::Mutex<ProgressState>,
}

#[derive(Default)]
struct ProgressState {
    stage: String,
    done: u64,
    total: u64,
    /// The first exception the callback raised (re-raised when the run ends).
    error: Option<PyErr>,
}

impl PyProgress {
    fn new(callback: Option<Py<PyAny>>) -> Self {
        Self {
            callback,
            state: std::sync::Mutex::new(ProgressState::default()),
        }
    }

    /// The first exception the callback raised.
    fn take_error(&mut self) -> Option<PyErr> {
        self.state.get_mut().ok().and_then(|s| s.error.take())
    }

    /// Updates the state with `change` and reports it.
    fn update(&self, finished: bool, change: impl FnOnce(&mut ProgressState)) {
        let Ok(mut state) = self.state.lock() else {
            return;
        };
        change(&mut state);
        let Some(cb) = &self.callback else { return };
        if state.error.is_some() {
            return;
        }
        let r = Python::attach(|py| {
            cb.call1(
                py,
                (state.stage.as_str(), state.done, state.total, finished),
            )
            .map(|_| ())
        });
        if let Err(e) = r {
            state.error = Some(e);
        }
    }
}

impl StepCounter for PyProgress {
    fn stage(&self, name: &str, total: u64) {
        self.update(false, |s| {
            name.clone_into(&mut s.stage);
            s.done = 0;
            s.total = total;
        });
    }

    fn step(&self) {
        self.update(false, |s| s.done += 1);
    }
}

impl Progress for PyProgress {
    fn start(&mut self, stage: &str, total: u64) {
        StepCounter::stage(self, stage, total);
    }

    fn advance(&mut self) {
        self.step();
    }

    fn finish(&mut self) {
        self.update(true, |_| {});
    }

    fn counter(&self) -> &dyn StepCounter {
        self
    }
}

fn matrix_to_py<'py>(py: Python<'py>, m: &Matrix3<f64>) -> Bound<'py, PyArray2<f64>> {
    let a = Array2::from_shape_fn((3, 3), |(r, c)| m[(r, c)]);
    a.into_pyarray(py)
}

fn vector_to_py<'py>(py: Python<'py>, v: &[f64]) -> Bound<'py, PyArray1<f64>> {
    Array1::from_vec(v.to_vec()).into_pyarray(py)
}

fn matrix_from_py(a: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Matrix3<f64>> {
    let v = a.as_array();
    if v.shape() != [3, 3] {
        return Err(value_err(format!(
            "{what} must be 3×3, got shape {:?}",
            v.shape()
        )));
    }
    Ok(Matrix3::from_fn(|r, c| v[[r, c]]))
}

fn vector_from_py<const N: usize>(a: &PyReadonlyArray1<'_, f64>, what: &str) -> PyResult<[f64; N]> {
    let v = a.as_array();
    if v.len() != N {
        return Err(value_err(format!(
            "{what} must have {N} entries, got {}",
            v.len()
        )));
    }
    let mut out = [0.0; N];
    for (o, x) in out.iter_mut().zip(v.iter()) {
        *o = *x;
    }
    Ok(out)
}

/// One camera as numpy arrays: `K` (3×3), `R` (3×3), `t` (3,).
type Krt<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<f64>>,
);

/// N cameras stacked: `K` (N, 3, 3), `R` (N, 3, 3), `t` (N, 3).
type KrtStack<'py> = (
    Bound<'py, PyArray3<f64>>,
    Bound<'py, PyArray3<f64>>,
    Bound<'py, PyArray2<f64>>,
);

/// PyTorch3D's `image_size`: `(height, width)`.
fn size_from_hw(image_size: (u32, u32)) -> PyResult<ImageSize> {
    let (h, w) = image_size;
    ImageSize::new(w, h).map_err(|e| value_err(format!("image_size (height, width): {e}")))
}

/// One image's camera, OpenCV convention: `x_cam = R @ x_world + t`, pixels with pixel
/// centres at integers. `K`, `R`, `t` are `None` when the image was not estimated (`reason`
/// then says why, where the estimator knows).
#[pyclass(module = "posediff", name = "Camera", frozen)]
#[derive(Clone)]
struct PyCamera {
    name: String,
    size: ImageSize,
    camera: Option<Camera>,
    reason: Option<String>,
}

#[pymethods]
impl PyCamera {
    /// The image's name relative to the input folder (the key of every per-image record).
    #[getter]
    fn name(&self) -> &str {
        &self.name
    }

    /// Image width, px.
    #[getter]
    fn width(&self) -> u32 {
        self.size.width()
    }

    /// Image height, px.
    #[getter]
    fn height(&self) -> u32 {
        self.size.height()
    }

    /// Whether the image has a camera.
    #[getter]
    fn estimated(&self) -> bool {
        self.camera.is_some()
    }

    /// Why the image has no camera (`None` when it has one).
    #[getter]
    fn reason(&self) -> Option<&str> {
        self.reason.as_deref()
    }

    /// Intrinsics, 3×3 float64.
    #[getter(K)]
    fn k<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<f64>>> {
        self.camera
            .map(|c| matrix_to_py(py, &c.intrinsics.matrix()))
    }

    /// World-to-camera rotation, 3×3 float64.
    #[getter(R)]
    fn r<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<f64>>> {
        self.camera
            .map(|c| matrix_to_py(py, &c.cam_from_world.rotation))
    }

    /// World-to-camera translation, (3,) float64.
    #[getter]
    fn t<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray1<f64>>> {
        self.camera
            .map(|c| vector_to_py(py, c.cam_from_world.translation.as_slice()))
    }

    /// The camera centre in the world, (3,) float64 (`-R.T @ t`).
    #[getter]
    fn center<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray1<f64>>> {
        self.camera
            .map(|c| vector_to_py(py, c.center().coords.as_slice()))
    }

    fn __repr__(&self) -> String {
        match &self.camera {
            Some(c) => format!(
                "Camera({:?}, {}x{}, fx={:.1}, centre=[{:.3}, {:.3}, {:.3}])",
                self.name,
                self.size.width(),
                self.size.height(),
                c.intrinsics.fx(),
                c.center().x,
                c.center().y,
                c.center().z
            ),
            None => format!(
                "Camera({:?}, {}x{}, not estimated{})",
                self.name,
                self.size.width(),
                self.size.height(),
                self.reason
                    .as_deref()
                    .map(|r| format!(": {r}"))
                    .unwrap_or_default()
            ),
        }
    }
}

impl PyCamera {
    fn from_entry(e: &ImageCamera, reason: Option<String>) -> Self {
        Self {
            name: e.image.clone(),
            size: e.size,
            camera: e.camera,
            reason: if e.camera.is_some() { None } else { reason },
        }
    }
}

/// The result of [`estimate`]: cameras per image, sparse points, the run report.
#[pyclass(module = "posediff", name = "Reconstruction", frozen)]
struct PyReconstruction {
    run: Run,
    /// Images given as arrays live here as PNG files while the result lives.
    _arrays: Option<ArrayDir>,
}

#[pymethods]
impl PyReconstruction {
    /// One `Camera` per input image, in input order.
    #[getter]
    fn cameras(&self) -> Vec<PyCamera> {
        let reasons = not_estimated_reasons(&self.run);
        self.run
            .reconstruction
            .images
            .iter()
            .enumerate()
            .map(|(i, r)| PyCamera::from_entry(&r.camera, reasons[i].clone()))
            .collect()
    }

    /// The sparse points as a dict of arrays (`xyz` (N, 3) float64 in the cameras' world,
    /// `rgb` (N, 3) uint8, `error` (N,) mean reprojection error in px, `track_length` (N,)
    /// int64), or `None` when there are none.
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let points = &self.run.reconstruction.points;
        if points.is_empty() {
            return Ok(None);
        }
        let n = points.len();
        let xyz = Array2::from_shape_fn((n, 3), |(i, k)| points[i].xyz[k]);
        let rgb = Array2::from_shape_fn((n, 3), |(i, k)| points[i].rgb[k]);
        let error = Array1::from_iter(points.iter().map(|p| p.error_px));
        let tracks = Array1::from_iter(points.iter().map(|p| p.track.len() as i64));
        let d = PyDict::new(py);
        d.set_item("xyz", xyz.into_pyarray(py))?;
        d.set_item("rgb", rgb.into_pyarray(py))?;
        d.set_item("error", error.into_pyarray(py))?;
        d.set_item("track_length", tracks.into_pyarray(py))?;
        Ok(Some(d))
    }

    /// What the run did, as a dict: run.json without its `outputs` (those are filled by
    /// `write`).
    #[getter]
    fn report<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let text = serde_json::to_string(&self.run.report)
            .map_err(|e| Error::new_err(format!("report as JSON: {e}")))?;
        py.import("json")?.call_method1("loads", (text,))
    }

    /// Writes the outputs into the folder `out` (created): cameras.json and run.json always,
    /// and each of `formats` (`"colmap"`: sparse/0, `"nerfstudio"`: transforms.json +
    /// sparse_pc.ply, `"pytorch3d"`: pytorch3d.json, `"view"`: view.html, `"undistorted"`:
    /// undistorted/, the photos resampled onto pinhole cameras where a lens was estimated, and
    /// a PINHOLE model). `images` makes
    /// out/images a `"link"` to the inputs, a `"copy"` or `"none"` (default: link, copy for
    /// images given as arrays). Returns what was written (run.json's `outputs`).
    #[pyo3(signature = (out, formats = None, *, colmap_format = "text", images = None))]
    fn write<'py>(
        &self,
        py: Python<'py>,
        out: PathBuf,
        formats: Option<Vec<String>>,
        colmap_format: &str,
        images: Option<&str>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let formats =
            formats.unwrap_or_else(|| DEFAULT_FORMATS.iter().map(|f| (*f).to_owned()).collect());
        let mut options = OutputOptions {
            colmap_format: match colmap_format {
                "text" => ColmapFormat::Text,
                "binary" => ColmapFormat::Binary,
                other => {
                    return Err(value_err(format!(
                        "colmap_format must be \"text\" or \"binary\", got {other:?}"
                    )));
                }
            },
            images: match images {
                None if self._arrays.is_some() => ImagesMode::Copy,
                Some("link") if self._arrays.is_some() => {
                    return Err(value_err(
                        "images given as arrays live in a temporary folder that goes with the \
                         result: write them with images=\"copy\" (the default for arrays) or \"none\"",
                    ));
                }
                None | Some("link") => ImagesMode::Link,
                Some("copy") => ImagesMode::Copy,
                Some("none") => ImagesMode::None,
                Some(other) => {
                    return Err(value_err(format!(
                        "images must be \"link\", \"copy\" or \"none\", got {other:?}"
                    )));
                }
            },
            view: false,
            colmap: false,
            nerfstudio: false,
            pytorch3d: false,
            undistort: false,
            database: false,
        };
        for f in &formats {
            match f.as_str() {
                "cameras" => {}
                "colmap" => options.colmap = true,
                "nerfstudio" => options.nerfstudio = true,
                "pytorch3d" => options.pytorch3d = true,
                "view" => options.view = true,
                "undistorted" => options.undistort = true,
                "database" => options.database = true,
                other => {
                    return Err(value_err(format!(
                        "unknown format {other:?}: give any of \"cameras\", \"colmap\", \"nerfstudio\", \"pytorch3d\", \"view\", \"undistorted\", \"database\""
                    )));
                }
            }
        }
        let run = &self.run;
        let written = py
            .detach(|| {
                prepare_output_dir(&out, &run.inputs, options.images)?;
                run.write(&out, &options)
            })
            .map_err(py_err)?;
        let text = serde_json::to_string(&written)
            .map_err(|e| Error::new_err(format!("outputs as JSON: {e}")))?;
        py.import("json")?.call_method1("loads", (text,))
    }

    fn __len__(&self) -> usize {
        self.run.reconstruction.images.len()
    }

    fn __repr__(&self) -> String {
        let images = &self.run.reconstruction.images;
        format!(
            "Reconstruction({} images, {} estimated, {} points)",
            images.len(),
            images.iter().filter(|i| i.camera.camera.is_some()).count(),
            self.run.reconstruction.points.len()
        )
    }
}

/// The formats `Reconstruction.write` writes by default.
const DEFAULT_FORMATS: [&str; 4] = ["cameras", "colmap", "nerfstudio", "pytorch3d"];

/// Per image, the mapper's reason for leaving it out (the network estimates every image).
fn not_estimated_reasons(run: &Run) -> Vec<Option<String>> {
    let mut reasons = vec![None; run.reconstruction.images.len()];
    if let posediff::estimate::run_report::MethodReport::Geometric { report, .. } =
        &run.report.method
    {
        for n in &report.not_estimated {
            if let Some(slot) = reasons.get_mut(n.image) {
                *slot = Some(n.reason.clone());
            }
        }
    }
    for (slot, record) in reasons.iter_mut().zip(&run.reconstruction.images) {
        if slot.is_none() && record.camera.camera.is_none() {
            *slot = Some("not estimated".into());
        }
    }
    reasons
}

/// A folder of its own in the system's temporary folder, removed when dropped: where images
/// given as arrays live as PNG files while their result lives (a few lines instead of the
/// `tempfile` crate, whose `getrandom` features would make the wheel rebuild candle).
struct ArrayDir(PathBuf);

impl ArrayDir {
    fn new() -> std::io::Result<Self> {
        static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let base = std::env::temp_dir();
        loop {
            let k = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let dir = base.join(format!("posediff-arrays-{}-{k}", std::process::id()));
            match std::fs::create_dir(&dir) {
                Ok(()) => return Ok(Self(dir)),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(e),
            }
        }
    }

    fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for ArrayDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The images argument: a folder, one file, a list of paths, or a list of H×W×3 uint8 arrays
/// (written losslessly as PNG files, named `names` or `image_000.png`, ...).
fn resolve_images(
    images: &Bound<'_, PyAny>,
    names: Option<Vec<String>>,
    skip_bad_images: bool,
) -> PyResult<(Inputs, Option<ArrayDir>)> {
    if let Ok(one) = images.extract::<PathBuf>() {
        return Ok((
            Inputs::resolve(&[one], skip_bad_images).map_err(py_err)?,
            None,
        ));
    }
    let list = images.cast::<PyList>().map_err(|_| {
        value_err("images must be a folder, a list of image paths or a list of H×W×3 uint8 arrays")
    })?;
    if let Ok(paths) = list.extract::<Vec<PathBuf>>() {
        if names.is_some() {
            return Err(value_err(
                "names are for images given as arrays: files are named by their paths",
            ));
        }
        return Ok((
            Inputs::resolve(&paths, skip_bad_images).map_err(py_err)?,
            None,
        ));
    }
    let mut arrays = Vec::with_capacity(list.len());
    for (i, item) in list.iter().enumerate() {
        let a: PyReadonlyArray3<'_, u8> = item.extract().map_err(|_| {
            value_err(format!(
                "images[{i}] is neither a path nor an H×W×3 uint8 array (convert with np.asarray(img, dtype=np.uint8); grey images need three channels)"
            ))
        })?;
        let view = a.as_array();
        let shape = view.shape();
        if shape[2] != 3 {
            return Err(value_err(format!(
                "images[{i}] has shape {shape:?}: give H×W×3 RGB"
            )));
        }
        let (h, w) = (shape[0] as u32, shape[1] as u32);
        arrays.push((w, h, view.iter().copied().collect::<Vec<u8>>()));
    }
    let names = match names {
        Some(n) if n.len() != arrays.len() => {
            return Err(value_err(format!(
                "{} names for {} images",
                n.len(),
                arrays.len()
            )));
        }
        Some(n) => n,
        None => (0..arrays.len())
            .map(|i| format!("image_{i:03}.png"))
            .collect(),
    };
    for n in &names {
        let p = Path::new(n);
        if n.is_empty() || p.components().count() != 1 || p.file_name().is_none() {
            return Err(value_err(format!(
                "name {n:?} must be a plain file name (no folders)"
            )));
        }
    }
    let dir = ArrayDir::new()
        .map_err(|e| Error::new_err(format!("a temporary folder for the arrays: {e}")))?;
    let py = images.py();
    let folder = dir.path().to_owned();
    py.detach(|| -> posediff::Result<()> {
        for ((w, h, rgb), name) in arrays.iter().zip(&names) {
            posediff::io::loader::write_rgb_png(&folder.join(name), *w, *h, rgb)?;
        }
        Ok(())
    })
    .map_err(py_err)?;
    let files: Vec<PathBuf> = names.iter().map(|n| folder.join(n)).collect();
    let inputs = Inputs::resolve(&files, skip_bad_images).map_err(py_err)?;
    Ok((inputs, Some(dir)))
}

/// The videos `images` names (a path or a list of paths ending in a video extension); `None`
/// when it names no video.
fn video_paths(images: &Bound<'_, PyAny>) -> PyResult<Option<Vec<PathBuf>>> {
    let paths: Vec<PathBuf> = if let Ok(one) = images.extract::<PathBuf>() {
        vec![one]
    } else if let Ok(list) = images.extract::<Vec<PathBuf>>() {
        list
    } else {
        return Ok(None);
    };
    let videos = paths
        .iter()
        .filter(|p| posediff::io::video::is_video(p))
        .count();
    match videos {
        0 => Ok(None),
        n if n == paths.len() => Ok(Some(paths)),
        _ => Err(value_err(
            "give videos or images, not both (each video's keyframes become the images)",
        )),
    }
}

/// Each video probed, its masks checked, then decoded once into a temporary folder of
/// keyframes that lives as long as the result (written with images="copy").
fn keyframes(
    py: Python<'_>,
    videos: &[PathBuf],
    options: &mut RunOptions,
    progress: &mut PyProgress,
) -> PyResult<(Inputs, ArrayDir)> {
    use posediff::io::video::{check_masks, extract_keyframes, probe};
    options.check().map_err(py_err)?;
    let dir = ArrayDir::new()
        .map_err(|e| Error::new_err(format!("a temporary folder for the keyframes: {e}")))?;
    let frames = dir.path().join("images");
    let mask_out = dir.path().join("masks");
    let user_masks = options.masks.clone();
    let video_options = options.pipeline.video.clone();
    let capture = py
        .detach(|| -> posediff::Result<_> {
            let infos = probe(videos)?;
            if let Some(m) = &user_masks {
                check_masks(m, &infos)?;
            }
            extract_keyframes(
                &infos,
                &frames,
                &video_options,
                user_masks.as_deref().map(|m| (m, mask_out.as_path())),
                progress.counter(),
            )
        })
        .map_err(py_err)?;
    if let Some(e) = progress.take_error() {
        return Err(e);
    }
    options.masks = capture.masks.clone();
    Ok((Inputs::from_capture(capture), dir))
}

/// The keyword arguments of an estimation.
struct Call {
    options: RunOptions,
    skip_bad_images: bool,
    names: Option<Vec<String>>,
}

/// The options `estimate` takes as keywords (the CLI's flags).
const OPTION_NAMES: [&str; 21] = [
    "fps",
    "max_frames",
    "config",
    "options",
    "focal_px",
    "intrinsics",
    "init",
    "start_step",
    "refine",
    "matcher",
    "weights_dir",
    "pairs",
    "samples",
    "seed",
    "ggs",
    "skip_bad_images",
    "names",
    "masks",
    "database",
    "shard",
    "import_from",
];

/// One keyword of `options`, or its default.
fn option<'py, T>(options: Option<&Bound<'py, PyDict>>, key: &str, default: T) -> PyResult<T>
where
    T: pyo3::conversion::FromPyObjectOwned<'py>,
    for<'a> <T as FromPyObject<'a, 'py>>::Error: Into<PyErr>,
{
    match options.map(|o| o.get_item(key)).transpose()?.flatten() {
        Some(v) if !v.is_none() => v.extract::<T>().map_err(|e| {
            let e: PyErr = e.into();
            value_err(format!("{key}: {e}"))
        }),
        _ => Ok(default),
    }
}

/// The options tree from the keywords: `config` (a TOML or JSON file), then `pairs`, then
/// `options` (a dict of dotted keys, or of tables, to values), as the CLI's `--config`,
/// `--pairs` and `--set`.
fn pipeline_options(
    options: Option<&Bound<'_, PyDict>>,
    pairs: Option<&str>,
) -> PyResult<posediff::estimate::options::PipelineOptions> {
    let mut pipeline = posediff::estimate::options::PipelineOptions::default();
    if let Some(path) = option::<Option<PathBuf>>(options, "config", None)? {
        pipeline = pipeline.with_file(&path).map_err(py_err)?;
    }
    if let Some(fps) = option::<Option<f64>>(options, "fps", None)? {
        pipeline.video.fps = Some(fps);
    }
    if let Some(n) = option::<Option<usize>>(options, "max_frames", None)? {
        pipeline.video.max_frames = Some(n);
    }
    if let Some(pairs) = pairs {
        pipeline.pairs.selection = pairs
            .parse()
            .map_err(|e| value_err(format!("pairs {pairs:?}: {e}")))?;
    }
    let fields = options
        .map(|o| o.get_item("options"))
        .transpose()?
        .flatten()
        .filter(|v| !v.is_none());
    if let Some(fields) = fields {
        let fields: Bound<'_, PyDict> = fields
            .extract()
            .map_err(|_| value_err("options must be a dict of option keys to values"))?;
        let json = fields.py().import("json")?;
        for (key, value) in fields.iter() {
            let key: String = key.extract().map_err(|_| {
                value_err("options' keys must be strings such as \"orientation.strong_pair\"")
            })?;
            let text: String = json.call_method1("dumps", (value,))?.extract()?;
            pipeline = pipeline.with_field(&key, &text).map_err(py_err)?;
        }
    }
    Ok(pipeline)
}

/// The keyword options of an estimation, checked.
fn call_options(options: Option<&Bound<'_, PyDict>>) -> PyResult<Call> {
    if let Some(o) = options {
        for key in o.keys() {
            let key: String = key.extract()?;
            if !OPTION_NAMES.contains(&key.as_str()) {
                return Err(pyo3::exceptions::PyTypeError::new_err(format!(
                    "estimate() got an unexpected keyword argument {key:?} (options: {})",
                    OPTION_NAMES.join(", ")
                )));
            }
        }
    }
    let focal_px: Option<f64> = option(options, "focal_px", None)?;
    let intrinsics = options
        .map(|o| o.get_item("intrinsics"))
        .transpose()?
        .flatten()
        .filter(|v| !v.is_none());
    let intrinsics = intrinsics.as_ref();
    let init: Option<PathBuf> = option(options, "init", None)?;
    let start_step: usize = option(
        options,
        "start_step",
        posediff::estimate::run::DEFAULT_START_STEP,
    )?;
    let refine: String = option(options, "refine", "converge".to_owned())?;
    let refine = refine.as_str();
    let matcher: String = option(options, "matcher", "sift".to_owned())?;
    let matcher = matcher.as_str();
    let pairs: Option<String> = option(options, "pairs", None)?;
    let pipeline = pipeline_options(options, pairs.as_deref())?;
    let samples: usize = option(options, "samples", 1)?;
    let seed: u64 = option(options, "seed", 0)?;
    let ggs: bool = option(options, "ggs", true)?;
    let skip_bad_images: bool = option(options, "skip_bad_images", false)?;
    let names: Option<Vec<String>> = option(options, "names", None)?;
    let intrinsics = match (focal_px, intrinsics) {
        (Some(_), Some(_)) => {
            return Err(value_err("give focal_px or intrinsics, not both"));
        }
        (Some(f), None) => IntrinsicsSource::FocalPx(f),
        (None, None) => IntrinsicsSource::Estimate,
        (None, Some(k)) => {
            if let Ok(path) = k.extract::<PathBuf>() {
                IntrinsicsSource::File(path)
            } else {
                let a: PyReadonlyArray3<'_, f64> = k.extract().map_err(|_| {
                    value_err(
                        "intrinsics must be a cameras.json path or an (N, 3, 3) float64 array",
                    )
                })?;
                let v = a.as_array();
                if v.shape()[1..] != [3, 3] {
                    return Err(value_err(format!(
                        "intrinsics must be (N, 3, 3), got {:?}",
                        v.shape()
                    )));
                }
                let list = (0..v.shape()[0])
                    .map(|i| {
                        let m = Matrix3::from_fn(|r, c| v[[i, r, c]]);
                        Intrinsics::from_matrix(&m)
                            .map_err(|e| value_err(format!("intrinsics[{i}]: {e}")))
                    })
                    .collect::<PyResult<Vec<_>>>()?;
                IntrinsicsSource::PerImage(list)
            }
        }
    };
    let options = RunOptions {
        init: init.map(InitSource::from),
        start_step,
        intrinsics,
        refine: match refine {
            "converge" => RefineMode::Converge,
            "bundle" => RefineMode::Bundle,
            "official" => RefineMode::Official,
            "none" => RefineMode::None,
            other => {
                return Err(value_err(format!(
                    "refine must be \"converge\", \"bundle\", \"official\" or \"none\", got {other:?}"
                )));
            }
        },
        pipeline,
        matcher: matcher.parse().map_err(py_err)?,
        weights_dir: option::<Option<PathBuf>>(options, "weights_dir", None)?,
        seed,
        samples,
        ggs,
        thumbnail_side: None,
        masks: option::<Option<PathBuf>>(options, "masks", None)?,
        database: option::<Option<PathBuf>>(options, "database", None)?,
        map_database: false,
        shard: option::<Option<String>>(options, "shard", None)?
            .map(|s| posediff::estimate::run::Shard::parse(&s))
            .transpose()
            .map_err(py_err)?,
        import_from: option::<Option<Vec<PathBuf>>>(options, "import_from", None)?
            .unwrap_or_default(),
    };
    options.check().map_err(py_err)?;
    Ok(Call {
        options,
        skip_bad_images,
        names,
    })
}

/// A checkpoint loaded once for many estimations.
#[pyclass(module = "posediff", name = "Estimator", frozen)]
struct PyEstimator {
    estimator: Estimator,
    weights: PathBuf,
    device: &'static str,
    load_seconds: f64,
}

fn device_from(name: &str) -> PyResult<(candle_core::Device, &'static str)> {
    match name {
        "cpu" => Ok((candle_core::Device::Cpu, "cpu")),
        "cuda" => candle_core::Device::new_cuda(0)
            .map(|d| (d, "cuda"))
            .map_err(|e| {
                value_err(format!(
                    "device \"cuda\" needs a CUDA build (feature `cuda`) and a GPU: {e}"
                ))
            }),
        other => Err(value_err(format!(
            "device must be \"cpu\" or \"cuda\", got {other:?}"
        ))),
    }
}

impl PyEstimator {
    fn network(&self) -> Network<'_> {
        Network {
            estimator: &self.estimator,
            weights: &self.weights,
            device: self.device,
            load_seconds: self.load_seconds,
        }
    }
}

#[pymethods]
impl PyEstimator {
    /// Loads an official PoseDiffusion checkpoint (.pth or safetensors) on `device`.
    #[new]
    #[pyo3(signature = (weights, *, device = "cpu"))]
    fn new(py: Python<'_>, weights: PathBuf, device: &str) -> PyResult<Self> {
        let (dev, name) = device_from(device)?;
        let (estimator, load_seconds) = py
            .detach(|| load_estimator(&weights, dev))
            .map_err(py_err)?;
        Ok(Self {
            estimator,
            weights,
            device: name,
            load_seconds,
        })
    }

    /// As `posediff.estimate`, with this checkpoint (`options`: its keywords).
    #[pyo3(signature = (images, options = None, progress = None))]
    fn estimate(
        &self,
        py: Python<'_>,
        images: &Bound<'_, PyAny>,
        options: Option<&Bound<'_, PyDict>>,
        progress: Option<Py<PyAny>>,
    ) -> PyResult<PyReconstruction> {
        let call = call_options(options)?;
        estimate_with(py, images, call, Some(self.network()), progress)
    }

    fn __repr__(&self) -> String {
        format!(
            "Estimator({:?}, device={:?})",
            self.weights.display().to_string(),
            self.device
        )
    }
}

fn estimate_with(
    py: Python<'_>,
    images: &Bound<'_, PyAny>,
    call: Call,
    network: Option<Network<'_>>,
    progress: Option<Py<PyAny>>,
) -> PyResult<PyReconstruction> {
    let mut progress = PyProgress::new(progress);
    let mut options = call.options;
    let (inputs, arrays) = match video_paths(images)? {
        Some(videos) => {
            if network.is_some() {
                return Err(value_err(
                    "videos run the checkpoint-free path: estimate without weights, then give \
                     the keyframes (reconstruction.write(..., images=\"copy\")) to the estimator",
                ));
            }
            let (inputs, dir) = keyframes(py, &videos, &mut options, &mut progress)?;
            (inputs, Some(dir))
        }
        None => resolve_images(images, call.names, call.skip_bad_images)?,
    };
    let result = py.detach(|| run(&inputs, &options, network, &mut progress));
    if let Some(e) = progress.take_error() {
        return Err(e);
    }
    Ok(PyReconstruction {
        run: result.map_err(py_err)?,
        _arrays: arrays,
    })
}

/// Cameras (and points) for `images`; see the package docstring (`options`: the keywords).
#[pyfunction]
#[pyo3(signature = (images, options = None, weights = None, device = "cpu", progress = None))]
fn estimate(
    py: Python<'_>,
    images: &Bound<'_, PyAny>,
    options: Option<&Bound<'_, PyDict>>,
    weights: Option<PathBuf>,
    device: &str,
    progress: Option<Py<PyAny>>,
) -> PyResult<PyReconstruction> {
    let call = call_options(options)?;
    match weights {
        Some(w) => {
            let est = PyEstimator::new(py, w, device)?;
            estimate_with(py, images, call, Some(est.network()), progress)
        }
        None if device != "cpu" => Err(value_err(format!(
            "device {device:?} runs the network: it needs weights"
        ))),
        None => estimate_with(py, images, call, None, progress),
    }
}

/// `posediff features` / `posediff match` (`stop`: "features" or "matching"; "import": only
/// `import_from`'s features and pairs taken in; "selection": features and the pair selection
/// stored, nothing matched) into
/// `options["database"]`, with `shard` and `import_from` as the CLI's `--shard` and `--from`:
/// the stages `posediff.distributed` runs as Ray tasks. Returns what the database holds.
#[pyfunction]
#[pyo3(signature = (images, stop, options = None, progress = None))]
fn run_stages<'py>(
    py: Python<'py>,
    images: &Bound<'py, PyAny>,
    stop: &str,
    options: Option<&Bound<'py, PyDict>>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let stop = match stop {
        "import" => posediff::estimate::run::StopAfter::Import,
        "selection" => posediff::estimate::run::StopAfter::Selection,
        "features" => posediff::estimate::run::StopAfter::Features,
        "matching" => posediff::estimate::run::StopAfter::Matching,
        other => {
            return Err(value_err(format!(
                "stop must be \"import\", \"features\", \"selection\" or \"matching\", got {other:?}"
            )));
        }
    };
    let call = call_options(options)?;
    if video_paths(images)?.is_some() {
        return Err(value_err(
            "run_stages takes images: extract a video's keyframes with estimate() first",
        ));
    }
    let (inputs, _arrays) = resolve_images(images, call.names, call.skip_bad_images)?;
    let mut progress = PyProgress::new(progress);
    let result = py.detach(|| {
        posediff::estimate::run::run_stages(&inputs, &call.options, stop, &mut progress)
    });
    if let Some(e) = progress.take_error() {
        return Err(e);
    }
    let summary = result.map_err(py_err)?;
    let d = PyDict::new(py);
    d.set_item("images", summary.images)?;
    d.set_item("pairs", summary.pairs)?;
    d.set_item("verified", summary.verified)?;
    d.set_item("selection", summary.selection)?;
    d.set_item("imported_images", summary.imported.0)?;
    d.set_item("imported_pairs", summary.imported.1)?;
    Ok(d)
}

/// Checks `options` as `estimate` would (names, types, ranges, files), doing no work.
#[pyfunction]
#[pyo3(signature = (options = None))]
fn check_options(options: Option<&Bound<'_, PyDict>>) -> PyResult<()> {
    call_options(options).map(|_| ())
}

/// The cameras of a cameras.json (posediff's or the shared sets' schema), in file order.
#[pyfunction]
fn read_cameras(path: PathBuf) -> PyResult<Vec<PyCamera>> {
    let entries = posediff::io::export::read_cameras_json_partial(&path).map_err(py_err)?;
    Ok(entries
        .iter()
        .map(|e| PyCamera::from_entry(e, Some("not estimated".into())))
        .collect())
}

/// An image file decoded as posediff decodes it: (H, W, 3) uint8 RGB.
#[pyfunction]
fn read_image<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyArray3<u8>>> {
    if !path.exists() {
        return Err(py_err(PosediffError::NotFound(path)));
    }
    let (size, rgb) = py
        .detach(|| posediff::io::loader::read_rgb(&path))
        .map_err(py_err)?;
    let a = Array3::from_shape_vec((size.height() as usize, size.width() as usize, 3), rgb)
        .map_err(|e| Error::new_err(format!("{}: {e}", path.display())))?;
    Ok(a.into_pyarray(py))
}

/// The official test.py metrics of `pred` against `gt` (every pair; images not estimated
/// fail all their pairs): a dict with `rra`, `rta` (at 5, 15, 30 degrees), `maa_30`, ... and
/// `cc_10`, the fraction of camera centres within 10 % of the scene's size after alignment.
/// `pred` is a `Reconstruction` or a cameras.json path, `gt` a cameras.json path; images are
/// matched by name.
#[pyfunction]
fn score<'py>(
    py: Python<'py>,
    pred: &Bound<'py, PyAny>,
    gt: PathBuf,
) -> PyResult<Bound<'py, PyAny>> {
    let entries: Vec<ImageCamera> = if let Ok(r) = pred.cast::<PyReconstruction>() {
        r.get()
            .run
            .reconstruction
            .images
            .iter()
            .map(|i| i.camera.clone())
            .collect()
    } else if let Ok(path) = pred.extract::<PathBuf>() {
        posediff::io::export::read_cameras_json_partial(&path).map_err(py_err)?
    } else {
        return Err(value_err(
            "pred must be a Reconstruction or the path of a cameras.json",
        ));
    };
    let names: Vec<String> = entries.iter().map(|e| e.image.clone()).collect();
    let truth = posediff::io::records::ground_truth_for(&names, &gt, "pred").map_err(py_err)?;
    let poses: Vec<Option<Pose>> = entries
        .iter()
        .map(|e| e.camera.map(|c| c.cam_from_world))
        .collect();
    let (scores, cc) = posediff::bench::score_set(&truth, &poses)
        .map_err(|e| value_err(format!("scoring against {}: {e}", gt.display())))?;
    let mut value =
        serde_json::to_value(scores).map_err(|e| Error::new_err(format!("scores as JSON: {e}")))?;
    if let Some(map) = value.as_object_mut() {
        map.insert("cc_10".into(), serde_json::json!(cc));
    }
    py.import("json")?
        .call_method1("loads", (value.to_string(),))
}

/// OpenCV `K, R, t` (one camera, pixels) to PyTorch3D `PerspectiveCameras` parameters in NDC,
/// as PyTorch3D's `cameras_from_opencv_projection`: a dict with `R` (3×3, row-vector:
/// `X_cam = X_world @ R + T`), `T` (3,), `focal_length` (2,), `principal_point` (2,).
/// `image_size` is `(height, width)`, PyTorch3D's order.
#[pyfunction]
#[allow(non_snake_case)] // the names users write: K, R, t
fn opencv_to_pytorch3d<'py>(
    py: Python<'py>,
    K: PyReadonlyArray2<'py, f64>,
    R: PyReadonlyArray2<'py, f64>,
    t: PyReadonlyArray1<'py, f64>,
    image_size: (u32, u32),
) -> PyResult<Bound<'py, PyDict>> {
    let (k, r) = (K, R);
    let size = size_from_hw(image_size)?;
    let intrinsics = Intrinsics::from_matrix(&matrix_from_py(&k, "K")?)
        .map_err(|e| value_err(format!("K: {e}")))?;
    let t = vector_from_py::<3>(&t, "t")?;
    let pose = Pose::new(matrix_from_py(&r, "R")?, Vector3::from(t));
    let cam = Camera::new(intrinsics, pose, size);
    let p = Pytorch3dCamera::from_opencv(&cam);
    let d = PyDict::new(py);
    d.set_item("R", matrix_to_py(py, &p.r))?;
    d.set_item("T", vector_to_py(py, p.t.as_slice()))?;
    d.set_item(
        "focal_length",
        vector_to_py(py, p.intrinsics.focal.as_slice()),
    )?;
    d.set_item(
        "principal_point",
        vector_to_py(py, p.intrinsics.principal_point.as_slice()),
    )?;
    Ok(d)
}

/// PyTorch3D `PerspectiveCameras` parameters in NDC (one camera) to OpenCV `(K, R, t)` in
/// pixels, as PyTorch3D's `opencv_from_cameras_projection`. `image_size` is
/// `(height, width)`.
#[pyfunction]
#[allow(non_snake_case)] // PyTorch3D's names R, T
fn pytorch3d_to_opencv<'py>(
    py: Python<'py>,
    R: PyReadonlyArray2<'py, f64>,
    T: PyReadonlyArray1<'py, f64>,
    focal_length: PyReadonlyArray1<'py, f64>,
    principal_point: PyReadonlyArray1<'py, f64>,
    image_size: (u32, u32),
) -> PyResult<Krt<'py>> {
    let (r, t) = (R, T);
    let size = size_from_hw(image_size)?;
    let p = Pytorch3dCamera {
        r: matrix_from_py(&r, "R")?,
        t: Vector3::from(vector_from_py::<3>(&t, "T")?),
        intrinsics: NdcIntrinsics {
            focal: Vector2::from(vector_from_py::<2>(&focal_length, "focal_length")?),
            principal_point: Vector2::from(vector_from_py::<2>(
                &principal_point,
                "principal_point",
            )?),
        },
    };
    let cam = p
        .to_opencv(size)
        .map_err(|e| value_err(format!("PyTorch3D camera: {e}")))?;
    Ok(camera_arrays(py, &cam))
}

fn camera_arrays<'py>(py: Python<'py>, cam: &Camera) -> Krt<'py> {
    (
        matrix_to_py(py, &cam.intrinsics.matrix()),
        matrix_to_py(py, &cam.cam_from_world.rotation),
        vector_to_py(py, cam.cam_from_world.translation.as_slice()),
    )
}

/// The official pose encoding (`absT_quaR_logFL`, (N, 9): T, quaternion wxyz, log focal in
/// NDC) to OpenCV cameras for images of `image_size` `(height, width)`: `(K, R, t)` stacked as
/// (N, 3, 3), (N, 3, 3), (N, 3) float64. This is the official `pose_encoding_to_camera`
/// followed by `opencv_from_cameras_projection` (focal clamped to [0.1, 20] NDC as there).
#[pyfunction]
fn pose_encoding_to_cameras<'py>(
    py: Python<'py>,
    encoding: PyReadonlyArray2<'py, f64>,
    image_size: (u32, u32),
) -> PyResult<KrtStack<'py>> {
    let size = size_from_hw(image_size)?;
    let v = encoding.as_array();
    if v.ndim() != 2 || v.shape()[1] != 9 {
        return Err(value_err(format!(
            "encoding must be (N, 9), got {:?}",
            v.shape()
        )));
    }
    let n = v.shape()[0];
    let mut k = Array3::<f64>::zeros((n, 3, 3));
    let mut r = Array3::<f64>::zeros((n, 3, 3));
    let mut t = Array2::<f64>::zeros((n, 3));
    for i in 0..n {
        let mut e = [0.0; 9];
        for (j, x) in e.iter_mut().enumerate() {
            *x = v[[i, j]];
        }
        let cam = PoseEncoding(e)
            .to_camera(size)
            .map_err(|err| value_err(format!("encoding[{i}]: {err}")))?;
        let km = cam.intrinsics.matrix();
        for a in 0..3 {
            t[[i, a]] = cam.cam_from_world.translation[a];
            for b in 0..3 {
                k[[i, a, b]] = km[(a, b)];
                r[[i, a, b]] = cam.cam_from_world.rotation[(a, b)];
            }
        }
    }
    Ok((k.into_pyarray(py), r.into_pyarray(py), t.into_pyarray(py)))
}

/// The extension module.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("Error", m.py().get_type::<Error>())?;
    m.add_class::<PyCamera>()?;
    m.add_class::<PyReconstruction>()?;
    m.add_class::<PyEstimator>()?;
    m.add_function(wrap_pyfunction!(estimate, m)?)?;
    m.add_function(wrap_pyfunction!(read_cameras, m)?)?;
    m.add_function(wrap_pyfunction!(run_stages, m)?)?;
    m.add_function(wrap_pyfunction!(check_options, m)?)?;
    m.add_function(wrap_pyfunction!(read_image, m)?)?;
    m.add_function(wrap_pyfunction!(score, m)?)?;
    m.add_function(wrap_pyfunction!(opencv_to_pytorch3d, m)?)?;
    m.add_function(wrap_pyfunction!(pytorch3d_to_opencv, m)?)?;
    m.add_function(wrap_pyfunction!(pose_encoding_to_cameras, m)?)?;
    Ok(())
}
