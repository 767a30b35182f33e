//! 8-bit PNG files, written whole through [`crate::atomic`]: the simulator's frames and
//! masks, and mavloc's plots; and read back ([`decode`]) faster than OpenCV's libpng.
//! The `png` crate itself, which is what `image` uses inside: `image` would add a
//! colour-management stack (`moxcms`, `pxfm`) to encode one format, about a minute of CPU
//! in a fresh build.

use std::io;
use std::path::Path;

/// Channels of the pixels given to [`write`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Channels {
    Grey,
    Rgb,
}

/// Writes `pixels` (row-major, `width x height`, 8 bits a channel) to `path` as a PNG,
/// atomically (see [`encode`]).
pub fn write(path: &Path, width: u32, height: u32, pixels: &[u8], channels: Channels) -> io::Result<()> {
    crate::write_atomic(path, &encode(width, height, pixels, channels)?)
}

/// `pixels` (row-major, `width x height`, 8 bits a channel) as a PNG file's bytes, for a
/// file written inside a [`crate::staged::StagedDir`] (made durable as a whole when it is
/// committed). Fast compression with the Sub filter: the files are written once and read
/// by OpenCV, and encoding is on the renderer's clock.
pub fn encode(width: u32, height: u32, pixels: &[u8], channels: Channels) -> io::Result<Vec<u8>> {
    let per_pixel = match channels {
        Channels::Grey => 1,
        Channels::Rgb => 3,
    };
    if pixels.len() != width as usize * height as usize * per_pixel {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{} bytes for a {width}x{height} image of {per_pixel} channels", pixels.len()),
        ));
    }
    let mut buf = Vec::new();
    let mut encoder = png::Encoder::new(&mut buf, width, height);
    encoder.set_color(match channels {
        Channels::Grey => png::ColorType::Grayscale,
        Channels::Rgb => png::ColorType::Rgb,
    });
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    encoder.set_filter(png::Filter::Sub);
    encoder.write_header().and_then(|mut w| w.write_image_data(pixels)).map_err(io::Error::other)?;
    Ok(buf)
}

/// A PNG's pixels, row-major, 8 bits a channel.
#[derive(Debug, PartialEq, Eq)]
pub struct Decoded {
    pub width: u32,
    pub height: u32,
    pub channels: Channels,
    pub pixels: Vec<u8>,
}

