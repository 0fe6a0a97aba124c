//! The view graph: images as nodes, pairs with a relative pose as edges; connected components
//! and the union-find forest the tracks and the centre ties are built with.

use std::collections::VecDeque;

/// A union-find forest over `0..n` (path halving, union by size).
#[derive(Debug, Clone)]
pub struct UnionFind {
    parent: Vec<usize>,
    size: Vec<usize>,
}

impl UnionFind {
    /// `n` singletons.
    pub fn new(n: usize) -> Self {
        Self {
            parent: (0..n).collect(),
            size: vec![1; n],
        }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.parent.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.parent.is_empty()
    }

    /// The representative of `v`.
    pub fn find(&mut self, mut v: usize) -> usize {
        while self.parent[v] != v {
            self.parent[v] = self.parent[self.parent[v]];
            v = self.parent[v];
        }
        v
    }

    /// Joins the sets of `a` and `b`; returns whether they were apart.
    pub fn union(&mut self, a: usize, b: usize) -> bool {
        let (mut a, mut b) = (self.find(a), self.find(b));
        if a == b {
            return false;
        }
        if self.size[a] < self.size[b] {
            std::mem::swap(&mut a, &mut b);
        }
        self.parent[b] = a;
        self.size[a] += self.size[b];
        true
    }
}

/// The images of the largest connected component of the graph with `n` nodes and weighted
/// `edges` (ties: the larger total weight, then the smallest image), sorted. Empty when there
/// is no edge. Linear in nodes and edges.
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
    let mut weight = vec![0.0; components.len()];
    for &(a, b, w) in edges {
        if a < n && b < n && a != b && label[a] != usize::MAX {
            weight[label[a]] += w;
        }
    }
    (0..components.len())
        .max_by(|&a, &b| {
            components[a]
                .len()
                .cmp(&components[b].len())
                .then(weight[a].total_cmp(&weight[b]))
                .then(components[b][0].cmp(&components[a][0]))
        })
        .map(|k| std::mem::take(&mut components[k]))
        .unwrap_or_default()
}

/// The bridges of the graph with `n` nodes and `edges`: the indices (into `edges`, ascending) of
/// the edges whose removal disconnects their component. A bridge pair's relative pose is
/// confirmed by no cycle. Parallel edges are never bridges; self-loops and edges naming a node
/// out of range are ignored. Iterative Tarjan: linear in nodes and edges, no recursion.
pub fn bridges(n: usize, edges: &[(usize, usize)]) -> Vec<usize> {
    let mut adjacency: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
    for (k, &(a, b)) in edges.iter().enumerate() {
        if a < n && b < n && a != b {
            adjacency[a].push((b, k));
            adjacency[b].push((a, k));
        }
    }
    const UNSEEN: usize = usize::MAX;
    let mut order = vec![UNSEEN; n];
    let mut low = vec![0usize; n];
    let mut found = Vec::new();
    let mut time = 0;
    // (node, the edge it was entered by, next adjacency slot to visit)
    let mut stack: Vec<(usize, usize, usize)> = Vec::new();
    for root in 0..n {
        if order[root] != UNSEEN {
            continue;
        }
        order[root] = time;
        low[root] = time;
        time += 1;
        stack.push((root, usize::MAX, 0));
        while let Some(&mut (v, entered, ref mut next)) = stack.last_mut() {
            if let Some(&(w, k)) = adjacency[v].get(*next) {
                *next += 1;
                if k == entered {
                    continue;
                }
                if order[w] == UNSEEN {
                    order[w] = time;
                    low[w] = time;
                    time += 1;
                    stack.push((w, k, 0));
                } else {
                    low[v] = low[v].min(order[w]);
                }
            } else {
                stack.pop();
                if let Some(&(parent, _, _)) = stack.last() {
                    low[parent] = low[parent].min(low[v]);
                    if low[v] > order[parent] {
                        found.push(entered);
                    }
                }
            }
        }
    }
    found.sort_unstable();
    found
}

/// The nodes reachable from `start` over `edges` without crossing edge `skip`, sorted.
pub fn side_of(n: usize, edges: &[(usize, usize)], skip: usize, start: usize) -> Vec<usize> {
    let mut adjacency: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (k, &(a, b)) in edges.iter().enumerate() {
        if k != skip && a < n && b < n && a != b {
            adjacency[a].push(b);
            adjacency[b].push(a);
        }
    }
    let mut seen = vec![false; n];
    let mut out = Vec::new();
    if start >= n {
        return out;
    }
    seen[start] = true;
    let mut queue = VecDeque::from([start]);
    while let Some(v) = queue.pop_front() {
        out.push(v);
        for &w in &adjacency[v] {
            if !seen[w] {
                seen[w] = true;
                queue.push_back(w);
            }
        }
    }
    out.sort_unstable();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn components_pick_the_largest() {
        let edges = [(0, 1, 1.0), (2, 3, 1.0), (3, 4, 1.0)];
        assert_eq!(largest_component(6, &edges), vec![2, 3, 4]);
        assert!(largest_component(3, &[]).is_empty());
        // Equal sizes: the heavier one.
        let edges = [(0, 1, 1.0), (2, 3, 5.0)];
        assert_eq!(largest_component(4, &edges), vec![2, 3]);
    }

    #[test]
    fn union_find_joins_sets() {
        let mut u = UnionFind::new(5);
        assert!(u.union(0, 1));
        assert!(u.union(3, 4));
        assert!(!u.union(1, 0));
        assert!(u.union(1, 4));
        assert_eq!(u.find(0), u.find(3));
        assert_ne!(u.find(0), u.find(2));
    }

    #[test]
    fn bridges_are_the_edges_on_no_cycle() {
        // Triangle 0-1-2, bridge 2-3, square 3-4-5-6, bridge 6-7, a parallel pair 8=9 joined
        // to 7 by a bridge, and an isolated node 10.
        let edges = [
            (0, 1),
            (1, 2),
            (2, 0),
            (2, 3),
            (3, 4),
            (4, 5),
            (5, 6),
            (6, 3),
            (6, 7),
            (7, 8),
            (8, 9),
            (9, 8),
            (4, 4),
        ];
        assert_eq!(bridges(11, &edges), vec![3, 8, 9]);
        assert_eq!(side_of(11, &edges, 3, 3), vec![3, 4, 5, 6, 7, 8, 9]);
        assert_eq!(side_of(11, &edges, 3, 2), vec![0, 1, 2]);
        assert_eq!(side_of(11, &edges, 0, 0), (0..10).collect::<Vec<_>>());
        // A path: every edge. A long path needs no recursion.
        let path: Vec<(usize, usize)> = (0..5000).map(|i| (i, i + 1)).collect();
        assert_eq!(bridges(5001, &path).len(), 5000);
        let cycle: Vec<(usize, usize)> = (0..5000).map(|i| (i, (i + 1) % 5000)).collect();
        assert!(bridges(5000, &cycle).is_empty());
    }
}
