//! Video input: each video probed before any work, decoded once, frame by frame, by OpenCV's
//! FFmpeg back end (Debian's `libopencv-videoio`, which `libopencv-dev` installs with the
//! codecs of Debian's FFmpeg: H.264, HEVC, VP9, AV1, MJPEG, …; no second decoder to set up),
//! its frames scored and tracked by [`posediff_matching::keyframes`], and the keyframes
//! written as JPEGs named by video, frame index and timestamp
//! (`<video stem>_f<index>_t<seconds>s.jpg`), with everything skipped counted by reason.
//!
//! Streaming: one decoded frame plus the selector's [`KeyframeOptions::lookback`] held frames
//! are in memory at any time, whatever the video's length.
//!
//! [`KeyframeOptions::lookback`]: posediff_matching::keyframes::KeyframeOptions::lookback

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::time::Instant;

use opencv::core::{Mat, Vector};
use opencv::prelude::*;
use opencv::videoio::{self, VideoCapture};
use posediff_matching::keyframes::{KeyframeSelector, SkipReason, Verdict};
use serde::Serialize;

use crate::error::{PosediffError, Result};
use crate::estimate::options::VideoOptions;
use posediff_pipeline::progress::StepCounter;

/// File extensions taken as videos.
pub const VIDEO_EXTENSIONS: [&str; 10] = [
    "mp4", "mov", "m4v", "avi", "mkv", "webm", "mts", "m2ts", "mpg", "mpeg",
];

