//! k nearest training histograms by Euclidean distance (indoor seed sec. 3.3.3).
//!
//! A brute force over a column-major copy of the training histograms: for each histogram
//! bin, one pass adds `(h_i[d] - q[d])^2` to every sample's distance, which the compiler
//! turns into SIMD over samples. `benches/indoor.rs` compares it with a k-d tree (kiddo)
//! at 500 and 50 000 samples; the brute force is faster at both for the 20-bin texton
//! histograms (see the README for the medians), so no tree is built. Histograms are
//! 20-dimensional points on a simplex, where k-d trees prune little.

/// One neighbour: its training index and squared distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Neighbour {
    pub index: usize,
    pub dist2: f32,
}

/// The training histograms, ready for queries.
#[derive(Clone, Debug)]
pub struct Knn {
    dims: usize,
    count: usize,
    /// `cols[d * count + i]` = bin `d` of histogram `i`.
    cols: Vec<f32>,
}

impl Knn {
    /// All histograms must have the same length.
    pub fn new(histograms: &[Vec<f32>]) -> Result<Knn, String> {
        let dims = histograms.first().map_or(0, Vec::len);
        if let Some((i, h)) = histograms.iter().enumerate().find(|(_, h)| h.len() != dims) {
            return Err(format!("histogram {i} has {} bins, the first has {dims}", h.len()));
        }
        let count = histograms.len();
        let mut cols = vec![0.0f32; dims * count];
        for (i, h) in histograms.iter().enumerate() {
            for (d, v) in h.iter().enumerate() {
                cols[d * count + i] = *v;
            }
        }
        Ok(Knn { dims, count, cols })
    }

    pub fn len(&self) -> usize {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    pub fn dims(&self) -> usize {
        self.dims
    }

    /// The `k` nearest to `query`, nearest first, into `out`; `exclude` leaves one sample
    /// out (for leave-one-out fits). `scratch` is reused between calls.
    pub fn nearest(
        &self,
        query: &[f32],
        k: usize,
        exclude: Option<usize>,
        scratch: &mut Vec<f32>,
        out: &mut Vec<Neighbour>,
    ) {
        out.clear();
        if query.len() != self.dims || k == 0 {
            return;
        }
        scratch.clear();
        scratch.resize(self.count, 0.0);
        for (d, q) in query.iter().enumerate() {
            let col = &self.cols[d * self.count..(d + 1) * self.count];
            for (acc, c) in scratch.iter_mut().zip(col) {
                let e = c - q;
                *acc += e * e;
            }
        }
        if let Some(i) = exclude.filter(|&i| i < self.count) {
            scratch[i] = f32::INFINITY;
        }
        // Insertion into a short sorted list: k is small (5) and most samples fail the
        // first comparison with the current k-th distance.
        let mut worst = f32::INFINITY;
        for (index, &dist2) in scratch.iter().enumerate() {
            if out.len() == k && dist2 >= worst {
                continue;
            }
            if !dist2.is_finite() {
                continue;
            }
            let at = out.partition_point(|n| n.dist2 <= dist2);
            if out.len() == k {
                out.pop();
            }
            out.insert(at, Neighbour { index, dist2 });
            if out.len() == k {
                worst = out[k - 1].dist2;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Same neighbours (by distance) as sorting every distance.
        #[test]
        fn matches_a_full_sort(
            data in prop::collection::vec(prop::collection::vec(0.0f32..1.0, 4), 1..60),
            query in prop::collection::vec(0.0f32..1.0, 4),
            k in 1usize..8,
            exclude in prop::option::of(0usize..60),
        ) {
            let knn = Knn::new(&data).unwrap();
            let (mut scratch, mut out) = (Vec::new(), Vec::new());
            knn.nearest(&query, k, exclude, &mut scratch, &mut out);
            let mut all: Vec<(f32, usize)> = data
                .iter()
                .enumerate()
                .filter(|(i, _)| Some(*i) != exclude)
                .map(|(i, h)| (h.iter().zip(&query).map(|(a, b)| (a - b) * (a - b)).sum(), i))
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0));
            prop_assert_eq!(out.len(), k.min(all.len()));
            for (n, (d, _)) in out.iter().zip(&all) {
                prop_assert!((n.dist2 - d).abs() <= 1e-5 * (1.0 + d));
            }
            prop_assert!(out.windows(2).all(|w| w[0].dist2 <= w[1].dist2));
            prop_assert!(out.iter().all(|n| Some(n.index) != exclude));
        }
    }

    #[test]
    fn rejects_ragged_histograms() {
        assert!(Knn::new(&[vec![0.0; 3], vec![0.0; 2]]).unwrap_err().contains("histogram 1"));
    }
}
