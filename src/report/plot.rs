//! Line plots drawn pixel by pixel into an RGB buffer and encoded as PNG:
//! axes, "nice" ticks (1, 2, 5 × 10^k) labelled with a built-in 3×5 bitmap
//! font, one line per series, and a legend by colour. No fonts, no plotting
//! crate, no transcendental functions: the same input gives the same bytes.

use crate::error::{Error, Result};

/// One line: a label for the legend, its colour and its (x, y) points in
/// order. Non-finite points break the line.
#[derive(Clone, Debug)]
pub struct Series {
    /// The legend's label.
    pub label: String,
    /// Line colour, RGB.
    pub color: [u8; 3],
    /// The points `(x, y)` in drawing order.
    pub points: Vec<(f64, f64)>,
}

/// Distinct line colours (the Tableau 10 palette).
pub const PALETTE: [[u8; 3]; 10] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
];

/// Plot width in pixels.
pub const WIDTH: u32 = 800;
/// Plot height in pixels.
pub const HEIGHT: u32 = 480;
const LEFT: i64 = 70;
const RIGHT: i64 = 230; // legend column
const TOP: i64 = 34;
const BOTTOM: i64 = 46;
const SCALE: i64 = 2; // font pixel size

/// Characters of the built-in 3×5 font, and their glyphs: one octal digit
/// per row, top row first, each digit's 3 bits the row's pixels left to right.
/// The last glyph ('?') stands for any character not listed.
const FONT_CHARS: &str = "0123456789abcdefghijklmnopqrstuvwxyz-._:+()/= ?";
const FONT_GLYPHS: [u16; 47] = [
    0o75557, 0o26227, 0o71747, 0o71717, 0o55711, 0o74717, 0o74757, 0o71222, 0o75757, 0o75717,
    0o25755, 0o65656, 0o34443, 0o65556, 0o74647, 0o74644, 0o34553, 0o55755, 0o72227, 0o11152,
    0o55655, 0o44447, 0o57755, 0o65555, 0o25552, 0o65644, 0o25563, 0o65655, 0o34216, 0o72222,
    0o55557, 0o55552, 0o55775, 0o55255, 0o55222, 0o71247, 0o00700, 0o00002, 0o00007, 0o02020,
    0o02720, 0o12221, 0o42224, 0o11244, 0o07070, 0o00000, 0o71202,
];

/// Horizontal advance of one character in pixels.
pub const CHAR_W: i64 = 4 * SCALE;

struct Canvas {
    w: i64,
    h: i64,
    rgb: Vec<u8>,
}

impl Canvas {
    fn put(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if (0..self.w).contains(&x) && (0..self.h).contains(&y) {
            let i = 3 * (y * self.w + x) as usize;
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }
    fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, c: [u8; 3]) {
        for yy in y..y + h {
            for xx in x..x + w {
                self.put(xx, yy, c);
            }
        }
    }
    /// Text with its top-left corner at (x, y); upper case is drawn as lower case.
    fn text(&mut self, x: i64, y: i64, s: &str, c: [u8; 3]) {
        for (i, ch) in s.chars().enumerate() {
            let ch = ch.to_ascii_lowercase();
            let g = FONT_GLYPHS[FONT_CHARS.find(ch).unwrap_or(FONT_GLYPHS.len() - 1)];
            for row in 0..5 {
                for col in 0..3 {
                    if g >> (3 * (4 - row) + 2 - col) & 1 != 0 {
                        let px = x + i as i64 * CHAR_W + col * SCALE;
                        self.rect(px, y + row * SCALE, SCALE, SCALE, c);
                    }
                }
            }
        }
    }
    /// A 2-pixel-thick segment (DDA with the step count of the longer side).
    fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), c: [u8; 3]) {
        let n = (x1 - x0).abs().max((y1 - y0).abs()).ceil().max(1.0) as i64;
        for k in 0..=n {
            let f = k as f64 / n as f64;
            let x = (x0 + (x1 - x0) * f).round() as i64;
            let y = (y0 + (y1 - y0) * f).round() as i64;
            self.rect(x, y, 2, 2, c);
        }
    }
}

/// Tick step (1, 2 or 5 × 10^k) giving about five intervals over `span`,
/// and the decimals its labels need.
fn nice_step(span: f64) -> (f64, usize) {
    let raw = span / 5.0;
    let (mut p, mut decimals) = (1.0f64, 0usize);
    while p > raw {
        p /= 10.0;
        decimals += 1;
    }
    while p * 10.0 <= raw {
        p *= 10.0;
        decimals = decimals.saturating_sub(1);
    }
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * p)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * p);
    if step >= 10.0 * p {
        decimals = decimals.saturating_sub(1);
    }
    (step, decimals)
}