/// Whether `path` names a video (by its extension).
pub fn is_video(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| VIDEO_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// What a video's container and first frame say.
#[derive(Debug, Clone, Serialize)]
pub struct VideoInfo {
    /// The file.
    pub path: PathBuf,
    /// Its file stem: the prefix of its keyframes' names.
    pub stem: String,
    /// The codec's four-character code (`avc1`, `hev1`, `MJPG`, …) as FFmpeg reports it.
    pub codec: String,
    /// Frames per second the container states (`None`: not stated).
    pub fps: Option<f64>,
    /// Frames the container states (`None`: not stated).
    pub frames_declared: Option<u64>,
    /// Frame width, px.
    pub width: u32,
    /// Frame height, px.
    pub height: u32,
}

/// Opens `path` as OpenCV's FFmpeg back end reads it.
fn open(path: &Path) -> Result<VideoCapture> {
    let cap = VideoCapture::from_file(path, videoio::CAP_FFMPEG)
        .map_err(|e| PosediffError::invalid(path, format!("cannot open the video: {e}")))?;
    if !cap.is_opened()? {
        return Err(PosediffError::invalid(
            path,
            "not a video OpenCV's FFmpeg back end can open (not a video, an unknown or \
             unsupported codec, a broken or truncated container, or audio only): re-encode it, \
             e.g. `ffmpeg -i IN -c:v libx264 -pix_fmt yuv420p OUT.mp4`",
        ));
    }
    Ok(cap)
}

/// Reads one frame (`None` at the end).
fn read(cap: &mut VideoCapture) -> Result<Option<Mat>> {
    let mut frame = Mat::default();
    Ok((cap.read(&mut frame)? && !frame.empty()).then_some(frame))
}

/// Probes each video before any work: it opens, its first frame decodes, and the names of the
/// keyframes it gives cannot collide with another video's.
///
/// # Errors
/// A missing, empty or unreadable file; one OpenCV's FFmpeg back end cannot open, or whose
/// first frame does not decode (audio only, unknown codec, truncated); a non-UTF-8 name; two
/// videos with one stem. Each error names the file and the fix.
pub fn probe(paths: &[PathBuf]) -> Result<Vec<VideoInfo>> {
    let mut stems: HashMap<String, &Path> = HashMap::new();
    paths
        .iter()
        .map(|path| {
            let size = std::fs::metadata(path)
                .map_err(|source| PosediffError::Read {
                    path: path.clone(),
                    source,
                })?
                .len();
            if size == 0 {
                return Err(PosediffError::invalid(path, "the video file is empty"));
            }
            let stem = path
                .file_stem()
                .and_then(|s| s.to_str())
                .ok_or_else(|| {
                    PosediffError::invalid(
                        path,
                        "the video's name is not UTF-8: rename it (its keyframes are named after it)",
                    )
                })?
                .to_owned();
            if let Some(other) = stems.insert(stem.clone(), path) {
                return Err(PosediffError::InvalidArgument(format!(
                    "{} and {} have the same name {stem:?}: their keyframes would share names; \
                     rename one",
                    other.display(),
                    path.display()
                )));
            }
            let mut cap = open(path)?;
            let fourcc = cap.get(videoio::CAP_PROP_FOURCC)? as u32;
            let codec: String = fourcc
                .to_le_bytes()
                .iter()
                .map(|&b| if b.is_ascii_graphic() { b as char } else { '?' })
                .collect();
            let fps = cap.get(videoio::CAP_PROP_FPS)?;
            let count = cap.get(videoio::CAP_PROP_FRAME_COUNT)?;
            let Some(first) = read(&mut cap)? else {
                return Err(PosediffError::invalid(
                    path,
                    format!(
                        "no video frame decodes (codec {codec:?}): audio only, an unsupported \
                         codec, or truncated; re-encode it, e.g. `ffmpeg -i IN -c:v libx264 \
                         -pix_fmt yuv420p OUT.mp4`"
                    ),
                ));
            };
            Ok(VideoInfo {
                path: path.clone(),
                stem,
                codec,
                fps: (fps.is_finite() && fps > 0.0).then_some(fps),
                frames_declared: (count.is_finite() && count >= 1.0).then_some(count as u64),
                width: first.cols().unsigned_abs(),
                height: first.rows().unsigned_abs(),
            })
        })
        .collect()
}

/// One keyframe: its image and where it came from.
#[derive(Debug, Clone, Serialize)]
pub struct KeyframeRecord {
    /// The image's name (in the frames folder, then `out/images`).
    pub image: String,
    /// Which video (index into `videos`).
    pub video: usize,
    /// The frame's index in its video (0-based, decoding order).
    pub frame: usize,
    /// Its timestamp, seconds.
    pub time_s: f64,
    /// Variance of the Laplacian at the tracking size.
    pub sharpness: f64,
    /// Displacement from the keyframe before it (fraction of the diagonal; `None`: not
    /// measurable).
    pub displacement: Option<f64>,
    /// Fraction of the keyframe before it's corners tracked to it.
    pub tracked: f64,
    /// It is farther from the keyframe before it than the overlap bound (too fast a motion
    /// for the frame rate, or lost tracking).
    pub beyond_overlap: bool,
}

/// A run of consecutive frames skipped for one reason.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SkippedFrames {
    /// First frame index.
    pub from: usize,
    /// Last frame index (inclusive).
    pub to: usize,
    /// Why.
    pub reason: FrameSkip,
}

/// Why a decoded frame is not a keyframe.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameSkip {
    /// Between the frames `video.fps` looks at.
    FrameRate,
    /// As the keyframe selection says ([`SkipReason`]).
    NearDuplicate,
    /// Between two keyframes, within the bounds: a sharper frame near it, or a later one, was
    /// kept.
    NotSharpest,
    /// A sharper frame near it was chosen, and it is blurred.
    Blurred,
    /// A keyframe dropped to keep `video.max_frames`.
    Thinned,
}

impl From<SkipReason> for FrameSkip {
    fn from(r: SkipReason) -> Self {
        match r {
            SkipReason::NearDuplicate => Self::NearDuplicate,
            SkipReason::NotSharpest => Self::NotSharpest,
            SkipReason::Blurred => Self::Blurred,
        }
    }
}

/// run.json's account of one video.
#[derive(Debug, Clone, Serialize)]
pub struct VideoReport {
    /// The container and codec.
    #[serde(flatten)]
    pub info: VideoInfo,
    /// Frames decoded.
    pub frames_decoded: usize,
    /// Keyframes kept.
    pub keyframes: usize,
    /// Skipped frames per reason.
    pub skipped: BTreeMap<FrameSkip, usize>,
    /// The skipped frames as runs of one reason.
    pub skipped_runs: Vec<SkippedFrames>,
    /// Keyframes farther apart than the overlap bound.
    pub beyond_overlap: usize,
    /// Decoding stopped before the frames the container states (a truncated or damaged
    /// file): what decoded is used.
    pub truncated: bool,
    /// Seconds decoding, scoring, tracking and writing.
    pub seconds: f64,
    /// Frames masked (`--masks`) of the keyframes.
    pub masked_keyframes: usize,
}

