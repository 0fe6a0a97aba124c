//! `posediff bench-cameras`: the real-cameras benchmark. Each set and three harder copies
//! (`posediff variant`: every second photo zoomed 1.3–1.6×, without and with the EXIF a phone
//! writes, and a wide-angle copy with OpenCV's `k1 = −0.12, k2 = 0.02`), estimated with
//! `--camera-mode single` and `auto`, and, with `--colmap-python`, COLMAP 4.2's incremental
//! and global mappers (pycolmap, default options: a SIMPLE_RADIAL camera per image) on the same
//! images in the same run; every column scored against the (transformed) ground truth, with
//! the median radial coefficient each method estimated beside the truth's `k1`.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, bail};
use posediff::io::colmap::ColmapModel;
use posediff::io::variants::{RadialVariant, ZoomVariant, radial_copy, zoom_copy};
use posediff_geometry::ImageSize;
use posediff_geometry::camera_json::CameraRecord;
use posediff_synth::scene::PathKind;
use posediff_synth::{DatasetSpec, LensSpec, write_dataset};
use serde::Serialize;

/// The real-cameras benchmark (JSON + Markdown).
#[derive(clap::Args)]
pub struct Args {
    /// Folder of the sets (`<set>/images`, `<set>/cameras.json`).
    #[arg(long)]
    data: PathBuf,
    /// Comma-separated set names.
    #[arg(
        long,
        default_value = "strecha_fountainP11,middlebury_templeSR,co3d_apple_posediffusion"
    )]
    sets: String,
    /// A Python with pycolmap 4.2.1 (e.g. target/client-venv/bin/python): adds COLMAP's columns.
    #[arg(long)]
    colmap_python: Option<PathBuf>,
    /// The COLMAP runner (`../shared/tools/pycolmap_run.py`).
    #[arg(long)]
    colmap_script: Option<PathBuf>,
    /// Output folder: variants, estimates, results.json, results.md.
    #[arg(long)]
    out: PathBuf,
    /// Also render synthetic orbits (posediff-synth, 20 frames of 640×480) with exact cameras:
    /// a pinhole one, a zoom lens and a SIMPLE_RADIAL lens.
    #[arg(long)]
    synthetic: bool,
}

/// One method on one set.
#[derive(Debug, Clone, Serialize)]
struct Cell {
    set: String,
    variant: &'static str,
    method: String,
    /// mAA(30), `None` when the method failed.
    maa_30: Option<f64>,
    /// Cameras estimated / images.
    registered: Option<f64>,
    /// Median relative focal error of the estimated cameras.
    focal_error: Option<f64>,
    /// Median radial coefficient of the estimated cameras (SIMPLE_RADIAL's `k`; 0 for pinhole).
    k1: Option<f64>,
    /// The truth's `k1` (OPENCV's, of the wide-angle copy; 0 otherwise).
    k1_truth: f64,
    seconds: f64,
    /// Why it failed.
    error: Option<String>,
}

fn records(path: &Path) -> anyhow::Result<Vec<serde_json::Value>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

