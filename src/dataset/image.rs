//! 8-bit image plumbing shared by the loaders and the scene generator: PNG decode and encode,
//! upstream's RGBA compositing, the integer box downscale, and conversion to `[3, H, W]` f32.

use super::Background;
use crate::error::{Error, Result};
use std::path::Path;

/// A decoded 8-bit image, interleaved, 1 to 4 channels.
#[derive(Clone, Debug, PartialEq)]
pub struct Image8 {
    pub width: usize,
    pub height: usize,
    /// Channels per pixel: 1 (L), 2 (LA), 3 (RGB) or 4 (RGBA).
    pub channels: usize,
    pub data: Vec<u8>,
}

/// Decode a PNG held in `bytes`. Only 8-bit L, LA, RGB and RGBA images are accepted (palette
/// images are expanded to RGB(A) by the decoder); 16-bit and float images are an error.
pub fn decode_png(path: &Path, bytes: &[u8]) -> Result<Image8> {
    use ::image::{ColorType, ImageFormat};
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
pub fn read_png(path: &Path) -> Result<Image8> {
    decode_png(path, &crate::io::read(path)?)
}

/// Encode interleaved 8-bit pixels as PNG (deterministic: fixed compression and filter).
pub fn encode_png(width: usize, height: usize, channels: usize, data: &[u8]) -> Result<Vec<u8>> {
    use ::image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use ::image::{ExtendedColorType, ImageEncoder};
    let ty = match channels {
        1 => ExtendedColorType::L8,
        2 => ExtendedColorType::La8,
        3 => ExtendedColorType::Rgb8,
        4 => ExtendedColorType::Rgba8,
        _ => return Err(Error::invalid("PNG channels", format!("{channels}"))),
    };
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Best, FilterType::Adaptive)
        .write_image(data, width as u32, height as u32, ty)
        .map_err(|e| Error::invalid("PNG encoding", e.to_string()))?;
    Ok(out)
}

impl Image8 {
    /// The value of channel `c` of pixel `p`, with grey expanded to RGB and a missing alpha 255
    /// (PIL's `convert("RGBA")`).
    fn rgba(&self, p: usize) -> [u8; 4] {
        let s = &self.data[p * self.channels..(p + 1) * self.channels];
        match self.channels {
            1 => [s[0], s[0], s[0], 255],
            2 => [s[0], s[0], s[0], s[1]],
            3 => [s[0], s[1], s[2], 255],
            _ => [s[0], s[1], s[2], s[3]],
        }
    }

    /// Upstream's D-NeRF compositing, interleaved RGB bytes out: `n = v/255` and `a = A/255`
    /// in f64, `x = n·a + bg·(1 − a)`, then `x·255` truncated to a byte.
    pub fn composite(&self, bg: Background) -> Vec<u8> {
        let b = bg.value();
        let mut out = Vec::with_capacity(3 * self.width * self.height);
        for p in 0..self.width * self.height {
            let px = self.rgba(p);
            let a = px[3] as f64 / 255.0;
            for &v in &px[..3] {
                let x = (v as f64 / 255.0) * a + b * (1.0 - a);
                out.push((x * 255.0) as u8);
            }
        }
        out
    }

    /// The first three channels as interleaved RGB bytes, no compositing (nerfies; grey
    /// images are expanded).
    pub fn rgb(&self) -> Vec<u8> {
        (0..self.width * self.height)
            .flat_map(|p| {
                let px = self.rgba(p);
                [px[0], px[1], px[2]]
            })
            .collect()
    }
}