/// The keyframes of every video, written, and their account.
#[derive(Debug, Clone, Serialize)]
pub struct Capture {
    /// The folder the keyframes were written to.
    #[serde(skip)]
    pub folder: PathBuf,
    /// The keyframes in order (video by video).
    pub keyframes: Vec<KeyframeRecord>,
    /// Per video.
    pub videos: Vec<VideoReport>,
    /// The masks of the keyframes in COLMAP's naming (`<image name>.png`), when `--masks` was
    /// given.
    #[serde(skip)]
    pub masks: Option<PathBuf>,
}

impl Capture {
    /// The keyframe files, in order.
    pub fn files(&self) -> Vec<PathBuf> {
        self.keyframes
            .iter()
            .map(|k| self.folder.join(&k.image))
            .collect()
    }

    /// Decoded frames per second of wall time and seconds per keyframe, over all videos.
    pub fn costs(&self) -> (f64, f64) {
        let seconds: f64 = self.videos.iter().map(|v| v.seconds).sum();
        let decoded: usize = self.videos.iter().map(|v| v.frames_decoded).sum();
        (
            decoded as f64 / seconds.max(1e-9),
            seconds / self.keyframes.len().max(1) as f64,
        )
    }
}

/// Masks of a video's frames: `DIR/<video stem>/<frame>.png` or `DIR/<frame>.png` (one file
/// per frame index, any zero padding, as video segmenters such as SAM 2 write them).
fn frame_masks(dir: &Path, stem: &str) -> Result<HashMap<usize, PathBuf>> {
    let list = |d: &Path| -> Result<HashMap<usize, PathBuf>> {
        let entries = std::fs::read_dir(d).map_err(|source| PosediffError::Read {
            path: d.to_owned(),
            source,
        })?;
        Ok(entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")))
            .filter_map(|p| {
                let n = p.file_stem()?.to_str()?.parse::<usize>().ok()?;
                Some((n, p))
            })
            .collect())
    };
    let own = dir.join(stem);
    if own.is_dir() {
        return list(&own);
    }
    list(dir)
}

/// Writes `frame` as a JPEG.
fn write_jpeg(path: &Path, frame: &Mat, quality: u8) -> Result<()> {
    let params =
        Vector::<i32>::from_slice(&[opencv::imgcodecs::IMWRITE_JPEG_QUALITY, i32::from(quality)]);
    let name = path
        .to_str()
        .ok_or_else(|| PosediffError::invalid(path, "the keyframe folder's path is not UTF-8"))?;
    if !opencv::imgcodecs::imwrite(name, frame, &params)? {
        return Err(PosediffError::Write {
            path: path.to_owned(),
            source: std::io::Error::other("OpenCV could not write the JPEG"),
        });
    }
    Ok(())
}

/// Reads a mask (8-bit, zero = ignore) for the keyframe selection.
fn read_mask(path: &Path, width: u32, height: u32) -> Result<Mat> {
    let m = posediff_matching::image_check::decode(path, opencv::imgcodecs::IMREAD_GRAYSCALE)?;
    if m.cols().unsigned_abs() != width || m.rows().unsigned_abs() != height {
        return Err(PosediffError::invalid(
            path,
            format!(
                "the mask is {}x{} but the video's frames are {width}x{height}: a mask has its \
                 frame's size",
                m.cols(),
                m.rows()
            ),
        ));
    }
    Ok(m)
}

/// Checks, before any decoding, that `masks` has masks for each video and that the first of
/// them has the video's frame size.
///
/// # Errors
/// A video without any mask in the folder; a mask of the wrong size or unreadable.
pub fn check_masks(masks: &Path, videos: &[VideoInfo]) -> Result<()> {
    for v in videos {
        let found = frame_masks(masks, &v.stem)?;
        let Some(first) = found.keys().min().and_then(|k| found.get(k)) else {
            return Err(PosediffError::invalid(
                masks,
                format!(
                    "no mask for {}: masks of a video are <folder>/<frame index>.png or \
                     <folder>/{}/<frame index>.png",
                    v.path.display(),
                    v.stem
                ),
            ));
        };
        read_mask(first, v.width, v.height)?;
    }
    Ok(())
}

