//! Surface textures, generated once per building and baked with its static lighting.
//!
//! Feature trackers need corners, so surfaces are not flat colours: walls carry plaster grain,
//! posters with blocks, stripes and blobs, stickers and a skirting board; floors are tiles with
//! grout and scuffs; ceilings are panels with light fixtures. Everything is drawn from a seeded
//! random source, so a building looks the same on every run. Lighting is Lambertian from lamps
//! under the ceiling of each space, which does not depend on the viewpoint and can be baked.

use crate::random::Random;

/// A grey texture over a surface rectangle, one byte per texel; texel (0, 0) sits at the
/// rectangle's (u_min, v_min) corner.
#[derive(Clone, Debug)]
pub(crate) struct Texture {
    pub width: usize,
    pub height: usize,
    /// Texel side, metres.
    pub texel: f64,
    pub data: Vec<u8>,
}

impl Texture {
    /// Bilinear sample at surface-local metres (from the rectangle's min corner).
    #[inline]
    pub fn sample(&self, u: f64, v: f64) -> f32 {
        let x = (u / self.texel - 0.5).clamp(0.0, (self.width - 1) as f64);
        let y = (v / self.texel - 0.5).clamp(0.0, (self.height - 1) as f64);
        let (x0, y0) = (x as usize, y as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let at = |x: usize, y: usize| f32::from(self.data[y * self.width + x]);
        let top = at(x0, y0) + (at(x1, y0) - at(x0, y0)) * fx;
        let bottom = at(x0, y1) + (at(x1, y1) - at(x0, y1)) * fx;
        top + (bottom - top) * fy
    }
}

/// What a surface is, which decides its pattern.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Pattern {
    Wall,
    Floor,
    Ceiling,
}

/// A rectangle in surface-local metres, `[u0, u1, v0, v1]`, kept clear of decoration (markers
/// and their quiet zone).
pub(crate) type Keepout = [f64; 4];

/// Lamp positions and how the light falls on a surface point with a given normal.
pub(crate) struct Lighting<'a> {
    pub lamps: &'a [[f64; 3]],
    pub ambient: f64,
    pub gain: f64,
}

impl Lighting<'_> {
    /// Brightness factor (about 0.5–1.2) at `p` with unit normal `n`.
    pub fn at(&self, p: [f64; 3], n: [f64; 3]) -> f64 {
        let mut irradiance = 0.0;
        for lamp in self.lamps {
            let d = [lamp[0] - p[0], lamp[1] - p[1], lamp[2] - p[2]];
            let r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + 0.05;
            let cos = (d[0] * n[0] + d[1] * n[1] + d[2] * n[2]).max(0.0);
            irradiance += cos / (r2 * r2.sqrt());
        }
        (self.ambient + self.gain * irradiance).min(1.2)
    }
}

/// The surface's geometry as the generator needs it.
pub(crate) struct Canvas<'a> {
    pub size: [f64; 2],
    pub texel: f64,
    pub pattern: Pattern,
    pub keepout: &'a [Keepout],
    /// World point of surface-local (u, v).
    pub world: &'a (dyn Fn(f64, f64) -> [f64; 3] + Sync),
    pub normal: [f64; 3],
    pub seed: u64,
}

