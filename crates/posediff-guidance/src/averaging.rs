//! Global camera initialisation from pairwise relative poses: the view graph, robust rotation
//! averaging and robust translation averaging.
//!
//! Conventions (OpenCV, world → camera): camera `i` maps `x_i = R_i (X − C_i)`. A relative
//! rotation of the ordered pair `(a, b)` is `R_ab = R_b R_aᵀ`; a relative translation direction
//! `t_ab` (unit, camera `b`'s frame, as OpenCV's `recoverPose` returns it) says
//! `C_a − C_b ∝ R_bᵀ t_ab`.
//!
//! - [`largest_component`]: the connected component with the most images.
//! - [`average_rotations`]: maximum-spanning-tree start, then iteratively reweighted least
//!   squares on the Lie-algebra residuals `log(R_ab R_a R_bᵀ)` with Cauchy weights
//!   (Chatterjee & Govindu, ICCV 2013).
//! - [`average_translations`]: Least Unsquared Deviations (Özyeşil & Singer, CVPR 2015),
//!   `min Σ w ‖C_a − C_b − s_ab v_ab‖` subject to `s_ab ≥ 1`, solved by IRLS alternating
//!   between the centres (a weighted graph-Laplacian system) and the scales.

use std::collections::VecDeque;

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, Vector3};

/// A measured relative rotation of an ordered pair: `R_second = rotation · R_first`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativeRotation {
    /// First image.
    pub first: usize,
    /// Second image.
    pub second: usize,
    /// `R_second R_firstᵀ`.
    pub rotation: Rotation3<f64>,
    /// Confidence (e.g. the number of inlier matches).
    pub weight: f64,
}

/// A measured direction between two camera centres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CenterDirection {
    /// First image.
    pub first: usize,
    /// Second image.
    pub second: usize,
    /// Unit vector in the world frame along `C_first − C_second`; `None` for a pair with no
    /// measurable baseline (pure rotation, identical images), which ties the two centres
    /// together (one centre for both).
    pub direction: Option<Vector3<f64>>,
    /// Confidence.
    pub weight: f64,
}

/// The images of the largest connected component of the graph with `n` nodes and `edges`
/// (ties: the component with the larger total weight, then the one with the smallest image),
/// sorted. Empty when there is no edge.
pub fn largest_component(n: usize, edges: &[(usize, usize, f64)]) -> Vec<usize> {
    let mut adjacency = vec![Vec::new(); n];
    for &(a, b, _) in edges {
        if a < n && b < n && a != b {
            adjacency[a].push(b);
            adjacency[b].push(a);
        }
    }
    let mut label = vec![usize::MAX; n];
    let mut components: Vec<Vec<usize>> = Vec::new();
    for start in 0..n {
        if label[start] != usize::MAX || adjacency[start].is_empty() {
            continue;
        }
        let id = components.len();
        let mut members = vec![start];
        label[start] = id;
        let mut queue = VecDeque::from([start]);
        while let Some(v) = queue.pop_front() {
            for &w in &adjacency[v] {
                if label[w] == usize::MAX {
                    label[w] = id;
                    members.push(w);
                    queue.push_back(w);
                }
            }
        }
        members.sort_unstable();
        components.push(members);
    }
    let weight = |c: &[usize]| -> f64 {
        edges
            .iter()
            .filter(|e| c.binary_search(&e.0).is_ok())
            .map(|e| e.2)
            .sum()
    };
    components
        .into_iter()
        .max_by(|a, b| {
            a.len()
                .cmp(&b.len())
                .then(weight(a).total_cmp(&weight(b)))
                .then(b[0].cmp(&a[0]))
        })
        .unwrap_or_default()
}

/// The representative of `v` in a union-find forest (path halving).
pub(crate) fn find(parent: &mut [usize], mut v: usize) -> usize {
    while parent[v] != v {
        parent[v] = parent[parent[v]];
        v = parent[v];
    }
    v
}

/// Rotation-averaging settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotationAveragingConfig {
    /// Cauchy scale of the residual angle, degrees.
    pub cauchy_deg: f64,
    /// Iteration limit.
    pub max_iterations: usize,
    /// Stop when no rotation moves by more than this (radians).
    pub tolerance: f64,
}

impl Default for RotationAveragingConfig {
    fn default() -> Self {
        Self {
            cauchy_deg: 5.0,
            max_iterations: 100,
            tolerance: 1e-12,
        }
    }
}

