//! Everything `posediff estimate` writes into its output folder, in the layout Gaussian
//! splatting and NeRF tools load as it is:
//!
//! ```text
//! out/
//!   cameras.json          every image (OpenCV), "estimated": false where none
//!   sparse/0/             COLMAP model with points (text or binary)
//!   images/               the input images (a link to the folder, per-file links, or copies),
//!                         or a video's keyframes (moved in with the results)
//!   transforms.json       nerfstudio (file paths relative to out/, ply_file_path)
//!   sparse_pc.ply         the points in transforms.json's world
//!   pytorch3d.json        the official model's convention
//!   view.html             the 3-D viewer
//!   undistorted/          with --undistort: photos on pinhole cameras, a PINHOLE model
//!   run.json              options, stage times, reports, warnings
//! ```
//!
//! The results are written whole or not at all: into `out/.posediff-staging/` first, then
//! moved into place by renames ([`RESULTS`]: the previous run's entries moved aside first,
//! run.json last, so a folder with run.json holds one run's results). A run that fails or is
//! killed while writing leaves the previous results; one killed between those renames
//! (microseconds) is rolled back to them by the next run before it does any work.

use std::path::{Path, PathBuf};

use rayon::prelude::*;

use crate::error::{PosediffError, Result};
use crate::io::colmap::{ColmapFormat, ColmapModel};
use crate::io::export::{
    NerfstudioCamera, nerfstudio_applied_transform, write_cameras_json_partial, write_nerfstudio,
    write_ply, write_pytorch3d,
};
use crate::reconstruction::{Reconstruction, read_colour, thumbnail_jpeg};

/// How the images are made reachable as `out/images/`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ImagesMode {
    /// A symbolic link to the input folder (or one per image when files were given).
    #[default]
    Link,
    /// Copies.
    Copy,
    /// Nothing: `transforms.json` names the images by absolute path.
    None,
    /// The images are the run's own (a video's keyframes, in a work folder: the input
    /// folder): moved into `out/images` with the results, replacing what was there.
    Move,
}

/// What [`write_outputs`] writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OutputOptions {
    /// The COLMAP model's files.
    pub colmap_format: ColmapFormat,
    /// `out/images/`.
    pub images: ImagesMode,
    /// `view.html`.
    pub view: bool,
    /// The COLMAP model `sparse/0`.
    pub colmap: bool,
    /// nerfstudio's `transforms.json` and its points `sparse_pc.ply`.
    pub nerfstudio: bool,
    /// `pytorch3d.json`.
    pub pytorch3d: bool,
    /// `undistorted/` (images resampled onto their pinhole cameras and a PINHOLE model,
    /// [`crate::io::undistort`]), when some camera has a lens.
    pub undistort: bool,
    /// `database.db`: COLMAP's database of the keypoints and verified matches
    /// ([`crate::io::database`]).
    pub database: bool,
}

impl Default for OutputOptions {
    fn default() -> Self {
        Self {
            colmap_format: ColmapFormat::Text,
            images: ImagesMode::Link,
            view: true,
            colmap: true,
            nerfstudio: true,
            pytorch3d: true,
            undistort: false,
            database: false,
        }
    }
}

/// The input images: one file per image and the folder their names are relative to.
#[derive(Debug, Clone)]
pub struct InputImages {
    /// One per image, in input order.
    pub files: Vec<PathBuf>,
    /// The folder the names are relative to (the folder given, or the first file's).
    pub folder: Option<PathBuf>,
    /// Whether a folder was given (then `out/images` can link to it).
    pub folder_given: bool,
}

/// Longer side of the viewer's thumbnails, px (smaller for long sequences).
pub fn thumbnail_side(n: usize) -> u32 {
    if n > 300 {
        64
    } else if n > 100 {
        96
    } else {
        160
    }
}

/// Checks, before any computation, that `out` can be created and written and that
/// `out/images` can be made in `mode`.
///
/// # Errors
/// `out` is a file or cannot be created or written; `out/images` is in the way.
pub fn prepare_output_dir(out: &Path, inputs: &InputImages, mode: ImagesMode) -> Result<()> {
    if out.exists() && !out.is_dir() {
        return Err(PosediffError::InvalidArgument(format!(
            "--out {} is an existing file, not a folder: choose a folder",
            out.display()
        )));
    }
    std::fs::create_dir_all(out).map_err(|source| PosediffError::Write {
        path: out.to_owned(),
        source,
    })?;
    // What an interrupted run left is undone before anything else.
    recover(out)?;
    remove(&out.join(FRAMES))?;
    let probe = out.join(".posediff-write-test");
    std::fs::write(&probe, b"").map_err(|source| PosediffError::Write {
        path: probe.clone(),
        source,
    })?;
    let _ = std::fs::remove_file(&probe);
    if !matches!(mode, ImagesMode::None | ImagesMode::Move) {
        images_plan(out, inputs, mode)?;
    }
    Ok(())
}