/// Generates and lights a surface's texture.
pub(crate) fn generate(canvas: &Canvas, lighting: &Lighting) -> Texture {
    let width = ((canvas.size[0] / canvas.texel).ceil() as usize).max(2);
    let height = ((canvas.size[1] / canvas.texel).ceil() as usize).max(2);
    let mut albedo = vec![0f32; width * height];
    let noise = Noise(canvas.seed);
    let texel = canvas.texel;
    let centre = |i: usize| (i as f64 + 0.5) * texel;
    for y in 0..height {
        let v = centre(y);
        for x in 0..width {
            let u = centre(x);
            albedo[y * width + x] = (match canvas.pattern {
                Pattern::Wall => {
                    let stains = 24.0 * (noise.fbm(u / 0.7, v / 0.7, 3) - 0.5);
                    let grain = 26.0 * (noise.at(u / 0.035, v / 0.035, 11) - 0.5)
                        + 22.0 * (noise.at(u / 0.011, v / 0.011, 12) - 0.5);
                    let skirting = if v < 0.09 { -85.0 } else { 0.0 };
                    178.0 + stains + grain + skirting
                }
                Pattern::Floor => {
                    let tile = 0.5;
                    let (i, j) = ((u / tile).floor(), (v / tile).floor());
                    let grout = (u - i * tile).min(v - j * tile) < 0.008;
                    let shade = 110.0 + 50.0 * noise.lattice(i as i64, j as i64, 21);
                    let grain = 30.0 * (noise.fbm(u / 0.05, v / 0.05, 2) - 0.5);
                    if grout {
                        65.0 + grain * 0.3
                    } else {
                        shade + grain
                    }
                }
                Pattern::Ceiling => {
                    let panel = 0.6;
                    let (fu, fv) = (u.rem_euclid(panel), v.rem_euclid(panel));
                    let frame = fu.min(fv) < 0.015;
                    let grain = 16.0 * (noise.at(u / 0.02, v / 0.02, 31) - 0.5);
                    if frame {
                        120.0
                    } else {
                        205.0 + grain
                    }
                }
            }) as f32;
        }
    }
    let mut painter = Painter {
        albedo: &mut albedo,
        width,
        height,
        texel,
        keepout: canvas.keepout.to_vec(),
    };
    let mut random = Random::derive(canvas.seed, 0x5EED);
    let area = canvas.size[0] * canvas.size[1];
    match canvas.pattern {
        Pattern::Wall => {
            // About one poster per metre of wall, some tries failing where they would overlap.
            let posters = (canvas.size[0] * 1.3).round() as usize + 1;
            for _ in 0..posters {
                painter.poster(&mut random, &noise, canvas.size);
            }
            // Notes, stickers, switches and scuffs: small marks, light and dark.
            for _ in 0..(area * 45.0) as usize {
                let centre = [
                    random.range(0.0, canvas.size[0]),
                    random.range(0.12, canvas.size[1]),
                ];
                let size = random.range(0.008, 0.035);
                let grey = if random.uniform() < 0.7 {
                    random.range(20.0, 90.0)
                } else {
                    random.range(225.0, 255.0)
                } as f32;
                if random.uniform() < 0.5 {
                    painter.disc(centre, size, grey);
                } else {
                    // Elongated, like labels and switches: a dark square would read as an
                    // all-black marker.
                    let aspect = random.range(1.7, 3.0);
                    let half = if random.uniform() < 0.5 {
                        [size * aspect, size / aspect]
                    } else {
                        [size / aspect, size * aspect]
                    };
                    painter.block(centre, half, grey);
                }
            }
        }
        Pattern::Floor => {
            for _ in 0..(area * 1.5) as usize {
                let centre = [
                    random.range(0.0, canvas.size[0]),
                    random.range(0.0, canvas.size[1]),
                ];
                painter.disc(
                    centre,
                    random.range(0.01, 0.04),
                    random.range(40.0, 80.0) as f32,
                );
            }
        }
        Pattern::Ceiling => {}
    }
    let mut data = vec![0u8; width * height];
    for y in 0..height {
        for x in 0..width {
            let p = (canvas.world)(centre(x), centre(y));
            let light = lighting.at(p, canvas.normal) as f32;
            data[y * width + x] = (albedo[y * width + x] * light).clamp(0.0, 255.0) as u8;
        }
    }
    Texture {
        width,
        height,
        texel,
        data,
    }
}

/// Draws decorations onto an albedo buffer, avoiding keep-out rectangles.
struct Painter<'a> {
    albedo: &'a mut [f32],
    width: usize,
    height: usize,
    texel: f64,
    /// Markers' quiet zones, and posters already hung.
    keepout: Vec<Keepout>,
}

