//! `posediff import-colmap`: a COLMAP model to cameras.json.

use std::path::PathBuf;

use posediff::io::colmap::ColmapModel;
use posediff::io::export::{ImageCamera, write_cameras_json_partial};
use posediff::io::loader::image_files;

/// Convert a COLMAP model (text or binary) to cameras.json, e.g. for
/// `estimate --init`: with --images, one entry per image of that folder in its order
/// (images COLMAP did not register are marked not estimated).
#[derive(clap::Args)]
pub struct Args {
    /// Folder of the COLMAP model (e.g. sparse/0).
    model: PathBuf,
    /// The image folder the model belongs to.
    #[arg(long)]
    images: Option<PathBuf>,
    /// Output cameras.json.
    #[arg(long)]
    out: PathBuf,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        let Args { model, images, out } = self;
        let entries = match images {
            Some(dir) => {
                posediff::io::records::colmap_for_images(&model, &image_files(&dir)?, &dir)?
            }
            None => {
                let colmap = ColmapModel::read(&model)?;
                let cams = colmap.named_cameras(&model)?;
                let lenses = colmap.image_lenses(&model)?;
                let mut entries: Vec<ImageCamera> = cams
                    .into_iter()
                    .zip(lenses)
                    .map(|(c, lens)| ImageCamera {
                        image: c.image,
                        size: c.camera.image_size,
                        camera: Some(c.camera),
                        lens,
                    })
                    .collect();
                entries.sort_by(|a, b| a.image.cmp(&b.image));
                entries
            }
        };
        write_cameras_json_partial(&out, &entries)?;
        let points = ColmapModel::read(&model)?.points.len();
        println!(
            "wrote {} ({} of {} images registered; the model has {points} points)",
            out.display(),
            entries.iter().filter(|e| e.camera.is_some()).count(),
            entries.len()
        );
        Ok(())
    }
}
