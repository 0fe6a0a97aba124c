//! `view.html`: one self-contained page that shows the cameras (frusta with image thumbnails),
//! the sparse points and, when given, the ground truth aligned to the estimate (a similarity
//! from the camera centres, Umeyama) with per-camera errors, under an orbit camera. It opens
//! offline in any browser: three.js (vendored from the npm registry, MIT licence kept in the
//! page) and the data are inlined.
//!
//! The page sets `document.body.dataset.status` to `"rendered"` after its first frame, or to
//! `"error"` with the message shown, so a headless browser can check it.

use base64::Engine as _;
use nalgebra::{Matrix3, Point3, Vector3};
use posediff_geometry::Camera;
use serde::Serialize;

use crate::error::{PosediffError, Result};
use crate::reconstruction::Reconstruction;

/// three.js r170, `build/three.module.min.js` of the npm package `three@0.170.0`
/// (`cargo xtask vendor-three` fetches it again and checks its digest).
const THREE_JS: &str = include_str!("../../assets/three/three.module.min.js");
/// three.js's licence, kept in the page.
const THREE_LICENSE: &str = include_str!("../../assets/three/LICENSE");
/// The viewer's own script.
const VIEWER_JS: &str = include_str!("../../assets/viewer.js");

/// At most this many points go into the page (evenly subsampled beyond).
pub const MAX_VIEWER_POINTS: usize = 300_000;

#[derive(Serialize)]
struct ViewCamera {
    name: String,
    /// World-to-camera rotation, rows.
    r: [[f64; 3]; 3],
    t: [f64; 3],
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    w: u32,
    h: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    thumbnail: Option<String>,
    /// Rotation error against the ground truth, degrees (after the rotation alignment).
    #[serde(skip_serializing_if = "Option::is_none")]
    rotation_error_deg: Option<f64>,
    /// Centre error after alignment, in units of the ground truth's scene size.
    #[serde(skip_serializing_if = "Option::is_none")]
    centre_error: Option<f64>,
}

#[derive(Serialize)]
struct ViewData {
    title: String,
    cameras: Vec<ViewCamera>,
    /// The ground truth mapped into the estimate's world.
    ground_truth: Vec<ViewCamera>,
    /// `x y z` per point.
    points: Vec<f32>,
    /// `r g b` per point.
    colours: Vec<u8>,
    total_points: usize,
}

fn view_camera(name: &str, c: &Camera, thumbnail: Option<&[u8]>) -> ViewCamera {
    let r = c.cam_from_world.rotation;
    let t = c.cam_from_world.translation;
    let k = &c.intrinsics;
    ViewCamera {
        name: name.to_owned(),
        r: [0, 1, 2].map(|i| [0, 1, 2].map(|j| r[(i, j)])),
        t: [t.x, t.y, t.z],
        fx: k.fx(),
        fy: k.fy(),
        cx: k.cx(),
        cy: k.cy(),
        w: c.image_size.width(),
        h: c.image_size.height(),
        thumbnail: thumbnail.map(|b| {
            format!(
                "data:image/jpeg;base64,{}",
                base64::engine::general_purpose::STANDARD.encode(b)
            )
        }),
        rotation_error_deg: None,
        centre_error: None,
    }
}

