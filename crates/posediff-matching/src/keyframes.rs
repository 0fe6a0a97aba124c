//! Keyframes of a video: each decoded frame scored for sharpness and tracked, and frames kept
//! so that consecutive keyframes overlap enough to match but are not near duplicates.
//!
//! Streaming, with bounded memory: a frame is looked at once, at most
//! [`KeyframeOptions::lookback`] frames are held, and every frame gets one verdict, in frame
//! order ([`Verdict`]).
//!
//! - **Sharpness**: the variance of the Laplacian of the frame in grey at
//!   [`KeyframeOptions::track_side`] (the usual blur measure; a motion-blurred frame scores a
//!   fraction of its neighbours).
//! - **Motion**: Shi–Tomasi corners of the last keyframe tracked frame to frame by pyramidal
//!   Lucas–Kanade (OpenCV's `calcOpticalFlowPyrLK`); a frame's *displacement* is the median
//!   distance of the surviving corners from where they were in the keyframe, as a fraction of
//!   the image diagonal; its *tracked* fraction is how many of the keyframe's corners survive.
//! - **Choice**: when a frame moves [`KeyframeOptions::max_displacement`] or more from the
//!   keyframe (or loses all but [`KeyframeOptions::min_tracked`] of its corners), the sharpest
//!   held frame that moved at least [`KeyframeOptions::min_displacement`] becomes the next
//!   keyframe, and tracking starts again from it over the frames held after it. Consecutive
//!   keyframes are therefore `min_displacement` to `max_displacement` apart, except where one
//!   frame alone moves more (reported as [`Keyframe::beyond_overlap`]).

use opencv::core::{Mat, Point2f, Size, TermCriteria, Vector};
use opencv::prelude::*;
use opencv::{imgproc, video};

use crate::error::{MatchingError, Result};

/// The thresholds of the keyframe selection (the options tree's `video.keyframes`).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct KeyframeOptions {
    /// Longer side, px, at which frames are scored and tracked (the keyframes are written at
    /// full size). 640 keeps a 720p frame's corners within a pixel of the full-size track.
    pub track_side: u32,
    /// Corners tracked from each keyframe.
    pub corners: usize,
    /// A frame that moved less than this fraction of the image diagonal from the last keyframe
    /// is a near duplicate (never a keyframe). 0.015: about 10 px at 640 px, where a
    /// keyframe's baseline adds almost nothing to triangulation.
    pub min_displacement: f64,
    /// Consecutive keyframes are at most this fraction of the diagonal apart (the overlap
    /// bound). 0.05, with `min_tracked` 0.8, measured on an orbit video
    /// (`posediff synth-video --seed 3`, 640×480, 30 fps, 3 s): keyframes 4–11° apart, all
    /// 25 estimated, 200–1400 verified matches between neighbours; at 0.10 and 0.5 they were
    /// 25–34° apart and 4 of 7 were left unmatched (an orbit fixating the object moves the
    /// image little for a large change of view).
    pub max_displacement: f64,
    /// A new keyframe is taken before fewer than this fraction of the keyframe's corners are
    /// still tracked (occlusion, turning away; see `max_displacement`).
    pub min_tracked: f64,
    /// Fewer live corners than this and the motion is not measured: a keyframe with fewer is
    /// followed by the sharpest of every `lookback` frames, a frame tracking fewer ends the
    /// keyframe's run (8 is the fewest a median displacement is worth taking over).
    pub min_corners: usize,
    /// Frames held while looking for the sharpest one (bounded memory: this many full frames).
    pub lookback: usize,
    /// A skipped frame whose sharpness is below this fraction of the held frames' median is
    /// reported as blurred (reporting only; the choice takes the sharpest).
    pub blur_ratio: f64,
}

impl Default for KeyframeOptions {
    fn default() -> Self {
        Self {
            track_side: 640,
            corners: 500,
            min_displacement: 0.015,
            max_displacement: 0.05,
            min_tracked: 0.8,
            min_corners: 8,
            lookback: 8,
            blur_ratio: 0.5,
        }
    }
}

