//! A synthetic capture video with exact cameras (`posediff synth-video`): the frames of
//! [`posediff_synth::video::render_video`] encoded by OpenCV's video writer as phones write
//! them, H.264 in MP4 through FFmpeg where the system's FFmpeg has an H.264 encoder (Debian's
//! links libx264), else Motion JPEG in AVI (which OpenCV writes itself).
//!
//! Written into the folder: `capture.mp4` or `capture.avi`, `cameras.json` (every frame,
//! named `frame_<index:06>`, OpenCV `x_cam = R x_world + t`), `masks/<index:06>.png` (zero on
//! the distractor) when there is one, `video.json` (codec, fps, frames, size, seed).

use std::path::{Path, PathBuf};

use opencv::core::{Mat, Size};
use opencv::prelude::*;
use opencv::videoio::VideoWriter;
use posediff_geometry::camera_json::CameraRecord;
use posediff_synth::video::{VideoSpec, render_video};
use serde::Serialize;

use crate::error::{PosediffError, Result};

/// What was written.
#[derive(Debug, Clone, Serialize)]
pub struct VideoSummary {
    /// The video file.
    pub video: PathBuf,
    /// `H264` or `MJPG`.
    pub codec: String,
    /// Frames.
    pub frames: usize,
    /// Frames per second.
    pub fps: f64,
    /// The masks folder, with a distractor.
    pub masks: Option<PathBuf>,
}

/// An 8-bit image of `channels` from row-major bytes.
fn mat(bytes: &[u8], height: u32, channels: i32) -> Result<Mat> {
    let flat = Mat::from_slice(bytes)?;
    Ok(flat.reshape(channels, height as i32)?.try_clone()?)
}

/// Opens the writer: H.264 in MP4 where FFmpeg can encode it (unless `mjpeg`), else Motion
/// JPEG in AVI.
fn writer(out: &Path, spec: &VideoSpec, mjpeg: bool) -> Result<(VideoWriter, PathBuf, String)> {
    let size = Size::new(spec.size.width() as i32, spec.size.height() as i32);
    let mut tries = Vec::new();
    if !mjpeg {
        tries.push(("capture.mp4", ['a', 'v', 'c', '1'], "H264"));
    }
    tries.push(("capture.avi", ['M', 'J', 'P', 'G'], "MJPG"));
    for (name, c, codec) in tries {
        let path = out.join(name);
        let fourcc = VideoWriter::fourcc(c[0], c[1], c[2], c[3])?;
        if let Ok(w) = VideoWriter::new(&path, fourcc, spec.fps, size, true)
            && w.is_opened().unwrap_or(false)
        {
            return Ok((w, path, codec.to_owned()));
        }
        let _ = std::fs::remove_file(&path);
    }
    Err(PosediffError::invalid(
        out,
        "OpenCV's video writer opens neither H.264 (MP4) nor Motion JPEG (AVI)",
    ))
}

/// Renders and encodes the video of `spec` into `out` (created).
///
/// # Errors
/// A size or rate out of range; the writer cannot be opened; a write fails.
pub fn write_video(out: &Path, spec: &VideoSpec, mjpeg: bool) -> Result<VideoSummary> {
    let io = |path: &Path| {
        let path = path.to_owned();
        move |source| PosediffError::Write { path, source }
    };
    std::fs::create_dir_all(out).map_err(io(out))?;
    let masks = spec.distractor.map(|_| out.join("masks"));
    if let Some(m) = &masks {
        std::fs::create_dir_all(m).map_err(io(m))?;
    }
    let (mut w, video, codec) = writer(out, spec, mjpeg)?;
    let height = spec.size.height();
    let mut failed: Option<PosediffError> = None;
    let cameras = render_video(spec, |f| {
        let mut step = || -> Result<()> {
            let rgb = mat(&f.rgb, height, 3)?;
            let mut bgr = Mat::default();
            opencv::imgproc::cvt_color_def(&rgb, &mut bgr, opencv::imgproc::COLOR_RGB2BGR)?;
            w.write(&bgr)?;
            if let (Some(dir), Some(m)) = (&masks, &f.mask) {
                let path = dir.join(format!("{:06}.png", f.index));
                if !opencv::imgcodecs::imwrite_def(&path, &mat(m, height, 1)?)? {
                    return Err(PosediffError::Write {
                        path,
                        source: std::io::Error::other("OpenCV could not write the PNG"),
                    });
                }
            }
            Ok(())
        };
        step().map_err(|e| {
            let text = e.to_string();
            failed = Some(e);
            posediff_synth::SynthError::Invalid(text)
        })
    });
    if let Some(e) = failed {
        return Err(e);
    }
    let cameras = cameras.map_err(|e| PosediffError::invalid(out, e))?;
    w.release()?;
    let records: Vec<CameraRecord> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| CameraRecord::from_camera(format!("frame_{i:06}"), c))
        .collect();
    let path = out.join("cameras.json");
    std::fs::write(&path, serde_json::to_string_pretty(&records)?).map_err(io(&path))?;
    let summary = VideoSummary {
        video,
        codec,
        frames: cameras.len(),
        fps: spec.fps,
        masks,
    };
    let meta = serde_json::json!({
        "generator": "posediff synth-video (posediff-synth)",
        "seed": spec.seed,
        "codec": summary.codec,
        "frames": summary.frames,
        "fps": spec.fps,
        "width": spec.size.width(),
        "height": spec.size.height(),
        "distractor": spec.distractor.map(|d| d.as_str()),
        "cameras": "cameras.json: frame_<index> for every frame, OpenCV x_cam = R x_world + t",
    });
    let path = out.join("video.json");
    std::fs::write(&path, serde_json::to_string_pretty(&meta)?).map_err(io(&path))?;
    Ok(summary)
}