/// Absolute rotations of the images reachable from `reference` through `edges`
/// (`R_reference = I`), `None` for the others.
pub fn average_rotations(
    n: usize,
    edges: &[RelativeRotation],
    reference: usize,
    config: &RotationAveragingConfig,
) -> Vec<Option<Rotation3<f64>>> {
    let mut rotations = spanning_tree_rotations(n, edges, reference);
    let index = unknown_index(&rotations, reference);
    let unknowns = index.iter().filter(|i| i.is_some()).count();
    if unknowns == 0 {
        return rotations;
    }
    let c = config.cauchy_deg.to_radians();
    for _ in 0..config.max_iterations {
        let mut h = DMatrix::<f64>::zeros(3 * unknowns, 3 * unknowns);
        let mut g = DVector::<f64>::zeros(3 * unknowns);
        for e in edges {
            let (Some(ra), Some(rb)) = (rotations[e.first], rotations[e.second]) else {
                continue;
            };
            let r = (e.rotation * ra * rb.inverse()).scaled_axis();
            let w = e.weight / (1.0 + (r.norm() / c).powi(2));
            // Residual model r + J_a ω_a + J_b ω_b with J_a = R_ab, J_b = −I.
            let ja = *e.rotation.matrix();
            let jb = -Matrix3::identity();
            let blocks = [(index[e.first], ja), (index[e.second], jb)];
            for &(p, jp) in &blocks {
                let Some(p) = p else { continue };
                let gp = jp.transpose() * r * w;
                for k in 0..3 {
                    g[3 * p + k] += gp[k];
                }
                for &(q, jq) in &blocks {
                    let Some(q) = q else { continue };
                    let hpq = jp.transpose() * jq * w;
                    for (k, l) in (0..3).flat_map(|k| (0..3).map(move |l| (k, l))) {
                        h[(3 * p + k, 3 * q + l)] += hpq[(k, l)];
                    }
                }
            }
        }
        let scale = h.diagonal().max().max(1e-300);
        for k in 0..3 * unknowns {
            h[(k, k)] += 1e-12 * scale;
        }
        let Some(chol) = h.cholesky() else { break };
        let step = chol.solve(&(-g));
        let mut largest: f64 = 0.0;
        for (v, p) in index.iter().enumerate() {
            if let (Some(p), Some(rv)) = (p, rotations[v].as_mut()) {
                let w = Vector3::new(step[3 * p], step[3 * p + 1], step[3 * p + 2]);
                largest = largest.max(w.norm());
                *rv = Rotation3::from_scaled_axis(w) * *rv;
            }
        }
        if largest < config.tolerance {
            break;
        }
    }
    rotations
}

/// The rotation angle of `r` in radians, stable near 0 and π (no `acos` of a rounded trace).
pub fn rotation_angle(r: &Rotation3<f64>) -> f64 {
    let m = r.matrix();
    let sin2 = Vector3::new(
        m[(2, 1)] - m[(1, 2)],
        m[(0, 2)] - m[(2, 0)],
        m[(1, 0)] - m[(0, 1)],
    )
    .norm();
    sin2.atan2(m.trace() - 1.0)
}

/// The angle (degrees) between each measured relative rotation and the one the absolute
/// rotations imply; `None` where an image has no rotation.
pub fn rotation_residuals_deg(
    edges: &[RelativeRotation],
    rotations: &[Option<Rotation3<f64>>],
) -> Vec<Option<f64>> {
    edges
        .iter()
        .map(|e| match (rotations[e.first], rotations[e.second]) {
            (Some(a), Some(b)) => {
                Some(rotation_angle(&(e.rotation * a * b.inverse())).to_degrees())
            }
            _ => None,
        })
        .collect()
}

/// For each image with a value, its position among the unknowns (the reference is fixed).
fn unknown_index<T>(values: &[Option<T>], reference: usize) -> Vec<Option<usize>> {
    let mut next = 0;
    values
        .iter()
        .enumerate()
        .map(|(v, x)| {
            (x.is_some() && v != reference).then(|| {
                next += 1;
                next - 1
            })
        })
        .collect()
}