impl KeyframeOptions {
    /// Checks the numbers.
    ///
    /// # Errors
    /// A threshold out of range, named.
    pub fn check(&self) -> Result<()> {
        let bad = |what: &str| Err(MatchingError::Frames(format!("video.keyframes.{what}")));
        if self.track_side < 64 {
            return bad("track_side must be at least 64 px");
        }
        if self.min_corners < 1 || self.min_corners > self.corners {
            return bad("min_corners must be between 1 and corners");
        }
        if self.corners < 16 {
            return bad("corners must be at least 16");
        }
        if !(self.min_displacement >= 0.0 && self.min_displacement < self.max_displacement) {
            return bad("min_displacement must be ≥ 0 and below max_displacement");
        }
        if !(self.max_displacement > 0.0 && self.max_displacement <= 1.0) {
            return bad("max_displacement must be in (0, 1]");
        }
        if !(0.0..1.0).contains(&self.min_tracked) {
            return bad("min_tracked must be in [0, 1)");
        }
        if self.lookback < 2 {
            return bad("lookback must be at least 2 frames");
        }
        if !(0.0..=1.0).contains(&self.blur_ratio) {
            return bad("blur_ratio must be in [0, 1]");
        }
        Ok(())
    }
}

/// A chosen frame.
#[derive(Debug)]
pub struct Keyframe {
    /// Its index in the stream.
    pub index: usize,
    /// The frame as given (full size).
    pub frame: Mat,
    /// Variance of the Laplacian at the tracking size.
    pub sharpness: f64,
    /// Displacement from the previous keyframe (fraction of the diagonal; 0 for the first;
    /// `None` where it could not be measured: too little texture, or tracking lost).
    pub displacement: Option<f64>,
    /// Fraction of the previous keyframe's corners still tracked here (1 for the first).
    pub tracked: f64,
    /// No held frame between the previous keyframe and this one was within the overlap
    /// bound (the video moves too fast for it at this frame rate, or tracking was lost).
    pub beyond_overlap: bool,
}

/// Why a frame is not a keyframe.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "snake_case")
)]
pub enum SkipReason {
    /// It moved less than `min_displacement` from the keyframe before it.
    NearDuplicate,
    /// Between two keyframes, within the bounds: a sharper frame near it, or a later one,
    /// was kept.
    NotSharpest,
    /// As `NotSharpest`, and its sharpness is below `blur_ratio` of its neighbours'.
    Blurred,
}

/// A frame that is not a keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Skipped {
    /// Its index in the stream.
    pub index: usize,
    /// Why.
    pub reason: SkipReason,
}

/// What became of one frame.
#[derive(Debug)]
pub enum Verdict {
    /// Chosen.
    Keyframe(Keyframe),
    /// Left out.
    Skipped(Skipped),
}

/// One held frame.
struct Held {
    index: usize,
    frame: Mat,
    mask: Option<Mat>,
    grey: Mat,
    sharpness: f64,
    displacement: f64,
    tracked: f64,
}

/// The tracks of the current keyframe.
struct Tracks {
    /// Where each corner was in the keyframe.
    start: Vec<Point2f>,
    /// Where each live corner is in the last frame (`None`: lost).
    now: Vec<Option<Point2f>>,
    /// The last frame's grey image.
    last: Mat,
}

/// The streaming keyframe selector: [`Self::push`] each frame, then [`Self::finish`].
pub struct KeyframeSelector {
    options: KeyframeOptions,
    held: Vec<Held>,
    tracks: Option<Tracks>,
    /// Diagonal of the tracking size, px.
    diagonal: f64,
    /// Index of the last keyframe (none yet: the first is the sharpest of the first frames).
    last_keyframe: Option<usize>,
    next_index: usize,
}

impl KeyframeSelector {
    /// A selector with `options`.
    ///
    /// # Errors
    /// Options out of range.
    pub fn new(options: KeyframeOptions) -> Result<Self> {
        options.check()?;
        Ok(Self {
            options,
            held: Vec::new(),
            tracks: None,
            diagonal: 1.0,
            last_keyframe: None,
            next_index: 0,
        })
    }

