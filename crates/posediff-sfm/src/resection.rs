//! Resection of the cameras that hang on a bridge of the view graph.
//!
//! A bridge is a pair whose removal splits the estimated cameras in two (found by
//! [`crate::view_graph::bridges`]): its relative pose is confirmed by no cycle, so rotation and
//! translation averaging place the smaller side wherever that one pair says. A wrong two-view
//! solution there (a few wrong matches, or the planar ambiguity of a nearly flat scene) moves a
//! whole group of cameras rigidly and no later stage can undo it.
//!
//! The tracks can: the points seen by two or more cameras of the larger side (the anchor) are
//! triangulated with the anchor's cameras alone, and every camera of the smaller side that sees
//! enough of them is resected (PnP through the [`GeometrySolver`]). If the best resected camera
//! explains clearly more of its 2D–3D correspondences than its current pose does, the whole side
//! is moved by the similarity that takes that camera to its resected pose: the rotation and
//! centre from the resection, the side's scale from the points both sides triangulate (or from
//! the other resected cameras). As in incremental mappers (COLMAP's registration of a new image),
//! structure decides where a weakly attached camera goes, not the weakest pair.
//!
//! Tracks are often too short for that: a bridge is a pair few features survive. When the scene
//! is dominated by a plane (an object on a table: the captures CO3D is made of), the bridge's
//! two-view pose has the planar two-fold ambiguity, and both solutions fit its matches. The
//! plane decides it: the anchor's points seen by the bridge's anchor camera give the plane
//! `nᵀx = d` in that camera's frame (RANSAC, then least squares); the bridge's keypoints in the
//! anchor camera, back-projected onto it, are 3D points the moving camera sees, and it is
//! resected on them (the matches off the plane are PnP's outliers). The side is moved there when
//! the new pose explains the bridge's matches about as well as the current one (both ambiguous
//! solutions do), and the tracks do not contradict it. When the rotation agrees already, only
//! the bridge's length (which no pair observes) is taken from the plane. The side's own scale
//! is the one that puts its points, triangulated by its cameras, on the plane.
//!
//! The move is rigid about the placed camera, times the side's scale where it is observed; the
//! bundle adjustment that follows refines everything from there.
//!
//! Cost: per bridge, the sides (linear in the view graph) and one pass over the tracks of the
//! bridge's anchor camera and of the smaller side's cameras matched with the anchor. A chain of
//! N cameras, where every pair is a bridge, costs N graph traversals and about two cameras'
//! tracks per bridge.

use std::collections::HashMap;

use faer::Mat;
use nalgebra::{Matrix3, Rotation3, Vector3};
use posediff_geometry::PairMatches;

use crate::bundle::{project, triangulate};
use crate::camera::CameraPose;
use crate::error::{Result, SfmError};
use crate::intrinsics::ImageIntrinsics;
use crate::sampson_refine::{pair_fundamental, sampson_distance};
use crate::solver::GeometrySolver;
use crate::tracks::{Observation, Track};
use crate::view_graph::{bridges, side_of};

pub use crate::solver::AbsolutePose;

/// Settings of the bridge resection.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct ResectionOptions {
    /// Reprojection error of an inlier, pixels (triangulation check and PnP).
    pub threshold_px: f64,
    /// Fewest PnP inliers for a resection to count, and fewest epipolar inliers of a bridge
    /// pair for a plane-induced pose to count.
    pub min_inliers: usize,
    /// A side is moved by PnP only when the resected pose has at least this many times the
    /// inliers of the current pose (on the same correspondences).
    pub min_gain: f64,
    /// Smallest widest-ray angle of an anchor point, degrees.
    pub min_angle_deg: f64,
    /// Sampson distance of an epipolar inlier of the bridge pair, pixels.
    pub epipolar_px: f64,
    /// A move must leave at least this fraction of the bridge pair's epipolar inliers (the two
    /// solutions of the planar ambiguity explain about the same; a move that the tracks of
    /// wrong matches suggest does not).
    pub min_relative_inliers: f64,
    /// The plane-induced pose of planar bridges (`None`: tracks only).
    pub plane: Option<PlaneOptions>,
}

