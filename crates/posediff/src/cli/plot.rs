//! `posediff plot`: frusta from above and from the side.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use posediff::io::export::{ImageCamera, NamedCamera, read_cameras_json_partial};

use super::truth_for;

/// Plot cameras (frusta from above and from the side), optionally against the ground truth.
#[derive(clap::Args)]
pub struct Args {
    /// A cameras.json.
    cameras: PathBuf,
    /// Ground-truth cameras.json (matched by image name, any order).
    #[arg(long)]
    gt: Option<PathBuf>,
    /// Output PNG.
    #[arg(short = 'o', long = "out")]
    out: PathBuf,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        plot(&self.cameras, self.gt.as_deref(), &self.out)
    }
}

fn plot(cameras: &Path, gt: Option<&Path>, out: &Path) -> anyhow::Result<()> {
    let (est, truth) = plot_inputs(cameras, gt)?;
    let errors = posediff::plot::plot_cameras(out, &est, truth.as_deref())?;
    for e in &errors {
        println!(
            "{:<32} {:>8.2} deg {:>8.4} centre",
            e.image, e.rotation_deg, e.center_rel
        );
    }
    println!("wrote {}", out.display());
    Ok(())
}

/// The estimated cameras and, when given, the ground truth of the same images (images not
/// estimated are left out of both).
fn plot_inputs(
    cameras: &Path,
    gt: Option<&Path>,
) -> anyhow::Result<(Vec<NamedCamera>, Option<Vec<NamedCamera>>)> {
    let est = read_cameras_json_partial(cameras)
        .with_context(|| format!("reading {}", cameras.display()))?;
    let truth = gt.map(|g| truth_for(cameras, &est, g)).transpose()?;
    let keep: Vec<bool> = est.iter().map(|e| e.camera.is_some()).collect();
    if keep.iter().filter(|k| **k).count() < 2 {
        bail!("{} has fewer than two estimated cameras", cameras.display());
    }
    let est_named = ImageCamera::estimated(&est);
    let truth = truth.map(|t| {
        t.into_iter()
            .zip(&est)
            .filter(|(_, e)| e.camera.is_some())
            .map(|(camera, e)| NamedCamera {
                image: e.image.clone(),
                camera,
            })
            .collect()
    });
    Ok((est_named, truth))
}
