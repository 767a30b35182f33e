//! Frame preparation for the texton histograms: downscale to the working resolution and,
//! beyond the seed (its future work, indoor seed ch. 5), derotate by the camera's attitude.
//!
//! Derotation warps the frame to a virtual camera at the same place that looks straight
//! down with image right = east and image up = north. For a flat floor that is the pure
//! rotation homography `H = K_v R_v^T R_c K^-1` (`R_c` "local <- camera" of the real
//! camera, `R_v` of the virtual one). The histogram is then taken over a disk centred on the
//! nadir, so every frame describes the same footprint whatever the heading, roll and pitch;
//! textons are not rotation invariant, and without this a turned vehicle sees other
//! textons on the same floor. Parts of the disk the camera did not see are masked out.
//!
//! With a reference height (`indoor.height_ref_m`, kept in the model) the virtual camera's
//! focal length is also scaled by `height / height_ref`, so the floor appears at the scale
//! it has from the reference height whatever the height: textons are not scale invariant
//! either. Below the reference the camera sees only the middle of the disk (the rest is
//! masked out), above it the disk is a magnified middle of the frame. This is what lets
//! the vehicle localise while climbing or descending through heights the model was not
//! trained at.
//!
//! In flight nothing of this is done to whole images (issue #20: preparing a canvas cost
//! several times the rest of the frame): [`Preprocessor::sample`] draws the histogram's
//! patch positions on the canvas and reads only their pixels from the camera frame through
//! the homography, each canvas pixel the mean of the camera pixels it covers, then
//! normalises the gathered values. Training builds whole canvases ([`Preprocessor::prepare`])
//! with the same per-pixel rule, so both see the same floor.

use mavloc_geometry::{Intrinsics, Rot3};
use nalgebra::{Matrix3, Vector3};
use opencv::core::Mat;
use opencv::prelude::*;

use super::textons::{PatchMask, YuvImage};

// Moved to `crate::imaging` (the sim camera uses it too); this path is kept for callers.
pub use crate::imaging::bgr_from_rgb;

/// A prepared frame: the image to take patches from and where patches may be taken.
pub struct Canvas {
    pub img: YuvImage,
    pub mask: PatchMask,
}

/// Prepares frames of one camera.
#[derive(Clone, Debug)]
pub struct Preprocessor {
    /// The camera's intrinsics at its own resolution.
    pub camera: Intrinsics,
    /// The intrinsics at the working resolution.
    pub work: Intrinsics,
    pub derotate: bool,
    /// Remove brightness and contrast: Y to a fixed mean and SD over the valid pixels, U
    /// and V scaled about neutral by the same factor (an affine change of RGB is undone).
    pub normalise: bool,
    /// Rescale to the floor's scale from this camera height (m); `None`: no rescaling.
    pub height_ref: Option<f64>,
    patch: (usize, usize),
}

/// The rescaling is bounded: below a quarter of the reference height too little of the
/// disk is seen to describe the place, above four times it the magnified middle is blur.
const SCALE_RANGE: (f64, f64) = (0.25, 4.0);

/// Intrinsics of the same camera at `scale` times the resolution (pixel centres kept).
pub fn scaled(k: &Intrinsics, scale: f64) -> Intrinsics {
    Intrinsics {
        width: ((k.width as f64 * scale).round() as u32).max(1),
        height: ((k.height as f64 * scale).round() as u32).max(1),
        fx: k.fx * scale,
        fy: k.fy * scale,
        cx: (k.cx + 0.5) * scale - 0.5,
        cy: (k.cy + 0.5) * scale - 0.5,
    }
}

/// "local <- virtual camera": optical axis down, image x east, image y south.
fn virtual_camera() -> Matrix3<f64> {
    Matrix3::new(
        0.0, -1.0, 0.0, //
        1.0, 0.0, 0.0, //
        0.0, 0.0, 1.0,
    )
}

/// The homography from pixels of a camera with intrinsics `k` and rotation "local <-
/// camera (OpenCV axes)" to a virtual camera at the same place looking straight down,
/// image up north, with focal length `focal` and its principal point at (`centre`,
/// `centre`): the nadir. Exact for points on a level floor.
pub fn nadir_homography(k: &Intrinsics, local_from_camera: &Rot3, focal: f64, centre: f64) -> Matrix3<f64> {
    let kc = Matrix3::new(k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0);
    let kv = Matrix3::new(focal, 0.0, centre, 0.0, focal, centre, 0.0, 0.0, 1.0);
    let kc_inv = kc.try_inverse().expect("intrinsics with non-zero focal lengths are invertible");
    kv * virtual_camera().transpose() * local_from_camera.matrix() * kc_inv
}

impl Preprocessor {
    /// `work_width`: frames are downscaled to this width (never upscaled).
    pub fn new(camera: Intrinsics, work_width: u32, derotate: bool, patch: (usize, usize)) -> Preprocessor {
        let scale = (work_width as f64 / camera.width as f64).min(1.0);
        let work = scaled(&camera, scale);
        Preprocessor { camera, work, derotate, normalise: false, height_ref: None, patch }
    }