impl Default for ResectionOptions {
    fn default() -> Self {
        Self {
            threshold_px: 4.0,
            min_inliers: 12,
            min_gain: 1.5,
            min_angle_deg: 2.0,
            epipolar_px: 2.0,
            min_relative_inliers: 0.8,
            plane: Some(PlaneOptions::default()),
        }
    }
}

/// Settings of the plane-induced pose of a bridge.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct PlaneOptions {
    /// Fewest anchor points seen by the bridge's anchor camera.
    pub min_points: usize,
    /// Fewest of them on the fitted plane (a fraction).
    pub min_fraction: f64,
    /// Fewest of the bridge pair's matches that the plane-induced resection explains (a
    /// fraction). Low on purpose: the matches off the plane (the object on it) are its
    /// outliers but still fit the epipolar check that follows, which a wrong plane fails.
    pub min_plane_matches: f64,
    /// Distance from the plane of a point on it, relative to the points' median depth.
    pub tolerance: f64,
    /// A resection within this rotation (degrees) of the current pose changes at most the
    /// bridge's length.
    pub min_rotation_deg: f64,
    /// The bridge's length is changed only by at least this factor (either way).
    pub min_scale_change: f64,
}

impl Default for PlaneOptions {
    fn default() -> Self {
        Self {
            min_points: 20,
            min_fraction: 0.6,
            min_plane_matches: 0.4,
            tolerance: 0.01,
            min_rotation_deg: 2.0,
            min_scale_change: 1.1,
        }
    }
}

/// What moved a side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Evidence {
    /// PnP of a camera on the anchor side's triangulated tracks.
    Tracks,
    /// A PnP of the bridge's keypoints back-projected onto the plane the anchor reconstructs.
    Plane,
}

impl Evidence {
    /// The name in reports.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Tracks => "tracks",
            Self::Plane => "plane",
        }
    }
}

#[cfg(feature = "serde")]
serialize_as_str!(Evidence);

/// One bridge whose smaller side was moved.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct MovedSide {
    /// The bridge pair.
    pub first: usize,
    /// The bridge pair.
    pub second: usize,
    /// The camera placed by the evidence; the rest of its side moved with it.
    pub image: usize,
    /// Cameras moved (the side).
    pub images: usize,
    /// What placed it.
    pub evidence: Evidence,
    /// The correspondences weighed: 2D–3D (tracks) or the bridge pair's matches (plane).
    pub correspondences: usize,
    /// Inliers among them with the pose before.
    pub inliers_before: usize,
    /// Inliers among them with the new pose.
    pub inliers_after: usize,
    /// The side's scale change, `None` when unobserved (the side kept its scale).
    pub scale: Option<f64>,
}

/// What the bridge resection did.
#[derive(Debug, Clone, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct ResectionReport {
    /// Bridges of the view graph of the estimated cameras.
    pub bridges: usize,
    /// The sides moved.
    pub moved: Vec<MovedSide>,
    /// Bridges left as they were because the solver failed on them: the pair and the error.
    pub unchecked: Vec<(usize, usize, String)>,
}

fn resection_error(image: usize, detail: impl std::fmt::Display) -> SfmError {
    SfmError::Resection {
        image,
        detail: detail.to_string(),
    }
}

fn reprojects(
    c: &CameraPose,
    intrinsics: &ImageIntrinsics,
    phi: f64,
    o: &Observation,
    x: &Vector3<f64>,
    threshold: f64,
) -> bool {
    project(
        c,
        intrinsics.focal(phi, o.image),
        intrinsics.principal[o.image],
        x,
    )
    .is_some_and(|(uv, _)| (uv[0] - o.xy[0]).hypot(uv[1] - o.xy[1]) <= threshold)
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[v.len() / 2])
}

/// The rotation angle between two rotations, degrees.
fn angle_deg(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
    (a * b.inverse()).angle().to_degrees()
}

/// The camera whose world → camera map is `x ↦ R x + t`.
fn pose_from(rotation: &Matrix3<f64>, translation: &Vector3<f64>) -> CameraPose {
    let rotation = Rotation3::from_matrix(rotation);
    CameraPose {
        rotation,
        center: -(rotation.inverse() * translation),
    }
}