/// mAA(30), registered fraction and median focal error of `estimate` against `truth`.
fn score(estimate: &Path, truth: &Path) -> anyhow::Result<(f64, f64, Option<f64>)> {
    let s = posediff::bench::score_cameras_files(estimate, truth)?;
    Ok((s.scores.maa_30, s.scores.registered, s.focal_error))
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        std::fs::create_dir_all(&self.out)?;
        let exe = std::env::current_exe()?;
        let mut cells = Vec::new();
        for set in self.sets.split(',').filter(|s| !s.is_empty()) {
            let original = self.data.join(set);
            if !original.join("cameras.json").is_file() {
                bail!("{}: no cameras.json (is --data right?)", original.display());
            }
            let variants = self.out.join("variants");
            let zoomed = variants.join(format!("{set}-zoom"));
            zoom_copy(&original, &zoomed, &ZoomVariant::default())?;
            let exif = variants.join(format!("{set}-zoom-exif"));
            zoom_copy(
                &original,
                &exif,
                &ZoomVariant {
                    exif: true,
                    ..ZoomVariant::default()
                },
            )?;
            let radial = variants.join(format!("{set}-radial"));
            radial_copy(&original, &radial, &RadialVariant::default())?;
            for (variant, dir) in [
                ("original", original.clone()),
                ("zoomed", zoomed),
                ("zoomed + EXIF", exif),
                ("radial", radial),
            ] {
                self.run_variant(&exe, (set, variant), &dir, &mut cells)?;
            }
        }
        if self.synthetic {
            // Rendered with exact cameras: a zoom lens (every second frame 1.3–1.6×) and a
            // SIMPLE_RADIAL lens (k −0.1), so the truth's model is the one estimated.
            for (variant, lens) in [
                ("original", LensSpec::default()),
                (
                    "zoomed",
                    LensSpec {
                        zoom_every: 2,
                        ..LensSpec::default()
                    },
                ),
                (
                    "radial",
                    LensSpec {
                        radial_k: -0.1,
                        ..LensSpec::default()
                    },
                ),
            ] {
                let root = self.out.join("synthetic").join(variant);
                write_dataset(
                    &root,
                    &DatasetSpec {
                        sequences: 1,
                        frames: 20,
                        seed: 3,
                        sizes: vec![ImageSize::new(640, 480)?],
                        test_every: 0,
                        path: Some(PathKind::Orbit),
                        lens,
                    },
                )?;
                let dir = root.join("synthetic").join("synthetic_0000");
                self.run_variant(&exe, ("synthetic orbit", variant), &dir, &mut cells)?;
            }
        }
        let json = self.out.join("results.json");
        std::fs::write(&json, serde_json::to_string_pretty(&cells)?)?;
        let md = markdown(&cells);
        std::fs::write(self.out.join("results.md"), &md)?;
        println!("{md}");
        Ok(())
    }

    /// posediff `single` and `auto`, and COLMAP's two mappers when given, on the set in `dir`
    /// (`images/`, `cameras.json`), scored against its truth.
    fn run_variant(
        &self,
        exe: &Path,
        (set, variant): (&str, &'static str),
        dir: &Path,
        cells: &mut Vec<Cell>,
    ) -> anyhow::Result<()> {
        let truth = dir.join("cameras.json");
        let k1_truth = truth_k1(&truth)?;
        let tag = variant.replace(" + ", "-");
        for mode in ["single", "auto"] {
            let out = self.out.join("runs").join(format!("{set}-{tag}-{mode}"));
            let start = Instant::now();
            let status = Command::new(exe)
                .arg("estimate")
                .arg(dir.join("images"))
                .args(["--camera-mode", mode, "--no-view", "--quiet", "--out"])
                .arg(&out)
                .status()?;
            let seconds = start.elapsed().as_secs_f64();
            cells.push(cell(
                (set, variant, k1_truth),
                format!("posediff {mode}"),
                seconds,
                || {
                    if !status.success() {
                        bail!("posediff estimate failed ({status})");
                    }
                    let (m, r, f) = score(&out.join("cameras.json"), &truth)?;
                    Ok((m, r, f, ours_k1(&out.join("cameras.json"))?))
                },
            ));
        }
        if let (Some(python), Some(script)) = (&self.colmap_python, &self.colmap_script) {
            let out = self.out.join("colmap").join(format!("{set}-{tag}"));
            let start = Instant::now();
            let output = Command::new(python)
                .arg(script)
                .arg(dir.join("images"))
                .arg(&out)
                .output()?;
            let text = String::from_utf8_lossy(&output.stdout);
            for mapper in ["incremental", "global"] {
                let seconds =
                    seconds_of(&text, mapper).unwrap_or_else(|| start.elapsed().as_secs_f64());
                cells.push(cell(
                    (set, variant, k1_truth),
                    format!("COLMAP 4.2 {mapper}"),
                    seconds,
                    || {
                        if !output.status.success() {
                            bail!(
                                "pycolmap_run.py failed: {}",
                                String::from_utf8_lossy(&output.stderr)
                                    .lines()
                                    .last()
                                    .unwrap_or("")
                            );
                        }
                        let (m, r, f) = score(&out.join(mapper).join("cameras.json"), &truth)?;
                        Ok((m, r, f, colmap_k1(&out.join(mapper))))
                    },
                ));
            }
        }
        Ok(())
    }
}

