//! Writing renders: 8-bit PNG (through [`crate::io::png`]) (quantised as upstream's `save_image`:
//! `trunc(clamp(x·255 + 0.5, 0, 255))`) and 32-bit float OpenEXR (linear
//! values as rendered, unclamped). Inputs are channel-major `[3, H, W]`.

use crate::error::{Error, Result};
use crate::math::Real;
use std::path::Path;

fn check(path: &Path, len: usize, h: usize, w: usize) -> Result<()> {
    if len != 3 * h * w || h == 0 || w == 0 {
        return Err(Error::invalid(
            format!("image for {}", path.display()),
            format!("{len} values for a 3x{h}x{w} image"),
        ));
    }
    Ok(())
}

/// Encode `[3, H, W]` values as an RGB PNG.
pub fn png_bytes<T: Real>(path: &Path, chw: &[T], h: usize, w: usize) -> Result<Vec<u8>> {
    check(path, chw.len(), h, w)?;
    let mut rgb = vec![0u8; 3 * h * w];
    for c in 0..3 {
        for p in 0..h * w {
            rgb[3 * p + c] = crate::loss::metrics::to_u8(chw[c * h * w + p]);
        }
    }
    crate::io::png::encode(w, h, 3, &rgb)
        .map_err(|e| Error::format(path, format!("cannot encode PNG: {e}")))
}

/// Write `[3, H, W]` values as an 8-bit RGB PNG (atomically).
pub fn write_png<T: Real>(path: &Path, chw: &[T], h: usize, w: usize) -> Result<()> {
    crate::io::write_atomic(path, &png_bytes(path, chw, h, w)?)
}

/// Write `[3, H, W]` values as a float RGB OpenEXR (atomically).
pub fn write_exr<T: Real>(path: &Path, chw: &[T], h: usize, w: usize) -> Result<()> {
    check(path, chw.len(), h, w)?;
    use exr::prelude::{Image, SpecificChannels, Vec2, WritableImage};
    let px = |x: usize, y: usize, c: usize| chw[c * h * w + y * w + x].to_f64() as f32;
    let channels = SpecificChannels::rgb(|Vec2(x, y)| (px(x, y, 0), px(x, y, 1), px(x, y, 2)));
    let image = Image::from_channels((w, h), channels);
    let mut buf = std::io::Cursor::new(Vec::new());
    image
        .write()
        .to_buffered(&mut buf)
        .map_err(|e| crate::Error::format(path, format!("cannot encode EXR: {e}")))?;
    crate::io::write_atomic(path, &buf.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trip_quantises_like_save_image() {
        let (h, w) = (2, 3);
        let chw: Vec<f32> = (0..18).map(|i| i as f32 / 17.0).collect();
        let bytes = png_bytes(Path::new("x.png"), &chw, h, w).unwrap();
        let img = crate::io::png::decode(Path::new("x.png"), &bytes).unwrap();
        assert_eq!((img.width, img.height, img.channels), (w, h, 3));
        for c in 0..3 {
            for p in 0..h * w {
                let want = (chw[c * h * w + p] * 255.0 + 0.5).clamp(0.0, 255.0) as u8;
                assert_eq!(img.data[3 * p + c], want);
            }
        }
    }

    #[test]
    fn exr_round_trip_is_exact_in_f32() {
        let dir = std::env::temp_dir().join(format!("ls-exr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.exr");
        let chw: Vec<f64> = (0..12).map(|i| i as f64 * 0.37 - 1.0).collect();
        write_exr(&path, &chw, 2, 2).unwrap();
        use exr::prelude::*;
        let img = read_first_rgba_layer_from_file(
            &path,
            |res, _| vec![vec![(0f32, 0f32, 0f32); res.width()]; res.height()],
            |px, pos, (r, g, b, _a): (f32, f32, f32, f32)| px[pos.y()][pos.x()] = (r, g, b),
        )
        .unwrap();
        let px = &img.layer_data.channel_data.pixels;
        assert_eq!(px[1][0].1, chw[4 + 2] as f32);
        assert_eq!(px[0][1].2, chw[8 + 1] as f32);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn wrong_size_is_an_error() {
        assert!(png_bytes::<f32>(Path::new("x.png"), &[0.0; 5], 1, 2).is_err());
    }
}