    /// Side of the derotated canvas: the largest disk the level camera sees whole.
    pub fn side(&self) -> usize {
        self.work.width.min(self.work.height) as usize
    }

    /// The virtual camera's focal length over the real one's for a camera `height` above
    /// the floor: 1 without a reference height (or a usable height).
    pub fn scale(&self, height: Option<f64>) -> f64 {
        match (self.height_ref, height) {
            (Some(r), Some(h)) if r > 0.0 && h.is_finite() && h > 0.0 => {
                (h / r).clamp(SCALE_RANGE.0, SCALE_RANGE.1)
            }
            _ => 1.0,
        }
    }

    /// The homography from working-resolution pixels to canvas pixels for a camera with
    /// rotation "local <- camera (OpenCV axes)", its virtual focal length `scale` times the
    /// real one ([`Preprocessor::scale`]).
    pub fn homography(&self, local_from_camera: &Rot3, scale: f64) -> Matrix3<f64> {
        let c = (self.side() as f64 - 1.0) / 2.0;
        // At scale 1 one canvas pixel is one working pixel at the nadir.
        nadir_homography(&self.work, local_from_camera, self.work.fx * scale, c)
    }

    /// Ground offset (north, east) per metre of height of a canvas pixel from the nadir.
    pub fn canvas_offset(&self, u: f64, v: f64) -> (f64, f64) {
        let c = (self.side() as f64 - 1.0) / 2.0;
        (-(v - c) / self.work.fx, (u - c) / self.work.fx)
    }

