//! Texton dictionary and texton histograms (indoor seed sec. 3.3.1-3.3.2).
//!
//! Patches of `w x h` pixels over the Y, U and V channels are clustered into `n` textons by
//! the seed's winner-take-all competitive learning (`d_r += alpha (x - d_r)` for the nearest
//! texton `d_r`), or by k-means. A frame is described by the normalised histogram of the
//! nearest texton of its patches: every patch position ("full sampling", for training) or
//! `N` random positions (for flight).
//!
//! The nearest texton is found as `argmin_t (|t|^2 - 2 p . t)`, which drops the patch's own
//! norm from every comparison.

use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// An image in Y, U, V (BT.601, U and V offset to 128), row-major.
#[derive(Clone, Debug)]
pub struct YuvImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<[f32; 3]>,
}

impl YuvImage {
    /// From 8-bit RGB, 3 bytes per pixel.
    pub fn from_rgb(width: usize, height: usize, rgb: &[u8]) -> Result<YuvImage, String> {
        if rgb.len() != width * height * 3 {
            return Err(format!("RGB buffer of {} bytes is not {width}x{height}x3", rgb.len()));
        }
        let data = rgb
            .chunks_exact(3)
            .map(|p| {
                let (r, g, b) = (p[0] as f32, p[1] as f32, p[2] as f32);
                let y = 0.299 * r + 0.587 * g + 0.114 * b;
                [y, 0.492 * (b - y) + 128.0, 0.877 * (r - y) + 128.0]
            })
            .collect();
        Ok(YuvImage { width, height, data })
    }
}

/// How the dictionary is learned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Learning {
    /// Winner-take-all competitive learning with the given rate (the seed's, 0.02).
    Competitive { rate_millis: u32 },
    /// Lloyd's k-means, this many iterations.
    KMeans { iterations: u32 },
}

/// A texton dictionary.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dictionary {
    pub w: usize,
    pub h: usize,
    /// `n` textons of `w * h * 3` values each, channel-interleaved per pixel.
    pub textons: Vec<Vec<f32>>,
}

fn patch(img: &YuvImage, x: usize, y: usize, w: usize, h: usize, out: &mut Vec<f32>) {
    out.clear();
    for dy in 0..h {
        let row = (y + dy) * img.width + x;
        for p in &img.data[row..row + w] {
            out.extend_from_slice(p);
        }
    }
}