/// The page for `r`: thumbnails per image (JPEG bytes, optional), the ground truth per image
/// (optional; aligned here).
///
/// # Errors
/// Counts that do not match the images; a ground truth with fewer than three cameras in
/// common with the estimate, or whose centres cannot be aligned.
pub fn render(
    title: &str,
    r: &Reconstruction,
    thumbnails: &[Option<Vec<u8>>],
    ground_truth: Option<&[Option<Camera>]>,
) -> Result<String> {
    if thumbnails.len() != r.images.len() {
        return Err(PosediffError::InvalidArgument(format!(
            "{} thumbnails for {} images",
            thumbnails.len(),
            r.images.len()
        )));
    }
    let mut cameras: Vec<ViewCamera> = Vec::new();
    let mut estimated: Vec<(usize, Camera)> = Vec::new();
    for (i, (record, thumb)) in r.images.iter().zip(thumbnails).enumerate() {
        if let Some(c) = &record.camera.camera {
            cameras.push(view_camera(&record.camera.image, c, thumb.as_deref()));
            estimated.push((i, *c));
        }
    }
    let mut gt_view = Vec::new();
    if let Some(gt) = ground_truth {
        if gt.len() != r.images.len() {
            return Err(PosediffError::InvalidArgument(format!(
                "{} ground-truth cameras for {} images",
                gt.len(),
                r.images.len()
            )));
        }
        let both: Vec<(usize, usize, Camera, Camera)> = estimated
            .iter()
            .enumerate()
            .filter_map(|(slot, (i, c))| gt[*i].map(|g| (slot, *i, *c, g)))
            .collect();
        if both.len() < 3 {
            return Err(PosediffError::InvalidArgument(format!(
                "the ground truth shares {} estimated cameras with the estimate; aligning needs 3",
                both.len()
            )));
        }
        let src: Vec<Point3<f64>> = both.iter().map(|b| b.3.center()).collect();
        let dst: Vec<Point3<f64>> = both.iter().map(|b| b.2.center()).collect();
        // Ground truth → estimate: x_est = s R x_gt + t.
        let sim = posediff_geometry::umeyama_with_scale(&src, &dst).map_err(|e| {
            PosediffError::InvalidArgument(format!("aligning the ground truth: {e}"))
        })?;
        let (s, rot, trans) = (sim.scale, sim.rotation, sim.translation);
        let gt_centroid = src.iter().map(|p| p.coords).sum::<Vector3<f64>>() / src.len() as f64;
        let extent = src
            .iter()
            .map(|p| (p.coords - gt_centroid).norm())
            .fold(0.0, f64::max)
            .max(1e-12);
        // The rotation errors use the world rotation that best aligns the camera rotations
        // (chordal mean of R_estᵀ R_gt), not the centres' (which an arc of centres fixes
        // poorly): R_est Q = R_gt for a perfect estimate.
        let mut sum = Matrix3::zeros();
        for (_, _, est, g) in &both {
            sum += est.cam_from_world.rotation.transpose() * g.cam_from_world.rotation;
        }
        let svd = sum.svd(true, true);
        let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
            return Err(PosediffError::InvalidArgument(
                "aligning the ground truth's rotations failed".into(),
            ));
        };
        let mut q = u * v_t;
        if q.determinant() < 0.0 {
            let mut u = u;
            u.column_mut(2).neg_mut();
            q = u * v_t;
        }
        for (slot, i, est, g) in both {
            // The ground-truth camera moved into the estimate's world: centre s R c + t,
            // world-to-camera rotation R_gt Rᵀ.
            let centre = s * (rot * g.center().coords) + trans;
            let rotation: Matrix3<f64> = g.cam_from_world.rotation * rot.transpose();
            let moved = Camera::new(
                g.intrinsics,
                posediff_geometry::Pose::from_rotation_centre(rotation, centre),
                g.image_size,
            );
            // The angle of R_est · q · R_gtᵀ, i.e. between R_gt and R_est · q.
            let angle = posediff_geometry::rotation_angle_between_deg(
                &g.cam_from_world.rotation,
                &(est.cam_from_world.rotation * q),
            );
            let centre_error = (est.center().coords - centre).norm() / (s * extent);
            cameras[slot].rotation_error_deg = Some(angle);
            cameras[slot].centre_error = Some(centre_error);
            gt_view.push(view_camera(&r.images[i].camera.image, &moved, None));
        }
    }
    let stride = r.points.len().div_ceil(MAX_VIEWER_POINTS).max(1);
    let mut points = Vec::new();
    let mut colours = Vec::new();
    for p in r.points.iter().step_by(stride) {
        points.extend([p.xyz.x as f32, p.xyz.y as f32, p.xyz.z as f32]);
        colours.extend(p.rgb);
    }
    let data = ViewData {
        title: title.to_owned(),
        cameras,
        ground_truth: gt_view,
        points,
        colours,
        total_points: r.points.len(),
    };
    // `</` cannot close a script inside JSON: escape it.
    let json = serde_json::to_string(&data)?.replace("</", "<\\/");
    Ok(PAGE
        .replace("{{TITLE}}", &html_escape(title))
        .replace("{{THREE_LICENSE}}", &THREE_LICENSE.replace("--", "- -"))
        .replace("{{THREE}}", THREE_JS)
        .replace("{{VIEWER}}", VIEWER_JS)
        .replace("{{DATA}}", &json))
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

const PAGE: &str = r#"<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{{TITLE}} — posediff</title>
<!-- three.js r170 (https://threejs.org), inlined below under its licence:
{{THREE_LICENSE}}
-->
<style>
html, body { margin: 0; height: 100%; overflow: hidden; background: #1e1f24; color: #ddd;
  font: 13px/1.4 system-ui, sans-serif; }
#panel { position: absolute; top: 8px; left: 8px; max-width: 360px; max-height: calc(100% - 16px);
  overflow: auto; background: rgba(20, 20, 24, 0.85); padding: 8px 10px; border-radius: 6px; }