    /// How canvas pixels of one frame are found in the camera frame: without an attitude,
    /// or with derotation off, the canvas is the whole frame at the working resolution
    /// (as the seed takes it); otherwise the derotated, rescaled disk.
    fn view<'a>(
        &self,
        bgr: &'a Mat,
        attitude: Option<&Rot3>,
        height: Option<f64>,
    ) -> opencv::Result<View<'a>> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if (bgr.cols() as usize, bgr.rows() as usize) != (w, h) || bgr.typ() != opencv::core::CV_8UC3 {
            return Err(opencv::Error::new(
                opencv::core::StsBadSize,
                format!(
                    "frame is {}x{} of type {}, the camera gives {w}x{h} 8-bit BGR",
                    bgr.cols(),
                    bgr.rows(),
                    bgr.typ()
                ),
            ));
        }
        if !bgr.is_continuous() {
            return Err(opencv::Error::new(
                opencv::core::StsBadArg,
                "frame is a view into a larger image".to_string(),
            ));
        }
        // Working pixel <- camera pixel (pixel centres kept, as `scaled`).
        let s = self.work.width as f64 / self.camera.width as f64;
        let work_from_camera = Matrix3::new(s, 0.0, 0.5 * s - 0.5, 0.0, s, 0.5 * s - 0.5, 0.0, 0.0, 1.0);
        let (canvas_from_camera, cols, rows, disk, scale) = match attitude.filter(|_| self.derotate) {
            None => (work_from_camera, self.work.width as usize, self.work.height as usize, None, 1.0),
            Some(r) => {
                let n = self.side();
                let c = (n as f64 - 1.0) / 2.0;
                let scale = self.scale(height);
                let hm = self.homography(r, scale) * work_from_camera;
                (hm, n, n, Some((c as f32, (n as f32 / 2.0).powi(2))), scale)
            }
        };
        // Camera pixels one canvas pixel covers (across), at least 1: each canvas pixel is
        // their mean, so a frame from below the reference height, shrunk to the reference
        // scale, is averaged as a downscale would be and not point-sampled (measured on a
        // flight at 0.5 m with a 1 m reference: 0.22 m RMS point-sampled, 0.07 m averaged).
        let block = ((1.0 / (s * scale)).round() as usize).clamp(1, w.min(h));
        let g = canvas_from_camera.try_inverse().ok_or_else(|| {
            opencv::Error::new(
                opencv::core::StsBadArg,
                "the camera attitude gives a singular homography".to_string(),
            )
        })?;
        Ok(View {
            bgr: bgr.data_bytes()?,
            width: w,
            height: h,
            g: std::array::from_fn(|i| g[(i / 3, i % 3)] as f32),
            cols,
            rows,
            disk,
            block,
            block_scale: 1.0 / (block * block) as f32,
        })
    }

    /// Prepares a BGR frame at the camera's resolution as a whole canvas (training, map
    /// evaluation). `attitude` is the camera's rotation "local <- camera (OpenCV axes)";
    /// without it, or with derotation off, the whole frame at the working resolution is
    /// used as the seed does. `height`: the camera's height above the floor, for the
    /// rescaling to the reference height (if there is one). Every canvas pixel is found as
    /// [`Preprocessor::sample`] finds the pixels of its patches, so a model trained on
    /// canvases matches the patches sampled in flight.
    pub fn prepare(&self, bgr: &Mat, attitude: Option<&Rot3>, height: Option<f64>) -> opencv::Result<Canvas> {
        let view = self.view(bgr, attitude, height)?;
        let (cols, rows) = (view.cols, view.rows);
        let mut data = vec![[0.0f32; 3]; cols * rows];
        let mut valid = vec![false; cols * rows];
        for v in 0..rows {
            for u in 0..cols {
                if let Some(p) = view.pixel(u as f32, v as f32).filter(|_| view.in_disk(u as f32, v as f32)) {
                    data[v * cols + u] = p;
                    valid[v * cols + u] = true;
                }
            }
        }
        let mut img = YuvImage { width: cols, height: rows, data };
        if self.normalise {
            normalise(&mut img, &valid);
        }
        let (pw, ph) = self.patch;
        let mask = PatchMask::from_valid(cols, rows, &valid, pw, ph);
        Ok(Canvas { img, mask })
    }

    /// The flight path: `count` patches at random allowed positions of the canvas
    /// ([`Preprocessor::prepare`]'s, uniformly, as a random-sampling histogram draws them),
    /// gathered from the camera frame directly into `out` (`w * h` pixels of Y, U, V per
    /// patch, as textons are laid out), normalised over the gathered pixels. Only the
    /// pixels the histogram uses are derotated, converted and normalised: no canvas, no
    /// full-frame copy (issue #20: preparing whole canvases cost several times the rest of
    /// the frame). Returns the number of patches (fewer when the canvas has too few allowed
    /// positions, e.g. a camera tilted far from the floor).
    pub fn sample(
        &self,
        bgr: &Mat,
        attitude: Option<&Rot3>,
        height: Option<f64>,
        count: usize,
        rng: &mut impl rand::Rng,
        out: &mut Vec<f32>,
    ) -> opencv::Result<usize> {
        let view = self.view(bgr, attitude, height)?;
        let at = self.positions(&view, count, rng);
        let len = self.patch.0 * self.patch.1 * 3;
        out.clear();
        out.resize(at.len() * len, 0.0);
        for (&(x, y), patch) in at.iter().zip(out.chunks_exact_mut(len)) {
            view.gather(x as usize, y as usize, self.patch.0, self.patch.1, patch);
        }
        if self.normalise {
            normalise_values(out);
        }
        Ok(at.len())
    }

    /// [`Preprocessor::sample`] for flight: the same patches (same positions for the same
    /// random numbers), kept as the camera pixels' B, G, R sums with the affine map that
    /// makes them normalised Y, U, V (`yuv = gain * YUV_FROM_BGR * sums + offset`, per
    /// pixel). Colour conversion and normalisation are both affine, so the texton search
    /// applies them to its 20 textons once per frame
    /// ([`super::textons::Classifier::histogram_of_raw`]) instead of to 14 400 pixels.
    pub fn sample_raw(
        &self,
        bgr: &Mat,
        attitude: Option<&Rot3>,
        height: Option<f64>,
        count: usize,
        rng: &mut impl rand::Rng,
        out: &mut RawPatches,
    ) -> opencv::Result<usize> {
        let view = self.view(bgr, attitude, height)?;
        let at = self.positions(&view, count, rng);
        let len = self.patch.0 * self.patch.1 * 3;
        out.values.clear();
        out.values.resize(at.len() * len, 0.0);
        let (mut sum, mut sum2) = (0.0f64, 0.0f64);
        for (&(x, y), patch) in at.iter().zip(out.values.chunks_exact_mut(len)) {
            let (s, s2) = view.gather_sums(x as usize, y as usize, self.patch.0, self.patch.1, patch);
            sum += s;
            sum2 += s2;
        }
        // Y of a pixel is `block_scale * (YUV_FROM_BGR[0] . sums)`.
        let scale = view.block_scale;
        let n = at.len() * self.patch.0 * self.patch.1;
        let (sum, sum2) = (sum * scale as f64, sum2 * (scale as f64).powi(2));
        (out.gain, out.offset) = match standardising(sum, sum2, n).filter(|_| self.normalise) {
            Some((mean, g)) => (g * scale, [NORMAL_MEAN - g * mean, 128.0, 128.0]),
            None => (scale, [0.0, 128.0, 128.0]),
        };
        Ok(at.len())
    }

    /// Up to `count` patch positions (top-left corners), uniform over those the view
    /// allows: rejection sampling, bounded for a view with almost none.
    fn positions(&self, view: &View, count: usize, rng: &mut impl rand::Rng) -> Vec<(u16, u16)> {
        let (pw, ph) = self.patch;
        let mut at = Vec::with_capacity(count);
        if view.cols < pw || view.rows < ph || count == 0 {
            return at;
        }
        let (xmax, ymax) = (view.cols - pw, view.rows - ph);
        let mut tries = 0;
        while at.len() < count && tries < count * MAX_TRIES_PER_SAMPLE {
            tries += 1;
            let x = rng.random_range(0..=xmax);
            let y = rng.random_range(0..=ymax);
            if view.patch_allowed(x, y, pw, ph) {
                at.push((x as u16, y as u16));
            }
        }
        at
    }
}

