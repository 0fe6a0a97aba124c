//! Robust rotation averaging: a maximum-spanning-tree start, then iteratively reweighted least
//! squares on the Lie-algebra residuals `log(R_ab R_a R_bᵀ)` with Cauchy weights (Chatterjee &
//! Govindu, ICCV 2013), each step a sparse Cholesky solve of the 3N-unknown normal equations.
//!
//! Conventions (OpenCV, world → camera): a relative rotation of the ordered pair `(a, b)` is
//! `R_ab = R_b R_aᵀ`.

use nalgebra::{Matrix3, Rotation3, Vector3};
use posediff_geometry::rotation_angle;

use crate::error::Result;
use crate::linalg::{BlockSystem, Solver};

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

/// Rotation-averaging settings.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct RotationAveragingOptions {
    /// Cauchy scale of the residual angle, degrees.
    pub cauchy_deg: f64,
    /// Iteration limit.
    pub max_iterations: usize,
    /// Stop when no rotation moves by more than this (radians).
    pub tolerance: f64,
    /// Linear solver.
    pub solver: Solver,
}

impl Default for RotationAveragingOptions {
    fn default() -> Self {
        Self {
            cauchy_deg: 5.0,
            max_iterations: 100,
            tolerance: 1e-12,
            solver: Solver::Sparse,
        }
    }
}

/// What the averaging did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct RotationAveragingReport {
    /// Images with a rotation (reachable from the reference).
    pub images: usize,
    /// Edges between them.
    pub edges: usize,
    /// IRLS iterations.
    pub iterations: usize,
    /// Stopped because the update fell below the tolerance (not at the limit).
    pub converged: bool,
    /// Median residual angle over the edges at the end, degrees.
    pub median_residual_deg: f64,
}

/// Absolute rotations of the images reachable from `reference` through `edges`
/// (`R_reference = I`), `None` for the others.
///
/// # Errors
/// Normal equations that are not positive definite (cannot happen for a connected graph with
/// positive weights: reported, never replaced by a guess), faer failures.
pub fn average_rotations(
    n: usize,
    edges: &[RelativeRotation],
    reference: usize,
    options: &RotationAveragingOptions,
) -> Result<(Vec<Option<Rotation3<f64>>>, RotationAveragingReport)> {
    let mut rotations = spanning_tree_rotations(n, edges, reference);
    let index = unknown_index(&rotations, reference);
    let unknowns = index.iter().filter(|i| i.is_some()).count();
    let used: Vec<&RelativeRotation> = edges
        .iter()
        .filter(|e| e.first < n && e.second < n && e.first != e.second)
        .filter(|e| rotations[e.first].is_some() && rotations[e.second].is_some())
        .collect();
    let mut report = RotationAveragingReport {
        images: rotations.iter().filter(|r| r.is_some()).count(),
        edges: used.len(),
        converged: true,
        ..RotationAveragingReport::default()
    };
    if unknowns == 0 {
        report.median_residual_deg = median_residual(&used, &rotations);
        return Ok((rotations, report));
    }
    let pairs = used
        .iter()
        .filter_map(|e| Some((index[e.first]?, index[e.second]?)));
    let mut system = BlockSystem::new(
        "rotation averaging",
        &vec![3; unknowns],
        pairs,
        options.solver,
    )?;
    let c = options.cauchy_deg.to_radians();
    report.converged = false;
    for _ in 0..options.max_iterations {
        system.clear();
        for e in &used {
            let (Some(ra), Some(rb)) = (rotations[e.first], rotations[e.second]) else {
                continue;
            };
            let r = log_rotation(&(e.rotation * ra * rb.inverse()));
            let w = e.weight / (1.0 + (r.norm() / c).powi(2));
            // Residual model r + J_a ω_a + J_b ω_b with J_a = R_ab, J_b = −I.
            let ja = *e.rotation.matrix();
            let jb = -Matrix3::identity();
            let blocks = [(index[e.first], ja), (index[e.second], jb)];
            for &(p, jp) in &blocks {
                let Some(p) = p else { continue };
                let gp = jp.transpose() * r * (-w);
                system.add_rhs(p, |k| gp[k]);
                for &(q, jq) in &blocks {
                    let Some(q) = q else { continue };
                    if q > p {
                        continue;
                    }
                    let hpq = jp.transpose() * jq * w;
                    system.add_block(p, q, |k, l| hpq[(k, l)])?;
                }
            }
        }
        let step = system.solve_regularised(0.0)?.ok_or_else(|| {
            crate::error::SfmError::NotPositiveDefinite {
                what: "rotation averaging",
                detail: "disconnected or zero-weight view graph".into(),
            }
        })?;
        report.iterations += 1;
        let mut largest: f64 = 0.0;
        for (v, p) in index.iter().enumerate() {
            if let (Some(p), Some(rv)) = (p, rotations[v].as_mut()) {
                let w = Vector3::new(step[3 * p], step[3 * p + 1], step[3 * p + 2]);
                largest = largest.max(w.norm());
                *rv = Rotation3::from_scaled_axis(w) * *rv;
            }
        }
        if largest < options.tolerance {
            report.converged = true;
            break;
        }
    }
    report.median_residual_deg = median_residual(&used, &rotations);
    Ok((rotations, report))
}