/// Downscale interleaved RGB bytes by an integer factor `r` with an exact box filter: each
/// output byte is the mean of its `r×r` block, rounded half up (`(sum + r²/2) / r²` in
/// integers). Width and height must be multiples of `r`. (Upstream resizes with PIL's
/// default bicubic filter to `round(W/r)`; this is a deliberate, documented difference.)
pub fn box_downscale(path: &Path, rgb: &[u8], w: usize, h: usize, r: usize) -> Result<Vec<u8>> {
    if r == 1 {
        return Ok(rgb.to_vec());
    }
    if !w.is_multiple_of(r) || !h.is_multiple_of(r) {
        return Err(Error::format(
            path,
            format!("image size {w}x{h} is not divisible by the downscale factor {r}"),
        ));
    }
    let (ow, oh) = (w / r, h / r);
    let area = (r * r) as u32;
    let mut out = vec![0u8; 3 * ow * oh];
    for y in 0..oh {
        for x in 0..ow {
            for c in 0..3 {
                let mut s = 0u32;
                for dy in 0..r {
                    for dx in 0..r {
                        s += rgb[3 * ((y * r + dy) * w + x * r + dx) + c] as u32;
                    }
                }
                out[3 * (y * ow + x) + c] = ((s + area / 2) / area) as u8;
            }
        }
    }
    Ok(out)
}

/// Interleaved RGB bytes → `[3, H, W]` f32, `byte as f32 / 255` (upstream's PILtoTorch).
pub fn to_chw(rgb: &[u8], w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0f32; 3 * w * h];
    for p in 0..w * h {
        for c in 0..3 {
            out[c * w * h + p] = rgb[3 * p + c] as f32 / 255.0;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opaque_pixels_round_trip_through_compositing() {
        for v in 0..=255u8 {
            let img = Image8 {
                width: 1,
                height: 1,
                channels: 4,
                data: vec![v, v, v, 255],
            };
            assert_eq!(img.composite(Background::Black), vec![v; 3]);
            assert_eq!(img.composite(Background::White), vec![v; 3]);
        }
        // Fully transparent pixels become the background.
        let img = Image8 {
            width: 1,
            height: 1,
            channels: 4,
            data: vec![200, 10, 30, 0],
        };
        assert_eq!(img.composite(Background::Black), vec![0; 3]);
        assert_eq!(img.composite(Background::White), vec![255; 3]);
        // Half alpha: 200/255·128/255·255 = 100.39 → 100 (truncation).
        let img = Image8 {
            width: 1,
            height: 1,
            channels: 4,
            data: vec![200, 200, 200, 128],
        };
        assert_eq!(img.composite(Background::Black), vec![100; 3]);
    }

    #[test]
    fn box_downscale_averages_blocks() {
        // 4x2 image, factor 2: blocks (0,1,4,5)... per channel.
        let rgb: Vec<u8> = (0..24).map(|i| (i * 10) as u8).collect();
        let out = box_downscale(Path::new("x"), &rgb, 4, 2, 2).unwrap();
        // Output pixel 0 channel 0: bytes at pixels 0,1,4,5 → 0,30,120,150 → 75.
        assert_eq!(out[0], 75);
        assert_eq!(out.len(), 6);
        assert!(box_downscale(Path::new("x"), &rgb, 4, 2, 4).is_err());
    }

    #[test]
    fn png_round_trip_and_bad_modes() {
        let data: Vec<u8> = (0..4 * 3 * 2).map(|i| (i * 7) as u8).collect();
        let png = encode_png(3, 2, 4, &data).unwrap();
        assert_eq!(png, encode_png(3, 2, 4, &data).unwrap());
        let img = decode_png(Path::new("a.png"), &png).unwrap();
        assert_eq!((img.width, img.height, img.channels), (3, 2, 4));
        assert_eq!(img.data, data);
        let e = decode_png(Path::new("a.png"), b"not a png")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("a.png: "), "{e}");
        // A 16-bit PNG is refused with the mode named.
        let mut png16 = Vec::new();
        {
            use ::image::codecs::png::PngEncoder;
            use ::image::{ExtendedColorType, ImageEncoder};
            PngEncoder::new(&mut png16)
                .write_image(&[0u8; 6], 1, 1, ExtendedColorType::Rgb16)
                .unwrap();
        }
        let e = decode_png(Path::new("b.png"), &png16)
            .unwrap_err()
            .to_string();
        assert!(e.contains("b.png") && e.contains("Rgb16"), "{e}");
    }
}
