//! Distances to polylines: ground-truth borders, fitted border lines.

use crate::Vec3;

/// Nearest point to `p` on a set of polylines, and its distance; `None` when there are no
/// points. A one-point polyline is that point.
pub fn nearest_on_polylines(lines: &[Vec<Vec3>], p: &Vec3) -> Option<(Vec3, f64)> {
    let mut best: Option<(Vec3, f64)> = None;
    let mut consider = |q: Vec3| {
        let d = (p - q).norm();
        if best.is_none_or(|(_, bd)| d < bd) {
            best = Some((q, d));
        }
    };
    for line in lines {
        if line.len() == 1 {
            consider(line[0]);
        }
        for w in line.windows(2) {
            let (a, b) = (w[0], w[1]);
            let ab = b - a;
            let t = if ab.norm_squared() > 0.0 {
                ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0)
            } else {
                0.0
            };
            consider(a + ab * t);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_point_on_segments_and_single_points() {
        let lines =
            vec![vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(10.0, 0.0, 0.0)], vec![Vec3::new(5.0, 5.0, 0.0)]];
        let (q, d) = nearest_on_polylines(&lines, &Vec3::new(3.0, -2.0, 0.0)).unwrap();
        assert_eq!((q, d), (Vec3::new(3.0, 0.0, 0.0), 2.0));
        let (q, _) = nearest_on_polylines(&lines, &Vec3::new(5.0, 4.5, 0.0)).unwrap();
        assert_eq!(q, Vec3::new(5.0, 5.0, 0.0));
        let (q, _) = nearest_on_polylines(&lines, &Vec3::new(-4.0, 1.0, 0.0)).unwrap();
        assert_eq!(q, Vec3::zeros(), "clamped to the segment's end");
        assert!(nearest_on_polylines(&[], &Vec3::zeros()).is_none());
    }
}