/// The plane `nᵀx = d` (`|n| = 1`, `d > 0`) through most of `points` (camera frame), and how
/// many lie within `tolerance` × their median depth of it: RANSAC over deterministic triples,
/// then a least-squares refit of the inliers (faer SVD).
fn fit_plane(points: &[Vector3<f64>], tolerance: f64) -> Option<(Vector3<f64>, f64, usize)> {
    let n = points.len();
    if n < 3 {
        return None;
    }
    let tau = tolerance * median(points.iter().map(|p| p.z).collect())?;
    let count = |normal: &Vector3<f64>, d: f64| {
        points
            .iter()
            .filter(|p| (normal.dot(p) - d).abs() <= tau)
            .count()
    };
    let mut state: u64 = 0x9e37_79b9_7f4a_7c15;
    let mut next = |m: usize| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((state >> 33) as usize) % m
    };
    let mut best: Option<(Vector3<f64>, f64, usize)> = None;
    for _ in 0..300 {
        let (a, b, c) = (points[next(n)], points[next(n)], points[next(n)]);
        let normal = (b - a).cross(&(c - a));
        let norm = normal.norm();
        if norm.is_nan() || norm <= 1e-12 {
            continue;
        }
        let normal = normal / norm;
        let d = normal.dot(&a);
        let inliers = count(&normal, d);
        if best.is_none_or(|b| inliers > b.2) {
            best = Some((normal, d, inliers));
        }
    }
    let (normal, d, _) = best?;
    let on: Vec<&Vector3<f64>> = points
        .iter()
        .filter(|p| (normal.dot(p) - d).abs() <= tau)
        .collect();
    let centroid = on.iter().fold(Vector3::zeros(), |s, p| s + **p) / on.len() as f64;
    let mut m = Mat::<f64>::zeros(on.len(), 3);
    for (i, p) in on.iter().enumerate() {
        for j in 0..3 {
            m[(i, j)] = p[j] - centroid[j];
        }
    }
    let svd = m.thin_svd().ok()?;
    let v = svd.V();
    let mut normal = Vector3::new(v[(0, 2)], v[(1, 2)], v[(2, 2)]).normalize();
    let mut d = normal.dot(&centroid);
    if d < 0.0 {
        (normal, d) = (-normal, -d);
    }
    (d > 0.0 && normal.iter().all(|x| x.is_finite())).then(|| (normal, d, count(&normal, d)))
}

/// The per-run inputs of the bridge resection.
struct Context<'a> {
    tracks: &'a [Track],
    intrinsics: &'a ImageIntrinsics,
    phi: f64,
    by_image: Vec<Vec<(usize, usize)>>,
    /// The images each image has matches with.
    matched_with: Vec<Vec<usize>>,
    options: &'a ResectionOptions,
    solver: &'a dyn GeometrySolver,
}

/// One bridge's sides and the anchor's triangulated points (computed on demand).
struct Bridge {
    in_anchor: Vec<bool>,
    in_moving: Vec<bool>,
    moving: Vec<usize>,
    anchor_points: HashMap<usize, Option<Vector3<f64>>>,
}

impl Move {
    /// Camera `c` of the side after the move: `x_new = s Q (x_old − c_old) + c_new`, with
    /// `Q = R_newᵀ R_old` and `s` the scale (1 when unobserved).
    fn moved(&self, c: &CameraPose) -> CameraPose {
        c.warped(&self.old, &self.new, self.scale.unwrap_or(1.0))
    }
}

/// How to move a side: camera `image` goes from `old` to `new`, the side's scale by `scale`.
struct Move {
    image: usize,
    old: CameraPose,
    new: CameraPose,
    scale: Option<f64>,
    evidence: Evidence,
    correspondences: usize,
    before: usize,
    after: usize,
}