/// Patches of a flight frame as gathered by [`Preprocessor::sample_raw`].
#[derive(Clone, Debug, Default)]
pub struct RawPatches {
    /// Per pixel the B, G, R sums over its block of camera pixels, patch after patch.
    pub values: Vec<f32>,
    /// Normalised Y, U, V = `gain * YUV_FROM_BGR * (B, G, R sums) + offset`.
    pub gain: f32,
    pub offset: [f32; 3],
}

/// BT.601 Y, U, V (U and V before their offset of 128) from B, G, R: rows Y, U, V.
pub const YUV_FROM_BGR: [[f32; 3]; 3] = [
    [0.114, 0.587, 0.299],
    [0.492 * (1.0 - 0.114), -0.492 * 0.587, -0.492 * 0.299],
    [-0.877 * 0.114, -0.877 * 0.587, 0.877 * (1.0 - 0.299)],
];

/// Rejection-sampling draws per patch before giving up on a canvas.
const MAX_TRIES_PER_SAMPLE: usize = 50;

/// One frame seen through the virtual camera.
struct View<'a> {
    bgr: &'a [u8],
    width: usize,
    height: usize,
    /// Camera pixel <- canvas pixel, homogeneous, row-major.
    g: [f32; 9],
    cols: usize,
    rows: usize,
    /// Centre (both axes) and squared radius of the disk patches may use.
    disk: Option<(f32, f32)>,
    /// Side of the camera-pixel block one working pixel averages, and 1 / its area.
    block: usize,
    block_scale: f32,
}

