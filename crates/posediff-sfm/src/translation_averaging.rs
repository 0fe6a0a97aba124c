//! Robust translation averaging: camera centres from pairwise directions by Least Unsquared
//! Deviations (Özyeşil & Singer, CVPR 2015),
//! `min Σ w_e ‖C_a − C_b − s_e v_e‖` subject to `s_e ≥ 1`,
//! solved by IRLS. Each reweighted problem is a least-squares problem in the centres and the
//! per-edge scales; the scales are eliminated in closed form (a free scale's optimum is
//! `s = vᵀ(C_a − C_b)`, leaving the residual `(I − vvᵀ)(C_a − C_b)`; a scale at its bound leaves
//! `C_a − C_b − v`), so every solve is a sparse 3N-unknown system, factorised symbolically once.
//! An active set decides which scales sit at the bound.
//!
//! Conventions: a direction `v` (unit, world frame) says `C_first − C_second ∝ v`.

use std::collections::BinaryHeap;

use nalgebra::{Matrix3, Vector3};

use crate::error::{Result, SfmError};
use crate::linalg::{BlockSystem, Solver};
use crate::rotation_averaging::unknown_index;
use crate::view_graph::UnionFind;

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

/// Translation-averaging settings.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct TranslationAveragingOptions {
    /// IRLS iterations.
    pub max_iterations: usize,
    /// Residuals below this (relative to the unit scale bound) weigh as this.
    pub delta: f64,
    /// Stop when no centre moves by more than this (relative to the largest distance). The
    /// centres only start the Sampson refinement: at 1e-9 the 1000-frame orbit ran to the
    /// 300-round limit (8.9 s); at 1e-6 it converged in 79 rounds (3.5 s) with the final
    /// cameras as close to the truth (mean rotation error 0.068° against 0.069°, translation
    /// directions 0.142° against 0.132°, focal 1.3e-3 against 1.5e-3; docs/BENCHMARKS.md,
    /// "Video-scale speed", third session).
    pub tolerance: f64,
    /// Linear solver.
    pub solver: Solver,
}

impl Default for TranslationAveragingOptions {
    fn default() -> Self {
        Self {
            max_iterations: 300,
            delta: 1e-4,
            tolerance: 1e-6,
            solver: Solver::Sparse,
        }
    }
}

/// What the averaging did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct TranslationAveragingReport {
    /// Distinct centres solved for (tied images share one).
    pub centres: usize,
    /// Direction edges used.
    pub edges: usize,
    /// Members not connected to the reference by directions or ties (left without a centre).
    pub unreachable: usize,
    /// IRLS rounds.
    pub iterations: usize,
    /// Linear solves (IRLS rounds × active-set updates).
    pub solves: usize,
    /// Stopped because the centres stopped moving.
    pub converged: bool,
    /// Edges whose scale sits at the bound 1 at the end.
    pub scales_at_bound: usize,
    /// Groups of images joined by zero-baseline ties that a direction edge spans inside (so
    /// they are not one centre: e.g. a slow video whose short-baseline neighbours look like
    /// pure rotations): their ties were not merged.
    pub split_tie_groups: usize,
    /// Members without a direction edge to the solved centres, placed at the centre of a
    /// rotation-only partner in a split tie group.
    pub attached: usize,
}

