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

    /// From 8-bit BGR (OpenCV's order), 3 bytes per pixel.
    pub fn from_bgr(width: usize, height: usize, bgr: &[u8]) -> YuvImage {
        let data = bgr
            .chunks_exact(3)
            .take(width * height)
            .map(|p| {
                let (b, g, r) = (p[0] as f32, p[1] as f32, p[2] as f32);
                let y = 0.299 * r + 0.587 * g + 0.114 * b;
                [y, 0.492 * (b - y) + 128.0, 0.877 * (r - y) + 128.0]
            })
            .collect();
        YuvImage { width, height, data }
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
        if images.is_empty() {
            return Err("no images to learn textons from".into());
        }
        if images.iter().any(|i| i.width < w || i.height < h) {
            return Err(format!("an image is smaller than the {w}x{h} texton"));
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut buf = Vec::new();
        let mut samples = Vec::with_capacity(images.len() * patches_per_image);
        for img in images {
            for _ in 0..patches_per_image {
                let x = rng.random_range(0..=img.width - w);
                let y = rng.random_range(0..=img.height - h);
                patch(img, x, y, w, h, &mut buf);
                samples.push(buf.clone());
            }
        }
        Dictionary::learn_from_patches(&samples, n, w, h, learning)
    }

    /// Random patches of `canvas`'s allowed positions, flattened as textons are.
    pub fn sample_patches(
        img: &YuvImage,
        mask: &PatchMask,
        (w, h): (usize, usize),
        count: usize,
        rng: &mut impl Rng,
    ) -> Vec<Vec<f32>> {
        let mut buf = Vec::new();
        if mask.positions.is_empty() {
            return Vec::new();
        }
        (0..count)
            .map(|_| {
                let p = mask.positions[rng.random_range(0..mask.positions.len())] as usize;
                patch(img, p % mask.cols, p / mask.cols, w, h, &mut buf);
                buf.clone()
            })
            .collect()
    }

    /// Learns `n` textons of `w x h` from patches (in the order given; the seed starts
    /// from the first `n`, which should come from one image, sec. 3.3.1).
    pub fn learn_from_patches(
        samples: &[Vec<f32>],
        n: usize,
        w: usize,
        h: usize,
        learning: Learning,
    ) -> Result<Dictionary, String> {
        let dim = w * h * 3;
        if samples.len() < n || n == 0 {
            return Err(format!("{} patches cannot make {n} textons", samples.len()));
        }
        if let Some(s) = samples.iter().find(|s| s.len() != dim) {
            return Err(format!("a patch has {} values, a {w}x{h} texton {dim}", s.len()));
        }
        let mut textons: Vec<Vec<f32>> = samples[..n].to_vec();
        let samples = &samples[n..];
        let nearest = |textons: &[Vec<f32>], x: &[f32]| {
            (0..textons.len())
                .min_by(|&a, &b| dist2(&textons[a], x).total_cmp(&dist2(&textons[b], x)))
                .unwrap_or(0)
        };
        match learning {
            Learning::Competitive { rate_millis } => {
                let rate = rate_millis as f32 / 1000.0;
                for x in samples {
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
                    for x in samples {
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

    /// The nearest-texton search laid out for SIMD.
    pub fn classifier(&self) -> Classifier {
        Classifier::new(self)
    }

    /// Histogram over every allowed patch position (full sampling; every position when
    /// `mask` is `None`), normalised to sum 1.
    pub fn histogram_full(&self, img: &YuvImage, mask: Option<&PatchMask>) -> Vec<f32> {
        let c = self.classifier();
        let (w, h) = (self.w, self.h);
        if img.width < w || img.height < h || self.is_empty() {
            return vec![0.0; self.len()];
        }
        let counts = (0..=img.height - h)
            .into_par_iter()
            .fold(
                || (vec![0u64; self.len()], Vec::new()),
                |(mut counts, mut buf), y| {
                    c.count_row(img, mask, y, &mut counts, &mut buf);
                    (counts, buf)
                },
            )
            .map(|(counts, _)| counts)
            .reduce(|| vec![0u64; self.len()], |a, b| a.iter().zip(&b).map(|(x, y)| x + y).collect());
        normalise(&counts)
    }

    /// [`Self::histogram_full`] on the calling thread (when frames are already spread
    /// over threads).
    pub fn histogram_full_serial(&self, img: &YuvImage, mask: Option<&PatchMask>) -> Vec<f32> {
        let c = self.classifier();
        let (w, h) = (self.w, self.h);
        if img.width < w || img.height < h || self.is_empty() {
            return vec![0.0; self.len()];
        }
        let mut counts = vec![0u64; self.len()];
        let mut buf = Vec::new();
        for y in 0..=img.height - h {
            c.count_row(img, mask, y, &mut counts, &mut buf);
        }
        normalise(&counts)
    }

    /// Histogram of `samples` random allowed patch positions (random sampling), normalised.
    pub fn histogram_random(
        &self,
        img: &YuvImage,
        mask: Option<&PatchMask>,
        samples: usize,
        rng: &mut impl Rng,
    ) -> Vec<f32> {
        self.classifier().histogram_random(img, mask, samples, rng)
    }
}

/// Lanes per SIMD group: 8 f32 (two SSE or one AVX register).
const LANES: usize = 8;

/// Nearest-texton search, transposed so that one patch value updates the scores of 8
/// textons at once: the compiler vectorises fixed-size lane arrays reliably, while a dot
/// product's sum over the patch does not vectorise without reordering floats. Scores are
/// `|t|^2 - 2 p.t`, the squared distance without the patch's own norm.
#[derive(Clone, Debug)]
pub struct Classifier {
    w: usize,
    h: usize,
    n: usize,
    dim: usize,
    /// `weights[g * dim + k][l] = -2 t[g * 8 + l][k]`.
    weights: Vec<[f32; LANES]>,
    /// `|t|^2` per lane; padding lanes get +inf so they never win.
    norms: Vec<[f32; LANES]>,
}

impl Classifier {
    fn new(dict: &Dictionary) -> Classifier {
        let (n, dim) = (dict.len(), dict.w * dict.h * 3);
        let groups = n.div_ceil(LANES);
        let mut weights = vec![[0.0f32; LANES]; groups * dim];
        let mut norms = vec![[f32::INFINITY; LANES]; groups];
        for (t, texton) in dict.textons.iter().enumerate() {
            let (g, l) = (t / LANES, t % LANES);
            norms[g][l] = texton.iter().map(|v| v * v).sum();
            for (k, v) in texton.iter().enumerate() {
                weights[g * dim + k][l] = -2.0 * v;
            }
        }
        Classifier { w: dict.w, h: dict.h, n, dim, weights, norms }
    }

    /// Index of the nearest texton to the patch with top-left corner `(x, y)`.
    #[inline]
    pub fn nearest(&self, img: &YuvImage, x: usize, y: usize) -> usize {
        let mut best = (f32::INFINITY, 0);
        for (g, norm) in self.norms.iter().enumerate() {
            let mut acc = *norm;
            let weights = &self.weights[g * self.dim..(g + 1) * self.dim];
            let mut k = 0;
            for dy in 0..self.h {
                let row = (y + dy) * img.width + x;
                for px in &img.data[row..row + self.w] {
                    for v in px {
                        let wk = &weights[k];
                        for l in 0..LANES {
                            acc[l] += wk[l] * v;
                        }
                        k += 1;
                    }
                }
            }
            for (l, score) in acc.iter().enumerate() {
                if *score < best.0 {
                    best = (*score, g * LANES + l);
                }
            }
        }
        best.1.min(self.n.saturating_sub(1))
    }

    fn tables(&self) -> Tables<'_> {
        Tables { weights: &self.weights, norms: &self.norms, dim: self.dim, n: self.n }
    }

    /// Normalised histogram of the nearest textons of `patches` (consecutive patches of
    /// `w * h` pixels of Y, U, V, laid out as textons are: the patches
    /// [`super::derotate::Preprocessor::sample`] gathers); all zeros when there are none.
    pub fn histogram_of_patches(&self, patches: &[f32]) -> Vec<f32> {
        let mut counts = vec![0u64; self.n];
        if self.n > 0 && self.dim > 0 {
            self.tables().count(patches, &mut counts);
        }
        normalise(&counts)
    }

    /// The same for patches of B, G, R block sums
    /// ([`super::derotate::Preprocessor::sample_raw`]) whose normalised Y, U, V are
    /// `gain * yuv_from_bgr * sums + offset` per pixel. The distance to texton `t` is
    /// `|t|^2 - 2 t . (gain M q + c)`: the map moves onto the textons, once per frame
    /// (`scratch` keeps the moved ones), and the patches are searched as they were read.
    pub fn histogram_of_raw(
        &self,
        sums: &[f32],
        gain: f32,
        offset: [f32; 3],
        yuv_from_bgr: &[[f32; 3]; 3],
        scratch: &mut (Vec<[f32; LANES]>, Vec<[f32; LANES]>),
    ) -> Vec<f32> {
        let mut counts = vec![0u64; self.n];
        if self.n == 0 || self.dim == 0 || !self.dim.is_multiple_of(3) {
            return normalise(&counts);
        }
        let (weights, norms) = scratch;
        weights.clear();
        weights.resize(self.weights.len(), [0.0; LANES]);
        norms.clone_from(&self.norms);
        for g in 0..self.norms.len() {
            for p in 0..self.dim / 3 {
                let k = g * self.dim + p * 3;
                // -2 t per channel (Y, U, V) of this pixel, 8 textons at once.
                let a = [self.weights[k], self.weights[k + 1], self.weights[k + 2]];
                for l in 0..LANES {
                    for (j, w) in weights[k..k + 3].iter_mut().enumerate() {
                        w[l] = gain * (0..3).map(|c| a[c][l] * yuv_from_bgr[c][j]).sum::<f32>();
                    }
                    norms[g][l] += (0..3).map(|c| a[c][l] * offset[c]).sum::<f32>();
                }
            }
        }
        Tables { weights, norms, dim: self.dim, n: self.n }.count(sums, &mut counts);
        normalise(&counts)
    }

    /// Appends the patch with top-left corner `(x, y)` to `buf`, laid out as textons are.
    #[inline]
    fn gather(&self, img: &YuvImage, x: usize, y: usize, buf: &mut Vec<f32>) {
        for dy in 0..self.h {
            let row = (y + dy) * img.width + x;
            buf.extend(img.data[row..row + self.w].iter().flatten());
        }
    }

    /// Adds the nearest textons of the allowed patches whose top row is `y`. The row's
    /// patches are gathered first and searched by [`Tables::count`], the AVX2/FMA kernel
    /// the flight uses: searching each patch in place by [`Classifier::nearest`] leaves
    /// vectorising to the compiler, which unoptimised (test) builds do not do.
    fn count_row(
        &self,
        img: &YuvImage,
        mask: Option<&PatchMask>,
        y: usize,
        counts: &mut [u64],
        buf: &mut Vec<f32>,
    ) {
        buf.clear();
        for x in 0..=img.width - self.w {
            if mask.is_none_or(|m| m.allows(x, y)) {
                self.gather(img, x, y, buf);
            }
        }
        self.tables().count(buf, counts);
    }

    /// Histogram of `samples` random allowed patch positions, normalised.
    pub fn histogram_random(
        &self,
        img: &YuvImage,
        mask: Option<&PatchMask>,
        samples: usize,
        rng: &mut impl Rng,
    ) -> Vec<f32> {
        let mut counts = vec![0u64; self.n];
        if img.width < self.w || img.height < self.h || self.n == 0 {
            return vec![0.0; self.n];
        }
        let mut buf = Vec::with_capacity(samples * self.dim);
        match mask {
            Some(m) if m.positions.is_empty() => return vec![0.0; self.n],
            Some(m) => {
                for _ in 0..samples {
                    let p = m.positions[rng.random_range(0..m.positions.len())];
                    self.gather(img, p as usize % m.cols, p as usize / m.cols, &mut buf);
                }
            }
            None => {
                for _ in 0..samples {
                    let x = rng.random_range(0..=img.width - self.w);
                    let y = rng.random_range(0..=img.height - self.h);
                    self.gather(img, x, y, &mut buf);
                }
            }
        }
        self.tables().count(&buf, &mut counts);
        normalise(&counts)
    }
}

/// Texton weights laid out for the search (`weights[g * dim + k][l] = -2 t[g * 8 + l][k]`,
/// `norms[g][l] = |t|^2`, +inf in padding lanes), the dictionary's own or moved for raw
/// patches ([`Classifier::histogram_of_raw`]).
struct Tables<'a> {
    weights: &'a [[f32; LANES]],
    norms: &'a [[f32; LANES]],
    dim: usize,
    n: usize,
}

impl Tables<'_> {
    /// Adds the nearest texton of every patch (`dim` values each) to `counts`.
    fn count(&self, patches: &[f32], counts: &mut [u64]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX2 and FMA (checked just above).
            return unsafe { self.count_avx2(patches, counts) };
        }
        self.count_impl::<false>(patches, counts)
    }

    /// The same compiled for AVX2 and FMA: one fused multiply-add per 8 textons and patch
    /// value instead of two SSE multiplies and two adds. Chosen at run time so one binary
    /// runs on any x86-64 (and on ARM through the portable path).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn count_avx2(&self, patches: &[f32], counts: &mut [u64]) {
        match self.norms.len() {
            1 => self.count_avx2_groups::<1>(patches, counts),
            2 => self.count_avx2_groups::<2>(patches, counts),
            3 => self.count_avx2_groups::<3>(patches, counts),
            4 => self.count_avx2_groups::<4>(patches, counts),
            _ => self.count_impl::<true>(patches, counts),
        }
    }

    /// [`Self::nearest_groups`] written in AVX2 intrinsics, the same operations in the
    /// same order (so the same textons win): its speed then does not hang on the
    /// auto-vectoriser, which unoptimised builds (the tests') do not run.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn count_avx2_groups<const G: usize>(&self, patches: &[f32], counts: &mut [u64]) {
        use std::arch::x86_64::{
            _mm256_add_ps, _mm256_fmadd_ps, _mm256_loadu_ps, _mm256_set1_ps, _mm256_setzero_ps,
            _mm256_storeu_ps,
        };
        let dim = self.dim;
        assert!(self.weights.len() >= G * dim && self.norms.len() == G);
        let last = self.n.saturating_sub(1);
        for p in patches.chunks_exact(dim) {
            let mut even = [_mm256_setzero_ps(); G];
            let mut odd = [_mm256_setzero_ps(); G];
            let mut k = 0;
            while k + 1 < dim {
                let (v0, v1) = (_mm256_set1_ps(p[k]), _mm256_set1_ps(p[k + 1]));
                for g in 0..G {
                    // SAFETY: g * dim + k + 1 < G * dim <= weights.len() (asserted above),
                    // and each entry is 8 contiguous f32.
                    let (w0, w1) = unsafe {
                        let w = self.weights.as_ptr().add(g * dim + k) as *const f32;
                        (_mm256_loadu_ps(w), _mm256_loadu_ps(w.add(LANES)))
                    };
                    even[g] = _mm256_fmadd_ps(w0, v0, even[g]);
                    odd[g] = _mm256_fmadd_ps(w1, v1, odd[g]);
                }
                k += 2;
            }
            if k < dim {
                let v = _mm256_set1_ps(p[k]);
                for (g, e) in even.iter_mut().enumerate() {
                    // SAFETY: as above, g * dim + k < G * dim.
                    let w = unsafe { _mm256_loadu_ps(self.weights.as_ptr().add(g * dim + k) as *const f32) };
                    *e = _mm256_fmadd_ps(w, v, *e);
                }
            }
            let mut best = (f32::INFINITY, 0);
            for g in 0..G {
                let mut scores = [0.0f32; LANES];
                // SAFETY: norms[g] and scores are 8 contiguous f32 each.
                unsafe {
                    let norm = _mm256_loadu_ps(self.norms[g].as_ptr());
                    _mm256_storeu_ps(
                        scores.as_mut_ptr(),
                        _mm256_add_ps(_mm256_add_ps(norm, even[g]), odd[g]),
                    );
                }
                for (l, score) in scores.iter().enumerate() {
                    if *score < best.0 {
                        best = (*score, g * LANES + l);
                    }
                }
            }
            counts[best.1.min(last)] += 1;
        }
    }

    #[inline(always)]
    fn count_impl<const FMA: bool>(&self, patches: &[f32], counts: &mut [u64]) {
        for p in patches.chunks_exact(self.dim) {
            counts[self.nearest::<FMA>(p)] += 1;
        }
    }

    #[inline(always)]
    fn nearest<const FMA: bool>(&self, patch: &[f32]) -> usize {
        // The group count as a constant, so the sums stay in registers (a run-time count
        // kept them on the stack: 0.78 us per patch instead of 0.13).
        match self.norms.len() {
            1 => self.nearest_groups::<FMA, 1>(patch),
            2 => self.nearest_groups::<FMA, 2>(patch),
            3 => self.nearest_groups::<FMA, 3>(patch),
            4 => self.nearest_groups::<FMA, 4>(patch),
            _ => self.nearest_by_group::<FMA>(patch),
        }
    }

    /// `G` groups at once, even and odd patch values in separate sums: 2 x `G`
    /// independent chains of multiply-adds instead of one chain per group, which waits on
    /// each add's latency.
    #[inline(always)]
    fn nearest_groups<const FMA: bool, const G: usize>(&self, patch: &[f32]) -> usize {
        let mut even = [[0.0f32; LANES]; G];
        let mut odd = [[0.0f32; LANES]; G];
        let fma = |acc: &mut [f32; LANES], w: &[f32; LANES], v: f32| {
            for l in 0..LANES {
                acc[l] = if FMA { w[l].mul_add(v, acc[l]) } else { acc[l] + w[l] * v };
            }
        };
        let mut k = 0;
        while k + 1 < self.dim {
            let (v0, v1) = (patch[k], patch[k + 1]);
            for (g, (e, o)) in even.iter_mut().zip(odd.iter_mut()).enumerate() {
                fma(e, &self.weights[g * self.dim + k], v0);
                fma(o, &self.weights[g * self.dim + k + 1], v1);
            }
            k += 2;
        }
        if k < self.dim {
            for (g, e) in even.iter_mut().enumerate() {
                fma(e, &self.weights[g * self.dim + k], patch[k]);
            }
        }
        let mut best = (f32::INFINITY, 0);
        for (g, (norm, (e, o))) in self.norms.iter().zip(even.iter().zip(&odd)).enumerate() {
            for l in 0..LANES {
                let score = norm[l] + e[l] + o[l];
                if score < best.0 {
                    best = (score, g * LANES + l);
                }
            }
        }
        best.1.min(self.n.saturating_sub(1))
    }

    /// [`Self::nearest_groups`] for dictionaries of more than 32 textons: one group after
    /// the other.
    #[inline(always)]
    fn nearest_by_group<const FMA: bool>(&self, patch: &[f32]) -> usize {
        let mut best = (f32::INFINITY, 0);
        for (g, norm) in self.norms.iter().enumerate() {
            let mut acc = *norm;
            let weights = &self.weights[g * self.dim..(g + 1) * self.dim];
            for (wk, v) in weights.iter().zip(patch) {
                for l in 0..LANES {
                    acc[l] = if FMA { wk[l].mul_add(*v, acc[l]) } else { acc[l] + wk[l] * v };
                }
            }
            for (l, score) in acc.iter().enumerate() {
                if *score < best.0 {
                    best = (*score, g * LANES + l);
                }
            }
        }
        best.1.min(self.n.saturating_sub(1))
    }
}