impl View<'_> {
    #[inline]
    fn in_disk(&self, u: f32, v: f32) -> bool {
        self.disk.is_none_or(|(c, r2)| (u - c).powi(2) + (v - c).powi(2) <= r2)
    }

    #[inline(always)]
    fn source(&self, u: f32, v: f32) -> Option<(f32, f32)> {
        let (x, y, z) = self.project(u, v);
        if z <= 0.0 {
            return None;
        }
        let inside = x >= 0.0 && y >= 0.0 && x <= (self.width - 1) as f32 && y <= (self.height - 1) as f32;
        inside.then_some((x, y))
    }

    /// Camera position of canvas pixel `(u, v)` and the homogeneous scale.
    #[inline(always)]
    fn project(&self, u: f32, v: f32) -> (f32, f32, f32) {
        let g = &self.g;
        let z = g[6] * u + g[7] * v + g[8];
        let iz = 1.0 / z;
        ((g[0] * u + g[1] * v + g[2]) * iz, (g[3] * u + g[4] * v + g[5]) * iz, z)
    }

    /// A patch is allowed when its four corners are in the disk and in the frame: both
    /// regions are convex on the canvas (the frame's outline is a convex quadrilateral
    /// for any camera that sees the floor), so then every pixel between is too.
    #[inline]
    fn patch_allowed(&self, x: usize, y: usize, w: usize, h: usize) -> bool {
        let (x0, y0, x1, y1) = (x as f32, y as f32, (x + w - 1) as f32, (y + h - 1) as f32);
        [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
            .iter()
            .all(|&(u, v)| self.in_disk(u, v) && self.source(u, v).is_some())
    }

    /// Y, U, V of canvas pixel `(u, v)` ([`View::value`] at its source), `None` outside
    /// the frame.
    #[inline]
    fn pixel(&self, u: f32, v: f32) -> Option<[f32; 3]> {
        self.source(u, v).map(|(x, y)| self.value::<0>(x, y))
    }

    /// Y, U, V at camera position `(x, y)` (in `[0, width - 1] x [0, height - 1]`): the
    /// mean of the `block x block` camera pixels around it, the area average a downscale
    /// to the working resolution would give there (2 x 2 from 640 to 320 wide). Nearest
    /// block, not interpolated: a quarter of the reads of bilinear interpolation between
    /// four blocks, and the half-block shift it allows is what random sampling does anyway.
    #[inline(always)]
    /// `B`: the block side as a constant (loops unrolled), or 0 to read it from `self`.
    fn value<const B: usize>(&self, x: f32, y: f32) -> [f32; 3] {
        let [sb, sg, sr] = self.sums::<B>(x, y);
        let scale = self.block_scale;
        yuv([sb as f32 * scale, sg as f32 * scale, sr as f32 * scale])
    }

    /// The B, G, R sums over the block [`View::value`] averages.
    #[inline(always)]
    fn sums<const B: usize>(&self, x: f32, y: f32) -> [u32; 3] {
        let b = if B == 0 { self.block } else { B };
        let half = (b - 1) as f32 * 0.5;
        let x0 = ((x - half + 0.5) as usize).min(self.width - b);
        let y0 = ((y - half + 0.5) as usize).min(self.height - b);
        let (mut sb, mut sg, mut sr) = (0u32, 0u32, 0u32);
        for row in 0..b {
            let i = ((y0 + row) * self.width + x0) * 3;
            for p in self.bgr[i..i + 3 * b].chunks_exact(3) {
                sb += u32::from(p[0]);
                sg += u32::from(p[1]);
                sr += u32::from(p[2]);
            }
        }
        [sb, sg, sr]
    }

    /// Writes the patch with top-left corner `(x, y)` (allowed: every pixel has a
    /// source) into `out` (`w * h * 3` values).
    #[inline(always)]
    fn gather(&self, x: usize, y: usize, w: usize, h: usize, out: &mut [f32]) {
        self.gather_as::<false>(x, y, w, h, out);
    }

    /// [`View::gather`] as B, G, R block sums; returns the sums of Y and Y^2 over the
    /// patch's pixels in units of the sums (`YUV_FROM_BGR[0] . sums`).
    #[inline(always)]
    fn gather_sums(&self, x: usize, y: usize, w: usize, h: usize, out: &mut [f32]) -> (f64, f64) {
        self.gather_as::<true>(x, y, w, h, out)
    }

    #[inline(always)]
    fn gather_as<const RAW: bool>(
        &self,
        x: usize,
        y: usize,
        w: usize,
        h: usize,
        out: &mut [f32],
    ) -> (f64, f64) {
        // The block side as a constant for the common sizes: the summing loops unroll.
        match self.block {
            1 => self.gather_block::<1, RAW>(x, y, w, h, out),
            2 => self.gather_block::<2, RAW>(x, y, w, h, out),
            3 => self.gather_block::<3, RAW>(x, y, w, h, out),
            _ => self.gather_block::<0, RAW>(x, y, w, h, out),
        }
    }

    #[inline(always)]
    fn gather_block<const B: usize, const RAW: bool>(
        &self,
        x: usize,
        y: usize,
        w: usize,
        h: usize,
        out: &mut [f32],
    ) -> (f64, f64) {
        let [ky, kg, kr] = [YUV_FROM_BGR[0][0], YUV_FROM_BGR[0][1], YUV_FROM_BGR[0][2]];
        let (mut sum, mut sum2) = (0.0f32, 0.0f32);
        let (xmax, ymax) = ((self.width - 1) as f32, (self.height - 1) as f32);
        let mut px_out = out.chunks_exact_mut(3);
        let g = &self.g;
        for dy in 0..h {
            let v = (y + dy) as f32;
            let u0 = x as f32;
            // Along a row the homogeneous source moves by the first column of `g` (three
            // adds instead of six multiplies a pixel; the rounding may differ from
            // `project` by a few ulps, which can tip a pixel exactly on a block edge into
            // the neighbouring block: measured as rare, see the test).
            let (mut px, mut py, mut pz) =
                (g[0] * u0 + g[1] * v + g[2], g[3] * u0 + g[4] * v + g[5], g[6] * u0 + g[7] * v + g[8]);
            for _ in 0..w {
                let iz = 1.0 / pz;
                // Corners were checked; rounding inside the patch may not leave the frame.
                let (sx, sy) = ((px * iz).clamp(0.0, xmax), (py * iz).clamp(0.0, ymax));
                px += g[0];
                py += g[3];
                pz += g[6];
                if let Some(o) = px_out.next() {
                    if RAW {
                        let [b, gr, r] = self.sums::<B>(sx, sy);
                        let (b, gr, r) = (b as f32, gr as f32, r as f32);
                        o.copy_from_slice(&[b, gr, r]);
                        let yv = ky * b + kg * gr + kr * r;
                        sum += yv;
                        sum2 += yv * yv;
                    } else {
                        o.copy_from_slice(&self.value::<B>(sx, sy));
                    }
                }
            }
        }
        (sum as f64, sum2 as f64)
    }
}

/// BT.601 Y, U, V (U and V offset to 128) of a B, G, R triple, as [`YuvImage::from_bgr`].
#[inline]
fn yuv([b, g, r]: [f32; 3]) -> [f32; 3] {
    let y = 0.299 * r + 0.587 * g + 0.114 * b;
    [y, 0.492 * (b - y) + 128.0, 0.877 * (r - y) + 128.0]
}

/// Target mean and SD of Y after normalisation, grey levels.
const NORMAL_MEAN: f32 = 128.0;
const NORMAL_SD: f32 = 40.0;

/// Brightness `b` and contrast `c` (`RGB' = c RGB + b`) give `Y' = c Y + b` and
/// `U' - 128 = c (U - 128)`: standardising Y over the valid pixels and scaling U and V by
/// the same factor undoes them.
pub fn normalise(img: &mut YuvImage, valid: &[bool]) {
    let (mut sum, mut sum2, mut n) = (0.0f64, 0.0f64, 0usize);
    for (p, _) in img.data.iter().zip(valid).filter(|(_, v)| **v) {
        sum += p[0] as f64;
        sum2 += (p[0] as f64).powi(2);
        n += 1;
    }
    let Some((mean, gain)) = standardising(sum, sum2, n) else { return };
    for p in &mut img.data {
        p[0] = (p[0] - mean) * gain + NORMAL_MEAN;
        p[1] = (p[1] - 128.0) * gain + 128.0;
        p[2] = (p[2] - 128.0) * gain + 128.0;
    }
}

