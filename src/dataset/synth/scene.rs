//! The analytic shapes, the built-in animated scenes, and the ray caster that draws them.
//!
//! This renderer is independent of the splatting rasterizer on purpose: ground truth comes
//! from exact ray–shape intersections. Shading is Lambert with a fixed directional light plus
//! ambient: `albedo · (0.3 + 0.7·max(0, n·l))`. Coverage comes from a fixed `S×S` grid of
//! sub-pixel samples at `((a + ½)/S, (b + ½)/S)`; the pixel's alpha is the fraction of samples
//! that hit, its colour the mean colour of the hits (straight, not premultiplied alpha).
//! All arithmetic is f64 with transcendental functions from the pinned `libm`.

use crate::camera::Camera;
use crate::math::Rng;
use glam::DVec3;
use std::f64::consts::PI;

/// An analytic shape with a colour.
#[derive(Clone, Debug, PartialEq)]
///
/// Positions and lengths are in world units; `albedo` is linear RGB in `[0, 1]`.
pub enum Shape {
    /// A ball.
    Sphere {
        /// Centre.
        centre: DVec3,
        /// Radius.
        radius: f64,
        /// Colour.
        albedo: DVec3,
    },
    /// All points within `radius` of the segment `a`–`b`.
    Capsule {
        /// One end of the axis.
        a: DVec3,
        /// The other end of the axis.
        b: DVec3,
        /// Distance of the surface from the axis.
        radius: f64,
        /// Colour.
        albedo: DVec3,
    },
    /// Axis-aligned box.
    Box {
        /// Centre.
        centre: DVec3,
        /// Half the edge length along each axis.
        half: DVec3,
        /// Colour.
        albedo: DVec3,
    },
}

impl Shape {
    fn albedo(&self) -> DVec3 {
        match self {
            Shape::Sphere { albedo, .. }
            | Shape::Capsule { albedo, .. }
            | Shape::Box { albedo, .. } => *albedo,
        }
    }

    /// Nearest hit distance along the ray (`dir` unit) with `t > 1e-9`, and the unit normal.
    fn intersect(&self, o: DVec3, d: DVec3) -> Option<(f64, DVec3)> {
        match *self {
            Shape::Sphere { centre, radius, .. } => {
                let oc = o - centre;
                let b = oc.dot(d);
                let c = oc.dot(oc) - radius * radius;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                let t = if -b - s > 1e-9 { -b - s } else { -b + s };
                (t > 1e-9).then(|| (t, (o + d * t - centre).normalize()))
            }
            Shape::Capsule { a, b, radius, .. } => {
                // Cylinder body, then the two end spheres (closest hit wins).
                let ba = b - a;
                let oa = o - a;
                let baba = ba.dot(ba);
                let bard = ba.dot(d);
                let baoa = ba.dot(oa);
                let rdoa = d.dot(oa);
                let oaoa = oa.dot(oa);
                let qa = baba - bard * bard;
                let qb = baba * rdoa - baoa * bard;
                let qc = baba * oaoa - baoa * baoa - radius * radius * baba;
                let mut best: Option<(f64, DVec3)> = None;
                if qa > 1e-12 {
                    let h = qb * qb - qa * qc;
                    if h >= 0.0 {
                        let t = (-qb - h.sqrt()) / qa;
                        let y = baoa + t * bard;
                        if t > 1e-9 && y > 0.0 && y < baba {
                            let p = o + d * t;
                            let axis = a + ba * (y / baba);
                            best = Some((t, (p - axis).normalize()));
                        }
                    }
                }
                for end in [a, b] {
                    let s = Shape::Sphere {
                        centre: end,
                        radius,
                        albedo: DVec3::ZERO,
                    };
                    if let Some(h) = s.intersect(o, d) {
                        if best.is_none_or(|b| h.0 < b.0) {
                            best = Some(h);
                        }
                    }
                }
                best
            }
            Shape::Box { centre, half, .. } => {
                let mut tmin = f64::NEG_INFINITY;
                let mut tmax = f64::INFINITY;
                let mut axis = 0;
                let mut sign = 1.0;
                for k in 0..3 {
                    let lo = centre[k] - half[k];
                    let hi = centre[k] + half[k];
                    if d[k] == 0.0 {
                        if o[k] < lo || o[k] > hi {
                            return None;
                        }
                        continue;
                    }
                    let (mut t0, mut t1) = ((lo - o[k]) / d[k], (hi - o[k]) / d[k]);
                    let mut s = -1.0;
                    if t0 > t1 {
                        std::mem::swap(&mut t0, &mut t1);
                        s = 1.0;
                    }
                    if t0 > tmin {
                        tmin = t0;
                        axis = k;
                        sign = s;
                    }
                    tmax = tmax.min(t1);
                }
                if tmin > tmax || tmin <= 1e-9 {
                    return None;
                }
                let mut n = DVec3::ZERO;
                n[axis] = sign;
                Some((tmin, n))
            }
        }
    }

