//! The crate's one PNG codec: every PNG the crate reads or writes (dataset
//! images, the built-in scenes, renders, plots) goes through [`decode`] and
//! [`encode`].
//!
//! - Decoding accepts 8-bit L, LA, RGB and RGBA images (palette images are
//!   expanded to RGB(A) by the decoder); 16-bit and float images are an error
//!   naming the file and the mode.
//! - Encoding has fixed settings (best compression, adaptive filtering), so
//!   the same pixels always give the same bytes with a given version of the
//!   `image` and `png` crates (the committed scene fixtures rely on this).

use crate::error::{Error, Result};
use ::image::codecs::png::{CompressionType, FilterType, PngEncoder};
use ::image::{ColorType, ExtendedColorType, ImageEncoder, ImageFormat};
use std::path::Path;

/// An 8-bit image, interleaved, 1 to 4 channels.
#[derive(Clone, Debug, PartialEq)]
pub struct Image8 {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Channels per pixel: 1 (L), 2 (LA), 3 (RGB) or 4 (RGBA).
    pub channels: usize,
    /// `height · width · channels` bytes, row-major, channels interleaved.
    pub data: Vec<u8>,
}

impl Image8 {
    /// Pixel `p` (row-major index) as RGBA, grey expanded to RGB and a
    /// missing alpha 255 (PIL's `convert("RGBA")`).
    pub fn rgba(&self, p: usize) -> [u8; 4] {
        let s = &self.data[p * self.channels..(p + 1) * self.channels];
        match self.channels {
            1 => [s[0], s[0], s[0], 255],
            2 => [s[0], s[0], s[0], s[1]],
            3 => [s[0], s[1], s[2], 255],
            _ => [s[0], s[1], s[2], s[3]],
        }
    }

    /// The first three channels as interleaved RGB bytes, no compositing
    /// (grey images are expanded, alpha is dropped).
    pub fn rgb(&self) -> Vec<u8> {
        (0..self.width * self.height)
            .flat_map(|p| {
                let px = self.rgba(p);
                [px[0], px[1], px[2]]
            })
            .collect()
    }
}

/// Decode a PNG held in `bytes` (`path` names it in errors). An image of
/// more than [`crate::render::MAX_PIXELS`] pixels is refused from its
/// header, before it is decoded.
pub fn decode(path: &Path, bytes: &[u8]) -> Result<Image8> {
    let mut header =
        ::image::ImageReader::with_format(std::io::Cursor::new(bytes), ImageFormat::Png);
    // (The decoder's own memory limit would refuse the largest sizes
    // without naming them.)
    header.no_limits();
    let (w, h) = header
        .into_dimensions()
        .map_err(|e| Error::format(path, format!("cannot decode PNG: {e}")))?;
    if w as u64 * h as u64 > crate::render::MAX_PIXELS as u64 {
        return Err(Error::format(
            path,
            format!(
                "{w}x{h} pixels, more than the {} an image may have",
                crate::render::MAX_PIXELS
            ),
        ));
    }
    let img = ::image::load_from_memory_with_format(bytes, ImageFormat::Png)
        .map_err(|e| Error::format(path, format!("cannot decode PNG: {e}")))?;
    let channels = match img.color() {
        ColorType::L8 => 1,
        ColorType::La8 => 2,
        ColorType::Rgb8 => 3,
        ColorType::Rgba8 => 4,
        other => {
            return Err(Error::format(
                path,
                format!(
                    "image mode {other:?} is not supported (expected 8-bit L, LA, RGB or RGBA)"
                ),
            ))
        }
    };
    let (width, height) = (img.width() as usize, img.height() as usize);
    Ok(Image8 {
        width,
        height,
        channels,
        data: img.into_bytes(),
    })
}

/// Read and decode a PNG file.
pub fn read(path: &Path) -> Result<Image8> {
    decode(path, &crate::io::read(path)?)
}