/// Clearance kept between decorations and a marker's quiet zone, metres.
const KEEPOUT_MARGIN: f64 = 0.06;

impl Painter<'_> {
    fn clear(&self, rect: Keepout) -> bool {
        self.keepout.iter().all(|k| {
            rect[1] < k[0] - KEEPOUT_MARGIN
                || rect[0] > k[1] + KEEPOUT_MARGIN
                || rect[3] < k[2] - KEEPOUT_MARGIN
                || rect[2] > k[3] + KEEPOUT_MARGIN
        })
    }

    /// Texel index ranges covering `rect`.
    fn span(&self, rect: Keepout) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
        let index = |m: f64, n: usize| ((m / self.texel).max(0.0) as usize).min(n);
        (
            index(rect[0], self.width)..index(rect[1], self.width),
            index(rect[2], self.height)..index(rect[3], self.height),
        )
    }

    /// Blends `grey` into texel (x, y) by the fraction `coverage` of it the shape covers.
    /// Anti-aliased edges keep a magnified texture smooth: hard texel edges would read as rows
    /// of identical stair-step corners to a feature detector.
    fn blend(&mut self, x: usize, y: usize, grey: f32, coverage: f64) {
        if coverage > 0.0 {
            let texel = &mut self.albedo[y * self.width + x];
            *texel += (grey - *texel) * coverage.min(1.0) as f32;
        }
    }

    /// Texels covering `rect`, one texel wider on each side for the anti-aliased edge.
    fn span_with_edge(&self, rect: Keepout) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
        let t = self.texel;
        self.span([rect[0] - t, rect[1] + t, rect[2] - t, rect[3] + t])
    }

    fn block(&mut self, centre: [f64; 2], half: [f64; 2], grey: f32) {
        let rect = [
            centre[0] - half[0],
            centre[0] + half[0],
            centre[1] - half[1],
            centre[1] + half[1],
        ];
        if !self.clear(rect) {
            return;
        }
        let t = self.texel;
        // Fraction of a texel's extent [a, a + t] inside [lo, hi].
        let overlap = |a: f64, lo: f64, hi: f64| ((a + t).min(hi) - a.max(lo)).max(0.0) / t;
        let (xs, ys) = self.span_with_edge(rect);
        for y in ys {
            let fy = overlap(y as f64 * t, rect[2], rect[3]);
            for x in xs.clone() {
                let coverage = overlap(x as f64 * t, rect[0], rect[1]) * fy;
                self.blend(x, y, grey, coverage);
            }
        }
    }

    fn disc(&mut self, centre: [f64; 2], radius: f64, grey: f32) {
        let rect = [
            centre[0] - radius,
            centre[0] + radius,
            centre[1] - radius,
            centre[1] + radius,
        ];
        if !self.clear(rect) {
            return;
        }
        let (xs, ys) = self.span_with_edge(rect);
        for y in ys {
            for x in xs.clone() {
                let du = (x as f64 + 0.5) * self.texel - centre[0];
                let dv = (y as f64 + 0.5) * self.texel - centre[1];
                // Coverage from the signed distance to the rim, over one texel.
                let inside = radius - (du * du + dv * dv).sqrt();
                self.blend(x, y, grey, (0.5 + inside / self.texel).clamp(0.0, 1.0));
            }
        }
    }

    /// A framed rectangle with a high-contrast picture: blocks, stripes or blobs.
    fn poster(&mut self, random: &mut Random, noise: &Noise, size: [f64; 2]) {
        let w = random.range(0.25, 0.9).min(size[0] * 0.8);
        let h = random.range(0.2, 0.7).min(size[1] * 0.5);
        let u0 = random.range(0.0, (size[0] - w).max(0.0));
        let v0 = random.range(0.35, (size[1] - 0.2 - h).max(0.4));
        let rect = [u0, u0 + w, v0, v0 + h];
        if !self.clear(rect) {
            return;
        }
        self.keepout.push(rect);
        let kind = random.next_u64() % 3;
        let cell = random.range(0.03, 0.08);
        let seed = random.next_u64() as i64;
        let frame = 0.015;
        let picture = |u: f64, v: f64| -> f64 {
            // A light frame, and no black blocks: a dark square outline with a grid of dark
            // cells inside is what a marker detector looks for.
            if u < frame || v < frame || w - u < frame || h - v < frame {
                return 150.0;
            }
            match kind {
                0 => {
                    let (i, j) = ((u / cell).floor() as i64, (v / (cell * 1.3)).floor() as i64);
                    75.0 + 160.0 * noise.lattice(i + seed, j, 41)
                }
                1 => {
                    // Wavy, irregular stripes: straight periodic ones are a row of identical
                    // corners that no descriptor can tell apart.
                    let warp = 2.5 * noise.fbm(u / 0.15, v / 0.15, 2);
                    let stripe = (u * 1.7 + v * 0.6) / cell + warp;
                    let width = 0.3 + 0.5 * noise.lattice(stripe.floor() as i64 + seed, 0, 42);
                    if stripe.fract() < width {
                        45.0
                    } else {
                        225.0
                    }
                }
                _ => {
                    let n = noise.fbm(u / cell + seed as f64 * 1e-3, v / cell, 2);
                    if n > 0.5 {
                        230.0
                    } else {
                        50.0
                    }
                }
            }
        };
        // 3 × 3 samples per texel: the picture's edges are anti-aliased like the stickers'.
        let t = self.texel;
        let (xs, ys) = self.span_with_edge(rect);
        for y in ys {
            for x in xs.clone() {
                let (mut sum, mut inside) = (0.0, 0usize);
                for sy in 0..3 {
                    for sx in 0..3 {
                        let u = (x as f64 + (sx as f64 + 0.5) / 3.0) * t - u0;
                        let v = (y as f64 + (sy as f64 + 0.5) / 3.0) * t - v0;
                        if (0.0..w).contains(&u) && (0.0..h).contains(&v) {
                            sum += picture(u, v);
                            inside += 1;
                        }
                    }
                }
                if inside > 0 {
                    self.blend(x, y, (sum / inside as f64) as f32, inside as f64 / 9.0);
                }
            }
        }
    }
}