impl Context<'_> {
    /// The point of track `t` triangulated from its observations in the images `side` marks,
    /// kept only when each of them reprojects within the threshold.
    fn side_point(
        &self,
        t: usize,
        side: &[bool],
        cameras: &[Option<CameraPose>],
    ) -> Option<Vector3<f64>> {
        let o = self.options;
        let obs: Vec<Observation> = self.tracks[t]
            .iter()
            .filter(|ob| side[ob.image] && cameras[ob.image].is_some())
            .copied()
            .collect();
        if obs.len() < 2 {
            return None;
        }
        let x = triangulate(
            &obs,
            cameras,
            self.intrinsics,
            self.phi,
            o.min_angle_deg.to_radians(),
        )?;
        obs.iter()
            .all(|ob| {
                cameras[ob.image].is_some_and(|c| {
                    reprojects(&c, self.intrinsics, self.phi, ob, &x, o.threshold_px)
                })
            })
            .then_some(x)
    }

    fn anchor_point(
        &self,
        bridge: &mut Bridge,
        t: usize,
        cameras: &[Option<CameraPose>],
    ) -> Option<Vector3<f64>> {
        if let Some(x) = bridge.anchor_points.get(&t) {
            return *x;
        }
        let x = self.side_point(t, &bridge.in_anchor, cameras);
        bridge.anchor_points.insert(t, x);
        x
    }

    /// Image `m`'s 2D–3D correspondences with the anchor: (track, pixel, point).
    fn correspondences(
        &self,
        bridge: &mut Bridge,
        m: usize,
        cameras: &[Option<CameraPose>],
    ) -> Vec<(usize, [f64; 2], Vector3<f64>)> {
        let mut out = Vec::new();
        for &(t, k) in &self.by_image[m] {
            if let Some(x) = self.anchor_point(bridge, t, cameras) {
                out.push((t, self.tracks[t][k].xy, x));
            }
        }
        out
    }

    fn count_reprojected(
        &self,
        camera: &CameraPose,
        m: usize,
        corr: &[(usize, [f64; 2], Vector3<f64>)],
    ) -> usize {
        corr.iter()
            .filter(|(_, xy, x)| {
                let ob = Observation {
                    image: m,
                    keypoint: 0,
                    xy: *xy,
                };
                reprojects(
                    camera,
                    self.intrinsics,
                    self.phi,
                    &ob,
                    x,
                    self.options.threshold_px,
                )
            })
            .count()
    }

    /// The bridge pair's matches within the epipolar threshold of cameras `a` and `b`.
    fn epipolar_inliers(
        &self,
        pair: &PairMatches,
        (ia, a): (usize, &CameraPose),
        (ib, b): (usize, &CameraPose),
    ) -> usize {
        let (kp_a, kp_b) = if pair.first == ia {
            (&pair.kp1, &pair.kp2)
        } else {
            (&pair.kp2, &pair.kp1)
        };
        let f = pair_fundamental(a, b, self.phi, self.intrinsics, ia, ib);
        let f = [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| f[(k / 3, k % 3)]);
        kp_a.iter()
            .zip(kp_b.iter())
            .filter(|(x, y)| {
                sampson_distance(&f, **x, **y).is_some_and(|r| r.abs() <= self.options.epipolar_px)
            })
            .count()
    }

    /// PnP of the smaller side's cameras on the anchor's points: the best resected camera, if
    /// it beats its current pose by the gain.
    fn by_tracks(
        &self,
        bridge: &mut Bridge,
        cameras: &[Option<CameraPose>],
        (u, v): (usize, usize),
        pair: &PairMatches,
    ) -> Result<Option<Move>> {
        let o = self.options;
        let mut best: Option<(Move, Vec<usize>)> = None;
        let mut resected: Vec<(usize, CameraPose)> = Vec::new();
        for m in bridge.moving.clone() {
            let Some(current) = cameras[m] else { continue };
            // Only cameras matched with the anchor see its points (and the work per bridge
            // stays with the few cameras next to it, not the whole side).
            if !self.matched_with[m].iter().any(|&j| bridge.in_anchor[j]) {
                continue;
            }
            let corr = self.correspondences(bridge, m, cameras);
            if corr.len() < o.min_inliers {
                continue;
            }
            let points: Vec<Vector3<f64>> = corr.iter().map(|c| c.2).collect();
            let pixels: Vec<[f64; 2]> = corr.iter().map(|c| c.1).collect();
            let k_m = self.intrinsics.k(self.phi, m);
            let Some(pose) =
                self.solver
                    .absolute_pose(m, &points, &pixels, &k_m, o.threshold_px)?
            else {
                continue;
            };
            if pose.inliers.iter().any(|&i| i >= corr.len()) {
                return Err(resection_error(
                    m,
                    "the solver named an inlier out of range",
                ));
            }
            if pose.inliers.len() < o.min_inliers {
                continue;
            }
            let new = pose_from(&pose.rotation, &pose.translation);
            resected.push((m, new));
            if best.as_ref().is_none_or(|b| pose.inliers.len() > b.0.after) {
                let tracks = pose.inliers.iter().map(|&i| corr[i].0).collect();
                best = Some((
                    Move {
                        image: m,
                        old: current,
                        new,
                        scale: None,
                        evidence: Evidence::Tracks,
                        correspondences: corr.len(),
                        before: self.count_reprojected(&current, m, &corr),
                        after: pose.inliers.len(),
                    },
                    tracks,
                ));
            }
        }
        let Some((mut mv, inlier_tracks)) = best else {
            return Ok(None);
        };
        if !((mv.after as f64) >= o.min_gain * mv.before as f64 && mv.after > mv.before) {
            return Ok(None);
        }
        // The scale: points both sides triangulate, else the other resected cameras.
        let mut ratios = Vec::new();
        for t in inlier_tracks {
            let (Some(Some(xa)), Some(xb)) = (
                bridge.anchor_points.get(&t),
                self.side_point(t, &bridge.in_moving, cameras),
            ) else {
                continue;
            };
            let (da, db) = ((xa - mv.new.center).norm(), (xb - mv.old.center).norm());
            if db > 0.0 {
                ratios.push(da / db);
            }
        }
        if ratios.len() < 3 {
            for (j, pose) in &resected {
                let Some(cj) = cameras[*j] else { continue };
                let db = (cj.center - mv.old.center).norm();
                if *j != mv.image && db > 0.0 {
                    ratios.push((pose.center - mv.new.center).norm() / db);
                }
            }
        }
        mv.scale = median(ratios).filter(|s| s.is_finite() && *s > 0.0);
        // Tracks can be wrong too (repeated structure matched across the set): the move must
        // keep the bridge pair's own epipolar geometry.
        let (Some(cu), Some(cv)) = (cameras[u], cameras[v]) else {
            return Ok(None);
        };
        let before = self.epipolar_inliers(pair, (u, &cu), (v, &cv));
        let after = self.epipolar_inliers(pair, (u, &cu), (v, &mv.moved(&cv)));
        if (after as f64) < o.min_relative_inliers * before as f64 {
            return Ok(None);
        }
        Ok(Some(mv))
    }

    /// The plane-induced pose of the bridge's moving camera, if the anchor has a plane, the
    /// bridge's keypoints on it resect the camera, and the pose fits the bridge's matches and
    /// the tracks as the module says.
    fn by_plane(
        &self,
        bridge: &mut Bridge,
        cameras: &[Option<CameraPose>],
        (u, v): (usize, usize),
        pair: &PairMatches,
    ) -> Result<Option<Move>> {
        let Some(po) = self.options.plane else {
            return Ok(None);
        };
        let (Some(cu), Some(cv)) = (cameras[u], cameras[v]) else {
            return Ok(None);
        };
        let mut on_u = Vec::new();
        for &(t, _) in &self.by_image[u] {
            if let Some(x) = self.anchor_point(bridge, t, cameras) {
                let xc = cu.rotation * (x - cu.center);
                if xc.z > 0.0 {
                    on_u.push(xc);
                }
            }
        }
        if on_u.len() < po.min_points {
            return Ok(None);
        }
        let Some((normal, d, on_plane)) = fit_plane(&on_u, po.tolerance) else {
            return Ok(None);
        };
        if (on_plane as f64) < po.min_fraction * on_u.len() as f64 {
            return Ok(None);
        }
        // The bridge's keypoints in the anchor camera, back-projected onto the plane, are 3D
        // points the moving camera sees: it is resected on them (the matches off the plane are
        // PnP's outliers).
        let (kp_u, kp_v) = if pair.first == u {
            (&pair.kp1, &pair.kp2)
        } else {
            (&pair.kp2, &pair.kp1)
        };
        let ku_inv = self.intrinsics.k_inverse(self.phi, u);
        let (mut points, mut pixels, mut kept) = (Vec::new(), Vec::new(), Vec::new());
        for (m, (x, y)) in kp_u.iter().zip(kp_v.iter()).enumerate() {
            let ray = ku_inv * Vector3::new(x[0], x[1], 1.0);
            let depth = normal.dot(&ray);
            if depth > 0.0 {
                let on_plane = ray * (d / depth);
                points.push(cu.rotation.inverse() * on_plane + cu.center);
                pixels.push(*y);
                kept.push(m);
            }
        }
        if points.len() < self.options.min_inliers {
            return Ok(None);
        }
        let k_v = self.intrinsics.k(self.phi, v);
        let Some(pose) =
            self.solver
                .absolute_pose(v, &points, &pixels, &k_v, self.options.threshold_px)?
        else {
            return Ok(None);
        };
        if pose.inliers.iter().any(|&i| i >= points.len()) {
            return Err(resection_error(
                v,
                "the solver named an inlier out of range",
            ));
        }
        let on_plane = pose.inliers.len();
        if on_plane < self.options.min_inliers
            || (on_plane as f64) < po.min_plane_matches * kp_u.len() as f64
        {
            return Ok(None);
        }
        let mut candidate = pose_from(&pose.rotation, &pose.translation);
        if angle_deg(&candidate.rotation, &cv.rotation) < po.min_rotation_deg {
            // The pair agrees with the plane: only the bridge's length, which no pair observes,
            // is taken from it (the rotation and direction stay).
            let old = (cv.center - cu.center).norm();
            let ratio = (candidate.center - cu.center).norm() / old;
            if !(ratio.is_finite() && ratio > 0.0 && ratio.ln().abs() >= po.min_scale_change.ln()) {
                return Ok(None);
            }
            candidate = CameraPose {
                rotation: cv.rotation,
                center: cu.center + (cv.center - cu.center) * ratio,
            };
        }
        let (before, after) = (
            self.epipolar_inliers(pair, (u, &cu), (v, &cv)),
            self.epipolar_inliers(pair, (u, &cu), (v, &candidate)),
        );
        let corr = self.correspondences(bridge, v, cameras);
        // The tracks contradict the candidate when the current pose explains clearly more of
        // the camera's 2D–3D correspondences (a few either way are noise).
        let (tracks_now, tracks_then) = (
            self.count_reprojected(&cv, v, &corr),
            self.count_reprojected(&candidate, v, &corr),
        );
        let tracks_agree =
            tracks_now < 3 || (tracks_now as f64) <= self.options.min_gain * tracks_then as f64;
        if after < self.options.min_inliers
            || (after as f64) < self.options.min_relative_inliers * before as f64
            || !tracks_agree
        {
            return Ok(None);
        }
        // The side's own scale: the one that puts its points on the plane. They are the
        // tracks of the resection's inliers (bridge keypoints on the plane) that two or more of
        // the side's cameras triangulate; each gives the scale about the new centre at which it
        // meets the plane.
        let kp_index = if pair.first == u {
            &pair.idx2
        } else {
            &pair.idx1
        };
        let track_of: HashMap<u32, usize> = self.by_image[v]
            .iter()
            .map(|&(t, k)| (self.tracks[t][k].keypoint, t))
            .collect();
        let normal_world = cu.rotation.inverse() * normal;
        let d_world = d + normal_world.dot(&cu.center);
        let q = candidate.rotation.inverse() * cv.rotation;
        let mut ratios = Vec::new();
        for &i in &pose.inliers {
            let Some(&t) = kept.get(i).and_then(|&m| track_of.get(&kp_index[m])) else {
                continue;
            };
            let Some(x) = self.side_point(t, &bridge.in_moving, cameras) else {
                continue;
            };
            let along = normal_world.dot(&(q * (x - cv.center)));
            let s = (d_world - normal_world.dot(&candidate.center)) / along;
            if s.is_finite() && s > 0.0 {
                ratios.push(s);
            }
        }
        let scale = if ratios.len() >= 3 {
            median(ratios)
        } else {
            None
        };
        Ok(Some(Move {
            image: v,
            old: cv,
            new: candidate,
            scale,
            evidence: Evidence::Plane,
            correspondences: kp_u.len(),
            before,
            after,
        }))
    }
}