    /// The options in use.
    pub fn options(&self) -> &KeyframeOptions {
        &self.options
    }

    /// Takes the next frame (BGR or grey, any size; every frame of a stream the same size) and
    /// its optional mask (8-bit, the frame's size, zero = ignore: no corner is tracked there).
    /// Returns the verdicts this frame settles, in frame order.
    ///
    /// # Errors
    /// An empty frame, a frame of another size than the first, a mask of another size, or an
    /// OpenCV failure.
    pub fn push(&mut self, frame: Mat, mask: Option<Mat>) -> Result<Vec<Verdict>> {
        if frame.empty() {
            return Err(MatchingError::Frames(format!(
                "frame {} is empty",
                self.next_index
            )));
        }
        if let Some(first) = self.held.first()
            && first.frame.size()? != frame.size()?
        {
            return Err(MatchingError::Frames(format!(
                "frame {} is {}x{}, the stream's frames {}x{}",
                self.next_index,
                frame.cols(),
                frame.rows(),
                first.frame.cols(),
                first.frame.rows()
            )));
        }
        if let Some(m) = &mask
            && m.size()? != frame.size()?
        {
            return Err(MatchingError::Frames(format!(
                "the mask of frame {} is {}x{}, the frame {}x{}",
                self.next_index,
                m.cols(),
                m.rows(),
                frame.cols(),
                frame.rows()
            )));
        }
        let index = self.next_index;
        self.next_index += 1;
        let grey = self.tracking_grey(&frame)?;
        let sharpness = sharpness(&grey)?;
        let mask = match mask {
            Some(m) => Some(self.resized(&m, imgproc::INTER_NEAREST)?),
            None => None,
        };
        let (displacement, tracked) = match self.tracks.as_mut() {
            Some(t) => track(t, &grey, self.diagonal)?,
            None => (0.0, 1.0),
        };
        self.held.push(Held {
            index,
            frame,
            mask,
            grey,
            sharpness,
            displacement,
            tracked,
        });
        let mut verdicts = Vec::new();
        if self.last_keyframe.is_none() {
            // The first keyframe: the sharpest of the first `lookback` frames.
            if self.held.len() >= self.options.lookback {
                let best = sharpest(&self.held, |_| true).unwrap_or(0);
                self.emit(best, false, &mut verdicts)?;
            }
            return Ok(verdicts);
        }
        let (started, live) = self
            .tracks
            .as_ref()
            .map_or((0, 0), |t| (t.start.len(), t.now.iter().flatten().count()));
        if started < self.options.min_corners {
            // Too little texture in the keyframe to measure motion: the sharpest of every
            // `lookback` frames.
            if self.held.len() >= self.options.lookback {
                let best = sharpest(&self.held, |_| true).unwrap_or(0);
                self.emit(best, false, &mut verdicts)?;
            }
        } else if displacement >= self.options.max_displacement
            || tracked < self.options.min_tracked
            || live < self.options.min_corners
        {
            // The newest frame is past the bound: the sharpest earlier held frame that moved
            // enough, else the newest itself.
            let newest = self.held.len() - 1;
            let min = self.options.min_displacement;
            match sharpest(&self.held[..newest], |h| h.displacement >= min) {
                Some(best) => self.emit(best, false, &mut verdicts)?,
                None => self.emit(newest, true, &mut verdicts)?,
            }
        } else if self.held.len() > self.options.lookback {
            let h = self.held.remove(0);
            verdicts.push(self.skipped(&h, self.median_sharpness()));
        }
        Ok(verdicts)
    }