fn dist2(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

impl Dictionary {
    pub fn len(&self) -> usize {
        self.textons.len()
    }

    pub fn is_empty(&self) -> bool {
        self.textons.is_empty()
    }

    /// Learns `n` textons of `w x h` from `patches_per_image` random patches of each image.
    pub fn learn(
        images: &[YuvImage],
        n: usize,
        w: usize,
        h: usize,
        patches_per_image: usize,
        learning: Learning,
        seed: u64,
    ) -> Result<Dictionary, String> {
        let first = images.first().ok_or("no images to learn textons from")?;
        if images.iter().any(|i| i.width < w || i.height < h) {
            return Err(format!("an image is smaller than the {w}x{h} texton"));
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut buf = Vec::new();
        let mut random_patch = |img: &YuvImage, rng: &mut rand::rngs::StdRng| {
            let x = rng.random_range(0..=img.width - w);
            let y = rng.random_range(0..=img.height - h);
            patch(img, x, y, w, h, &mut buf);
            buf.clone()
        };
        // Seed sec. 3.3.1: start from n random patches of the first image.
        let mut textons: Vec<Vec<f32>> = (0..n).map(|_| random_patch(first, &mut rng)).collect();
        let samples: Vec<Vec<f32>> = images
            .iter()
            .flat_map(|img| (0..patches_per_image).map(|_| random_patch(img, &mut rng)).collect::<Vec<_>>())
            .collect();
        let nearest = |textons: &[Vec<f32>], x: &[f32]| {
            (0..textons.len())
                .min_by(|&a, &b| dist2(&textons[a], x).total_cmp(&dist2(&textons[b], x)))
                .unwrap_or(0)
        };
        match learning {
            Learning::Competitive { rate_millis } => {
                let rate = rate_millis as f32 / 1000.0;
                for x in &samples {
                    let r = nearest(&textons, x);
                    for (d, v) in textons[r].iter_mut().zip(x) {
                        *d += rate * (v - *d);
                    }
                }
            }
            Learning::KMeans { iterations } => {
                for _ in 0..iterations {
                    let mut sums = vec![vec![0.0f64; w * h * 3]; n];
                    let mut counts = vec![0usize; n];
                    for x in &samples {
                        let r = nearest(&textons, x);
                        counts[r] += 1;
                        for (s, v) in sums[r].iter_mut().zip(x) {
                            *s += *v as f64;
                        }
                    }
                    for (t, (s, c)) in textons.iter_mut().zip(sums.iter().zip(&counts)) {
                        if *c > 0 {
                            for (d, v) in t.iter_mut().zip(s) {
                                *d = (*v / *c as f64) as f32;
                            }
                        }
                    }
                }
            }
        }
        Ok(Dictionary { w, h, textons })
    }

    /// Index of the nearest texton to a patch, with `norms[t] = |t|^2`.
    fn nearest(&self, p: &[f32], norms: &[f32]) -> usize {
        let mut best = (f32::INFINITY, 0);
        for (t, (texton, norm)) in self.textons.iter().zip(norms).enumerate() {
            let dot: f32 = texton.iter().zip(p).map(|(a, b)| a * b).sum();
            let score = norm - 2.0 * dot;
            if score < best.0 {
                best = (score, t);
            }
        }
        best.1
    }

    fn norms(&self) -> Vec<f32> {
        self.textons.iter().map(|t| t.iter().map(|v| v * v).sum()).collect()
    }

    /// Histogram over every patch position (full sampling), normalised to sum 1.
    pub fn histogram_full(&self, img: &YuvImage) -> Vec<f32> {
        let norms = self.norms();
        let (w, h) = (self.w, self.h);
        if img.width < w || img.height < h || self.is_empty() {
            return vec![0.0; self.len()];
        }
        let counts = (0..=img.height - h)
            .into_par_iter()
            .fold(
                || (vec![0u64; self.len()], Vec::with_capacity(w * h * 3)),
                |(mut counts, mut buf), y| {
                    for x in 0..=img.width - w {
                        patch(img, x, y, w, h, &mut buf);
                        counts[self.nearest(&buf, &norms)] += 1;
                    }
                    (counts, buf)
                },
            )
            .map(|(c, _)| c)
            .reduce(|| vec![0u64; self.len()], |a, b| a.iter().zip(&b).map(|(x, y)| x + y).collect());
        normalise(&counts)
    }

    /// Histogram of `samples` random patch positions (random sampling), normalised.
    pub fn histogram_random(&self, img: &YuvImage, samples: usize, rng: &mut impl Rng) -> Vec<f32> {
        let norms = self.norms();
        let (w, h) = (self.w, self.h);
        if img.width < w || img.height < h || self.is_empty() {
            return vec![0.0; self.len()];
        }
        let mut counts = vec![0u64; self.len()];
        let mut buf = Vec::with_capacity(w * h * 3);
        for _ in 0..samples {
            let x = rng.random_range(0..=img.width - w);
            let y = rng.random_range(0..=img.height - h);
            patch(img, x, y, w, h, &mut buf);
            counts[self.nearest(&buf, &norms)] += 1;
        }
        normalise(&counts)
    }
}

fn normalise(counts: &[u64]) -> Vec<f32> {
    let total: u64 = counts.iter().sum();
    counts.iter().map(|&c| if total > 0 { c as f32 / total as f32 } else { 0.0 }).collect()
}

/// Cosine similarity of two histograms (indoor seed sec. 3.4.1).
pub fn cosine(a: &[f32], b: &[f32]) -> f32 {
    let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let na: f32 = a.iter().map(|x| x * x).sum::<f32>().sqrt();
    let nb: f32 = b.iter().map(|x| x * x).sum::<f32>().sqrt();
    if na > 0.0 && nb > 0.0 {
        dot / (na * nb)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Left half: black and white vertical stripes 3 px wide; right half: flat red.
    fn two_textures(width: usize, height: usize) -> YuvImage {
        let mut rgb = Vec::with_capacity(width * height * 3);
        for _y in 0..height {
            for x in 0..width {
                if x < width / 2 {
                    let v = if (x / 3) % 2 == 0 { 0 } else { 255 };
                    rgb.extend_from_slice(&[v, v, v]);
                } else {
                    rgb.extend_from_slice(&[200, 30, 30]);
                }
            }
        }
        YuvImage::from_rgb(width, height, &rgb).unwrap()
    }

    fn crop(img: &YuvImage, x0: usize, w: usize) -> YuvImage {
        let mut data = Vec::new();
        for y in 0..img.height {
            data.extend_from_slice(&img.data[y * img.width + x0..y * img.width + x0 + w]);
        }
        YuvImage { width: w, height: img.height, data }
    }

    #[test]
    fn yuv_of_grey_has_neutral_chroma() {
        let img = YuvImage::from_rgb(1, 1, &[100, 100, 100]).unwrap();
        let p = img.data[0];
        assert!((p[0] - 100.0).abs() < 1e-3 && (p[1] - 128.0).abs() < 1e-3 && (p[2] - 128.0).abs() < 1e-3);
        assert!(YuvImage::from_rgb(2, 2, &[0; 5]).is_err());
    }

    #[test]
    fn textons_tell_the_two_textures_apart() {
        let img = two_textures(96, 48);
        for learning in [Learning::Competitive { rate_millis: 20 }, Learning::KMeans { iterations: 10 }] {
            let dict = Dictionary::learn(std::slice::from_ref(&img), 6, 6, 6, 3000, learning, 7).unwrap();
            let left = dict.histogram_full(&crop(&img, 0, 40));
            let right = dict.histogram_full(&crop(&img, 56, 40));
            assert!((left.iter().sum::<f32>() - 1.0).abs() < 1e-5);
            assert!(cosine(&left, &right) < 0.2, "{learning:?}: {left:?} vs {right:?}");
        }
    }

    #[test]
    fn random_sampling_approaches_full_sampling() {
        let img = two_textures(96, 48);
        let dict = Dictionary::learn(
            std::slice::from_ref(&img),
            8,
            6,
            6,
            2000,
            Learning::Competitive { rate_millis: 20 },
            1,
        )
        .unwrap();
        let full = dict.histogram_full(&img);
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let random = dict.histogram_random(&img, 4000, &mut rng);
        assert!(cosine(&full, &random) > 0.99, "{full:?} vs {random:?}");
    }

    #[test]
    fn nearest_by_norm_trick_matches_plain_distance() {
        let img = two_textures(40, 20);
        let dict = Dictionary::learn(
            std::slice::from_ref(&img),
            5,
            4,
            4,
            500,
            Learning::KMeans { iterations: 5 },
            2,
        )
        .unwrap();
        let norms = dict.norms();
        let mut buf = Vec::new();
        for (x, y) in [(0, 0), (17, 3), (30, 10), (36, 16)] {
            patch(&img, x, y, 4, 4, &mut buf);
            let plain = (0..dict.len())
                .min_by(|&a, &b| dist2(&dict.textons[a], &buf).total_cmp(&dist2(&dict.textons[b], &buf)))
                .unwrap();
            assert_eq!(dict.nearest(&buf, &norms), plain);
        }
    }
}