/// Which patch positions (top-left corners) a histogram may use: those whose whole patch
/// lies on valid pixels (after derotation, parts of the canvas have no source pixel).
#[derive(Clone, Debug)]
pub struct PatchMask {
    cols: usize,
    allowed: Vec<bool>,
    positions: Vec<u32>,
}

impl PatchMask {
    /// From a per-pixel validity map of a `width x height` image and a `w x h` patch.
    pub fn from_valid(width: usize, height: usize, valid: &[bool], w: usize, h: usize) -> PatchMask {
        assert_eq!(valid.len(), width * height);
        if width < w || height < h {
            return PatchMask { cols: 0, allowed: Vec::new(), positions: Vec::new() };
        }
        // Integral image of invalid pixels: a patch is allowed when its sum is 0.
        let iw = width + 1;
        let mut integral = vec![0u32; iw * (height + 1)];
        for y in 0..height {
            let mut row = 0u32;
            for x in 0..width {
                row += u32::from(!valid[y * width + x]);
                integral[(y + 1) * iw + x + 1] = integral[y * iw + x + 1] + row;
            }
        }
        let (cols, rows) = (width - w + 1, height - h + 1);
        let mut allowed = vec![false; cols * rows];
        let mut positions = Vec::new();
        for y in 0..rows {
            for x in 0..cols {
                let s = integral[(y + h) * iw + x + w] + integral[y * iw + x]
                    - integral[y * iw + x + w]
                    - integral[(y + h) * iw + x];
                if s == 0 {
                    allowed[y * cols + x] = true;
                    positions.push((y * cols + x) as u32);
                }
            }
        }
        PatchMask { cols, allowed, positions }
    }