    /// A point on the surface drawn from `r` (roughly uniform; used for seed point clouds).
    fn sample_surface(&self, r: &mut Rng) -> DVec3 {
        let unit = |r: &mut Rng| {
            let (x, y, z) = (r.normal(), r.normal(), r.normal());
            DVec3::new(x, y, z).normalize()
        };
        match *self {
            Shape::Sphere { centre, radius, .. } => centre + unit(r) * radius,
            Shape::Capsule { a, b, radius, .. } => {
                let ba = b - a;
                let axis = ba.normalize();
                let u = unit(r);
                let perp = (u - axis * u.dot(axis)).normalize();
                let along = r.uniform();
                a + ba * along + perp * radius
            }
            Shape::Box { centre, half, .. } => {
                let face = r.below(6) as usize;
                let k = face % 3;
                let mut p = DVec3::ZERO;
                for j in 0..3 {
                    p[j] = if j == k {
                        if face < 3 {
                            half[j]
                        } else {
                            -half[j]
                        }
                    } else {
                        r.uniform_range(-half[j], half[j])
                    }
                }
                centre + p
            }
        }
    }
}

/// The built-in scenes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneName {
    /// Three balls bouncing on a floor tile: rigid motion.
    Bouncing,
    /// A hanging chain of three capsules swinging fast: high-frequency articulated motion.
    Swing,
    /// Six overlapping spheres pulsating out of phase: a non-rigid, deforming blob.
    Blob,
}

impl SceneName {
    /// Every scene, in a fixed order.
    pub const ALL: [SceneName; 3] = [SceneName::Bouncing, SceneName::Swing, SceneName::Blob];

    /// Parse a scene name.
    pub fn parse(s: &str) -> Option<SceneName> {
        SceneName::ALL.into_iter().find(|n| n.name() == s)
    }

    /// Parse a scene name given as `what` (an option, an argument); an
    /// unknown one is an error naming `what` and the scenes there are.
    pub fn parse_named(what: &str, s: &str) -> crate::Result<SceneName> {
        SceneName::parse(s).ok_or_else(|| {
            let names: Vec<&str> = SceneName::ALL.iter().map(|n| n.name()).collect();
            crate::Error::invalid(what, format!("`{s}` is not one of {}", names.join(", ")))
        })
    }

    /// The scene's name.
    pub fn name(self) -> &'static str {
        match self {
            SceneName::Bouncing => "bouncing",
            SceneName::Swing => "swing",
            SceneName::Blob => "blob",
        }
    }

    /// The shapes at time `t ∈ [0, 1]`. Everything stays inside `[-1.3, 1.3]³`.
    pub fn shapes(self, t: f64) -> Vec<Shape> {
        let s = |x: f64| libm::sin(x);
        let c = |x: f64| libm::cos(x);
        match self {
            SceneName::Bouncing => {
                let floor = -0.8;
                let mut v = vec![Shape::Box {
                    centre: DVec3::new(0.0, 0.0, floor - 0.06),
                    half: DVec3::new(0.9, 0.9, 0.06),
                    albedo: DVec3::new(0.55, 0.55, 0.6),
                }];
                let balls = [
                    (0.30, [0.9, 0.2, 0.15], 2.0, 0.0, 0.5),
                    (0.22, [0.2, 0.8, 0.3], 3.0, 1.3, -0.4),
                    (0.18, [0.2, 0.35, 0.95], 5.0, 2.1, 0.1),
                ];
                for (k, &(radius, albedo, freq, phase, x0)) in balls.iter().enumerate() {
                    let height = 1.1 * s(PI * freq * t + phase).abs();
                    let ang = 2.0 * PI * t + k as f64 * 2.0;
                    v.push(Shape::Sphere {
                        centre: DVec3::new(
                            x0 + 0.15 * c(ang),
                            0.5 * s(ang + k as f64),
                            floor + radius + height,
                        ),
                        radius,
                        albedo: DVec3::from(albedo),
                    });
                }
                v
            }
            SceneName::Swing => {
                let top = DVec3::new(0.0, 0.0, 0.95);
                let mut v = vec![Shape::Box {
                    centre: DVec3::new(0.0, 0.0, 1.02),
                    half: DVec3::new(0.3, 0.08, 0.05),
                    albedo: DVec3::new(0.5, 0.5, 0.5),
                }];
                let len = 0.4;
                let colours = [[0.95, 0.6, 0.1], [0.2, 0.7, 0.9], [0.85, 0.25, 0.6]];
                let (mut p, mut angle) = (top, 0.0);
                let yaw = 0.4 * s(2.0 * PI * 2.0 * t);
                for (k, albedo) in colours.into_iter().enumerate() {
                    let f = [3.0, 5.0, 7.0][k];
                    angle += [0.7, 0.8, 1.0][k] * s(2.0 * PI * f * t + k as f64);
                    let dir = DVec3::new(s(angle) * c(yaw), s(angle) * s(yaw), -c(angle));
                    let q = p + dir * len;
                    v.push(Shape::Capsule {
                        a: p,
                        b: q,
                        radius: 0.09,
                        albedo: DVec3::from(albedo),
                    });
                    p = q;
                }
                v
            }
            SceneName::Blob => (0..6)
                .map(|i| {
                    let fi = i as f64;
                    let dir = DVec3::new(
                        c(2.0 * PI * fi / 6.0) * c(0.5 * fi),
                        s(2.0 * PI * fi / 6.0) * c(0.5 * fi),
                        s(0.5 * fi) - 0.3,
                    );
                    let reach = 0.35 * (1.0 + 0.4 * s(2.0 * PI * (t + fi / 3.0)));
                    Shape::Sphere {
                        centre: dir * reach,
                        radius: 0.35 + 0.12 * s(2.0 * PI * (2.0 * t + fi / 6.0)),
                        albedo: DVec3::new(0.9 - 0.1 * fi, 0.3 + 0.1 * fi, 0.5 + 0.05 * fi),
                    }
                })
                .collect(),
        }
    }

    /// `n` points on the surfaces at time 0 (for `points.npy`), shapes in turn.
    pub fn surface_points(self, n: usize, seed: u64) -> Vec<f64> {
        let shapes = self.shapes(0.0);
        let mut r = Rng::new(seed);
        (0..n)
            .flat_map(|i| shapes[i % shapes.len()].sample_surface(&mut r).to_array())
            .collect()
    }
}