/// [`normalise`] over interleaved Y, U, V values (gathered patches), every value valid.
pub fn normalise_values(values: &mut [f32]) {
    let (mut sum, mut sum2, mut n) = (0.0f64, 0.0f64, 0usize);
    for p in values.chunks_exact(3) {
        sum += p[0] as f64;
        sum2 += (p[0] as f64).powi(2);
        n += 1;
    }
    let Some((mean, gain)) = standardising(sum, sum2, n) else { return };
    for p in values.chunks_exact_mut(3) {
        p[0] = (p[0] - mean) * gain + NORMAL_MEAN;
        p[1] = (p[1] - 128.0) * gain + 128.0;
        p[2] = (p[2] - 128.0) * gain + 128.0;
    }
}

/// Mean of Y and the gain to `NORMAL_SD`, from sums over `n` values; `None` when too few
/// or too flat to standardise.
fn standardising(sum: f64, sum2: f64, n: usize) -> Option<(f32, f32)> {
    if n < 2 {
        return None;
    }
    let mean = sum / n as f64;
    let sd = ((sum2 / n as f64 - mean * mean).max(0.0)).sqrt();
    (sd >= 1e-3).then(|| (mean as f32, NORMAL_SD / sd as f32))
}

/// A continuous 8-bit BGR image to Y, U, V.
pub fn yuv_from_bgr(bgr: &Mat) -> opencv::Result<YuvImage> {
    let (w, h) = (bgr.cols() as usize, bgr.rows() as usize);
    if bgr.is_continuous() {
        return Ok(YuvImage::from_bgr(w, h, bgr.data_bytes()?));
    }
    // A view into a larger image: copy it to one block first.
    Ok(YuvImage::from_bgr(w, h, bgr.try_clone()?.data_bytes()?))
}

