//! 8-bit image conversions for the loaders and the scene generator: upstream's RGBA
//! compositing, the integer box downscale, and conversion to `[3, H, W]` f32. PNG decoding
//! and encoding is [`crate::io::png`], re-exported here under the names the loaders use.

use super::Background;
use crate::error::{Error, Result};
use std::path::Path;

use crate::io::png::Image8;

/// Upstream's D-NeRF compositing, interleaved RGB bytes out: `n = v/255` and `a = A/255`
/// in f64, `x = n·a + bg·(1 − a)`, then `x·255` truncated to a byte.
pub fn composite(img: &Image8, bg: Background) -> Vec<u8> {
    let b = bg.value();
    let mut out = Vec::with_capacity(3 * img.width * img.height);
    for p in 0..img.width * img.height {
        let px = img.rgba(p);
        let a = px[3] as f64 / 255.0;
        for &v in &px[..3] {
            let x = (v as f64 / 255.0) * a + b * (1.0 - a);
            out.push((x * 255.0) as u8);
        }
    }
    out
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
    use crate::io::png::{decode as decode_png, encode as encode_png};

    #[test]
    fn opaque_pixels_round_trip_through_compositing() {
        for v in 0..=255u8 {
            let img = Image8 {
                width: 1,
                height: 1,
                channels: 4,
                data: vec![v, v, v, 255],
            };
            assert_eq!(composite(&img, Background::Black), vec![v; 3]);
            assert_eq!(composite(&img, Background::White), vec![v; 3]);
        }
        // Fully transparent pixels become the background.
        let img = Image8 {
            width: 1,
            height: 1,
            channels: 4,
            data: vec![200, 10, 30, 0],
        };
        assert_eq!(composite(&img, Background::Black), vec![0; 3]);
        assert_eq!(composite(&img, Background::White), vec![255; 3]);
        // Half alpha: 200/255·128/255·255 = 100.39 → 100 (truncation).
        let img = Image8 {
            width: 1,
            height: 1,
            channels: 4,
            data: vec![200, 200, 200, 128],
        };
        assert_eq!(composite(&img, Background::Black), vec![100; 3]);
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
        let img = decode_png(Path::new("a.png"), &png).unwrap();
        assert_eq!(img.data, data);
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