    /// The end of the stream: the held frames' verdicts (the sharpest one that moved enough
    /// becomes the last keyframe, so that the end of the video is covered).
    ///
    /// # Errors
    /// An OpenCV failure.
    pub fn finish(mut self) -> Result<Vec<Verdict>> {
        let mut verdicts = Vec::new();
        if self.held.is_empty() {
            return Ok(verdicts);
        }
        let best = if self.last_keyframe.is_none() {
            sharpest(&self.held, |_| true)
        } else {
            let min = self.options.min_displacement;
            sharpest(&self.held, |h| h.displacement >= min)
        };
        if let Some(best) = best {
            self.emit(best, false, &mut verdicts)?;
        }
        let median = self.median_sharpness();
        for h in std::mem::take(&mut self.held) {
            verdicts.push(self.skipped(&h, median));
        }
        Ok(verdicts)
    }

    /// Makes held frame `at` the keyframe: the frames before it are skipped, tracking starts
    /// from it and runs over the frames held after it.
    fn emit(&mut self, at: usize, beyond_overlap: bool, verdicts: &mut Vec<Verdict>) -> Result<()> {
        let median = self.median_sharpness();
        let rest = self.held.split_off(at + 1);
        let chosen = self
            .held
            .pop()
            .ok_or_else(|| MatchingError::Frames("keyframe selection: no held frame".into()))?;
        for h in std::mem::take(&mut self.held) {
            verdicts.push(self.skipped(&h, median));
        }
        let mut tracks = start_tracks(&chosen.grey, chosen.mask.as_ref(), &self.options)?;
        self.last_keyframe = Some(chosen.index);
        self.held = rest;
        for h in &mut self.held {
            let (d, t) = track(&mut tracks, &h.grey, self.diagonal)?;
            h.displacement = d;
            h.tracked = t;
        }
        self.tracks = Some(tracks);
        verdicts.push(Verdict::Keyframe(Keyframe {
            index: chosen.index,
            frame: chosen.frame,
            sharpness: chosen.sharpness,
            displacement: chosen
                .displacement
                .is_finite()
                .then_some(chosen.displacement),
            tracked: chosen.tracked,
            beyond_overlap,
        }));
        Ok(())
    }

    fn skipped(&self, h: &Held, median: f64) -> Verdict {
        let reason = if self.last_keyframe.is_some_and(|k| k < h.index)
            && h.displacement < self.options.min_displacement
        {
            SkipReason::NearDuplicate
        } else if h.sharpness < self.options.blur_ratio * median {
            SkipReason::Blurred
        } else {
            SkipReason::NotSharpest
        };
        Verdict::Skipped(Skipped {
            index: h.index,
            reason,
        })
    }

    fn median_sharpness(&self) -> f64 {
        let mut s: Vec<f64> = self.held.iter().map(|h| h.sharpness).collect();
        if s.is_empty() {
            return 0.0;
        }
        s.sort_by(f64::total_cmp);
        s[s.len() / 2]
    }

    /// `m` resized so that its longer side is `track_side` (never enlarged).
    fn resized(&self, m: &Mat, interpolation: i32) -> Result<Mat> {
        let long = m.cols().max(m.rows());
        let side = i32::try_from(self.options.track_side).unwrap_or(i32::MAX);
        if long <= side {
            return Ok(m.clone());
        }
        let scale = f64::from(side) / f64::from(long);
        let size = Size::new(
            ((f64::from(m.cols()) * scale).round() as i32).max(1),
            ((f64::from(m.rows()) * scale).round() as i32).max(1),
        );
        let mut out = Mat::default();
        imgproc::resize(m, &mut out, size, 0.0, 0.0, interpolation)?;
        Ok(out)
    }

    fn tracking_grey(&mut self, frame: &Mat) -> Result<Mat> {
        let grey = if frame.channels() == 1 {
            frame.clone()
        } else {
            let mut g = Mat::default();
            let code = if frame.channels() == 4 {
                imgproc::COLOR_BGRA2GRAY
            } else {
                imgproc::COLOR_BGR2GRAY
            };
            imgproc::cvt_color_def(frame, &mut g, code)?;
            g
        };
        let small = self.resized(&grey, imgproc::INTER_AREA)?;
        self.diagonal = f64::from(small.cols()).hypot(f64::from(small.rows()));
        Ok(small)
    }
}