/// Camera centres of the images `members` from centre directions, `C_reference = 0`; `None`
/// for images outside `members` and members not connected to the reference.
///
/// Zero-baseline ties (`direction: None`) are hard where they are consistent: a group of images
/// joined by ties that no direction edge spans inside is merged into one centre before the
/// averaging, so its images come out at exactly the same place (a panorama, a camera standing
/// still). Ties are not transitive beyond that: a pair without measurable baseline says only
/// that its baseline is small, and a chain of them (the neighbours of a slow video) adds up to
/// a long one, which the direction edges inside the group measure. So in a group that a
/// direction edge spans, the ties are not merged; its images are solved from their directions,
/// and those that have none are placed at the centre of a tied partner
/// ([`TranslationAveragingReport::attached`]).
///
/// # Errors
/// A reference outside `members`; normal equations that are not positive definite.
pub fn average_translations(
    n: usize,
    members: &[usize],
    directions: &[CenterDirection],
    reference: usize,
    options: &TranslationAveragingOptions,
) -> Result<(Vec<Option<Vector3<f64>>>, TranslationAveragingReport)> {
    let mut is_member = vec![false; n];
    for &m in members {
        if m < n {
            is_member[m] = true;
        }
    }
    if reference >= n || !is_member[reference] {
        return Err(SfmError::InvalidInput(format!(
            "translation averaging: the reference image {reference} is not among the members"
        )));
    }
    let valid = |d: &&CenterDirection| {
        d.first < n
            && d.second < n
            && d.first != d.second
            && is_member[d.first]
            && is_member[d.second]
    };
    let tie_pairs: Vec<(usize, usize, f64)> = directions
        .iter()
        .filter(valid)
        .filter(|d| d.direction.is_none())
        .map(|d| (d.first, d.second, d.weight))
        .collect();
    let mut groups = UnionFind::new(n);
    for &(a, b, _) in &tie_pairs {
        groups.union(a, b);
    }
    // A group that a direction edge spans inside is not one centre.
    let mut split = vec![false; n];
    for d in directions.iter().filter(valid) {
        if d.direction.is_some_and(|v| v.norm() > 0.0) {
            let g = groups.find(d.first);
            if g == groups.find(d.second) {
                split[g] = true;
            }
        }
    }
    let mut ties = UnionFind::new(n);
    for &(a, b, _) in &tie_pairs {
        if !split[groups.find(a)] {
            ties.union(a, b);
        }
    }
    let edges: Vec<DirectionEdge> = directions
        .iter()
        .filter(valid)
        .filter_map(|d| {
            let v = d.direction?;
            let (a, b) = (ties.find(d.first), ties.find(d.second));
            (a != b && v.norm() > 0.0).then(|| DirectionEdge {
                a,
                b,
                v: v.normalize(),
                weight: d.weight,
            })
        })
        .collect();
    // Representatives reachable from the reference's over direction edges.
    let reference_rep = ties.find(reference);
    let mut reach = UnionFind::new(n);
    for e in &edges {
        reach.union(e.a, e.b);
    }
    let root = reach.find(reference_rep);
    let mut rep_value: Vec<Option<Vector3<f64>>> = vec![None; n];
    let mut report = TranslationAveragingReport {
        split_tie_groups: (0..n).filter(|&i| split[i] && groups.find(i) == i).count(),
        ..TranslationAveragingReport::default()
    };
    for &m in members.iter().filter(|&&m| m < n) {
        let r = ties.find(m);
        if reach.find(r) == root {
            rep_value[r] = Some(Vector3::zeros());
        } else {
            report.unreachable += 1;
        }
    }
    let edges: Vec<DirectionEdge> = edges
        .into_iter()
        .filter(|e| rep_value[e.a].is_some() && rep_value[e.b].is_some())
        .collect();
    report.centres = rep_value.iter().filter(|c| c.is_some()).count();
    report.edges = edges.len();
    let centres = lud(&edges, rep_value, reference_rep, options, &mut report)?;
    let mut out = vec![None; n];
    for &m in members.iter().filter(|&&m| m < n) {
        out[m] = centres[ties.find(m)];
    }
    // Members of split groups left without a centre: outwards from the solved ones along the
    // ties, the strongest tie first (a maximum spanning forest grown from the solved members
    // by a heap, as Prim's: each tie is pushed and popped once).
    let mut ties_of: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
    for &(a, b, w) in tie_pairs.iter().filter(|(a, _, _)| split[groups.find(*a)]) {
        ties_of[a].push((b, w));
        ties_of[b].push((a, w));
    }
    let mut heap = BinaryHeap::new();
    let push = |heap: &mut BinaryHeap<Tie>, out: &[Option<Vector3<f64>>], from: usize| {
        for &(to, weight) in &ties_of[from] {
            if out[to].is_none() {
                heap.push(Tie { weight, from, to });
            }
        }
    };
    for from in 0..n {
        if out[from].is_some() {
            push(&mut heap, &out, from);
        }
    }
    let mut placed = 0;
    while let Some(Tie { from, to, .. }) = heap.pop() {
        if out[to].is_none() {
            out[to] = out[from];
            placed += 1;
            push(&mut heap, &out, to);
        }
    }
    report.attached += placed;
    report.unreachable = report.unreachable.saturating_sub(placed);
    Ok((out, report))
}

/// A tie from a placed image to one without a centre, ordered by weight (the strongest
/// first), then by the lower images (so the order does not depend on the heap's).
#[derive(Debug, Clone, Copy)]
struct Tie {
    weight: f64,
    from: usize,
    to: usize,
}