/// Rotations chained along the maximum-weight spanning tree grown from `reference` (Prim).
fn spanning_tree_rotations(
    n: usize,
    edges: &[RelativeRotation],
    reference: usize,
) -> Vec<Option<Rotation3<f64>>> {
    let mut rotations: Vec<Option<Rotation3<f64>>> = vec![None; n];
    if reference >= n {
        return rotations;
    }
    rotations[reference] = Some(Rotation3::identity());
    loop {
        let best = edges
            .iter()
            .filter_map(|e| match (rotations[e.first], rotations[e.second]) {
                (Some(a), None) => Some((e.weight, e.second, e.rotation * a)),
                (None, Some(b)) => Some((e.weight, e.first, e.rotation.inverse() * b)),
                _ => None,
            })
            .max_by(|x, y| x.0.total_cmp(&y.0));
        match best {
            Some((_, v, r)) => rotations[v] = Some(r),
            None => return rotations,
        }
    }
}

/// Translation-averaging settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TranslationAveragingConfig {
    /// IRLS iterations.
    pub max_iterations: usize,
    /// Residuals below this (relative to the unit scale bound) weigh as this.
    pub delta: f64,
    /// Stop when no centre moves by more than this (relative to the largest distance).
    pub tolerance: f64,
}

impl Default for TranslationAveragingConfig {
    fn default() -> Self {
        Self {
            max_iterations: 300,
            delta: 1e-4,
            tolerance: 1e-9,
        }
    }
}

/// Camera centres of the images `members` from centre directions (LUD by IRLS), `C_reference
/// = 0`; `None` for images outside `members`. Every member must be connected to the reference
/// through `directions`.
///
/// Zero-baseline ties (`direction: None`) are hard: tied images are merged into one centre
/// before the averaging, so they come out at exactly the same place.
pub fn average_translations(
    n: usize,
    members: &[usize],
    directions: &[CenterDirection],
    reference: usize,
    config: &TranslationAveragingConfig,
) -> Vec<Option<Vector3<f64>>> {
    let mut parent: Vec<usize> = (0..n).collect();
    let is_member = |v: usize| members.binary_search(&v).is_ok();
    for d in directions {
        if d.direction.is_none()
            && d.first < n
            && d.second < n
            && is_member(d.first)
            && is_member(d.second)
        {
            let (a, b) = (find(&mut parent, d.first), find(&mut parent, d.second));
            if a != b {
                parent[a] = b;
            }
        }
    }
    let merged: Vec<CenterDirection> = directions
        .iter()
        .filter(|d| d.direction.is_some() && d.first < n && d.second < n)
        .filter_map(|d| {
            let (a, b) = (find(&mut parent, d.first), find(&mut parent, d.second));
            (a != b).then_some(CenterDirection {
                first: a,
                second: b,
                ..*d
            })
        })
        .collect();
    let mut reps: Vec<usize> = members
        .iter()
        .filter(|&&m| m < n)
        .map(|&m| find(&mut parent, m))
        .collect();
    reps.sort_unstable();
    reps.dedup();
    if reference >= n {
        return vec![None; n];
    }
    let reference_rep = find(&mut parent, reference);
    let rep_centres = lud_centres(n, &reps, &merged, reference_rep, config);
    let mut out = vec![None; n];
    for &m in members {
        if m < n {
            out[m] = rep_centres[find(&mut parent, m)];
        }
    }
    out
}

/// A direction edge of the (tie-merged) graph: `C_a − C_b ∝ v`, unit `v`.
#[derive(Debug, Clone, Copy)]
struct DirectionEdge {
    a: usize,
    b: usize,
    v: Vector3<f64>,
    weight: f64,
}