/// Hashed value noise on the integer lattice.
struct Noise(u64);

impl Noise {
    /// A value in [0, 1) for lattice point (i, j) of layer `layer`.
    #[inline]
    fn lattice(&self, i: i64, j: i64, layer: u64) -> f64 {
        let mut h = self.0 ^ layer.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        h ^= (i as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        h = h.rotate_left(31) ^ (j as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
        h = (h ^ (h >> 29)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 32;
        (h >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Smoothly interpolated noise at (x, y) in lattice units.
    fn at(&self, x: f64, y: f64, layer: u64) -> f64 {
        let (i, j) = (x.floor(), y.floor());
        let (fx, fy) = (x - i, y - j);
        let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
        let (i, j) = (i as i64, j as i64);
        let a = self.lattice(i, j, layer);
        let b = self.lattice(i + 1, j, layer);
        let c = self.lattice(i, j + 1, layer);
        let d = self.lattice(i + 1, j + 1, layer);
        let top = a + (b - a) * sx;
        let bottom = c + (d - c) * sx;
        top + (bottom - top) * sy
    }

    /// Octaves of noise, each twice as fine and half as strong, normalised to [0, 1).
    fn fbm(&self, x: f64, y: f64, octaves: u32) -> f64 {
        let (mut sum, mut weight, mut total, mut scale) = (0.0, 1.0, 0.0, 1.0);
        for octave in 0..octaves {
            sum += weight * self.at(x * scale, y * scale, 100 + u64::from(octave));
            total += weight;
            weight *= 0.5;
            scale *= 2.0;
        }
        sum / total
    }
}