/// The seconds pycolmap_run.py printed for `what` (a mapper's include the features).
fn seconds_of(text: &str, what: &str) -> Option<f64> {
    text.lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find(|v| {
            v.get("mapper").and_then(|m| m.as_str()) == Some(what)
                || v.get("stage").and_then(|m| m.as_str()) == Some(what)
        })
        .and_then(|v| v.get("seconds")?.as_f64())
}

/// The median of `values` (`None` when empty).
fn median(mut values: Vec<f64>) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    (!values.is_empty()).then(|| values[values.len() / 2])
}

/// The truth's `k1`: an OPENCV/RADIAL/SIMPLE_RADIAL record's first distortion term, 0 for
/// pinhole records.
fn truth_k1(path: &Path) -> anyhow::Result<f64> {
    let gt: Vec<CameraRecord> = serde_json::from_value(serde_json::Value::Array(records(path)?))?;
    let lens = gt.first().context("an empty ground truth")?.lens()?;
    Ok(lens.distortion().first().copied().unwrap_or(0.0))
}

/// The median radial coefficient of our cameras.json (0 for pinhole cameras).
fn ours_k1(path: &Path) -> anyhow::Result<Option<f64>> {
    let mut ks = Vec::new();
    for v in records(path)? {
        if v.get("estimated") == Some(&serde_json::Value::Bool(false)) {
            continue;
        }
        let r: CameraRecord = serde_json::from_value(v)?;
        ks.push(r.lens()?.distortion().first().copied().unwrap_or(0.0));
    }
    Ok(median(ks))
}

/// The median radial coefficient of COLMAP's largest model under `dir` (`dir/0`, `dir/1`, …);
/// `None` when none reads.
fn colmap_k1(dir: &Path) -> Option<f64> {
    let models = std::fs::read_dir(dir).ok()?;
    let best = models
        .filter_map(|e| ColmapModel::read(&e.ok()?.path()).ok())
        .max_by_key(|m| m.images.len())?;
    median(
        best.images
            .iter()
            .filter_map(|im| best.cameras.iter().find(|c| c.id == im.camera_id))
            .filter_map(|c| c.lens().ok())
            .map(|l| l.distortion().first().copied().unwrap_or(0.0))
            .collect(),
    )
}

/// What a scored method gives: mAA(30), registered, median focal error, median `k1`.
type Scores = (f64, f64, Option<f64>, Option<f64>);

fn cell(
    (set, variant, k1_truth): (&str, &'static str, f64),
    method: String,
    seconds: f64,
    scored: impl FnOnce() -> anyhow::Result<Scores>,
) -> Cell {
    let (maa_30, registered, focal_error, k1, error) = match scored() {
        Ok((m, r, f, k)) => (Some(m), Some(r), f, k, None),
        Err(e) => (None, None, None, None, Some(format!("{e:#}"))),
    };
    Cell {
        set: set.to_owned(),
        variant,
        method,
        maa_30,
        registered,
        focal_error,
        k1,
        k1_truth,
        seconds,
        error,
    }
}

fn markdown(cells: &[Cell]) -> String {
    let mut s = String::from(
        "| set | variant | method | mAA(30) | registered | median focal error | k1 (truth) | seconds |\n|---|---|---|---|---|---|---|---|\n",
    );
    let f = |v: Option<f64>, pct: bool| match v {
        Some(v) if pct => format!("{:.1} %", 100.0 * v),
        Some(v) => format!("{v:.3}"),
        None => "failed".into(),
    };
    for c in cells {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} ({:.3}) | {:.1} |\n",
            c.set,
            c.variant,
            c.method,
            f(c.maa_30, false),
            f(c.registered, false),
            f(c.focal_error, true),
            f(c.k1, false),
            c.k1_truth,
            c.seconds
        ));
    }
    s
}
