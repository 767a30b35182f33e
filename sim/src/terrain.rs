//! Terrain as a regular height field in the local frame.
//!
//! Heights are elevations (metres, up) relative to the local origin; the local NED "down"
//! coordinate of a ground point is `-height`. Vertex `(i, j)` sits at north
//! `north0 + i * cell`, east `east0 + j * cell`; between vertices each cell is split into
//! two triangles along the same diagonal the renderer uses, so the height the world
//! reports ([`HeightField::height`]) is exactly the surface the camera sees.

use mavloc_geometry::Vec3;

#[derive(Clone, Debug)]
pub struct HeightField {
    pub north0: f64,
    pub east0: f64,
    pub cell: f64,
    /// Vertices along north.
    pub rows: usize,
    /// Vertices along east.
    pub cols: usize,
    heights: Vec<f32>,
}

impl HeightField {
    /// Samples `f(north, east)` at every vertex of a `size_n x size_e` metre grid centred
    /// on the origin.
    pub fn from_fn(size_n: f64, size_e: f64, cell: f64, f: impl Fn(f64, f64) -> f64 + Sync) -> Self {
        use rayon::prelude::*;
        let rows = (size_n / cell).round() as usize + 1;
        let cols = (size_e / cell).round() as usize + 1;
        let north0 = -((rows - 1) as f64) * cell / 2.0;
        let east0 = -((cols - 1) as f64) * cell / 2.0;
        let heights = (0..rows * cols)
            .into_par_iter()
            .map(|k| f(north0 + (k / cols) as f64 * cell, east0 + (k % cols) as f64 * cell) as f32)
            .collect();
        HeightField { north0, east0, cell, rows, cols, heights }
    }

    /// Height of vertex `(i, j)`.
    pub fn at(&self, i: usize, j: usize) -> f64 {
        self.heights[i * self.cols + j] as f64
    }

    /// Local NED position of vertex `(i, j)`.
    pub fn vertex(&self, i: usize, j: usize) -> Vec3 {
        Vec3::new(self.north0 + i as f64 * self.cell, self.east0 + j as f64 * self.cell, -self.at(i, j))
    }

    /// Whether (north, east) lies on the grid.
    pub fn contains(&self, north: f64, east: f64) -> bool {
        let (u, v) = ((north - self.north0) / self.cell, (east - self.east0) / self.cell);
        u >= 0.0 && v >= 0.0 && u <= (self.rows - 1) as f64 && v <= (self.cols - 1) as f64
    }

    /// Height of the rendered surface at (north, east): linear on the cell's triangle
    /// (diagonal from vertex (i, j) to (i+1, j+1)). Clamped to the grid's edge outside.
    pub fn height(&self, north: f64, east: f64) -> f64 {
        let u = ((north - self.north0) / self.cell).clamp(0.0, (self.rows - 1) as f64);
        let v = ((east - self.east0) / self.cell).clamp(0.0, (self.cols - 1) as f64);
        let i = (u.floor() as usize).min(self.rows - 2);
        let j = (v.floor() as usize).min(self.cols - 2);
        let (fu, fv) = (u - i as f64, v - j as f64);
        let h00 = self.at(i, j);
        let h11 = self.at(i + 1, j + 1);
        if fu >= fv {
            // Triangle (i,j), (i+1,j), (i+1,j+1).
            let h10 = self.at(i + 1, j);
            h00 + fu * (h10 - h00) + fv * (h11 - h10)
        } else {
            // Triangle (i,j), (i,j+1), (i+1,j+1).
            let h01 = self.at(i, j + 1);
            h00 + fv * (h01 - h00) + fu * (h11 - h01)
        }
    }

    /// Local NED point on the surface at (north, east).
    pub fn surface_point(&self, north: f64, east: f64) -> Vec3 {
        Vec3::new(north, east, -self.height(north, east))
    }

    /// Upward unit normal (in NED, pointing to negative down) from central differences.
    pub fn normal(&self, north: f64, east: f64) -> Vec3 {
        let d = self.cell;
        let dh_dn = (self.height(north + d, east) - self.height(north - d, east)) / (2.0 * d);
        let dh_de = (self.height(north, east + d) - self.height(north, east - d)) / (2.0 * d);
        Vec3::new(-dh_dn, -dh_de, -1.0).normalize()
    }

    /// Lowest and highest vertex.
    pub fn range(&self) -> (f64, f64) {
        self.heights
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &h| (lo.min(h as f64), hi.max(h as f64)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_is_reproduced_exactly() {
        let hf = HeightField::from_fn(20.0, 30.0, 0.5, |n, e| 0.1 * n - 0.2 * e + 3.0);
        assert_eq!((hf.rows, hf.cols), (41, 61));
        for (n, e) in [(0.0, 0.0), (3.3, -7.1), (-9.9, 14.2)] {
            assert!((hf.height(n, e) - (0.1 * n - 0.2 * e + 3.0)).abs() < 1e-5);
        }
        let nrm = hf.normal(1.0, 1.0);
        let expected = Vec3::new(-0.1, 0.2, -1.0).normalize();
        assert!((nrm - expected).norm() < 1e-5);
    }

    #[test]
    fn vertices_are_where_the_grid_says() {
        let hf = HeightField::from_fn(10.0, 10.0, 1.0, |n, e| n + 10.0 * e);
        let v = hf.vertex(2, 3);
        assert_eq!(v, Vec3::new(-3.0, -2.0, -(-3.0 + 10.0 * -2.0)));
        assert!(hf.contains(5.0, -5.0) && !hf.contains(5.1, 0.0));
    }
}