/// The pixel (working resolution) where the camera's nadir appears, if in front of it.
pub fn nadir_pixel(k: &Intrinsics, local_from_camera: &Rot3) -> Option<(f64, f64)> {
    let d = local_from_camera.inverse() * Vector3::new(0.0, 0.0, 1.0);
    (d.z > 1e-9).then(|| (k.fx * d.x / d.z + k.cx, k.fy * d.y / d.z + k.cy))
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavloc_geometry::{body_rotation, CameraPose, GimbalAngles, GimbalChain, Mount, Vec3};
    use proptest::prelude::*;
    use rand::SeedableRng;
    use std::f64::consts::PI;

    fn down_camera(roll: f64, pitch: f64, yaw: f64) -> Rot3 {
        let pose = CameraPose::from_gimbal(
            Vec3::zeros(),
            GimbalChain::YawPitchRoll,
            GimbalAngles { yaw: 0.0, pitch: -PI / 2.0, roll: 0.0 },
            Mount::Body { attitude: body_rotation(roll, pitch, yaw) },
        );
        pose.local_from_camera()
    }

    proptest! {
        /// A floor point lands where the virtual north-up nadir camera would see it.
        #[test]
        fn homography_maps_floor_points_to_the_virtual_view(
            roll in -0.2f64..0.2, pitch in -0.2f64..0.2, yaw in -PI..PI,
            north in -0.3f64..0.3, east in -0.3f64..0.3, height in 0.5f64..2.0,
        ) {
            let k = Intrinsics::from_hfov(320, 240, 70f64.to_radians());
            let pre = Preprocessor::new(k, 320, true, (6, 6));
            let r = down_camera(roll, pitch, yaw);
            let pose = CameraPose { position: Vec3::new(0.0, 0.0, -height), attitude: r * mavloc_geometry::gimbal_from_camera().inverse() };
            let point = Vec3::new(north, east, 0.0);
            let px = pose.project(&k, &point).unwrap();
            let h = pre.homography(&r, 1.0);
            let q = h * Vector3::new(px.u, px.v, 1.0);
            let (u, v) = (q.x / q.z, q.y / q.z);
            let (dn, de) = pre.canvas_offset(u, v);
            prop_assert!((dn * height - north).abs() < 1e-9 && (de * height - east).abs() < 1e-9);
        }

        /// With a reference height, a floor point lands where the level camera at the
        /// reference height would see it, from any height and tilt: the floor keeps one
        /// scale on the canvas.
        #[test]
        fn with_a_reference_height_the_floor_keeps_its_scale(
            roll in -0.2f64..0.2, pitch in -0.2f64..0.2, yaw in -PI..PI,
            north in -0.15f64..0.15, east in -0.15f64..0.15, height in 0.4f64..2.0,
        ) {
            let k = Intrinsics::from_hfov(320, 240, 70f64.to_radians());
            let mut pre = Preprocessor::new(k, 320, true, (6, 6));
            pre.height_ref = Some(1.0);
            let r = down_camera(roll, pitch, yaw);
            let pose = CameraPose { position: Vec3::new(0.0, 0.0, -height), attitude: r * mavloc_geometry::gimbal_from_camera().inverse() };
            let px = pose.project(&k, &Vec3::new(north, east, 0.0)).unwrap();
            let q = pre.homography(&r, pre.scale(Some(height))) * Vector3::new(px.u, px.v, 1.0);
            let (dn, de) = pre.canvas_offset(q.x / q.z, q.y / q.z);
            // canvas_offset is per metre of height at scale 1: times the reference height.
            prop_assert!((dn - north).abs() < 1e-9 && (de - east).abs() < 1e-9, "{dn} {de} vs {north} {east}");
        }
    }

    /// A textured 160x120 BGR frame (blobs and stripes in colour) with a downward
    /// camera's rotation. (Pipelines may not use the simulator, tests included.)
    fn floor_frame(roll: f64, pitch: f64, yaw: f64, _height: f64) -> (Mat, Rot3, Intrinsics) {
        let k = Intrinsics::from_hfov(160, 120, 70f64.to_radians());
        let mut rgb = Vec::with_capacity(160 * 120 * 3);
        for y in 0..120 {
            for x in 0..160 {
                let (fx, fy) = (x as f64, y as f64);
                let a = 128.0 + 60.0 * (fx * 0.31 + fy * 0.07).sin() + 40.0 * (fy * 0.23).cos();
                let b = 128.0 + 80.0 * ((fx - 60.0).hypot(fy - 50.0) * 0.2).sin();
                let c = 128.0 + 70.0 * (fx * 0.11 - fy * 0.19).cos();
                rgb.extend_from_slice(&[a as u8, b as u8, c as u8]);
            }
        }
        (bgr_from_rgb(&rgb, 120).unwrap(), down_camera(roll, pitch, yaw), k)
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]
        /// The patches flight gathers from the frame are the canvas's patches training
        /// takes, at exactly the positions the canvas allows: a model trained on canvases
        /// sees in flight what it was trained on.
        #[test]
        fn sampled_patches_are_the_canvas_patches(
            roll in -0.15f64..0.15, pitch in -0.15f64..0.15, yaw in -PI..PI, height in 0.6f64..1.5,
            with_ref in proptest::bool::ANY, derotate in proptest::bool::ANY,
        ) {
            let (bgr, r, k) = floor_frame(roll, pitch, yaw, height);
            let mut pre = Preprocessor::new(k, 80, derotate, (4, 4));
            pre.height_ref = with_ref.then_some(1.0);
            let canvas = pre.prepare(&bgr, Some(&r), Some(height)).unwrap();
            let view = pre.view(&bgr, Some(&r), Some(height)).unwrap();
            let (cols, rows) = (canvas.img.width - 3, canvas.img.height - 3);
            let mut out = Vec::new();
            let (mut compared, mut differ) = (0usize, 0usize);
            for y in 0..rows {
                for x in 0..cols {
                    prop_assert_eq!(view.patch_allowed(x, y, 4, 4), canvas.mask.allows(x, y), "at {},{}", x, y);
                    if canvas.mask.allows(x, y) && (x + y) % 7 == 0 {
                        out.clear();
                        out.resize(4 * 4 * 3, 0.0);
                        view.gather(x, y, 4, 4, &mut out);
                        for (i, o) in out.chunks_exact(3).enumerate() {
                            let p = canvas.img.data[(y + i / 4) * canvas.img.width + x + i % 4];
                            compared += 1;
                            if o.iter().zip(p).any(|(a, b)| (a - b).abs() >= 0.05) {
                                differ += 1;
                            }
                        }
                    }
                }
            }
            // Only pixels within float rounding of a block edge may land in the next block.
            prop_assert!(differ * 200 <= compared, "{} of {} pixels differ", differ, compared);
        }
    }

    #[test]
    fn a_sampled_histogram_approaches_the_canvas_histogram() {
        use crate::indoor::textons::{Dictionary, Learning};
        let (bgr, r, k) = floor_frame(0.05, -0.08, 0.7, 1.0);
        let mut pre = Preprocessor::new(k, 120, true, (4, 4));
        pre.normalise = true;
        let canvas = pre.prepare(&bgr, Some(&r), Some(1.0)).unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let patches = Dictionary::sample_patches(&canvas.img, &canvas.mask, (4, 4), 3000, &mut rng);
        let dict =
            Dictionary::learn_from_patches(&patches, 12, 4, 4, Learning::Competitive { rate_millis: 20 })
                .unwrap();
        let full = dict.histogram_full(&canvas.img, Some(&canvas.mask));
        let mut out = Vec::new();
        let n = pre.sample(&bgr, Some(&r), Some(1.0), 5000, &mut rng, &mut out).unwrap();
        assert_eq!(n, 5000);
        let sampled = dict.classifier().histogram_of_patches(&out);
        let cos = crate::indoor::textons::cosine(&full, &sampled);
        assert!(cos > 0.995, "cosine {cos}: {full:?} vs {sampled:?}");
    }

    /// The flight's fast path (block sums, colour conversion and normalisation moved onto
    /// the textons) gives the histogram of the normalised patches, for the same positions.
    #[test]
    fn raw_patches_give_the_histogram_of_the_normalised_patches() {
        use crate::indoor::textons::{Dictionary, Learning};
        for (roll, pitch, yaw, normalise) in [(0.05, -0.08, 0.7, true), (0.0, 0.1, -2.0, false)] {
            let (bgr, r, k) = floor_frame(roll, pitch, yaw, 1.0);
            let mut pre = Preprocessor::new(k, 80, true, (4, 4));
            pre.normalise = normalise;
            pre.height_ref = Some(1.3);
            let canvas = pre.prepare(&bgr, Some(&r), Some(1.0)).unwrap();
            let mut rng = rand::rngs::StdRng::seed_from_u64(5);
            let patches = Dictionary::sample_patches(&canvas.img, &canvas.mask, (4, 4), 2000, &mut rng);
            let dict =
                Dictionary::learn_from_patches(&patches, 12, 4, 4, Learning::Competitive { rate_millis: 20 })
                    .unwrap();
            let c = dict.classifier();
            let mut out = Vec::new();
            pre.sample(&bgr, Some(&r), Some(1.0), 3000, &mut rand::rngs::StdRng::seed_from_u64(9), &mut out)
                .unwrap();
            let mut raw = RawPatches::default();
            let n = pre
                .sample_raw(
                    &bgr,
                    Some(&r),
                    Some(1.0),
                    3000,
                    &mut rand::rngs::StdRng::seed_from_u64(9),
                    &mut raw,
                )
                .unwrap();
            assert_eq!(n, 3000);
            let a = c.histogram_of_patches(&out);
            let b = c.histogram_of_raw(
                &raw.values,
                raw.gain,
                raw.offset,
                &YUV_FROM_BGR,
                &mut (Vec::new(), Vec::new()),
            );
            // The same patches; float rounding may tip a near tie.
            let diff: f32 = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).sum();
            assert!(diff <= 4.0 / 3000.0, "normalise {normalise}: {a:?} vs {b:?}");
        }
    }

    #[test]
    fn a_frame_of_another_size_or_type_is_refused_by_name() {
        let (bgr, r, k) = floor_frame(0.0, 0.0, 0.0, 1.0);
        let pre = Preprocessor::new(Intrinsics { width: 320, ..k }, 80, true, (4, 4));
        let mut out = Vec::new();
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let e = pre.sample(&bgr, Some(&r), None, 10, &mut rng, &mut out).err().unwrap();
        assert!(e.message.contains("frame is 160x120"), "{e}");
    }

    #[test]
    fn the_scale_is_bounded_and_off_without_a_reference() {
        let k = Intrinsics::from_hfov(320, 240, 1.2);
        let mut pre = Preprocessor::new(k, 320, true, (6, 6));
        assert_eq!(pre.scale(Some(0.5)), 1.0, "no reference: no rescaling");
        pre.height_ref = Some(1.0);
        assert_eq!(pre.scale(Some(0.5)), 0.5);
        assert_eq!(pre.scale(Some(0.01)), SCALE_RANGE.0);
        assert_eq!(pre.scale(Some(f64::NAN)), 1.0);
        assert_eq!(pre.scale(None), 1.0);
    }

    #[test]
    fn nadir_of_a_level_camera_is_the_principal_point() {
        let k = Intrinsics::from_hfov(320, 240, 1.2);
        let (u, v) = nadir_pixel(&k, &down_camera(0.0, 0.0, 0.7)).unwrap();
        assert!((u - k.cx).abs() < 1e-9 && (v - k.cy).abs() < 1e-9);
        let (u, _) = nadir_pixel(&k, &down_camera(0.1, 0.0, 0.0)).unwrap();
        assert!(u != k.cx);
    }

    #[test]
    fn normalisation_undoes_brightness_and_contrast() {
        let rgb: Vec<u8> = (0..300).map(|i| ((i * 37) % 200 + 20) as u8).collect();
        let changed: Vec<u8> = rgb.iter().map(|&v| (v as f32 * 1.15 - 12.0).round() as u8).collect();
        let mut a = YuvImage::from_rgb(10, 10, &rgb).unwrap();
        let mut b = YuvImage::from_rgb(10, 10, &changed).unwrap();
        let valid = vec![true; 100];
        normalise(&mut a, &valid);
        normalise(&mut b, &valid);
        for (p, q) in a.data.iter().zip(&b.data) {
            for c in 0..3 {
                // Within the rounding of the 8-bit change.
                assert!((p[c] - q[c]).abs() < 1.5, "{p:?} vs {q:?}");
            }
        }
    }

    #[test]
    fn scaled_intrinsics_keep_the_field_of_view() {
        let k = Intrinsics::from_hfov(640, 480, 1.2);
        let s = scaled(&k, 0.5);
        assert_eq!((s.width, s.height), (320, 240));
        assert!((s.hfov() - k.hfov()).abs() < 1e-9);
        assert!((s.cx - (s.width as f64 - 1.0) / 2.0).abs() < 1e-9);
    }
}