    #[inline]
    pub fn allows(&self, x: usize, y: usize) -> bool {
        self.allowed.get(y * self.cols + x).copied().unwrap_or(false)
    }

    /// Number of allowed positions.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
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
            let left = dict.histogram_full(&crop(&img, 0, 40), None);
            let right = dict.histogram_full(&crop(&img, 56, 40), None);
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
        let full = dict.histogram_full(&img, None);
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let random = dict.histogram_random(&img, None, 4000, &mut rng);
        assert!(cosine(&full, &random) > 0.99, "{full:?} vs {random:?}");
    }

    #[test]
    fn patch_mask_allows_only_fully_valid_patches() {
        // 10x8 image, invalid pixel at (5, 4); 3x3 patches.
        let mut valid = vec![true; 80];
        valid[4 * 10 + 5] = false;
        let m = PatchMask::from_valid(10, 8, &valid, 3, 3);
        for y in 0..6 {
            for x in 0..8 {
                let covers = (x..x + 3).contains(&5) && (y..y + 3).contains(&4);
                assert_eq!(m.allows(x, y), !covers, "{x},{y}");
            }
        }
        assert_eq!(m.len(), 48 - 9);
        let img = two_textures(10, 8);
        let dict = Dictionary { w: 3, h: 3, textons: vec![vec![0.0; 27], vec![255.0; 27]] };
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let h = dict.histogram_random(&img, Some(&m), 50, &mut rng);
        assert!((h.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        let none = PatchMask::from_valid(10, 8, &[false; 80], 3, 3);
        assert!(none.is_empty());
        assert_eq!(dict.histogram_random(&img, Some(&none), 50, &mut rng), vec![0.0, 0.0]);
    }

    /// A 40x20 image of two textures and 5 textons of 4x4 learned from it.
    fn two_texture_dictionary() -> (YuvImage, Dictionary) {
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
        (img, dict)
    }

    #[test]
    fn nearest_by_norm_trick_matches_plain_distance() {
        let (img, dict) = two_texture_dictionary();
        let c = dict.classifier();
        let mut buf = Vec::new();
        for y in 0..=16 {
            for x in 0..=36 {
                patch(&img, x, y, 4, 4, &mut buf);
                let d: Vec<f32> = dict.textons.iter().map(|t| dist2(t, &buf)).collect();
                let plain = (0..dict.len()).min_by(|&a, &b| d[a].total_cmp(&d[b])).unwrap();
                // Ties within float rounding may go either way.
                assert!(d[c.nearest(&img, x, y)] <= d[plain] * (1.0 + 1e-4) + 1e-2, "at {x},{y}");
                // The flat path (AVX2 and FMA where the CPU has them) agrees.
                let mut counts = vec![0u64; dict.len()];
                c.tables().count(&buf, &mut counts);
                let flat = counts.iter().position(|n| *n > 0).unwrap();
                assert!(d[flat] <= d[plain] * (1.0 + 1e-4) + 1e-2, "flat at {x},{y}");
                assert!(d[c.tables().nearest::<false>(&buf)] <= d[plain] * (1.0 + 1e-4) + 1e-2);
                assert!(d[c.tables().nearest_by_group::<false>(&buf)] <= d[plain] * (1.0 + 1e-4) + 1e-2);
            }
        }
    }

    /// The AVX2 kernel (1-4 groups of 8 textons) and the portable one with fused
    /// multiply-adds do the same operations in the same order: the same texton wins for
    /// every patch, for every group count and an odd patch size.
    #[test]
    fn the_avx2_kernel_picks_the_textons_the_portable_kernel_picks() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for n in [3, 8, 12, 20, 27, 32, 40] {
            let dim = 3 * 3 * 3;
            let textons: Vec<Vec<f32>> =
                (0..n).map(|_| (0..dim).map(|_| rng.random_range(0.0..255.0)).collect()).collect();
            let c = Dictionary { w: 3, h: 3, textons }.classifier();
            let patches: Vec<f32> = (0..500 * dim).map(|_| rng.random_range(0.0..255.0)).collect();
            let (mut fast, mut portable) = (vec![0u64; n], vec![0u64; n]);
            c.tables().count(&patches, &mut fast);
            c.tables().count_impl::<true>(&patches, &mut portable);
            assert_eq!(fast, portable, "{n} textons");
            assert_eq!(fast.iter().sum::<u64>(), 500);
        }
    }

    /// The whole-image histogram (rows gathered, then searched by the flat kernel) counts
    /// every allowed patch once, as the per-patch search does; a mask drops exactly the
    /// patches it forbids.
    #[test]
    fn full_histograms_count_every_allowed_patch_as_the_per_patch_search_does() {
        let (img, dict) = two_texture_dictionary();
        let c = dict.classifier();
        let mut valid = vec![true; 40 * 20];
        for i in (0..valid.len()).step_by(37) {
            valid[i] = false;
        }
        let mask = PatchMask::from_valid(40, 20, &valid, 4, 4);
        for m in [None, Some(&mask)] {
            let mut counts = vec![0u64; dict.len()];
            for y in 0..=16 {
                for x in 0..=36 {
                    if m.is_none_or(|m| m.allows(x, y)) {
                        counts[c.nearest(&img, x, y)] += 1;
                    }
                }
            }
            let total = counts.iter().sum::<u64>() as f32;
            assert_eq!(total as usize, m.map_or(37 * 17, |m| m.len()));
            let want: Vec<f32> = counts.iter().map(|n| *n as f32 / total).collect();
            for got in [dict.histogram_full(&img, m), dict.histogram_full_serial(&img, m)] {
                // Float ties may fall either way: at most a patch or two of 629.
                let l1: f32 = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).sum();
                assert!(l1 <= 4.0 / total, "{got:?} vs {want:?}");
            }
        }
    }
}