/// Index of the sharpest of `held` that passes `keep`.
fn sharpest(held: &[Held], keep: impl Fn(&Held) -> bool) -> Option<usize> {
    held.iter()
        .enumerate()
        .filter(|(_, h)| keep(h))
        .max_by(|a, b| a.1.sharpness.total_cmp(&b.1.sharpness))
        .map(|(i, _)| i)
}

/// Variance of the Laplacian of `grey`.
fn sharpness(grey: &Mat) -> Result<f64> {
    let mut lap = Mat::default();
    imgproc::laplacian(
        grey,
        &mut lap,
        opencv::core::CV_32F,
        3,
        1.0,
        0.0,
        opencv::core::BORDER_REPLICATE,
    )?;
    let mut mean = Mat::default();
    let mut std = Mat::default();
    opencv::core::mean_std_dev(&lap, &mut mean, &mut std, &opencv::core::no_array())?;
    let s = *std.at_2d::<f64>(0, 0)?;
    Ok(s * s)
}

/// Corners of a keyframe (outside its mask's zeros).
fn start_tracks(grey: &Mat, mask: Option<&Mat>, options: &KeyframeOptions) -> Result<Tracks> {
    let mut corners = Vector::<Point2f>::new();
    let no_mask = Mat::default();
    let min_distance = f64::from(grey.cols().max(grey.rows())) / 80.0;
    imgproc::good_features_to_track(
        grey,
        &mut corners,
        i32::try_from(options.corners).unwrap_or(i32::MAX),
        0.01,
        min_distance,
        mask.unwrap_or(&no_mask),
        3,
        false,
        0.04,
    )?;
    let start: Vec<Point2f> = corners.to_vec();
    Ok(Tracks {
        now: start.iter().copied().map(Some).collect(),
        start,
        last: grey.clone(),
    })
}

/// Tracks `tracks` into `grey`: the median displacement of the live corners from the keyframe
/// (fraction of `diagonal`) and the fraction still live.
fn track(tracks: &mut Tracks, grey: &Mat, diagonal: f64) -> Result<(f64, f64)> {
    let live: Vec<usize> = (0..tracks.now.len())
        .filter(|&i| tracks.now[i].is_some())
        .collect();
    if live.is_empty() {
        tracks.last = grey.clone();
        return Ok((f64::INFINITY, 0.0));
    }
    let previous: Vector<Point2f> = live.iter().filter_map(|&i| tracks.now[i]).collect();
    let mut next = Vector::<Point2f>::new();
    let mut status = Vector::<u8>::new();
    let mut err = Vector::<f32>::new();
    video::calc_optical_flow_pyr_lk(
        &tracks.last,
        grey,
        &previous,
        &mut next,
        &mut status,
        &mut err,
        Size::new(21, 21),
        3,
        TermCriteria::new(
            opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
            30,
            0.01,
        )?,
        0,
        1e-4,
    )?;
    let (w, h) = (grey.cols() as f32, grey.rows() as f32);
    for (k, &i) in live.iter().enumerate() {
        let ok = status.get(k).is_ok_and(|s| s != 0);
        let p = next.get(k).ok();
        tracks.now[i] = match (ok, p) {
            (true, Some(p)) if p.x >= 0.0 && p.y >= 0.0 && p.x < w && p.y < h => Some(p),
            _ => None,
        };
    }
    tracks.last = grey.clone();
    let mut moved: Vec<f64> = tracks
        .now
        .iter()
        .zip(&tracks.start)
        .filter_map(|(now, start)| {
            now.map(|p| f64::from(p.x - start.x).hypot(f64::from(p.y - start.y)))
        })
        .collect();
    let tracked = moved.len() as f64 / tracks.start.len().max(1) as f64;
    if moved.is_empty() {
        return Ok((f64::INFINITY, 0.0));
    }
    moved.sort_by(f64::total_cmp);
    Ok((moved[moved.len() / 2] / diagonal, tracked))
}
