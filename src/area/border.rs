//! A 3D border line from converged landmarks: what the area seed names as future work
//! (sec. 7, ch. 9) and leaves as a point cloud.
//!
//! The cloud is thinned on a horizontal grid (cell centroids), isolated cells are dropped
//! as outliers, a minimum spanning tree joins the rest without edges longer than a gap
//! limit, and the longest path through each tree orders its points along the border. A
//! moving average smooths the path, and a path whose ends meet is closed into a ring.

use crate::geometry::Vec3;

/// Parameters of the border fit, metres.
#[derive(Clone, Copy, Debug)]
pub struct BorderParams {
    pub cell_m: f64,
    pub neighbour_radius_m: f64,
    pub min_neighbours: usize,
    pub max_gap_m: f64,
    pub min_points: usize,
    pub smooth_half_window: usize,
}

impl Default for BorderParams {
    fn default() -> Self {
        BorderParams {
            cell_m: 2.0,
            neighbour_radius_m: 6.0,
            min_neighbours: 2,
            max_gap_m: 15.0,
            min_points: 6,
            smooth_half_window: 2,
        }
    }
}

fn dist2d(a: &Vec3, b: &Vec3) -> f64 {
    dist2d_sq(a, b).sqrt()
}

/// Squared: what the O(n^2) neighbour and tree steps compare (`hypot` guards against
/// overflow these metres never reach, and was a tenth of a 360-frame run's time).
fn dist2d_sq(a: &Vec3, b: &Vec3) -> f64 {
    (a.x - b.x).powi(2) + (a.y - b.y).powi(2)
}

/// Border polylines through `points`.
pub fn fit(points: &[Vec3], p: &BorderParams) -> Vec<Vec<Vec3>> {
    // 1. Thin on a grid.
    let mut cells: std::collections::HashMap<(i64, i64), (Vec3, usize)> = std::collections::HashMap::new();
    for q in points.iter().filter(|q| q.iter().all(|c| c.is_finite())) {
        let key = ((q.x / p.cell_m).floor() as i64, (q.y / p.cell_m).floor() as i64);
        let e = cells.entry(key).or_insert((Vec3::zeros(), 0));
        e.0 += q;
        e.1 += 1;
    }
    let mut keys: Vec<_> = cells.keys().copied().collect();
    keys.sort_unstable();
    let nodes: Vec<Vec3> = keys.iter().map(|k| cells[k].0 / cells[k].1 as f64).collect();
    // 2. Drop isolated cells.
    let nodes: Vec<Vec3> = nodes
        .iter()
        .filter(|a| {
            nodes.iter().filter(|b| dist2d_sq(a, b) <= p.neighbour_radius_m.powi(2)).count()
                > p.min_neighbours
        })
        .copied()
        .collect();
    let n = nodes.len();
    if n < p.min_points {
        return Vec::new();
    }
    // 3. Minimum spanning forest (Prim, O(n^2): n is a few hundred cells).
    let mut in_tree = vec![false; n];
    let mut best = vec![f64::INFINITY; n];
    let mut parent = vec![usize::MAX; n];
    let mut adjacency: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
    for root in 0..n {
        if in_tree[root] {
            continue;
        }
        best[root] = 0.0;
        loop {
            let next = (0..n)
                .filter(|&i| !in_tree[i] && best[i].is_finite())
                .min_by(|&a, &b| best[a].total_cmp(&best[b]));
            let Some(u) = next else { break };
            in_tree[u] = true;
            if parent[u] != usize::MAX {
                let d = best[u].sqrt();
                adjacency[u].push((parent[u], d));
                adjacency[parent[u]].push((u, d));
            }
            // `best` holds squared distances: the same order, no square roots.
            for v in 0..n {
                let d = dist2d_sq(&nodes[u], &nodes[v]);
                if !in_tree[v] && d <= p.max_gap_m.powi(2) && d < best[v] {
                    best[v] = d;
                    parent[v] = u;
                }
            }
        }
    }
    // 4. Longest path of each tree: farthest node from any node, then farthest from it.
    let farthest = |start: usize| -> (usize, Vec<usize>, Vec<f64>) {
        let mut dist = vec![f64::INFINITY; n];
        let mut prev = vec![usize::MAX; n];
        dist[start] = 0.0;
        let mut stack = vec![start];
        while let Some(u) = stack.pop() {
            for &(v, w) in &adjacency[u] {
                if dist[v].is_infinite() {
                    dist[v] = dist[u] + w;
                    prev[v] = u;
                    stack.push(v);
                }
            }
        }
        let end = (0..n)
            .filter(|&i| dist[i].is_finite())
            .max_by(|&a, &b| dist[a].total_cmp(&dist[b]))
            .unwrap_or(start);
        (end, prev, dist)
    };
    let mut seen = vec![false; n];
    let mut lines = Vec::new();
    for start in 0..n {
        if seen[start] {
            continue;
        }
        let (_, _, reach) = farthest(start);
        for (i, d) in reach.iter().enumerate() {
            if d.is_finite() {
                seen[i] = true;
            }
        }
        let (a, _, _) = farthest(start);
        let (b, prev, _) = farthest(a);
        let mut path = vec![b];
        while *path.last().expect("non-empty") != a {
            path.push(prev[*path.last().expect("non-empty")]);
        }
        if path.len() < p.min_points {
            continue;
        }
        // 5. Smooth.
        let pts: Vec<Vec3> = path.iter().map(|&i| nodes[i]).collect();
        let h = p.smooth_half_window;
        let mut smooth: Vec<Vec3> = (0..pts.len())
            .map(|i| {
                let (lo, hi) = (i.saturating_sub(h), (i + h).min(pts.len() - 1));
                pts[lo..=hi].iter().sum::<Vec3>() / (hi - lo + 1) as f64
            })
            .collect();
        // 6. Close rings.
        let length: f64 = smooth.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
        if smooth.len() > 2
            && dist2d(&smooth[0], smooth.last().expect("non-empty")) < p.max_gap_m
            && length > 4.0 * p.max_gap_m
        {
            smooth.push(smooth[0]);
        }
        lines.push(smooth);
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_noisy_ring_becomes_a_closed_ring_near_the_circle() {
        let mut pts = Vec::new();
        for i in 0..600 {
            let t = i as f64 / 600.0 * std::f64::consts::TAU;
            let r = 50.0 + ((i * 7919) % 13) as f64 * 0.1 - 0.6;
            pts.push(Vec3::new(r * t.cos(), r * t.sin(), 0.0));
        }
        pts.push(Vec3::new(200.0, 200.0, 0.0)); // an outlier
        let lines = fit(&pts, &BorderParams::default());
        assert_eq!(lines.len(), 1);
        let ring = &lines[0];
        assert_eq!(ring.first(), ring.last(), "closed");
        for q in ring {
            assert!((q.x.hypot(q.y) - 50.0).abs() < 2.0, "{q:?}");
        }
        let length: f64 = ring.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
        assert!(length > 0.9 * std::f64::consts::TAU * 50.0, "{length}");
    }

    #[test]
    fn too_few_points_give_nothing() {
        assert!(fit(&[Vec3::zeros(), Vec3::new(1.0, 0.0, 0.0)], &BorderParams::default()).is_empty());
    }
}