impl Tie {
    fn key(&self) -> (std::cmp::Reverse<usize>, std::cmp::Reverse<usize>) {
        (std::cmp::Reverse(self.to), std::cmp::Reverse(self.from))
    }
}

impl PartialEq for Tie {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other).is_eq()
    }
}

impl Eq for Tie {}

impl PartialOrd for Tie {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Tie {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.weight
            .total_cmp(&other.weight)
            .then_with(|| self.key().cmp(&other.key()))
    }
}

/// A direction edge of the tie-merged graph: `C_a − C_b ∝ v`, unit `v`.
#[derive(Debug, Clone, Copy)]
struct DirectionEdge {
    a: usize,
    b: usize,
    v: Vector3<f64>,
    weight: f64,
}

/// LUD by IRLS on `edges` over the centres that are `Some` (all connected to `reference`).
fn lud(
    edges: &[DirectionEdge],
    mut centres: Vec<Option<Vector3<f64>>>,
    reference: usize,
    options: &TranslationAveragingOptions,
    report: &mut TranslationAveragingReport,
) -> Result<Vec<Option<Vector3<f64>>>> {
    let index = unknown_index(&centres, reference);
    let unknowns = index.iter().filter(|i| i.is_some()).count();
    if unknowns == 0 || edges.is_empty() {
        report.converged = true;
        return Ok(centres);
    }
    let mut system = BlockSystem::new(
        "translation averaging",
        &vec![3; unknowns],
        edges
            .iter()
            .filter_map(|e| Some((index[e.a]?, index[e.b]?))),
        options.solver,
    )?;
    let mut weights: Vec<f64> = edges.iter().map(|e| e.weight).collect();
    // Whether each edge's scale is free (else held at the bound 1).
    let mut free = vec![false; edges.len()];
    let centre = |x: &[f64], v: usize| -> Vector3<f64> {
        index[v].map_or(Vector3::zeros(), |p| {
            Vector3::new(x[3 * p], x[3 * p + 1], x[3 * p + 2])
        })
    };
    for _ in 0..options.max_iterations {
        report.iterations += 1;
        let mut solution = None;
        for _ in 0..4 * edges.len() + 4 {
            let x = solve_centres(&mut system, edges, &weights, &free, &index)?;
            report.solves += 1;
            // Active set: free scales that want to shrink below 1 are fixed; fixed ones whose
            // residual pulls outwards are freed.
            let mut changed = false;
            for (k, e) in edges.iter().enumerate() {
                let d = centre(&x, e.a) - centre(&x, e.b);
                if free[k] {
                    if e.v.dot(&d) < 1.0 {
                        free[k] = false;
                        changed = true;
                    }
                } else if e.v.dot(&(d - e.v)) > 1e-12 {
                    free[k] = true;
                    changed = true;
                }
            }
            solution = Some(x);
            if !changed {
                break;
            }
        }
        let Some(x) = solution else { break };
        let mut moved: f64 = 0.0;
        let mut extent: f64 = 0.0;
        for (v, c) in centres.iter_mut().enumerate() {
            if let Some(c) = c.as_mut() {
                let new = centre(&x, v);
                moved = moved.max((new - *c).norm());
                extent = extent.max(new.norm());
                *c = new;
            }
        }
        for (k, e) in edges.iter().enumerate() {
            let (Some(ca), Some(cb)) = (centres[e.a], centres[e.b]) else {
                continue;
            };
            let d = ca - cb;
            let scale = if free[k] { e.v.dot(&d).max(1.0) } else { 1.0 };
            weights[k] = e.weight / (d - e.v * scale).norm().max(options.delta);
        }
        if moved <= options.tolerance * extent.max(1.0) {
            report.converged = true;
            break;
        }
    }
    report.scales_at_bound = free.iter().filter(|f| !**f).count();
    Ok(centres)
}