/// LUD on direction edges: the centres of the images `members`, `C_reference = 0`; `None` for
/// images outside `members`. Every member must be connected to the reference through
/// `directions` (ties are merged by [`average_translations`] before; any left here are ignored).
///
/// Each IRLS round fixes the weights `w_e / max(‖r_e‖, δ)` and solves the weighted least-squares
/// problem in the centres and the scales `s_e ≥ 1` jointly by an active-set method (scales at
/// the bound are held at 1 until their multiplier says to free them).
fn lud_centres(
    n: usize,
    members: &[usize],
    directions: &[CenterDirection],
    reference: usize,
    config: &TranslationAveragingConfig,
) -> Vec<Option<Vector3<f64>>> {
    let mut centers: Vec<Option<Vector3<f64>>> = vec![None; n];
    for &m in members {
        if m < n {
            centers[m] = Some(Vector3::zeros());
        }
    }
    let index = unknown_index(&centers, reference);
    let unknowns = index.iter().filter(|i| i.is_some()).count();
    let edges: Vec<DirectionEdge> = directions
        .iter()
        .filter(|d| centers[d.first].is_some() && centers[d.second].is_some())
        .filter_map(|d| {
            d.direction.map(|v| DirectionEdge {
                a: d.first,
                b: d.second,
                v,
                weight: d.weight,
            })
        })
        .collect();
    if unknowns == 0 || edges.is_empty() {
        return centers;
    }
    let mut weights: Vec<f64> = edges.iter().map(|e| e.weight).collect();
    // Whether each edge's scale is free (else held at the bound 1).
    let mut free: Vec<bool> = vec![false; edges.len()];
    for _ in 0..config.max_iterations {
        let mut solved = None;
        for _ in 0..4 * edges.len() + 4 {
            let Some((new_centres, new_scales)) =
                solve_centres(&edges, &weights, &free, &index, unknowns)
            else {
                break;
            };
            // Active-set update: free scales that want to shrink below 1 are fixed; fixed ones
            // whose residual pulls outwards are freed.
            let mut changed = false;
            for (k, e) in edges.iter().enumerate() {
                if free[k] {
                    if new_scales[k] < 1.0 {
                        free[k] = false;
                        changed = true;
                    }
                } else {
                    let ca = centre_of(&new_centres, &index, e.a);
                    let cb = centre_of(&new_centres, &index, e.b);
                    if e.v.dot(&(ca - cb - e.v)) > 1e-12 {
                        free[k] = true;
                        changed = true;
                    }
                }
            }
            solved = Some((new_centres, new_scales));
            if !changed {
                break;
            }
        }
        let Some((new_centres, new_scales)) = solved else {
            break;
        };
        let mut moved: f64 = 0.0;
        let mut extent: f64 = 0.0;
        for (v, c) in centers.iter_mut().enumerate() {
            if let Some(c) = c.as_mut() {
                let new = centre_of(&new_centres, &index, v);
                moved = moved.max((new - *c).norm());
                extent = extent.max(new.norm());
                *c = new;
            }
        }
        for (k, e) in edges.iter().enumerate() {
            let scale = if free[k] { new_scales[k].max(1.0) } else { 1.0 };
            let (Some(ca), Some(cb)) = (centers[e.a], centers[e.b]) else {
                continue;
            };
            weights[k] = e.weight / (ca - cb - e.v * scale).norm().max(config.delta);
        }
        if moved <= config.tolerance * extent.max(1.0) {
            break;
        }
    }
    centers
}

fn centre_of(solution: &DVector<f64>, index: &[Option<usize>], v: usize) -> Vector3<f64> {
    index[v].map_or(Vector3::zeros(), |p| {
        Vector3::new(solution[3 * p], solution[3 * p + 1], solution[3 * p + 2])
    })
}