/// What `out/images` becomes.
enum ImagesPlan {
    /// `out/images` already is the input folder (or links to it).
    AlreadyThere,
    /// `out/images` → the input folder.
    LinkFolder(PathBuf),
    /// One entry per image inside the real folder `out/images` (replacing a link that is
    /// there).
    PerFile {
        /// `out/images` is a link to remove first.
        replace_link: bool,
    },
}

fn images_plan(out: &Path, inputs: &InputImages, mode: ImagesMode) -> Result<ImagesPlan> {
    let dest = out.join("images");
    if let (Some(folder), true) = (&inputs.folder, inputs.folder_given) {
        let canonical = folder
            .canonicalize()
            .map_err(|source| PosediffError::Read {
                path: folder.clone(),
                source,
            })?;
        if dest.canonicalize().is_ok_and(|d| d == canonical) {
            return Ok(ImagesPlan::AlreadyThere);
        }
        if mode == ImagesMode::Link && (dest.is_symlink() || !dest.exists()) {
            return Ok(ImagesPlan::LinkFolder(canonical));
        }
    }
    // `out/images` as a link (an earlier run's, to other images) is replaced by a real folder,
    // never written through.
    if dest.is_symlink() {
        return Ok(ImagesPlan::PerFile { replace_link: true });
    }
    if dest.exists() && !dest.is_dir() {
        return Err(PosediffError::InvalidArgument(format!(
            "{} exists and is not a folder: remove it or give --images none",
            dest.display()
        )));
    }
    // Per-file links into a real folder: an existing file of another image in the way is an
    // error (never overwritten in link mode).
    if mode == ImagesMode::Link && dest.is_dir() {
        for (file, name) in inputs.files.iter().zip(names(inputs)) {
            let entry = dest.join(&name);
            if entry.exists() && !entry.is_symlink() {
                let same = entry.canonicalize().ok() == file.canonicalize().ok();
                if !same {
                    return Err(PosediffError::InvalidArgument(format!(
                        "{} exists and is not a link to {}: remove it or give --images copy|none",
                        entry.display(),
                        file.display()
                    )));
                }
            }
        }
    }
    Ok(ImagesPlan::PerFile {
        replace_link: false,
    })
}

/// Image names as the outputs record them.
fn names(inputs: &InputImages) -> Vec<String> {
    inputs
        .files
        .iter()
        .map(|p| crate::io::loader::relative_name(p, inputs.folder.as_deref()))
        .collect()
}

fn make_images(out: &Path, inputs: &InputImages, mode: ImagesMode) -> Result<()> {
    let dest = out.join("images");
    let io = |path: &Path| {
        let path = path.to_owned();
        move |source| PosediffError::Write { path, source }
    };
    match images_plan(out, inputs, mode)? {
        ImagesPlan::AlreadyThere => Ok(()),
        ImagesPlan::LinkFolder(target) => {
            if dest.is_symlink() {
                std::fs::remove_file(&dest).map_err(io(&dest))?;
            }
            symlink(&target, &dest).map_err(io(&dest))
        }
        ImagesPlan::PerFile { replace_link } => {
            if replace_link {
                std::fs::remove_file(&dest).map_err(io(&dest))?;
            }
            for (file, name) in inputs.files.iter().zip(names(inputs)) {
                let entry = dest.join(&name);
                if let Some(parent) = entry.parent() {
                    std::fs::create_dir_all(parent).map_err(io(parent))?;
                }
                if entry.is_symlink() {
                    std::fs::remove_file(&entry).map_err(io(&entry))?;
                }
                match mode {
                    ImagesMode::Copy => {
                        if entry.canonicalize().ok() != file.canonicalize().ok() {
                            std::fs::copy(file, &entry).map_err(io(&entry))?;
                        }
                    }
                    _ => {
                        if !entry.exists() {
                            let target =
                                file.canonicalize().map_err(|source| PosediffError::Read {
                                    path: file.clone(),
                                    source,
                                })?;
                            symlink(&target, &entry).map_err(io(&entry))?;
                        }
                    }
                }
            }
            Ok(())
        }
    }
}

#[cfg(unix)]
fn symlink(target: &Path, link: &Path) -> std::io::Result<()> {
    std::os::unix::fs::symlink(target, link)
}