/// The rotation vector (axis × angle) of `r`, finite for every rotation: the angle by
/// `atan2` (nalgebra's `scaled_axis` takes `acos` of a trace that rounding can push past 3,
/// giving NaN at the identity), the axis near π from the symmetric part.
pub fn log_rotation(r: &Rotation3<f64>) -> Vector3<f64> {
    let m = r.matrix();
    let v = 0.5
        * Vector3::new(
            m[(2, 1)] - m[(1, 2)],
            m[(0, 2)] - m[(2, 0)],
            m[(1, 0)] - m[(0, 1)],
        );
    let s = v.norm();
    let c = 0.5 * (m.trace() - 1.0);
    let angle = s.atan2(c);
    if s > 1e-6 || c > 0.0 {
        return if s > 0.0 { v * (angle / s) } else { v };
    }
    // Near π: R + I = 2 a aᵀ (approximately); its largest column is along the axis.
    let sym = m + Matrix3::identity();
    let k = (0..3)
        .max_by(|&a, &b| sym.column(a).norm().total_cmp(&sym.column(b).norm()))
        .unwrap_or(0);
    let mut axis = sym.column(k).normalize();
    if axis.dot(&v) < 0.0 {
        axis = -axis;
    }
    axis * angle
}

fn median_residual(edges: &[&RelativeRotation], rotations: &[Option<Rotation3<f64>>]) -> f64 {
    let mut r: Vec<f64> = edges
        .iter()
        .filter_map(|e| match (rotations[e.first], rotations[e.second]) {
            (Some(a), Some(b)) => {
                Some(rotation_angle(&(e.rotation * a * b.inverse())).to_degrees())
            }
            _ => None,
        })
        .collect();
    if r.is_empty() {
        return 0.0;
    }
    r.sort_by(f64::total_cmp);
    r[r.len() / 2]
}

/// The angle (degrees) between each measured relative rotation and the one the absolute
/// rotations imply; `None` where an image has no rotation.
pub fn rotation_residuals_deg(
    edges: &[RelativeRotation],
    rotations: &[Option<Rotation3<f64>>],
) -> Vec<Option<f64>> {
    edges
        .iter()
        .map(
            |e| match (rotations.get(e.first), rotations.get(e.second)) {
                (Some(Some(a)), Some(Some(b))) => {
                    Some(rotation_angle(&(e.rotation * a * b.inverse())).to_degrees())
                }
                _ => None,
            },
        )
        .collect()
}