/// Encode interleaved 8-bit pixels (`channels` = 1 L, 2 LA, 3 RGB, 4 RGBA)
/// as PNG bytes, with the fixed settings of the module documentation.
pub fn encode(width: usize, height: usize, channels: usize, data: &[u8]) -> Result<Vec<u8>> {
    let ty = match channels {
        1 => ExtendedColorType::L8,
        2 => ExtendedColorType::La8,
        3 => ExtendedColorType::Rgb8,
        4 => ExtendedColorType::Rgba8,
        _ => return Err(Error::invalid("PNG channels", format!("{channels}"))),
    };
    let size = |v: usize| {
        u32::try_from(v)
            .map_err(|_| Error::invalid("PNG size", format!("{width}x{height} is too large")))
    };
    let (w, h) = (size(width)?, size(height)?);
    let want = width
        .checked_mul(height)
        .and_then(|p| p.checked_mul(channels));
    if want != Some(data.len()) {
        return Err(Error::invalid(
            "PNG pixels",
            format!(
                "{} bytes for a {width}x{height} image with {channels} channels",
                data.len()
            ),
        ));
    }
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Best, FilterType::Adaptive)
        .write_image(data, w, h, ty)
        .map_err(|e| Error::invalid("PNG encoding", e.to_string()))?;
    Ok(out)
}

/// Encode and write a PNG file atomically ([`crate::io::write_atomic`]).
pub fn write(path: &Path, width: usize, height: usize, channels: usize, data: &[u8]) -> Result<()> {
    crate::io::write_atomic(path, &encode(width, height, channels, data)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_is_exact_and_deterministic() {
        for channels in 1..=4 {
            let data: Vec<u8> = (0..channels * 3 * 2).map(|i| (i * 7) as u8).collect();
            let png = encode(3, 2, channels, &data).unwrap();
            assert_eq!(png, encode(3, 2, channels, &data).unwrap());
            let img = decode(Path::new("a.png"), &png).unwrap();
            assert_eq!((img.width, img.height, img.channels), (3, 2, channels));
            assert_eq!(img.data, data);
        }
    }

    #[test]
    fn grey_and_alpha_expand_to_rgb() {
        let img = Image8 {
            width: 2,
            height: 1,
            channels: 2,
            data: vec![10, 99, 20, 0],
        };
        assert_eq!(img.rgba(1), [20, 20, 20, 0]);
        assert_eq!(img.rgb(), vec![10, 10, 10, 20, 20, 20]);
    }

    #[test]
    fn bad_input_is_an_error_naming_the_file() {
        let e = decode(Path::new("a.png"), b"not a png")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("a.png: "), "{e}");
        assert!(encode(2, 2, 5, &[0; 20]).is_err());
        // Too few bytes for the stated size.
        assert!(encode(2, 2, 3, &[0; 5]).is_err());
    }

    /// CRC-32 (ISO 3309, as PNG chunks use it), bit by bit.
    fn crc32(bytes: &[u8]) -> u32 {
        let mut c = !0u32;
        for &b in bytes {
            c ^= b as u32;
            for _ in 0..8 {
                c = if c & 1 == 1 {
                    (c >> 1) ^ 0xedb8_8320
                } else {
                    c >> 1
                };
            }
        }
        !c
    }

    #[test]
    fn an_image_past_the_pixel_limit_is_refused_from_its_header() {
        let mut png = encode(1, 1, 3, &[1, 2, 3]).unwrap();
        // IHDR: length (4), "IHDR" (4), width, height (4 each): bytes 8..33.
        let sizes = [
            (8192, 8192, true),
            (8193, 8192, false),
            (1 << 30, 1 << 30, false),
        ];
        for (w, h, ok) in sizes {
            png[16..20].copy_from_slice(&(w as u32).to_be_bytes());
            png[20..24].copy_from_slice(&(h as u32).to_be_bytes());
            let crc = crc32(&png[12..29]);
            png[29..33].copy_from_slice(&crc.to_be_bytes());
            let err = decode(Path::new("big.png"), &png).unwrap_err().to_string();
            // An image within the limit gets past the header to the
            // (truncated) pixel data.
            assert_eq!(err.contains("more than the 67108864"), !ok, "{err}");
            assert!(err.starts_with("big.png: "), "{err}");
        }
    }
}
