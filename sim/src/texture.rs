//! Ground textures in world units: an RGB image draped over the local frame at a fixed
//! scale, repeated by mirroring (so tiles meet without seams), with a mip pyramid so distant
//! ground is averaged rather than aliased (aliasing would hand SIFT features that flicker
//! from frame to frame and exist in no real image).

use std::path::Path;

/// One mip level: RGB, row-major, `width x height`.
#[derive(Clone, Debug)]
struct Level {
    width: usize,
    height: usize,
    rgb: Vec<[f32; 3]>,
}

impl Level {
    fn halve(&self) -> Level {
        let (w, h) = ((self.width / 2).max(1), (self.height / 2).max(1));
        let mut rgb = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let mut acc = [0.0f32; 3];
                for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let sx = (2 * x + dx).min(self.width - 1);
                    let sy = (2 * y + dy).min(self.height - 1);
                    let p = self.rgb[sy * self.width + sx];
                    for c in 0..3 {
                        acc[c] += p[c] * 0.25;
                    }
                }
                rgb.push(acc);
            }
        }
        Level { width: w, height: h, rgb }
    }

    /// Mirrored-repeat index: ... 2 1 0 | 0 1 2 ... n-1 | n-1 n-2 ...
    // The renderer calls this eight times per pixel: inside the texture it is the index
    // itself, and a power-of-two period (the detail texture) needs a mask, not a division.
    #[inline]
    fn wrap(i: i64, n: usize) -> usize {
        if (i as u64) < n as u64 {
            return i as usize;
        }
        let period = 2 * n as i64;
        let m = if period & (period - 1) == 0 { i & (period - 1) } else { i.rem_euclid(period) };
        if m < n as i64 {
            m as usize
        } else {
            (period - 1 - m) as usize
        }
    }

    /// The first `N` channels, bilinearly interpolated (`N = 1` for a grey texture, whose
    /// three channels are equal: a third of the arithmetic, the same values).
    #[inline]
    fn bilinear<const N: usize>(&self, x: f64, y: f64) -> [f32; N] {
        let (x, y) = (x - 0.5, y - 0.5); // texel centres at +0.5
        let (x0, y0) = (floor(x), floor(y));
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let xs = [Self::wrap(x0, self.width), Self::wrap(x0 + 1, self.width)];
        let ys = [Self::wrap(y0, self.height), Self::wrap(y0 + 1, self.height)];
        let p = |xi: usize, yi: usize| self.rgb[ys[yi] * self.width + xs[xi]];
        let mut out = [0.0f32; N];
        for (c, o) in out.iter_mut().enumerate() {
            let top = p(0, 0)[c] * (1.0 - fx) + p(1, 0)[c] * fx;
            let bottom = p(0, 1)[c] * (1.0 - fx) + p(1, 1)[c] * fx;
            *o = top * (1.0 - fy) + bottom * fy;
        }
        out
    }
}

/// `x.floor()` without the libm call (x86-64 without SSE4.1 has no floor instruction):
/// exact for |x| < 2^52, which texture coordinates are.
#[inline]
fn floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

/// A texture draped over the ground: image column = east, image row = south.
#[derive(Clone, Debug)]
pub struct Texture {
    /// Ground size of one texel at level 0, metres.
    pub metres_per_texel: f64,
    levels: Vec<Level>,
}

impl Texture {
    /// From RGB values in 0..=255 (row-major), `width x height`.
    pub fn from_rgb(width: usize, height: usize, rgb: Vec<[f32; 3]>, metres_per_texel: f64) -> Texture {
        assert_eq!(rgb.len(), width * height, "texture size mismatch");
        let mut levels = vec![Level { width, height, rgb }];
        while levels.last().is_some_and(|l| l.width > 1 || l.height > 1) && levels.len() < 16 {
            let next = levels.last().expect("non-empty").halve();
            levels.push(next);
        }
        Texture { metres_per_texel, levels }
    }

    /// Loads an image file (PNG, JPEG).
    pub fn load(path: &Path, metres_per_texel: f64) -> Result<Texture, String> {
        let bytes =
            std::fs::read(path).map_err(|e| format!("cannot read texture {}: {e}", path.display()))?;
        Texture::decode(&bytes, metres_per_texel).map_err(|e| format!("texture {}: {e}", path.display()))
    }