/// Weighted least squares of `Σ w_e ‖C_a − C_b − s_e v_e‖²` with `s_e` unknown where `free`
/// and 1 elsewhere. Returns the centres (3 per unknown) and a scale per edge.
fn solve_centres(
    edges: &[DirectionEdge],
    weights: &[f64],
    free: &[bool],
    index: &[Option<usize>],
    unknowns: usize,
) -> Option<(DVector<f64>, Vec<f64>)> {
    let scale_index: Vec<Option<usize>> = {
        let mut next = 3 * unknowns;
        free.iter()
            .map(|&f| {
                f.then(|| {
                    next += 1;
                    next - 1
                })
            })
            .collect()
    };
    let size = 3 * unknowns + free.iter().filter(|f| **f).count();
    let mut h = DMatrix::<f64>::zeros(size, size);
    let mut g = DVector::<f64>::zeros(size);
    for (k, e) in edges.iter().enumerate() {
        let w = weights[k];
        // r = C_a − C_b − s v; constant part with s held at 1.
        let r0 = if free[k] { Vector3::zeros() } else { -e.v };
        // Jacobian columns: (index, 3×1 column per unknown coordinate).
        let mut cols: Vec<(usize, Vector3<f64>)> = Vec::with_capacity(7);
        for (node, sign) in [(e.a, 1.0), (e.b, -1.0)] {
            if let Some(p) = index[node] {
                for d in 0..3 {
                    let mut c = Vector3::zeros();
                    c[d] = sign;
                    cols.push((3 * p + d, c));
                }
            }
        }
        if let Some(si) = scale_index[k] {
            cols.push((si, -e.v));
        }
        for &(i, ci) in &cols {
            g[i] += w * ci.dot(&r0);
            for &(j, cj) in &cols {
                h[(i, j)] += w * ci.dot(&cj);
            }
        }
    }
    let scale = h.diagonal().max().max(1e-300);
    for k in 0..size {
        h[(k, k)] += 1e-12 * scale;
    }
    let x = h.cholesky()?.solve(&(-g));
    let scales = scale_index
        .iter()
        .map(|s| s.map_or(1.0, |i| x[i]))
        .collect();
    Some((x.rows(0, 3 * unknowns).into_owned(), scales))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn ring(n: usize) -> (Vec<Rotation3<f64>>, Vec<Vector3<f64>>) {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.5;
                let c = Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.3 * i as f64);
                let r = Rotation3::from_euler_angles(0.1 * i as f64, a, -0.2 * i as f64);
                (r, c)
            })
            .unzip()
    }

    #[test]
    fn components_pick_the_largest() {
        let edges = [(0, 1, 1.0), (2, 3, 1.0), (3, 4, 1.0)];
        assert_eq!(largest_component(6, &edges), vec![2, 3, 4]);
        assert!(largest_component(3, &[]).is_empty());
    }

    #[test]
    fn rotations_survive_an_outlier_edge() {
        let (rs, _) = ring(6);
        let mut edges = Vec::new();
        for a in 0..6 {
            for b in a + 1..6 {
                let mut rel = rs[b] * rs[a].inverse();
                if (a, b) == (1, 4) {
                    rel = Rotation3::from_euler_angles(0.0, 1.0, 0.0) * rel;
                }
                edges.push(RelativeRotation {
                    first: a,
                    second: b,
                    rotation: rel,
                    weight: 100.0,
                });
            }
        }
        let got = average_rotations(6, &edges, 2, &RotationAveragingConfig::default());
        for (i, g) in got.iter().enumerate() {
            // Compare relative to the reference (the gauge).
            let want = rs[i] * rs[2].inverse();
            let err = rotation_angle(&(g.unwrap() * want.inverse())).to_degrees();
            assert!(err < 1e-3, "camera {i}: {err}°");
        }
        let res = rotation_residuals_deg(&edges, &got);
        assert!(res.iter().filter(|r| r.unwrap() > 10.0).count() == 1);
    }

    #[test]
    fn unreachable_images_have_no_rotation() {
        let e = RelativeRotation {
            first: 0,
            second: 1,
            rotation: Rotation3::identity(),
            weight: 1.0,
        };
        let got = average_rotations(3, &[e], 0, &RotationAveragingConfig::default());
        assert!(got[0].is_some() && got[1].is_some() && got[2].is_none());
    }

    #[test]
    fn centres_from_directions_up_to_scale() {
        let (_, cs) = ring(5);
        let mut dirs = Vec::new();
        for a in 0..5 {
            for b in a + 1..5 {
                let mut d = (cs[a] - cs[b]).normalize();
                if (a, b) == (0, 3) {
                    d = Vector3::new(d.y, -d.x, d.z).normalize();
                }
                dirs.push(CenterDirection {
                    first: a,
                    second: b,
                    direction: Some(d),
                    weight: 1.0,
                });
            }
        }
        let got = average_translations(
            5,
            &[0, 1, 2, 3, 4],
            &dirs,
            0,
            &TranslationAveragingConfig::default(),
        );
        let got: Vec<Vector3<f64>> = got.into_iter().map(Option::unwrap).collect();
        let s = (got[1] - got[0]).norm() / (cs[1] - cs[0]).norm();
        for i in 0..5 {
            let want = (cs[i] - cs[0]) * s;
            assert!(
                (got[i] - want).norm() < 1e-4 * s,
                "centre {i}: {} vs {}",
                got[i],
                want
            );
        }
    }

    #[test]
    fn zero_baseline_ties_collapse_centres() {
        let dirs = [
            CenterDirection {
                first: 0,
                second: 1,
                direction: Some(Vector3::x()),
                weight: 1.0,
            },
            CenterDirection {
                first: 1,
                second: 2,
                direction: None,
                weight: 1.0,
            },
        ];
        let got = average_translations(
            3,
            &[0, 1, 2],
            &dirs,
            0,
            &TranslationAveragingConfig::default(),
        );
        let (c1, c2) = (got[1].unwrap(), got[2].unwrap());
        assert!((c1 - c2).norm() < 1e-6);
        assert!((c1 + Vector3::x()).norm() < 1e-6, "{c1}");
    }
}