/// The cycle check on the view graph's triangles: for each edge, whether it closes at least
/// `min_triangles` triangles and none of them within `threshold_deg` (`R_jk R_ij R_ikᵀ` the
/// identity up to that angle). Such an edge disagrees with every pair of other edges that could
/// confirm it: the signature of a pair whose two-view geometry is wrong (non-overlapping views
/// that a learned matcher still gives enough inliers). Edges in no triangle (bridges) and edges
/// that one triangle confirms are kept. Cost: `O(Σ_edges min(deg))` with sorted adjacency.
pub fn unconfirmed_by_cycles(
    edges: &[RelativeRotation],
    threshold_deg: f64,
    min_triangles: usize,
) -> Vec<bool> {
    use std::collections::HashMap;
    // rel[(a, b)] = R_b R_aᵀ for both directions.
    let mut rel: HashMap<(usize, usize), Rotation3<f64>> = HashMap::new();
    let mut neighbours: HashMap<usize, Vec<usize>> = HashMap::new();
    for e in edges {
        rel.insert((e.first, e.second), e.rotation);
        rel.insert((e.second, e.first), e.rotation.inverse());
        neighbours.entry(e.first).or_default().push(e.second);
        neighbours.entry(e.second).or_default().push(e.first);
    }
    for list in neighbours.values_mut() {
        list.sort_unstable();
        list.dedup();
    }
    let empty = Vec::new();
    edges
        .iter()
        .map(|e| {
            let (i, j) = (e.first, e.second);
            let (ni, nj) = (
                neighbours.get(&i).unwrap_or(&empty),
                neighbours.get(&j).unwrap_or(&empty),
            );
            let (mut triangles, mut confirmed) = (0, 0);
            // Sorted intersection of the two neighbour lists.
            let (mut a, mut b) = (0, 0);
            while a < ni.len() && b < nj.len() {
                match ni[a].cmp(&nj[b]) {
                    std::cmp::Ordering::Less => a += 1,
                    std::cmp::Ordering::Greater => b += 1,
                    std::cmp::Ordering::Equal => {
                        let k = ni[a];
                        let (Some(jk), Some(ki)) = (rel.get(&(j, k)), rel.get(&(k, i))) else {
                            a += 1;
                            b += 1;
                            continue;
                        };
                        triangles += 1;
                        let cycle = ki * jk * e.rotation;
                        if rotation_angle(&cycle).to_degrees() <= threshold_deg {
                            confirmed += 1;
                        }
                        a += 1;
                        b += 1;
                    }
                }
            }
            triangles >= min_triangles.max(1) && confirmed == 0
        })
        .collect()
}

/// Which edges to keep when only the `trusted` ones have independent evidence: every trusted
/// edge, and an untrusted edge `(i, j)` once a triangle `i–k–j` of two kept edges confirms it
/// (`R_ki R_jk R_ij` within `threshold_deg` of the identity); confirmed edges confirm others in
/// turn (a worklist until nothing changes). An untrusted edge that no such triangle closes is
/// dropped, even where no trusted path could have confirmed it: this is the rule for the pairs
/// of a learned matcher that its own descriptors do not support, which on the shared sets are
/// either wide bridges between neighbours (confirmed through the neighbours) or views of the
/// other side of a symmetric object (whose triangles, if any, close only among themselves).
/// Cost: `O(E · d²)` for `E` edges of largest degree `d`, with sorted adjacency.
pub fn confirmed_by_trusted_triangles(
    edges: &[RelativeRotation],
    trusted: &[bool],
    threshold_deg: f64,
) -> Vec<bool> {
    use std::collections::{BTreeSet, HashMap, VecDeque};
    // An edge without a flag is untrusted.
    let mut keep: Vec<bool> = (0..edges.len())
        .map(|i| trusted.get(i).copied().unwrap_or(false))
        .collect();
    // Kept edges as rel[(a, b)] = R_b R_aᵀ both ways, and each image's kept neighbours.
    let mut rel: HashMap<(usize, usize), Rotation3<f64>> = HashMap::new();
    let mut kept_neighbours: HashMap<usize, BTreeSet<usize>> = HashMap::new();
    let mut incident: HashMap<usize, Vec<usize>> = HashMap::new();
    let insert = |e: &RelativeRotation,
                  rel: &mut HashMap<(usize, usize), Rotation3<f64>>,
                  kept: &mut HashMap<usize, BTreeSet<usize>>| {
        rel.insert((e.first, e.second), e.rotation);
        rel.insert((e.second, e.first), e.rotation.inverse());
        kept.entry(e.first).or_default().insert(e.second);
        kept.entry(e.second).or_default().insert(e.first);
    };
    for (index, e) in edges.iter().enumerate() {
        incident.entry(e.first).or_default().push(index);
        incident.entry(e.second).or_default().push(index);
        if keep[index] {
            insert(e, &mut rel, &mut kept_neighbours);
        }
    }
    let mut queued: Vec<bool> = keep.iter().map(|k| !k).collect();
    let mut queue: VecDeque<usize> = (0..edges.len()).filter(|&i| queued[i]).collect();
    let empty = BTreeSet::new();
    while let Some(index) = queue.pop_front() {
        queued[index] = false;
        if keep[index] {
            continue;
        }
        let e = &edges[index];
        let (i, j) = (e.first, e.second);
        let ni = kept_neighbours.get(&i).unwrap_or(&empty);
        let nj = kept_neighbours.get(&j).unwrap_or(&empty);
        let confirmed = ni
            .intersection(nj)
            .any(|&k| match (rel.get(&(j, k)), rel.get(&(k, i))) {
                (Some(jk), Some(ki)) => {
                    rotation_angle(&(ki * jk * e.rotation)).to_degrees() <= threshold_deg
                }
                _ => false,
            });
        if !confirmed {
            continue;
        }
        keep[index] = true;
        insert(e, &mut rel, &mut kept_neighbours);
        for image in [i, j] {
            for &other in incident.get(&image).map_or(&[][..], Vec::as_slice) {
                if !keep[other] && !queued[other] {
                    queued[other] = true;
                    queue.push_back(other);
                }
            }
        }
    }
    keep
}