    /// From a PNG or JPEG file's bytes.
    pub fn decode(bytes: &[u8], metres_per_texel: f64) -> Result<Texture, String> {
        let (w, h, rgba) = decode_rgba(bytes)?;
        Texture::from_rgba(w, h, &rgba, metres_per_texel)
    }

    /// From RGBA pixels, row-major, `w x h`. Orthomosaic renders mark no-data as
    /// transparent or pure white (ODM's previews: white). No-data reached from the image
    /// border is cut away (the texture is the largest rectangle free of it); enclosed
    /// no-data holes are filled from their surroundings, so no-data never reaches the
    /// simulated ground.
    pub fn from_rgba(w: usize, h: usize, rgba: &[u8], metres_per_texel: f64) -> Result<Texture, String> {
        assert_eq!(rgba.len(), w * h * 4, "texture size mismatch");
        let pixel = |x: usize, y: usize| &rgba[(y * w + x) * 4..(y * w + x) * 4 + 4];
        let nodata: Vec<bool> =
            rgba.chunks_exact(4).map(|p| p[3] < 255 || (p[0] == 255 && p[1] == 255 && p[2] == 255)).collect();
        // Flood from the border through no-data.
        let mut outside = vec![false; w * h];
        let mut queue: Vec<usize> = (0..w * h)
            .filter(|&k| nodata[k] && (k % w == 0 || k % w == w - 1 || k / w == 0 || k / w == h - 1))
            .collect();
        for &k in &queue {
            outside[k] = true;
        }
        while let Some(k) = queue.pop() {
            let (x, y) = (k % w, k / w);
            let mut visit = |nk: usize| {
                if nodata[nk] && !outside[nk] {
                    outside[nk] = true;
                    queue.push(nk);
                }
            };
            if x > 0 {
                visit(k - 1)
            }
            if x + 1 < w {
                visit(k + 1)
            }
            if y > 0 {
                visit(k - w)
            }
            if y + 1 < h {
                visit(k + w)
            }
        }
        let inside: Vec<bool> = outside.iter().map(|o| !o).collect();
        let (x0, y0, cw, ch) = largest_rectangle(w, h, &inside);
        if cw < 4 || ch < 4 {
            return Err(format!("texture has no area free of no-data larger than {cw}x{ch} px"));
        }
        let mut rgb = Vec::with_capacity(cw * ch);
        let mut hole = Vec::with_capacity(cw * ch);
        for y in y0..y0 + ch {
            for x in x0..x0 + cw {
                let p = pixel(x, y);
                rgb.push([p[0] as f32, p[1] as f32, p[2] as f32]);
                hole.push(nodata[y * w + x]);
            }
        }
        fill_holes(cw, ch, &mut rgb, &mut hole);
        Ok(Texture::from_rgb(cw, ch, rgb, metres_per_texel))
    }

    /// Colour at ground position (north, east) for a pixel footprint of `footprint`
    /// metres: picks the mip level whose texels are about that size.
    pub fn sample(&self, north: f64, east: f64, footprint: f64) -> [f32; 3] {
        self.sample_channels(north, east, footprint)
    }

    /// [`Texture::sample`]'s first channel alone: the value of a grey texture (the
    /// simulator's detail noise), with a third of the arithmetic.
    pub fn sample_grey(&self, north: f64, east: f64, footprint: f64) -> f32 {
        self.sample_channels::<1>(north, east, footprint)[0]
    }

    #[inline]
    fn sample_channels<const N: usize>(&self, north: f64, east: f64, footprint: f64) -> [f32; N] {
        let ratio = footprint / self.metres_per_texel;
        // log2 only when the footprint spans two texels or more (level 0 otherwise).
        let level = if ratio < 2.0 { 0 } else { (ratio.log2().floor() as usize).min(self.levels.len() - 1) };
        let scale = self.metres_per_texel * (1u64 << level) as f64;
        // The texture is centred on the local origin, so a texture that covers a scene
        // (the indoor floor) covers it without a mirror line through its middle.
        let l = &self.levels[level];
        l.bilinear(east / scale + l.width as f64 / 2.0, -north / scale + l.height as f64 / 2.0)
    }
}