#[cfg(not(unix))]
fn symlink(target: &Path, link: &Path) -> std::io::Result<()> {
    // Without symbolic links (or the right to make them), copy.
    std::fs::copy(target, link).map(|_| ())
}

pub use crate::estimate::run_report::Written;

/// Writes every output of `r` into `out` (see the module's layout), `run` as run.json with
/// its `outputs` filled. The viewer's thumbnails are `thumbnails_made` when given (e.g. from
/// [`Reconstruction::colour_and_thumbnails`], one decode per image), else made here.
///
/// # Errors
/// I/O errors naming the file; images that cannot be read for the thumbnails.
pub fn write_outputs(
    out: &Path,
    r: &Reconstruction,
    inputs: &InputImages,
    run: &crate::estimate::run_report::RunReport,
    options: &OutputOptions,
    thumbnails_made: Option<&[Option<Vec<u8>>]>,
) -> Result<Written> {
    write_outputs_with_pairs(out, r, &[], inputs, run, options, thumbnails_made)
}

/// [`write_outputs`] with the run's verified pairs (for `database.db`).
///
/// # Errors
/// As [`write_outputs`]; a database that cannot be written.
pub fn write_outputs_with_pairs(
    out: &Path,
    r: &Reconstruction,
    pairs: &[posediff_geometry::PairMatches],
    inputs: &InputImages,
    run: &crate::estimate::run_report::RunReport,
    options: &OutputOptions,
    thumbnails_made: Option<&[Option<Vec<u8>>]>,
) -> Result<Written> {
    let results = (r, pairs);
    write_and_commit(
        out,
        results,
        inputs,
        run,
        options,
        thumbnails_made,
        usize::MAX,
    )
}

/// [`write_outputs`] stopped after `steps` of its commit's renames, as a kill there would
/// leave the folder (for tests of [`recover`]); `Ok(true)` when the commit was complete.
///
/// # Errors
/// As [`write_outputs`].
#[doc(hidden)]
pub fn write_outputs_interrupted(
    out: &Path,
    r: &Reconstruction,
    inputs: &InputImages,
    run: &crate::estimate::run_report::RunReport,
    options: &OutputOptions,
    steps: usize,
) -> Result<bool> {
    let results = (r, &[][..]);
    write_and_commit(out, results, inputs, run, options, None, steps)?;
    Ok(!exists(&out.join(PREVIOUS)) && !exists(&out.join(STAGING)))
}

fn write_and_commit(
    out: &Path,
    (r, pairs): (&Reconstruction, &[posediff_geometry::PairMatches]),
    inputs: &InputImages,
    run: &crate::estimate::run_report::RunReport,
    options: &OutputOptions,
    thumbnails_made: Option<&[Option<Vec<u8>>]>,
    steps: usize,
) -> Result<Written> {
    std::fs::create_dir_all(out).map_err(|source| PosediffError::Write {
        path: out.to_owned(),
        source,
    })?;
    recover(out)?;
    let staging = out.join(STAGING);
    std::fs::create_dir_all(&staging).map_err(|source| PosediffError::Write {
        path: staging.clone(),
        source,
    })?;
    let written = match write_results(
        out,
        &staging,
        (r, pairs),
        inputs,
        run,
        options,
        thumbnails_made,
    ) {
        Ok(w) => w,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&staging);
            return Err(e);
        }
    };
    commit(out, &staging, steps)?;
    Ok(written)
}

/// Where a run's results are written before they are moved into `out`.
const STAGING: &str = ".posediff-staging";
/// Where the previous run's results wait while the new ones are moved in.
const PREVIOUS: &str = ".posediff-previous";
/// Every result entry a run may write (relative to `out`), in the order they are moved aside:
/// run.json first (the folder then no longer claims a result), and moved in last. `images` is
/// not among them: it is the input, made before the results.
pub const RESULTS: [&str; 9] = [
    "run.json",
    "database.db",
    "cameras.json",
    "sparse/0",
    "transforms.json",
    "sparse_pc.ply",
    "pytorch3d.json",
    "view.html",
    "undistorted",
];

fn rename(from: &Path, to: &Path) -> Result<()> {
    if let Some(parent) = to.parent() {
        std::fs::create_dir_all(parent).map_err(|source| PosediffError::Write {
            path: parent.to_owned(),
            source,
        })?;
    }
    std::fs::rename(from, to).map_err(|source| PosediffError::Write {
        path: to.to_owned(),
        source,
    })
}

fn remove(path: &Path) -> Result<()> {
    let gone = match std::fs::symlink_metadata(path) {
        Err(_) => Ok(()),
        Ok(m) if m.is_dir() => std::fs::remove_dir_all(path),
        Ok(_) => std::fs::remove_file(path),
    };
    gone.map_err(|source| PosediffError::Write {
        path: path.to_owned(),
        source,
    })
}