#panel h1 { font-size: 14px; margin: 0 0 4px; }
#panel table { border-collapse: collapse; font-variant-numeric: tabular-nums; }
#panel td, #panel th { padding: 0 6px 0 0; text-align: right; }
#panel td:first-child, #panel th:first-child { text-align: left; }
#panel tr.hover { color: #ffd866; }
#error { color: #ff6b6b; white-space: pre-wrap; }
canvas { display: block; }
</style>
</head>
<body data-status="loading">
<div id="panel"><h1>{{TITLE}}</h1><div id="summary"></div><div id="error"></div>
<div>drag: orbit · right-drag or shift-drag: pan · wheel: zoom · double-click: reset</div>
<div id="legend"></div><table id="table"></table></div>
<script type="application/json" id="posediff-data">{{DATA}}</script>
<script type="text/plain" id="three-source">{{THREE}}</script>
<script>
window.addEventListener('error', (e) => {
  document.body.dataset.status = 'error';
  document.getElementById('error').textContent = String(e.message || e);
});
window.addEventListener('unhandledrejection', (e) => {
  document.body.dataset.status = 'error';
  document.getElementById('error').textContent = String(e.reason);
});
</script>
<script type="module">
{{VIEWER}}
</script>
</body>
</html>
"#;

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    use crate::reconstruction::ImageCamera;
    use nalgebra::Rotation3;
    use posediff_geometry::{ImageSize, Intrinsics, Pose};

    fn data_of(page: &str) -> serde_json::Value {
        let start = page.find("id=\"posediff-data\">").unwrap() + "id=\"posediff-data\">".len();
        let end = start + page[start..].find("</script>").unwrap();
        serde_json::from_str(&page[start..end].replace("<\\/", "</")).unwrap()
    }

    fn ring() -> Vec<Camera> {
        (0..6)
            .map(|i| {
                let a = f64::from(i) * 0.5;
                let r = *Rotation3::from_euler_angles(0.1 * a, a, 0.0).matrix();
                let centre = Vector3::new(3.0 * a.sin(), 0.3 * a, -3.0 * a.cos());
                Camera::new(
                    Intrinsics::new(400.0, 400.0, 159.5, 119.5).unwrap(),
                    Pose::from_rotation_centre(r, centre),
                    ImageSize::new(320, 240).unwrap(),
                )
            })
            .collect()
    }

    #[test]
    fn a_ground_truth_off_by_a_similarity_has_zero_errors_and_a_moved_one_does_not() {
        let cams = ring();
        let r = Reconstruction::from_cameras(
            cams.iter()
                .enumerate()
                .map(|(i, c)| ImageCamera {
                    image: format!("{i}.jpg"),
                    size: c.image_size,
                    camera: Some(*c),
                    lens: None,
                })
                .collect(),
        );
        // x_gt = s Q x + t: the same cameras in another world.
        let (s, q, t) = (
            2.5,
            *Rotation3::from_euler_angles(0.3, -0.2, 1.0).matrix(),
            Vector3::new(1.0, -2.0, 0.5),
        );
        let moved = |c: &Camera| {
            let centre = s * (q * c.center().coords) + t;
            let rot = c.cam_from_world.rotation * q.transpose();
            Camera::new(
                c.intrinsics,
                Pose::from_rotation_centre(rot, centre),
                c.image_size,
            )
        };
        let mut gt: Vec<Option<Camera>> = cams.iter().map(|c| Some(moved(c))).collect();
        let page = render("t", &r, &vec![None; cams.len()], Some(&gt)).unwrap();
        let data = data_of(&page);
        assert_eq!(data["ground_truth"].as_array().unwrap().len(), cams.len());
        for c in data["cameras"].as_array().unwrap() {
            assert!(c["rotation_error_deg"].as_f64().unwrap() < 1e-5, "{c}");
            assert!(c["centre_error"].as_f64().unwrap() < 1e-9, "{c}");
        }
        // One ground-truth camera turned by 10° about its centre: that one shows it.
        let g = gt[2].unwrap();
        let turn = *Rotation3::from_euler_angles(0.0, 10f64.to_radians(), 0.0).matrix();
        let rot = turn * g.cam_from_world.rotation;
        gt[2] = Some(Camera::new(
            g.intrinsics,
            Pose::from_rotation_centre(rot, g.center().coords),
            g.image_size,
        ));
        gt[4] = None;
        let data = data_of(&render("t", &r, &vec![None; cams.len()], Some(&gt)).unwrap());
        let errors: Vec<f64> = data["cameras"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["rotation_error_deg"].as_f64().unwrap_or(-1.0))
            .collect();
        assert!(errors[2] > 7.0, "{errors:?}");
        assert!(errors[4] < 0.0, "no ground truth, no error: {errors:?}");
        assert!(
            errors.iter().enumerate().all(|(k, e)| k == 2 || *e < 3.0),
            "{errors:?}"
        );
        // Too few cameras in common.
        let few: Vec<Option<Camera>> = gt.iter().take(2).copied().chain(vec![None; 4]).collect();
        assert!(render("t", &r, &vec![None; cams.len()], Some(&few)).is_err());
    }

    #[test]
    fn the_vendored_library_cannot_close_its_script_element() {
        assert!(!THREE_JS.contains("</script"));
        assert!(THREE_JS.contains("REVISION"));
        assert!(THREE_LICENSE.contains("MIT"));
    }
}