/// Adds to `keep` the dropped edges that link two groups of kept edges, strongest first (a
/// maximum spanning forest over the groups): an edge that nothing could confirm or contradict
/// because no other path joins its images. `n` is the number of images.
pub fn keep_bridges(n: usize, edges: &[RelativeRotation], keep: &mut [bool]) {
    let mut groups = crate::view_graph::UnionFind::new(n);
    for (e, k) in edges.iter().zip(keep.iter()) {
        if *k && e.first < n && e.second < n {
            groups.union(e.first, e.second);
        }
    }
    let mut order: Vec<usize> = (0..edges.len().min(keep.len()))
        .filter(|&i| !keep[i])
        .collect();
    order.sort_by(|&a, &b| edges[b].weight.total_cmp(&edges[a].weight).then(a.cmp(&b)));
    for i in order {
        let e = &edges[i];
        if e.first < n && e.second < n && groups.union(e.first, e.second) {
            keep[i] = true;
        }
    }
}

/// For each image with a value, its position among the unknowns (the reference is fixed).
pub(crate) fn unknown_index<T>(values: &[Option<T>], reference: usize) -> Vec<Option<usize>> {
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

/// Rotations chained along the maximum-weight spanning tree grown from `reference` (Prim with
/// a binary heap: `O(E log E)`).
fn spanning_tree_rotations(
    n: usize,
    edges: &[RelativeRotation],
    reference: usize,
) -> Vec<Option<Rotation3<f64>>> {
    use std::cmp::Ordering;
    use std::collections::BinaryHeap;

    struct Candidate(f64, usize, usize);
    impl PartialEq for Candidate {
        fn eq(&self, o: &Self) -> bool {
            self.cmp(o) == Ordering::Equal
        }
    }
    impl Eq for Candidate {}
    impl PartialOrd for Candidate {
        fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
            Some(self.cmp(o))
        }
    }
    impl Ord for Candidate {
        // Heaviest first; ties to the latest edge in the order given (as a linear scan with
        // `max_by` picks them).
        fn cmp(&self, o: &Self) -> Ordering {
            self.0.total_cmp(&o.0).then(self.2.cmp(&o.2))
        }
    }

    let mut rotations: Vec<Option<Rotation3<f64>>> = vec![None; n];
    if reference >= n {
        return rotations;
    }
    let mut incident: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (k, e) in edges.iter().enumerate() {
        if e.first < n && e.second < n && e.first != e.second {
            incident[e.first].push(k);
            incident[e.second].push(k);
        }
    }
    rotations[reference] = Some(Rotation3::identity());
    let mut heap = BinaryHeap::new();
    let push = |heap: &mut BinaryHeap<Candidate>, v: usize| {
        for &k in &incident[v] {
            let e = &edges[k];
            let other = if e.first == v { e.second } else { e.first };
            heap.push(Candidate(e.weight, other, k));
        }
    };
    push(&mut heap, reference);
    while let Some(Candidate(_, v, k)) = heap.pop() {
        if rotations[v].is_some() {
            continue;
        }
        let e = &edges[k];
        rotations[v] = if e.second == v {
            rotations[e.first].map(|a| e.rotation * a)
        } else {
            rotations[e.second].map(|b| e.rotation.inverse() * b)
        };
        push(&mut heap, v);
    }
    rotations
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    pub(crate) fn ring(n: usize) -> Vec<Rotation3<f64>> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.5;
                Rotation3::from_euler_angles(0.1 * i as f64, a, -0.2 * i as f64)
            })
            .collect()
    }

    #[test]
    fn rotations_survive_an_outlier_edge() {
        let rs = ring(6);
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
        let error = |got: &[Option<Rotation3<f64>>]| -> f64 {
            (0..6)
                .map(|i| {
                    let want = rs[i] * rs[2].inverse();
                    rotation_angle(&(got[i].unwrap() * want.inverse())).to_degrees()
                })
                .fold(0.0, f64::max)
        };
        for solver in [Solver::Sparse, Solver::Dense] {
            let options = RotationAveragingOptions {
                solver,
                ..RotationAveragingOptions::default()
            };
            // The Cauchy estimate is pulled a little by the 57° outlier, which stands out.
            let (got, report) = average_rotations(6, &edges, 2, &options).unwrap();
            assert!(report.converged && report.iterations > 1, "{report:?}");
            assert!(error(&got) < 0.5, "{solver:?}: {}°", error(&got));
            let res = rotation_residuals_deg(&edges, &got);
            let outliers: Vec<usize> = (0..edges.len())
                .filter(|&k| res[k].unwrap() > 10.0)
                .collect();
            assert_eq!(outliers.len(), 1);
            assert_eq!(
                (edges[outliers[0]].first, edges[outliers[0]].second),
                (1, 4)
            );
            // Without it the rotations are exact.
            let clean: Vec<RelativeRotation> = edges
                .iter()
                .enumerate()
                .filter(|(k, _)| *k != outliers[0])
                .map(|(_, e)| *e)
                .collect();
            let (got, _) = average_rotations(6, &clean, 2, &options).unwrap();
            assert!(error(&got) < 1e-6, "{solver:?}: {}°", error(&got));
        }
    }

    #[test]
    fn the_rotation_log_is_finite_and_exact() {
        for w in [
            Vector3::zeros(),
            Vector3::new(1e-9, -2e-9, 0.0),
            Vector3::new(0.3, -0.2, 0.5),
            Vector3::new(0.0, 0.0, std::f64::consts::PI - 1e-9),
            Vector3::new(1.0, 2.0, -1.0).normalize() * (std::f64::consts::PI - 1e-4),
        ] {
            let got = log_rotation(&Rotation3::from_scaled_axis(w));
            assert!((got - w).norm() < 1e-7, "{w} -> {got}");
        }
        // An identity whose trace rounds above 3.
        let r = Rotation3::from_matrix_unchecked(Matrix3::identity() * (1.0 + 1e-16));
        assert!(log_rotation(&r).iter().all(|x| x.is_finite()));
    }

    #[test]
    fn unreachable_images_have_no_rotation() {
        let e = RelativeRotation {
            first: 0,
            second: 1,
            rotation: Rotation3::identity(),
            weight: 1.0,
        };
        let (got, report) =
            average_rotations(3, &[e], 0, &RotationAveragingOptions::default()).unwrap();
        assert!(got[0].is_some() && got[1].is_some() && got[2].is_none());
        assert_eq!(report.images, 2);
    }

    #[test]
    fn a_pair_that_every_triangle_contradicts_is_unconfirmed() {
        // Five cameras, every pair measured exactly, except (0, 2) turned by 40°.
        let absolute: Vec<Rotation3<f64>> = (0..5)
            .map(|i| Rotation3::from_euler_angles(0.1 * i as f64, 0.3 * i as f64, -0.05 * i as f64))
            .collect();
        let mut edges = Vec::new();
        for i in 0..5 {
            for j in i + 1..5 {
                let mut rotation = absolute[j] * absolute[i].inverse();
                if (i, j) == (0, 2) {
                    rotation =
                        Rotation3::from_euler_angles(0.0, 40f64.to_radians(), 0.0) * rotation;
                }
                edges.push(RelativeRotation {
                    first: i,
                    second: j,
                    rotation,
                    weight: 1.0,
                });
            }
        }
        let flagged = unconfirmed_by_cycles(&edges, 5.0, 2);
        let which: Vec<(usize, usize)> = edges
            .iter()
            .zip(&flagged)
            .filter(|(_, f)| **f)
            .map(|(e, _)| (e.first, e.second))
            .collect();
        // Every other pair has triangles that do not use (0, 2) and close exactly.
        assert_eq!(which, vec![(0, 2)]);
        // With more triangles required than the pair closes (3), nothing is dropped.
        assert!(unconfirmed_by_cycles(&edges, 5.0, 4).iter().all(|f| !f));
        // A bridge (in no triangle) is never dropped.
        let chain = &edges[..1];
        assert_eq!(unconfirmed_by_cycles(chain, 5.0, 0), vec![false]);
    }

    #[test]
    fn untrusted_pairs_need_a_triangle_of_kept_pairs() {
        // Eight cameras on a ring 20° apart about one axis; trusted: the neighbours (i, i+1).
        // Untrusted and exact: bridges that chains of trusted and confirmed pairs close, and
        // (3, 7), which no triangle of measured pairs closes. Untrusted and wrong by 150° (the
        // other side of a symmetric object): (1, 6) and (1, 7), which close a consistent
        // triangle with the trusted (6, 7) — one kept edge, which must not confirm them.
        let absolute: Vec<Rotation3<f64>> = (0..8)
            .map(|i| Rotation3::from_euler_angles(0.0, (20.0 * i as f64).to_radians(), 0.0))
            .collect();
        let flip = Rotation3::from_euler_angles(0.0, 150f64.to_radians(), 0.0);
        let edge = |i: usize, j: usize, wrong: bool| RelativeRotation {
            first: i,
            second: j,
            rotation: if wrong {
                flip * absolute[j] * absolute[i].inverse()
            } else {
                absolute[j] * absolute[i].inverse()
            },
            weight: 1.0,
        };
        let mut edges = Vec::new();
        let mut trusted = Vec::new();
        for i in 0..7 {
            edges.push(edge(i, i + 1, false));
            trusted.push(true);
        }
        // Listed so that (0, 4) and (2, 5) are examined before what confirms them.
        for (i, j) in [(0, 4), (2, 5), (0, 2), (1, 3), (2, 4), (0, 3), (3, 7)] {
            edges.push(edge(i, j, false));
            trusted.push(false);
        }
        for (i, j) in [(1, 6), (1, 7)] {
            edges.push(edge(i, j, true));
            trusted.push(false);
        }
        let keep = confirmed_by_trusted_triangles(&edges, &trusted, 5.0);
        let kept = |i: usize, j: usize| {
            edges
                .iter()
                .zip(&keep)
                .any(|(e, k)| *k && (e.first, e.second) == (i, j))
        };
        for i in 0..7 {
            assert!(kept(i, i + 1), "a trusted pair is always kept");
        }
        for (i, j) in [(0, 2), (1, 3), (2, 4), (0, 3)] {
            assert!(kept(i, j), "({i}, {j}) bridges trusted neighbours");
        }
        assert!(
            kept(0, 4),
            "(0, 4) closes with the confirmed (0, 2) and (2, 4)"
        );
        assert!(
            kept(2, 5),
            "(2, 5) closes with the confirmed (2, 4) and the trusted (4, 5)"
        );
        assert!(!kept(3, 7), "an edge that no triangle closes is dropped");
        assert!(!kept(1, 6) && !kept(1, 7), "wrong pairs are dropped");
        // The same wrong pairs with (6, 7) trusted and (1, 6) trusted: (1, 7) now closes a
        // triangle of two kept edges, 1–6–7, consistent because the flip commutes with the
        // ring's rotations: the rule trusts what it is told.
        let mut told = trusted.clone();
        let last = edges.len() - 2;
        told[last] = true;
        assert!(confirmed_by_trusted_triangles(&edges, &told, 5.0)[last + 1]);
        // Nothing trusted: nothing kept; a missing flag counts as untrusted.
        assert!(
            confirmed_by_trusted_triangles(&edges, &[], 5.0)
                .iter()
                .all(|k| !k)
        );
    }

    #[test]
    fn bridges_join_groups_strongest_first() {
        let edge = |first: usize, second: usize, weight: f64| RelativeRotation {
            first,
            second,
            rotation: Rotation3::identity(),
            weight,
        };
        // Groups {0, 1} and {2, 3} kept; three candidate links between them and one inside.
        let edges = [
            edge(0, 1, 100.0),
            edge(2, 3, 100.0),
            edge(1, 2, 30.0),
            edge(0, 3, 50.0),
            edge(0, 2, 40.0),
            edge(0, 1, 80.0),
        ];
        let mut keep = vec![true, true, false, false, false, false];
        keep_bridges(4, &edges, &mut keep);
        // Only the strongest link joins the groups; the others and the edge inside a group stay
        // dropped.
        assert_eq!(keep, vec![true, true, false, true, false, false]);
    }
}