/// Decodes each video once, selects its keyframes and writes them into `folder` (created,
/// emptied first), their masks (when `masks` is given) into `masks_folder` in COLMAP's naming.
///
/// # Errors
/// A video that stops decoding at its first frame, an unreadable mask or one of another size, a
/// write that fails.
pub fn extract_keyframes(
    videos: &[VideoInfo],
    folder: &Path,
    options: &VideoOptions,
    masks: Option<(&Path, &Path)>,
    progress: &dyn StepCounter,
) -> Result<Capture> {
    let fresh = |d: &Path| -> Result<()> {
        if d.exists() {
            std::fs::remove_dir_all(d).map_err(|source| PosediffError::Write {
                path: d.to_owned(),
                source,
            })?;
        }
        std::fs::create_dir_all(d).map_err(|source| PosediffError::Write {
            path: d.to_owned(),
            source,
        })
    };
    fresh(folder)?;
    if let Some((_, out)) = masks {
        fresh(out)?;
    }
    let mut capture = Capture {
        folder: folder.to_owned(),
        keyframes: Vec::new(),
        videos: Vec::new(),
        masks: masks.map(|(_, out)| out.to_owned()),
    };
    for (v, info) in videos.iter().enumerate() {
        let report = extract_one(
            v,
            info,
            folder,
            options,
            masks,
            &mut capture.keyframes,
            progress,
        )?;
        capture.videos.push(report);
    }
    if capture.keyframes.len() < 2 {
        return Err(PosediffError::InvalidArgument(format!(
            "the video(s) gave {} keyframe(s): a still or too short video; at least two views \
             are needed (lower video.keyframes.min_displacement, or give more footage)",
            capture.keyframes.len()
        )));
    }
    Ok(capture)
}

