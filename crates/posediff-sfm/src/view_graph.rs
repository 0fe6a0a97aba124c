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
}