/// The weighted least-squares centres of `Σ w_e ‖C_a − C_b − s_e v_e‖²` with the free scales
/// eliminated and the others at 1 (3 values per unknown).
fn solve_centres(
    system: &mut BlockSystem,
    edges: &[DirectionEdge],
    weights: &[f64],
    free: &[bool],
    index: &[Option<usize>],
) -> Result<Vec<f64>> {
    system.clear();
    for (k, e) in edges.iter().enumerate() {
        let w = weights[k];
        let m = if free[k] {
            (Matrix3::identity() - e.v * e.v.transpose()) * w
        } else {
            Matrix3::identity() * w
        };
        let pull = if free[k] { Vector3::zeros() } else { e.v * w };
        let (ia, ib) = (index[e.a], index[e.b]);
        if let Some(p) = ia {
            system.add_block(p, p, |r, c| m[(r, c)])?;
            system.add_rhs(p, |r| pull[r]);
        }
        if let Some(q) = ib {
            system.add_block(q, q, |r, c| m[(r, c)])?;
            system.add_rhs(q, |r| -pull[r]);
        }
        if let (Some(p), Some(q)) = (ia, ib) {
            system.add_block(p, q, |r, c| -m[(r, c)])?;
        }
    }
    system
        .solve_regularised(0.0)?
        .ok_or_else(|| SfmError::NotPositiveDefinite {
            what: "translation averaging",
            detail: "the direction graph does not fix the centres".into(),
        })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn ring(n: usize) -> Vec<Vector3<f64>> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.5;
                Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.3 * i as f64)
            })
            .collect()
    }

    #[test]
    fn centres_from_directions_up_to_scale() {
        let cs = ring(5);
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
        for solver in [Solver::Sparse, Solver::Dense] {
            let options = TranslationAveragingOptions {
                solver,
                ..TranslationAveragingOptions::default()
            };
            let (got, report) =
                average_translations(5, &[0, 1, 2, 3, 4], &dirs, 0, &options).unwrap();
            assert!(report.converged, "{report:?}");
            let got: Vec<Vector3<f64>> = got.into_iter().map(Option::unwrap).collect();
            let s = (got[1] - got[0]).norm() / (cs[1] - cs[0]).norm();
            for i in 0..5 {
                let want = (cs[i] - cs[0]) * s;
                assert!(
                    (got[i] - want).norm() < 1e-4 * s,
                    "centre {i}: {} vs {want}",
                    got[i]
                );
            }
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
        let (got, _) = average_translations(
            3,
            &[0, 1, 2],
            &dirs,
            0,
            &TranslationAveragingOptions::default(),
        )
        .unwrap();
        let (c1, c2) = (got[1].unwrap(), got[2].unwrap());
        assert!((c1 - c2).norm() < 1e-6);
        assert!((c1 + Vector3::x()).norm() < 1e-6, "{c1}");
    }

    /// A chain of short-baseline pairs (0–1–2–3 tied) that direction edges span (0→3 and 1→3
    /// measured): the ties are not merged into one centre; 2, which has no direction, sits
    /// at a tied partner's centre.
    #[test]
    fn tie_chains_spanned_by_directions_are_not_one_centre() {
        let tie = |first, second| CenterDirection {
            first,
            second,
            direction: None,
            weight: 1.0,
        };
        let dirs = [
            tie(0, 1),
            tie(1, 2),
            tie(2, 3),
            CenterDirection {
                first: 0,
                second: 3,
                direction: Some(-Vector3::x()),
                weight: 1.0,
            },
            CenterDirection {
                first: 1,
                second: 3,
                direction: Some(-Vector3::x()),
                weight: 1.0,
            },
        ];
        let (got, report) = average_translations(
            4,
            &[0, 1, 2, 3],
            &dirs,
            0,
            &TranslationAveragingOptions::default(),
        )
        .unwrap();
        assert_eq!(
            (report.split_tie_groups, report.attached),
            (1, 1),
            "{report:?}"
        );
        assert_eq!(report.unreachable, 0);
        let c: Vec<Vector3<f64>> = got.into_iter().map(Option::unwrap).collect();
        assert!((c[3] - c[0]).norm() > 0.5, "{c:?}");
        assert!(
            (c[3] - c[0]).normalize().dot(&Vector3::x()) > 0.999,
            "{c:?}"
        );
        assert!(c[2] == c[1] || c[2] == c[3], "{c:?}");
    }

    #[test]
    fn unreachable_members_get_no_centre() {
        let dirs = [CenterDirection {
            first: 0,
            second: 1,
            direction: Some(Vector3::x()),
            weight: 1.0,
        }];
        let (got, report) = average_translations(
            3,
            &[0, 1, 2],
            &dirs,
            0,
            &TranslationAveragingOptions::default(),
        )
        .unwrap();
        assert!(got[2].is_none() && got[1].is_some());
        assert_eq!(report.unreachable, 1);
        assert!(average_translations(3, &[1, 2], &dirs, 0, &Default::default()).is_err());
    }
}