fn exists(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok()
}

/// Moves the staged results into `out`: the previous ones aside (run.json first), a marker
/// ([`MOVED_ASIDE`], listing what the new run moves in) once they all are, the new ones in
/// (run.json last), then the previous ones and the staging folder removed.
fn commit(out: &Path, staging: &Path, steps: usize) -> Result<()> {
    // Each step is one rename (or the marker's write): atomic, so a kill lands between two.
    let mut left = steps;
    let mut step = || {
        left = left.saturating_sub(1);
        left > 0
    };
    let previous = out.join(PREVIOUS);
    remove(&previous)?;
    let entries = entries_of(staging);
    for entry in &entries {
        if exists(&out.join(entry)) {
            rename(&out.join(entry), &previous.join(entry))?;
            if !step() {
                return Ok(());
            }
        }
    }
    // Until this marker exists, every result entry still in `out` is the previous run's
    // (not yet moved aside); once it does, every one is the new run's.
    std::fs::create_dir_all(&previous).map_err(|source| PosediffError::Write {
        path: previous.clone(),
        source,
    })?;
    let partial = previous.join(".posediff-moved-aside.partial");
    std::fs::write(&partial, entries.join("\n")).map_err(|source| PosediffError::Write {
        path: partial.clone(),
        source,
    })?;
    rename(&partial, &previous.join(MOVED_ASIDE))?;
    if !step() {
        return Ok(());
    }
    for entry in entries.iter().rev() {
        if exists(&staging.join(entry)) {
            rename(&staging.join(entry), &out.join(entry))?;
            if !step() {
                return Ok(());
            }
        }
    }
    remove(&previous)?;
    remove(staging)
}

/// The marker in [`PREVIOUS`] that says every previous entry has been moved aside: from then
/// on, the result entries in `out` are the new run's. It lists them, one per line.
const MOVED_ASIDE: &str = ".posediff-moved-aside";

/// [`RESULTS`], and `images` after run.json when `folder` holds images of the run's own
/// ([`ImagesMode::Move`]).
fn entries_of(folder: &Path) -> Vec<&'static str> {
    let mut entries = RESULTS.to_vec();
    if exists(&folder.join("images")) {
        entries.insert(1, "images");
    }
    entries
}

/// Where a video's keyframes are written before the run's results are (an interrupted run's
/// are removed by [`recover`]).
pub const FRAMES: &str = ".posediff-frames";