/// Re-places the smaller side of every bridge of the graph of estimated cameras (`edges`: the
/// pairs with a relative pose, whose matches are in `pairs`) from the larger side's tracks or
/// plane, as the module says. `cameras` are changed in place; images not estimated stay so.
///
/// # Errors
/// Invalid options, intrinsics of the wrong length. (The solver's failures on a bridge are
/// reported in [`ResectionReport::unchecked`].)
#[allow(clippy::too_many_arguments)]
pub fn resect_bridged_sides(
    tracks: &[Track],
    pairs: &[PairMatches],
    intrinsics: &ImageIntrinsics,
    phi: f64,
    cameras: &mut [Option<CameraPose>],
    edges: &[(usize, usize)],
    solver: &dyn GeometrySolver,
    options: &ResectionOptions,
) -> Result<ResectionReport> {
    let o = options;
    let plane_ok = o.plane.is_none_or(|p| {
        [p.min_fraction, p.min_plane_matches]
            .iter()
            .all(|f| *f > 0.0 && *f <= 1.0)
            && p.tolerance > 0.0
            && p.min_rotation_deg >= 0.0
            && p.min_scale_change >= 1.0
    });
    if !(o.threshold_px > 0.0
        && o.epipolar_px > 0.0
        && o.min_relative_inliers >= 0.0
        && o.min_gain >= 1.0
        && o.min_angle_deg >= 0.0
        && o.min_inliers >= 6
        && plane_ok)
    {
        return Err(SfmError::InvalidInput(format!(
            "resection options {o:?}: need positive thresholds, a gain of at least 1, at least \
             6 inliers and fractions in (0, 1]"
        )));
    }
    let n = cameras.len();
    intrinsics.check(n)?;
    let edges: Vec<(usize, usize)> = edges
        .iter()
        .copied()
        .filter(|&(a, b)| a < n && b < n && cameras[a].is_some() && cameras[b].is_some())
        .collect();
    let found = bridges(n, &edges);
    let mut report = ResectionReport {
        bridges: found.len(),
        ..ResectionReport::default()
    };
    if found.is_empty() {
        return Ok(report);
    }
    let mut by_image: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
    for (t, track) in tracks.iter().enumerate() {
        for (k, obs) in track.iter().enumerate() {
            if obs.image < n {
                by_image[obs.image].push((t, k));
            }
        }
    }
    let by_pair: HashMap<(usize, usize), &PairMatches> = pairs
        .iter()
        .map(|p| ((p.first.min(p.second), p.first.max(p.second)), p))
        .collect();
    let mut matched_with = vec![Vec::new(); n];
    for p in pairs.iter().filter(|p| !p.is_empty()) {
        if p.first < n && p.second < n {
            matched_with[p.first].push(p.second);
            matched_with[p.second].push(p.first);
        }
    }
    let context = Context {
        tracks,
        intrinsics,
        phi,
        by_image,
        matched_with,
        options,
        solver,
    };
    for k in found {
        let (u, v) = edges[k];
        let side_u = side_of(n, &edges, k, u);
        let side_v = side_of(n, &edges, k, v);
        // The smaller side moves; equal sides: the one without the smallest image.
        let (moving, anchor, ends) = if (side_v.len(), side_u[0]) < (side_u.len(), side_v[0]) {
            (side_v, side_u, (u, v))
        } else {
            (side_u, side_v, (v, u))
        };
        let mut in_anchor = vec![false; n];
        for &i in &anchor {
            in_anchor[i] = true;
        }
        let mut in_moving = vec![false; n];
        for &i in &moving {
            in_moving[i] = true;
        }
        let mut bridge = Bridge {
            in_anchor,
            in_moving,
            moving,
            anchor_points: HashMap::new(),
        };
        let Some(pair) = by_pair.get(&(u.min(v), u.max(v))).copied() else {
            report
                .unchecked
                .push((u, v, "no matches for the bridge pair".into()));
            continue;
        };
        // A solver failure leaves this bridge as it is (reported): the cameras are then the
        // averaging's, as without this stage.
        let mut mv = match context.by_tracks(&mut bridge, cameras, ends, pair) {
            Ok(mv) => mv,
            Err(e) => {
                report.unchecked.push((u, v, e.to_string()));
                continue;
            }
        };
        if mv.is_none() {
            mv = match context.by_plane(&mut bridge, cameras, ends, pair) {
                Ok(mv) => mv,
                Err(e) => {
                    report.unchecked.push((u, v, e.to_string()));
                    continue;
                }
            };
        }
        let Some(mv) = mv else { continue };
        for &j in &bridge.moving {
            if let Some(c) = cameras[j] {
                cameras[j] = Some(mv.moved(&c));
            }
        }
        report.moved.push(MovedSide {
            first: u,
            second: v,
            image: mv.image,
            images: bridge.moving.len(),
            evidence: mv.evidence,
            correspondences: mv.correspondences,
            inliers_before: mv.before,
            inliers_after: mv.after,
            scale: mv.scale,
        });
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::solver::RelativePose;
    use crate::tracks::build_tracks;

    /// A solver whose resection always fails (the other methods are not used here).
    struct Failing;

    impl GeometrySolver for Failing {
        fn homography(&self, _: &PairMatches) -> Result<Option<(Matrix3<f64>, f64)>> {
            Ok(None)
        }
        fn fundamental(&self, _: &PairMatches) -> Result<Option<Matrix3<f64>>> {
            Ok(None)
        }
        fn relative_pose(
            &self,
            _: &PairMatches,
            _: Option<(Matrix3<f64>, f64)>,
            _: &Matrix3<f64>,
            _: &Matrix3<f64>,
        ) -> Result<Option<RelativePose>> {
            Ok(None)
        }
        fn absolute_pose(
            &self,
            image: usize,
            _: &[Vector3<f64>],
            _: &[[f64; 2]],
            _: &Matrix3<f64>,
            _: f64,
        ) -> Result<Option<AbsolutePose>> {
            Err(resection_error(image, "no PnP here"))
        }
    }

    #[test]
    fn a_solver_failure_leaves_the_bridge_as_it_was_and_says_so() {
        // Four cameras in a row looking down +z at points 5 ahead; triangle 0-1-2, bridge 2-3.
        let cameras: Vec<Option<CameraPose>> = (0..4)
            .map(|i| {
                Some(CameraPose {
                    rotation: Rotation3::identity(),
                    center: Vector3::new(0.5 * f64::from(i), 0.0, 0.0),
                })
            })
            .collect();
        let intrinsics = ImageIntrinsics::new(vec![[320.0, 240.0]; 4], vec![500.0; 4]);
        let points: Vec<Vector3<f64>> = (0..30)
            .map(|k| {
                let k = f64::from(k);
                Vector3::new(
                    (k * 0.37) % 2.0 - 0.2,
                    (k * 0.53) % 1.5 - 0.7,
                    5.0 + k % 3.0,
                )
            })
            .collect();
        let pixel = |i: usize, x: &Vector3<f64>| {
            let p = intrinsics.k(1.0, i) * (x - cameras[i].unwrap().center);
            [p.x / p.z, p.y / p.z]
        };
        let pairs: Vec<PairMatches> = [(0, 1), (1, 2), (0, 2), (2, 3)]
            .iter()
            .map(|&(a, b)| PairMatches {
                first: a,
                second: b,
                kp1: points.iter().map(|x| pixel(a, x)).collect(),
                kp2: points.iter().map(|x| pixel(b, x)).collect(),
                idx1: (0..30).collect(),
                idx2: (0..30).collect(),
            })
            .collect();
        let (tracks, _) = build_tracks(4, &pairs).unwrap();
        let edges: Vec<(usize, usize)> = pairs.iter().map(|p| (p.first, p.second)).collect();
        let mut moved = cameras.clone();
        let report = resect_bridged_sides(
            &tracks,
            &pairs,
            &intrinsics,
            1.0,
            &mut moved,
            &edges,
            &Failing,
            &ResectionOptions::default(),
        )
        .unwrap();
        assert_eq!(report.bridges, 1);
        assert!(report.moved.is_empty());
        assert_eq!(report.unchecked.len(), 1, "{report:?}");
        assert_eq!((report.unchecked[0].0, report.unchecked[0].1), (2, 3));
        assert!(report.unchecked[0].2.contains("no PnP here"));
        assert_eq!(moved, cameras);
        // Invalid options are an error before any work.
        let bad = ResectionOptions {
            min_gain: 0.5,
            ..ResectionOptions::default()
        };
        assert!(
            resect_bridged_sides(
                &tracks,
                &pairs,
                &intrinsics,
                1.0,
                &mut moved,
                &edges,
                &Failing,
                &bad
            )
            .is_err()
        );
    }
}
