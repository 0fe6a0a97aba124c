//! `posediff view`: view.html for an output folder.

use std::path::{Path, PathBuf};

use anyhow::Context;
use posediff::io::colmap::ColmapModel;
use posediff::io::export::read_cameras_json_partial;

/// Write view.html (cameras with thumbnails, points, the aligned ground truth) for an
/// output folder of `estimate`.
#[derive(clap::Args)]
pub struct Args {
    /// The output folder (its sparse/0 and images/ are read).
    dir: PathBuf,
    /// Ground-truth cameras.json (matched by image name), drawn aligned, with errors.
    #[arg(long)]
    gt: Option<PathBuf>,
    /// The page to write (default: <dir>/view.html).
    #[arg(short = 'o', long = "out")]
    out: Option<PathBuf>,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        view(&self.dir, self.gt.as_deref(), self.out.as_deref())
    }
}

/// `posediff view`: view.html from an output folder's COLMAP model and images.
fn view(dir: &Path, gt: Option<&Path>, out: Option<&Path>) -> anyhow::Result<()> {
    let model_dir = dir.join("sparse").join("0");
    let model = ColmapModel::read(&model_dir)
        .with_context(|| format!("{} is not a posediff output folder", dir.display()))?;
    let recon = model.to_reconstruction(&model_dir)?;
    let files: Vec<PathBuf> = recon
        .images
        .iter()
        .map(|i| dir.join("images").join(&i.camera.image))
        .collect();
    let thumbs: Vec<Option<Vec<u8>>> = if files.iter().all(|f| f.is_file()) {
        posediff::io::outputs::thumbnails(&recon, &files)?
    } else {
        log::warn!(
            "{}/images does not hold the images: no thumbnails",
            dir.display()
        );
        vec![None; recon.images.len()]
    };
    let truth = match gt {
        None => None,
        Some(path) => {
            let given = read_cameras_json_partial(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let by_name = |name: &str| {
                given.iter().find(|g| g.image == name).or_else(|| {
                    let file = Path::new(name).file_name();
                    given
                        .iter()
                        .find(|g| Path::new(&g.image).file_name() == file)
                })
            };
            Some(
                recon
                    .images
                    .iter()
                    .map(|i| by_name(&i.camera.image).and_then(|g| g.camera))
                    .collect::<Vec<_>>(),
            )
        }
    };
    let title = posediff::io::outputs::set_title(Some(&dir.join("images")));
    let html = posediff::io::viewer::render(&title, &recon, &thumbs, truth.as_deref())?;
    let path = out.map_or_else(|| dir.join("view.html"), Path::to_path_buf);
    std::fs::write(&path, html).with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}