/// Decodes a PNG or JPEG (told apart by their signatures) into RGBA, 8 bits a channel:
/// `(width, height, pixels)`. Through the `png` and `zune-jpeg` crates themselves, which
/// is what `image` does inside; `image` would add its colour-management stack (`moxcms`,
/// `pxfm`) for two formats, about a minute of CPU in a fresh build.
fn decode_rgba(bytes: &[u8]) -> Result<(usize, usize, Vec<u8>), String> {
    if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        // Palettes and low bit depths expanded, 16 bits cut to 8.
        decoder.set_transformations(png::Transformations::normalize_to_color8());
        let mut reader = decoder.read_info().map_err(|e| format!("PNG: {e}"))?;
        let size = reader.output_buffer_size().ok_or("PNG: image too large")?;
        let mut buf = vec![0u8; size];
        let info = reader.next_frame(&mut buf).map_err(|e| format!("PNG: {e}"))?;
        buf.truncate(info.buffer_size());
        let (w, h) = (info.width as usize, info.height as usize);
        let rgba: Vec<u8> = match info.color_type {
            png::ColorType::Rgba => buf,
            png::ColorType::Rgb => buf.chunks_exact(3).flat_map(|p| [p[0], p[1], p[2], 255]).collect(),
            png::ColorType::Grayscale => buf.iter().flat_map(|&v| [v, v, v, 255]).collect(),
            png::ColorType::GrayscaleAlpha => {
                buf.chunks_exact(2).flat_map(|p| [p[0], p[0], p[0], p[1]]).collect()
            }
            png::ColorType::Indexed => return Err("PNG: palette not expanded".into()),
        };
        Ok((w, h, rgba))
    } else if bytes.starts_with(&[0xff, 0xd8]) {
        use zune_jpeg::zune_core::{bytestream::ZCursor, colorspace::ColorSpace, options::DecoderOptions};
        let options = DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::RGBA);
        let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options);
        let rgba = decoder.decode().map_err(|e| format!("JPEG: {e:?}"))?;
        let (w, h) = decoder.dimensions().ok_or("JPEG: no size")?;
        Ok((w, h, rgba))
    } else {
        Err("neither PNG nor JPEG".into())
    }
}

/// Fills hole pixels from the mean of their filled 4-neighbours, growing inwards.
fn fill_holes(w: usize, h: usize, rgb: &mut [[f32; 3]], hole: &mut [bool]) {
    let mut remaining: Vec<usize> = (0..w * h).filter(|&k| hole[k]).collect();
    while !remaining.is_empty() {
        let mut filled = Vec::new();
        for &k in &remaining {
            let (x, y) = (k % w, k / w);
            let mut acc = [0.0f32; 3];
            let mut n = 0.0;
            for (dx, dy) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                    continue;
                }
                let nk = ny as usize * w + nx as usize;
                if !hole[nk] {
                    for c in 0..3 {
                        acc[c] += rgb[nk][c];
                    }
                    n += 1.0;
                }
            }
            if n > 0.0 {
                filled.push((k, [acc[0] / n, acc[1] / n, acc[2] / n]));
            }
        }
        if filled.is_empty() {
            break; // nothing valid to grow from
        }
        for (k, c) in &filled {
            rgb[*k] = *c;
            hole[*k] = false;
        }
        remaining.retain(|&k| hole[k]);
    }
}

