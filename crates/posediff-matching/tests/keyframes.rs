//! Keyframe selection on a "video" with exact motion: a window panned over a real photo at a
//! known speed, with a pause (repeated frames) and motion-blurred frames. The true shift
//! between two frames is known to the pixel, so the bounds are checked against the truth.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use opencv::core::{Mat, Rect, Size};
use opencv::prelude::*;
use posediff_fixtures::shared_path;
use posediff_matching::keyframes::{KeyframeOptions, KeyframeSelector, SkipReason, Verdict};

const W: i32 = 320;
const H: i32 = 240;

/// Frame `i`'s window origin and whether it is blurred: 4 px a frame to the right, a pause of
/// 20 frames at frame 60, every 4th moving frame blurred.
fn script(frames: usize) -> Vec<(i32, bool)> {
    let mut x = 0;
    (0..frames)
        .map(|i| {
            let paused = (60..80).contains(&i);
            if !paused && i > 0 {
                x += 4;
            }
            (x, !paused && i % 4 == 2)
        })
        .collect()
}

fn frame(photo: &Mat, x: i32, blurred: bool) -> Mat {
    let roi = Mat::roi(photo, Rect::new(x, 200, W, H))
        .unwrap()
        .try_clone()
        .unwrap();
    if !blurred {
        return roi;
    }
    let mut out = Mat::default();
    opencv::imgproc::gaussian_blur_def(&roi, &mut out, Size::new(0, 0), 3.0).unwrap();
    out
}

#[test]
fn keyframes_are_sharp_and_within_the_overlap_and_duplicate_bounds() {
    let path = shared_path("data/strecha_fountainP11/images/0000.jpg");
    let photo = opencv::imgcodecs::imread_def(path.to_str().unwrap()).unwrap();
    assert!(
        photo.cols() >= 1024 && photo.rows() >= 440,
        "the fountain photo"
    );
    let plan = script(170);
    assert!(plan.last().unwrap().0 + W <= photo.cols());
    let options = KeyframeOptions::default();
    let mut selector = KeyframeSelector::new(options.clone()).unwrap();
    let mut verdicts = Vec::new();
    for &(x, blurred) in &plan {
        verdicts.extend(selector.push(frame(&photo, x, blurred), None).unwrap());
    }
    verdicts.extend(selector.finish().unwrap());

    // Every frame exactly once, in order.
    let order: Vec<usize> = verdicts
        .iter()
        .map(|v| match v {
            Verdict::Keyframe(k) => k.index,
            Verdict::Skipped(s) => s.index,
        })
        .collect();
    assert_eq!(order, (0..plan.len()).collect::<Vec<_>>());

    let keys: Vec<usize> = verdicts
        .iter()
        .filter_map(|v| match v {
            Verdict::Keyframe(k) => Some(k.index),
            Verdict::Skipped(_) => None,
        })
        .collect();
    assert!(keys.len() >= 10, "{keys:?}");
    let diagonal = f64::from(W).hypot(f64::from(H));
    for pair in keys.windows(2) {
        let shift = f64::from(plan[pair[1]].0 - plan[pair[0]].0) / diagonal;
        // The true shift, against the bounds (half a pixel of tracking error allowed).
        let slack = 0.5 / diagonal;
        assert!(
            shift >= options.min_displacement - slack,
            "keyframes {pair:?} are {shift:.4} of the diagonal apart: near duplicates"
        );
        assert!(
            shift <= options.max_displacement + slack,
            "keyframes {pair:?} are {shift:.4} of the diagonal apart: beyond the overlap bound"
        );
    }
    // No blurred frame is chosen (each has sharp neighbours within the bounds).
    for k in &keys {
        assert!(
            !plan[*k].1,
            "blurred frame {k} chosen as a keyframe: {keys:?}"
        );
    }
    // The pause gives at most one keyframe.
    assert!(keys.iter().filter(|k| (61..80).contains(*k)).count() <= 1);
    // The frame just after a keyframe (4 px from it, below the 6 px bound) is a near
    // duplicate.
    let duplicates: Vec<usize> = verdicts
        .iter()
        .filter_map(|v| match v {
            Verdict::Skipped(s) if s.reason == SkipReason::NearDuplicate => Some(s.index),
            _ => None,
        })
        .collect();
    for k in &keys[..keys.len() - 1] {
        if !(55..80).contains(k) {
            assert!(
                duplicates.contains(&(k + 1)),
                "frame {} after keyframe {k}",
                k + 1
            );
        }
    }
    // Blurred frames that are not near duplicates are reported as blurred.
    let mut blurred = 0;
    let mut reported = 0;
    for v in &verdicts {
        if let Verdict::Skipped(s) = v
            && plan[s.index].1
            && s.reason != SkipReason::NearDuplicate
        {
            blurred += 1;
            reported += usize::from(s.reason == SkipReason::Blurred);
        }
    }
    assert!(
        blurred >= 10 && reported * 5 >= blurred * 4,
        "{reported} of {blurred}"
    );
    // The end of the video is covered: the last keyframe is within the overlap bound of the
    // last frame.
    let last = *keys.last().unwrap();
    let tail = f64::from(plan.last().unwrap().0 - plan[last].0) / diagonal;
    assert!(tail <= options.max_displacement, "{tail}");
}

#[test]
fn a_textureless_video_still_gives_keyframes_at_the_lookback_rate() {
    let options = KeyframeOptions::default();
    let mut selector = KeyframeSelector::new(options.clone()).unwrap();
    let grey = Mat::new_rows_cols_with_default(H, W, opencv::core::CV_8UC3, 128.into()).unwrap();
    let mut keys = 0;
    for _ in 0..40 {
        for v in selector.push(grey.clone(), None).unwrap() {
            if let Verdict::Keyframe(k) = v {
                assert_eq!(k.displacement.unwrap_or(0.0), 0.0);
                keys += 1;
            }
        }
    }
    for v in selector.finish().unwrap() {
        if matches!(v, Verdict::Keyframe(_)) {
            keys += 1;
        }
    }
    // One keyframe per `lookback` frames, never every frame.
    assert!(
        (3..=6).contains(&keys),
        "{keys} keyframes of 40 flat frames"
    );
}

#[test]
fn frames_of_another_size_and_bad_options_are_errors() {
    assert!(
        KeyframeSelector::new(KeyframeOptions {
            min_displacement: 0.2,
            ..KeyframeOptions::default()
        })
        .is_err()
    );
    let mut selector = KeyframeSelector::new(KeyframeOptions::default()).unwrap();
    let a = Mat::new_rows_cols_with_default(H, W, opencv::core::CV_8UC3, 0.into()).unwrap();
    let b = Mat::new_rows_cols_with_default(H + 2, W, opencv::core::CV_8UC3, 0.into()).unwrap();
    selector.push(a, None).unwrap();
    let e = selector.push(b, None).unwrap_err().to_string();
    assert!(e.contains("322") || e.contains("242"), "{e}");
    assert!(selector.push(Mat::default(), None).is_err());
}