/// One video's keyframes, appended to `keyframes`.
fn extract_one(
    v: usize,
    info: &VideoInfo,
    folder: &Path,
    options: &VideoOptions,
    masks: Option<(&Path, &Path)>,
    keyframes: &mut Vec<KeyframeRecord>,
    progress: &dyn StepCounter,
) -> Result<VideoReport> {
    let start = Instant::now();
    let mask_files = match masks {
        Some((dir, _)) => frame_masks(dir, &info.stem)?,
        None => HashMap::new(),
    };
    let mut cap = open(&info.path)?;
    let mut selector = KeyframeSelector::new(options.keyframes.clone())?;
    let fps = info.fps.unwrap_or(30.0);
    progress.stage(
        &format!("video {} (decoding, scoring, tracking)", info.stem),
        info.frames_declared.unwrap_or(0),
    );
    let first_new = keyframes.len();
    // The video's frame index and timestamp of each frame given to the selector and not yet
    // settled: the selector settles frames in the order it was given them.
    let mut pending: VecDeque<(usize, f64)> = VecDeque::new();
    let mut verdicts: Vec<(usize, FrameSkip)> = Vec::new();
    let mut decoded = 0usize;
    let mut last_bucket: Option<i64> = None;
    let settle = |vs: Vec<Verdict>,
                  pending: &mut VecDeque<(usize, f64)>,
                  keyframes: &mut Vec<KeyframeRecord>,
                  verdicts: &mut Vec<(usize, FrameSkip)>|
     -> Result<()> {
        for verdict in vs {
            let Some((frame, time_s)) = pending.pop_front() else {
                return Err(PosediffError::InvalidArgument(format!(
                    "{}: the keyframe selection settled more frames than it was given",
                    info.path.display()
                )));
            };
            match verdict {
                Verdict::Keyframe(k) => {
                    let image = format!("{}_f{frame:06}_t{time_s:.3}s.jpg", info.stem);
                    write_jpeg(&folder.join(&image), &k.frame, options.jpeg_quality)?;
                    if let (Some((_, out)), Some(mask)) = (masks, mask_files.get(&frame)) {
                        let dest = out.join(format!("{image}.png"));
                        std::fs::copy(mask, &dest)
                            .map_err(|source| PosediffError::Write { path: dest, source })?;
                    }
                    keyframes.push(KeyframeRecord {
                        image,
                        video: v,
                        frame,
                        time_s,
                        sharpness: k.sharpness,
                        displacement: k.displacement,
                        tracked: k.tracked,
                        beyond_overlap: k.beyond_overlap,
                    });
                }
                Verdict::Skipped(s) => verdicts.push((frame, s.reason.into())),
            }
        }
        Ok(())
    };
    while let Some(frame) = read(&mut cap)? {
        let index = decoded;
        decoded += 1;
        progress.step();
        let ms = cap.get(videoio::CAP_PROP_POS_MSEC)?;
        let time_s = if ms.is_finite() && (ms > 0.0 || index == 0) {
            ms / 1000.0
        } else {
            index as f64 / fps
        };
        if let Some(rate) = options.fps {
            let bucket = (time_s * rate + 1e-6).floor() as i64;
            if last_bucket == Some(bucket) {
                verdicts.push((index, FrameSkip::FrameRate));
                continue;
            }
            last_bucket = Some(bucket);
        }
        let mask = match mask_files.get(&index) {
            Some(p) => Some(read_mask(p, info.width, info.height)?),
            None => None,
        };
        pending.push_back((index, time_s));
        let vs = selector.push(frame, mask)?;
        settle(vs, &mut pending, keyframes, &mut verdicts)?;
    }
    let vs = selector.finish()?;
    settle(vs, &mut pending, keyframes, &mut verdicts)?;
    if decoded == 0 {
        return Err(PosediffError::invalid(
            &info.path,
            "no frame decodes on the second reading",
        ));
    }
    // Thinning to `max_frames`, evenly.
    if let Some(max) = options.max_frames
        && keyframes.len() - first_new > max
    {
        let mine: Vec<KeyframeRecord> = keyframes.drain(first_new..).collect();
        let n = mine.len();
        let keep: std::collections::HashSet<usize> = (0..max)
            .map(|i| ((i as f64) * (n - 1) as f64 / (max - 1) as f64).round() as usize)
            .collect();
        for (i, k) in mine.into_iter().enumerate() {
            if keep.contains(&i) {
                keyframes.push(k);
            } else {
                let path = folder.join(&k.image);
                std::fs::remove_file(&path).map_err(|source| PosediffError::Write {
                    path: path.clone(),
                    source,
                })?;
                if let Some((_, out)) = masks {
                    let _ = std::fs::remove_file(out.join(format!("{}.png", k.image)));
                }
                verdicts.push((k.frame, FrameSkip::Thinned));
            }
        }
    }
    let mine = &keyframes[first_new..];
    verdicts.sort_by_key(|(i, _)| *i);
    let mut skipped = BTreeMap::new();
    let mut runs: Vec<SkippedFrames> = Vec::new();
    for &(i, reason) in &verdicts {
        *skipped.entry(reason).or_insert(0) += 1;
        match runs.last_mut() {
            Some(r) if r.reason == reason && r.to + 1 == i => r.to = i,
            _ => runs.push(SkippedFrames {
                from: i,
                to: i,
                reason,
            }),
        }
    }
    // Containers state their frame count from the stream's duration, which can round up by
    // one frame: one frame short is not a truncated file.
    let truncated = info
        .frames_declared
        .is_some_and(|n| (decoded as u64) + 1 < n);
    if truncated {
        log::warn!(
            "{}: decoding stopped after {decoded} of the {} frames its container states (a \
             truncated or damaged file); the frames that decoded are used",
            info.path.display(),
            info.frames_declared.unwrap_or(0)
        );
    }
    Ok(VideoReport {
        info: info.clone(),
        frames_decoded: decoded,
        keyframes: mine.len(),
        skipped,
        skipped_runs: runs,
        beyond_overlap: mine.iter().filter(|k| k.beyond_overlap).count(),
        truncated,
        seconds: start.elapsed().as_secs_f64(),
        masked_keyframes: if masks.is_some() {
            mine.iter()
                .filter(|k| mask_files.contains_key(&k.frame))
                .count()
        } else {
            0
        },
    })
}