/// Largest axis-aligned rectangle of `true` cells: (x, y, width, height). The classic
/// histogram-and-stack method, O(w h).
fn largest_rectangle(w: usize, h: usize, cells: &[bool]) -> (usize, usize, usize, usize) {
    let mut heights = vec![0usize; w];
    let mut best = (0, 0, 0, 0);
    for y in 0..h {
        for x in 0..w {
            heights[x] = if cells[y * w + x] { heights[x] + 1 } else { 0 };
        }
        let mut stack: Vec<usize> = Vec::new();
        for x in 0..=w {
            let cur = if x < w { heights[x] } else { 0 };
            while let Some(&top) = stack.last() {
                if heights[top] <= cur {
                    break;
                }
                stack.pop();
                let height = heights[top];
                let left = stack.last().map_or(0, |&l| l + 1);
                let width = x - left;
                if width * height > best.2 * best.3 {
                    best = (left, y + 1 - height, width, height);
                }
            }
            stack.push(x);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn largest_rectangle_finds_the_opaque_block() {
        // 6x4 with a 3x2 block of true at (2, 1) and stray cells elsewhere.
        let mut cells = vec![false; 24];
        for y in 1..3 {
            for x in 2..5 {
                cells[y * 6 + x] = true;
            }
        }
        cells[0] = true;
        cells[23] = true;
        assert_eq!(largest_rectangle(6, 4, &cells), (2, 1, 3, 2));
    }

    #[test]
    fn no_data_border_is_cut_and_holes_are_filled() {
        // 8x8 grey with a white no-data corner and one enclosed white hole.
        let mut img = [100u8, 100, 100, 255].repeat(64);
        for (x, y) in [(0, 0), (1, 0), (0, 1), (5, 5)] {
            img[(y * 8 + x) * 4..(y * 8 + x) * 4 + 3].fill(255);
        }
        let t = Texture::from_rgba(8, 8, &img, 1.0).unwrap();
        let l = &t.levels[0];
        assert!(l.width * l.height >= 48 && l.width * l.height < 64, "{}x{}", l.width, l.height);
        assert!(l.rgb.iter().all(|p| p[0] == 100.0), "no white left");
    }

    /// Grey, RGB and RGBA PNGs all come out as the same RGBA; a JPEG (a DJI photo) with its
    /// size and opaque; anything else is named.
    #[test]
    fn png_and_jpeg_decode_to_rgba() {
        let encode = |colour: png::ColorType, pixels: &[u8]| {
            let mut buf = Vec::new();
            let mut e = png::Encoder::new(&mut buf, 2, 1);
            e.set_color(colour);
            e.set_depth(png::BitDepth::Eight);
            e.write_header().unwrap().write_image_data(pixels).unwrap();
            buf
        };
        let want = vec![10, 10, 10, 255, 200, 200, 200, 255];
        assert_eq!(
            decode_rgba(&encode(png::ColorType::Grayscale, &[10, 200])).unwrap(),
            (2, 1, want.clone())
        );
        let rgb = encode(png::ColorType::Rgb, &[10, 10, 10, 200, 200, 200]);
        assert_eq!(decode_rgba(&rgb).unwrap(), (2, 1, want.clone()));
        assert_eq!(decode_rgba(&encode(png::ColorType::Rgba, &want)).unwrap(), (2, 1, want));
        let photo = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/data/dji-sample/DJI_0030.JPG");
        let (w, h, rgba) = decode_rgba(&std::fs::read(photo).unwrap()).unwrap();
        assert_eq!((w, h, rgba.len()), (4000, 2250, 4000 * 2250 * 4));
        assert!(rgba.chunks_exact(4).all(|p| p[3] == 255));
        let mean = rgba.chunks_exact(4).map(|p| p[1] as f64).sum::<f64>() / (w * h) as f64;
        assert!(mean > 30.0 && mean < 220.0, "a photo, not a blank: mean green {mean:.0}");
        assert_eq!(decode_rgba(b"GIF89a").unwrap_err(), "neither PNG nor JPEG");
    }

    #[test]
    fn mirrored_wrap_has_no_seam() {
        assert_eq!(Level::wrap(-1, 4), 0);
        assert_eq!(Level::wrap(4, 4), 3);
        assert_eq!(Level::wrap(7, 4), 0);
        assert_eq!(Level::wrap(8, 4), 0);
    }

    #[test]
    fn constant_texture_samples_constant_at_every_level() {
        let t = Texture::from_rgb(8, 4, vec![[10.0, 20.0, 30.0]; 32], 0.5);
        for fp in [0.1, 0.5, 2.0, 100.0] {
            let c = t.sample(1.3, -7.7, fp);
            assert!((c[0] - 10.0).abs() < 1e-4 && (c[2] - 30.0).abs() < 1e-4);
        }
    }

    #[test]
    fn east_is_image_right_and_north_is_image_up() {
        // Left half dark, right half bright; top half red-free, bottom half red.
        let mut rgb = Vec::new();
        for y in 0..4 {
            for x in 0..4 {
                rgb.push([if y >= 2 { 255.0 } else { 0.0 }, if x >= 2 { 255.0 } else { 0.0 }, 0.0]);
            }
        }
        let t = Texture::from_rgb(4, 4, rgb, 1.0);
        // The centre of the texture is at the origin: east +1.5 m -> column 3.5 (right),
        // north -1.5 m -> row 3.5 (bottom).
        let c = t.sample(-1.5, 1.5, 0.1);
        assert!(c[1] > 200.0 && c[0] > 200.0, "{c:?}");
        let c = t.sample(1.5, -1.5, 0.1);
        assert!(c[1] < 50.0 && c[0] < 50.0, "{c:?}");
    }
}