/// Axis range rounded out to whole ticks, and the ticks. A range too
/// narrow for its ticks (equal ends, or a span below 1e-300) is widened
/// around its middle; one wider than `f64` can hold is an error.
fn axis(lo: f64, hi: f64) -> Result<(f64, f64, Vec<f64>, usize)> {
    if !(hi - lo).is_finite() {
        return Err(Error::invalid(
            "plot axis",
            format!("values from {lo:e} to {hi:e}: the range is too wide to draw"),
        ));
    }
    let (lo, hi) = if hi - lo > 1e-300 {
        (lo, hi)
    } else {
        let pad = (lo.abs() * 0.05).max(1e-300);
        let pad = if lo == 0.0 { 1.0 } else { pad };
        (lo - pad, hi + pad)
    };
    let (step, decimals) = nice_step(hi - lo);
    let (a, b) = ((lo / step).floor(), (hi / step).ceil());
    let ticks = (0..=(b - a) as i64)
        .map(|k| (a + k as f64) * step)
        .collect();
    Ok((a * step, b * step, ticks, decimals))
}

/// Draw a line plot and return PNG bytes of `WIDTH`×`HEIGHT` pixels.
pub fn line_plot_png(title: &str, x_label: &str, series: &[Series]) -> Result<Vec<u8>> {
    let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let pts: Vec<(f64, f64)> = series
        .iter()
        .flat_map(|s| s.points.iter().filter(finite).copied())
        .collect();
    if pts.is_empty() {
        return Err(Error::invalid(
            format!("plot {title:?}"),
            "no finite points to draw",
        ));
    }
    let min_max = |f: fn(&(f64, f64)) -> f64| {
        pts.iter()
            .map(f)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                (a.min(v), b.max(v))
            })
    };
    let (x0, x1, xt, xd) = {
        let (a, b) = min_max(|p| p.0);
        axis(a, b)?
    };
    let (y0, y1, yt, yd) = {
        let (a, b) = min_max(|p| p.1);
        axis(a, b)?
    };
    let (w, h) = (WIDTH as i64, HEIGHT as i64);
    let mut cv = Canvas {
        w,
        h,
        rgb: vec![255; (3 * w * h) as usize],
    };
    let (pw, ph) = ((w - LEFT - RIGHT) as f64, (h - TOP - BOTTOM) as f64);
    let px = |x: f64| LEFT as f64 + (x - x0) / (x1 - x0) * pw;
    let py = |y: f64| (h - BOTTOM) as f64 - (y - y0) / (y1 - y0) * ph;
    let (grid, ink) = ([225, 225, 225], [0, 0, 0]);
    for &t in &xt {
        let x = px(t).round() as i64;
        cv.rect(x, TOP, 1, h - TOP - BOTTOM, grid);
        let s = format!("{t:.xd$}");
        cv.text(x - CHAR_W * s.len() as i64 / 2, h - BOTTOM + 8, &s, ink);
    }
    for &t in &yt {
        let y = py(t).round() as i64;
        cv.rect(LEFT, y, w - LEFT - RIGHT, 1, grid);
        let s = format!("{t:.yd$}");
        cv.text(LEFT - 6 - CHAR_W * s.len() as i64, y - 5, &s, ink);
    }
    cv.rect(LEFT, TOP, 1, h - TOP - BOTTOM + 1, ink);
    cv.rect(LEFT, h - BOTTOM, w - LEFT - RIGHT + 1, 1, ink);
    cv.text(LEFT, 10, title, ink);
    cv.text(
        LEFT + (pw as i64 - CHAR_W * x_label.chars().count() as i64) / 2,
        h - 18,
        x_label,
        ink,
    );
    for (i, s) in series.iter().enumerate() {
        for seg in s.points.windows(2) {
            if finite(&&seg[0]) && finite(&&seg[1]) {
                cv.line(
                    (px(seg[0].0), py(seg[0].1)),
                    (px(seg[1].0), py(seg[1].1)),
                    s.color,
                );
            }
        }
        if let [p] = s.points[..] {
            if finite(&&p) {
                cv.rect(
                    px(p.0).round() as i64 - 2,
                    py(p.1).round() as i64 - 2,
                    5,
                    5,
                    s.color,
                );
            }
        }
        let y = TOP + 4 + 18 * i as i64;
        cv.rect(w - RIGHT + 10, y + 3, 16, 4, s.color);
        let max_chars = ((RIGHT - 36) / CHAR_W) as usize;
        let label: String = s.label.chars().take(max_chars).collect();
        cv.text(w - RIGHT + 32, y, &label, ink);
    }
    crate::io::png::encode(WIDTH as usize, HEIGHT as usize, 3, &cv.rgb)
        .map_err(|e| Error::invalid(format!("plot {title:?}"), format!("cannot encode PNG: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_series() -> Vec<Series> {
        let a = (0..=20)
            .map(|i| (100.0 * i as f64, 0.2 / (1.0 + i as f64)))
            .collect();
        let b = (0..=20)
            .map(|i| {
                (
                    100.0 * i as f64,
                    if i == 7 {
                        f64::NAN
                    } else {
                        0.15 / (1.0 + i as f64)
                    },
                )
            })
            .collect();
        vec![
            Series {
                label: "mlp-d8-w256-relu".into(),
                color: PALETTE[0],
                points: a,
            },
            Series {
                label: "cfc-d6-w128-gelu".into(),
                color: PALETTE[1],
                points: b,
            },
        ]
    }

    #[test]
    fn plot_is_a_deterministic_png_of_the_stated_size() {
        let s = two_series();
        let png = line_plot_png("lego: training loss", "iteration", &s).unwrap();
        assert_eq!(
            png,
            line_plot_png("lego: training loss", "iteration", &s).unwrap()
        );
        let img = image::load_from_memory_with_format(&png, image::ImageFormat::Png)
            .unwrap()
            .to_rgb8();
        assert_eq!(img.dimensions(), (WIDTH, HEIGHT));
        // Both line colours are drawn, inside the plot area as well as in the legend.
        for c in [PALETTE[0], PALETTE[1]] {
            let inside = img
                .enumerate_pixels()
                .filter(|(x, _, p)| (*x as i64) < WIDTH as i64 - RIGHT && p.0 == c)
                .count();
            assert!(inside > 100, "{c:?}: {inside} pixels");
        }
        // The first point (x = 0, y = 0.2) lies on the axis corner's column: x pixel LEFT.
        let top_of_a = (0..HEIGHT).find(|&y| img.get_pixel(LEFT as u32, y).0 == PALETTE[0]);
        assert!(top_of_a.is_some());
    }

    #[test]
    fn nice_ticks() {
        assert_eq!(nice_step(2000.0), (500.0, 0));
        let (s, d) = nice_step(0.1);
        assert!((s - 0.02).abs() < 1e-15 && d == 2, "{s} {d}");
        assert_eq!(nice_step(7.0), (2.0, 0));
        assert_eq!(nice_step(4.0), (1.0, 0));
        let (s, d) = nice_step(0.03);
        assert!((s - 0.01).abs() < 1e-15 && d == 2, "{s} {d}");
        // Span 0.187: step 0.05, range rounded out to [0, 0.2], ticks 0, 0.05, …, 0.2.
        let (lo, hi, ticks, d) = axis(0.013, 0.2).unwrap();
        assert!(
            lo == 0.0 && (hi - 0.2).abs() < 1e-15 && d == 2 && ticks.len() == 5,
            "{lo} {hi} {ticks:?}"
        );
        let (lo, hi, _, _) = axis(5.0, 5.0).unwrap();
        assert!(lo < 5.0 && hi > 5.0);
        // Ranges whose ticks could not be stepped: tiny, subnormal, huge.
        for (a, b) in [
            (1e-323, 1e-323),
            (0.0, 5e-324),
            (1.0, 1.0 + 1e-16),
            (1e300, 1e300),
        ] {
            let (lo, hi, ticks, _) = axis(a, b).unwrap();
            assert!(
                lo <= a && hi >= b && (2..=12).contains(&ticks.len()),
                "{a} {b}: {ticks:?}"
            );
        }
        assert!(axis(-1e308, 1e308).is_err());
    }

    #[test]
    fn empty_plot_is_an_error() {
        let s = vec![Series {
            label: "x".into(),
            color: PALETTE[0],
            points: vec![(0.0, f64::NAN)],
        }];
        assert!(line_plot_png("t", "iteration", &s).is_err());
    }
}