const LIGHT: DVec3 = DVec3::new(0.4, 0.3, 0.866);
const AMBIENT: f64 = 0.3;

/// Render `shapes` through `camera` to interleaved RGBA bytes with `ss × ss` samples a pixel.
pub fn render(shapes: &[Shape], camera: &Camera, ss: usize) -> Vec<u8> {
    let (w, h) = (camera.width, camera.height);
    let (fx, fy) = camera.focal();
    let rt = camera.rotation_matrix().transpose();
    let o = DVec3::from(camera.centre());
    let l = LIGHT.normalize();
    let mut out = Vec::with_capacity(4 * w * h);
    for py in 0..h {
        for px in 0..w {
            let mut sum = [0.0; 3];
            let mut hits = 0usize;
            for a in 0..ss {
                for b in 0..ss {
                    let u = px as f64 + (b as f64 + 0.5) / ss as f64;
                    let v = py as f64 + (a as f64 + 0.5) / ss as f64;
                    let dc = DVec3::new((u - w as f64 / 2.0) / fx, (v - h as f64 / 2.0) / fy, 1.0);
                    // World direction Rᵀ·dc.
                    let d = (rt * dc).normalize();
                    let mut best: Option<(f64, DVec3, DVec3)> = None;
                    for s in shapes {
                        if let Some((t, n)) = s.intersect(o, d) {
                            if best.is_none_or(|b| t < b.0) {
                                best = Some((t, n, s.albedo()));
                            }
                        }
                    }
                    if let Some((_, n, alb)) = best {
                        let shade = AMBIENT + (1.0 - AMBIENT) * n.dot(l).max(0.0);
                        for k in 0..3 {
                            sum[k] += (alb[k] * shade).min(1.0);
                        }
                        hits += 1;
                    }
                }
            }
            let byte = |x: f64| (x * 255.0 + 0.5).floor().clamp(0.0, 255.0) as u8;
            if hits == 0 {
                out.extend([0, 0, 0, 0]);
            } else {
                for s in sum {
                    out.push(byte(s / hits as f64));
                }
                out.push(byte(hits as f64 / (ss * ss) as f64));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intersections_are_correct() {
        let o = DVec3::new(0.0, 0.0, -5.0);
        let d = DVec3::Z;
        let sph = Shape::Sphere {
            centre: DVec3::ZERO,
            radius: 1.0,
            albedo: DVec3::ONE,
        };
        assert_eq!(sph.intersect(o, d), Some((4.0, DVec3::NEG_Z)));
        let cap = Shape::Capsule {
            a: DVec3::NEG_X,
            b: DVec3::X,
            radius: 0.5,
            albedo: DVec3::ONE,
        };
        let (t, n) = cap.intersect(o, d).unwrap();
        assert!((t - 4.5).abs() < 1e-12 && (n[2] + 1.0).abs() < 1e-12);
        // Along the axis the end cap is hit.
        let (t, _) = cap.intersect(DVec3::new(-5.0, 0.0, 0.0), DVec3::X).unwrap();
        assert!((t - 3.5).abs() < 1e-12);
        let bx = Shape::Box {
            centre: DVec3::ZERO,
            half: DVec3::new(1.0, 2.0, 0.5),
            albedo: DVec3::ONE,
        };
        assert_eq!(bx.intersect(o, d), Some((4.5, DVec3::NEG_Z)));
        assert_eq!(bx.intersect(DVec3::new(3.0, 0.0, -5.0), d), None);
    }

    #[test]
    fn scenes_stay_in_the_box() {
        for name in SceneName::ALL {
            for k in 0..=20 {
                let t = k as f64 / 20.0;
                let mut r = Rng::new(1);
                for s in name.shapes(t) {
                    for _ in 0..50 {
                        let p = s.sample_surface(&mut r);
                        assert!(p.abs().max_element() < 1.3, "{name:?} {t} {p:?}");
                    }
                }
            }
        }
    }
}
