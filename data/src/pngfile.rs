//! 8-bit PNG files, written whole through [`crate::atomic`]: the simulator's frames and
//! masks, and mavloc's plots. The `png` crate itself, which is what `image` uses inside:
//! `image` would add a colour-management stack (`moxcms`, `pxfm`) to encode one format,
//! about a minute of CPU in a fresh build.

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

    #[test]
    fn a_wrong_size_is_refused_and_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.png");
        let e = write(&path, 4, 4, &[0; 15], Channels::Grey).unwrap_err();
        assert!(e.to_string().contains("15 bytes for a 4x4 image"), "{e}");
        assert!(!path.exists());
    }
}