/// Decodes a plain 8-bit grey or RGB PNG whose channels are among `accept`: the kind
/// [`encode`] writes, which is every frame and mask of a rendered dataset. `None`, told
/// from the header before any pixel is decoded, for any other kind (palette, alpha or
/// transparency, 16 or fewer than 8 bits, interlaced, an EXIF block whose orientation a
/// reader may apply, channels not accepted), and for a file this decoder refuses: the
/// caller decodes those otherwise. Why not only OpenCV: the frames are read on the pipeline's clock, and the
/// `png` crate (fdeflate) reads a 960x540 frame in 3.05 ms where OpenCV's libpng and zlib
/// take 11.2 ms (`cargo bench --bench area -- area_read_frame`, session 27).
pub fn decode(bytes: &[u8], accept: &[Channels]) -> Option<Decoded> {
    // 1 GiB: a 24 Mpx photo is 72 MB, over the crate's 64 MB default; a header that
    // claims more (a hostile or broken file) is declined before anything is allocated.
    // The crate's limit covers only its own buffers, so the output's is checked below.
    const LIMIT: usize = 1 << 30;
    let limits = png::Limits { bytes: LIMIT };
    let mut decoder = png::Decoder::new_with_limits(io::Cursor::new(bytes), limits);
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info().ok()?;
    let info = reader.info();
    let channels = match (info.color_type, info.bit_depth) {
        (png::ColorType::Grayscale, png::BitDepth::Eight) => Channels::Grey,
        (png::ColorType::Rgb, png::BitDepth::Eight) => Channels::Rgb,
        _ => return None,
    };
    if !accept.contains(&channels) || info.interlaced || info.trns.is_some() || info.exif_metadata.is_some() {
        return None;
    }
    let mut pixels = vec![0; reader.output_buffer_size().filter(|&n| n <= LIMIT)?];
    let out = reader.next_frame(&mut pixels).ok()?;
    pixels.truncate(out.buffer_size());
    Some(Decoded { width: out.width, height: out.height, channels, pixels })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What is written decodes to the same pixels, grey and colour.
    #[test]
    fn pixels_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        for (channels, n, colour) in
            [(Channels::Grey, 1, png::ColorType::Grayscale), (Channels::Rgb, 3, png::ColorType::Rgb)]
        {
            let (w, h) = (7u32, 5u32);
            let pixels: Vec<u8> = (0..w * h * n).map(|i| (i * 37 % 251) as u8).collect();
            let path = dir.path().join(format!("{n}.png"));
            write(&path, w, h, &pixels, channels).unwrap();
            let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
            let mut reader = decoder.read_info().unwrap();
            let mut out = vec![0; reader.output_buffer_size().unwrap()];
            let info = reader.next_frame(&mut out).unwrap();
            assert_eq!((info.width, info.height, info.color_type), (w, h, colour));
            assert_eq!(&out[..info.buffer_size()], &pixels[..]);
        }
    }

    /// What [`encode`] writes, [`decode`] reads back; other kinds are left to the caller.
    #[test]
    fn decode_reads_what_encode_writes_and_declines_other_kinds() {
        for (channels, n) in [(Channels::Grey, 1), (Channels::Rgb, 3)] {
            let (w, h) = (33u32, 17u32);
            let pixels: Vec<u8> = (0..w * h * n).map(|i| (i * 91 % 253) as u8).collect();
            let bytes = encode(w, h, &pixels, channels).unwrap();
            let d = decode(&bytes, &[channels]).unwrap();
            assert_eq!(d, Decoded { width: w, height: h, channels, pixels });
            let other = if channels == Channels::Grey { Channels::Rgb } else { Channels::Grey };
            assert_eq!(decode(&bytes, &[other]), None, "{channels:?} not accepted");
        }
        let other = |colour, depth, bytes: usize| {
            let mut buf = Vec::new();
            let mut e = png::Encoder::new(&mut buf, 4, 4);
            e.set_color(colour);
            e.set_depth(depth);
            e.write_header().and_then(|mut w| w.write_image_data(&vec![7; bytes])).unwrap();
            buf
        };
        let both = [Channels::Grey, Channels::Rgb];
        assert_eq!(decode(&other(png::ColorType::Rgba, png::BitDepth::Eight, 64), &both), None);
        assert_eq!(decode(&other(png::ColorType::Grayscale, png::BitDepth::Sixteen, 32), &both), None);
        assert_eq!(decode(&other(png::ColorType::Grayscale, png::BitDepth::Four, 8), &both), None);
        let whole = encode(8, 8, &[9; 64], Channels::Grey).unwrap();
        assert_eq!(decode(&whole[..whole.len() - 20], &both), None, "a cut file");
        assert_eq!(decode(b"not a png", &both), None);
        // A header claiming 2^20 x 2^20 grey pixels (1 TiB) over a few bytes of data.
        let mut huge = whole.clone();
        huge[16..24].copy_from_slice(&[0, 16, 0, 0, 0, 16, 0, 0]);
        let crc = crc32fast::hash(&huge[12..29]);
        huge[29..33].copy_from_slice(&crc.to_be_bytes());
        assert_eq!(decode(&huge, &both), None);
    }

    #[test]
    fn a_wrong_size_is_refused_and_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.png");
        let e = write(&path, 4, 4, &[0; 15], Channels::Grey).unwrap_err();
        assert!(e.to_string().contains("15 bytes for a 4x4 image"), "{e}");
        assert!(!path.exists());
    }
}