/// Undoes what an interrupted run left in `out`: its staging folder, and, when it was killed
/// while moving results (no run.json in place), the previous results put back: while it was
/// moving them aside, those it had moved; once it was moving the new ones in (the
/// `.posediff-moved-aside` marker), the new entries removed first.
///
/// # Errors
/// I/O errors naming the path.
pub fn recover(out: &Path) -> Result<()> {
    remove(&out.join(STAGING))?;
    let previous = out.join(PREVIOUS);
    if !exists(&previous) {
        return Ok(());
    }
    if !exists(&out.join("run.json")) {
        log::warn!(
            "{}: a run was interrupted while moving its results; the previous results are put \
             back",
            out.display()
        );
        let mut entries: Vec<String> = RESULTS.iter().map(|e| (*e).to_owned()).collect();
        entries.push("images".into());
        let moving_in = match std::fs::read_to_string(previous.join(MOVED_ASIDE)) {
            Ok(list) => {
                // The new run's entries (images only when it moved its own in).
                entries = list.lines().map(str::to_owned).collect();
                true
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
            Err(source) => {
                return Err(PosediffError::Read {
                    path: previous.join(MOVED_ASIDE),
                    source,
                });
            }
        };
        // run.json last: a recovery that is itself interrupted is taken up again by the next.
        for entry in entries.iter().rev() {
            let (now, before) = (out.join(entry), previous.join(entry));
            if moving_in {
                remove(&now)?;
            }
            if exists(&before) {
                rename(&before, &now)?;
            }
        }
    }
    remove(&previous)
}

/// The results of `r` written into `stage` (and `out/images` made in `out`): what
/// [`write_outputs`] then moves into `out`.
fn write_results(
    out: &Path,
    stage: &Path,
    (r, pairs): (&Reconstruction, &[posediff_geometry::PairMatches]),
    inputs: &InputImages,
    run: &crate::estimate::run_report::RunReport,
    options: &OutputOptions,
    thumbnails_made: Option<&[Option<Vec<u8>>]>,
) -> Result<Written> {
    let mut files = vec!["cameras.json".to_owned()];
    let entries: Vec<_> = r.images.iter().map(|i| i.camera.clone()).collect();
    write_cameras_json_partial(&stage.join("cameras.json"), &entries)?;
    let model = ColmapModel::from_reconstruction(r)?;
    if options.colmap {
        model.write(&stage.join("sparse").join("0"), options.colmap_format)?;
        files.push("sparse/0".into());
    }
    if !matches!(options.images, ImagesMode::None | ImagesMode::Move)
        && (options.colmap || options.nerfstudio)
    {
        make_images(out, inputs, options.images)?;
        files.push("images".into());
    }
    if options.nerfstudio {
        write_ply(
            &stage.join("sparse_pc.ply"),
            &r.points,
            &nerfstudio_applied_transform(),
        )?;
        files.push("sparse_pc.ply".into());
        let nerf: Vec<NerfstudioCamera> = r
            .images
            .iter()
            .zip(&inputs.files)
            .enumerate()
            .filter_map(|(i, (record, file))| {
                record.camera.camera.map(|camera| NerfstudioCamera {
                    camera,
                    lens: record.camera.lens.clone(),
                    file_path: match options.images {
                        ImagesMode::None => file
                            .canonicalize()
                            .unwrap_or_else(|_| file.clone())
                            .to_string_lossy()
                            .into_owned(),
                        _ => format!("images/{}", record.camera.image),
                    },
                    colmap_id: Some(i as u32 + 1),
                })
            })
            .collect();
        write_nerfstudio(&stage.join("transforms.json"), &nerf, Some("sparse_pc.ply"))?;
        files.push("transforms.json".into());
    }
    if options.undistort && r.images.iter().any(|i| i.camera.lens.is_some()) {
        crate::io::undistort::write_undistorted(
            &stage.join("undistorted"),
            r,
            &inputs.files,
            options.colmap_format,
        )?;
        files.push("undistorted".into());
    }
    if options.database {
        crate::io::database::write_database(&stage.join("database.db"), r, pairs)?;
        files.push("database.db".into());
    }
    if options.pytorch3d {
        write_pytorch3d(&stage.join("pytorch3d.json"), &entries)?;
        files.push("pytorch3d.json".into());
    }
    if options.view {
        let thumbs = match thumbnails_made {
            Some(t) => t.to_vec(),
            None => thumbnails(r, &inputs.files)?,
        };
        let title = set_title(inputs.folder.as_deref());
        let html = crate::io::viewer::render(&title, r, &thumbs, None)?;
        let path = stage.join("view.html");
        std::fs::write(&path, html).map_err(|source| PosediffError::Write { path, source })?;
        files.push("view.html".into());
    }
    if options.images == ImagesMode::Move {
        // Last, once nothing reads the images any more: the run's own images join the
        // results.
        let folder = inputs.folder.as_deref().ok_or_else(|| {
            PosediffError::InvalidArgument("--images move needs the images' folder".into())
        })?;
        rename(folder, &stage.join("images"))?;
        files.push("images".into());
    }
    files.push("run.json".into());
    let written = Written {
        files,
        points: model.points.len(),
        mean_reprojection_error_px: r.mean_error_px(),
        mean_track_length: r.mean_track_length(),
    };
    let mut run = run.clone();
    run.outputs = Some(written.clone());
    let path = stage.join("run.json");
    std::fs::write(&path, serde_json::to_string_pretty(&run)?)
        .map_err(|source| PosediffError::Write { path, source })?;
    Ok(written)
}

/// The set's name for the viewer: the folder's name, or its parent's when the folder is
/// called `images`.
pub fn set_title(folder: Option<&Path>) -> String {
    let Some(folder) = folder else {
        return "posediff".into();
    };
    let canonical = folder.canonicalize().unwrap_or_else(|_| folder.to_owned());
    let name = |p: &Path| p.file_name().map(|f| f.to_string_lossy().into_owned());
    match name(&canonical) {
        Some(n) if n == "images" => canonical.parent().and_then(name).unwrap_or(n),
        Some(n) => n,
        None => "posediff".into(),
    }
}

/// JPEG thumbnails of the estimated images (`None` for the others).
///
/// # Errors
/// An image that cannot be read.
pub fn thumbnails(r: &Reconstruction, files: &[PathBuf]) -> Result<Vec<Option<Vec<u8>>>> {
    let side = thumbnail_side(r.images.len());
    r.images
        .par_iter()
        .zip(files)
        .map(|(record, file)| {
            if record.camera.camera.is_none() {
                return Ok(None);
            }
            let img = read_colour(file)?;
            thumbnail_jpeg(&img, side).map(Some)
        })
        .collect()
}
