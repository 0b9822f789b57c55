//! The renderer: a ray caster over the building's rectangles, with an RGB-D sensor model.
//!
//! Colour: the baked texture under each pixel's ray; marker pixels are supersampled 4×4 so
//! their edges are anti-aliased (the pose test needs subpixel-true corners); a global exposure
//! that drifts over time, lens vignetting, and sensor noise; optionally motion blur, the mean
//! of several renders over the exposure.
//!
//! Depth (aligned with colour, as a registered D435 stream): the exact ray length along the
//! optical axis passed through a stereo model. Noise and quantisation act on disparity
//! `f·B/z`, so depth noise grows with z² as a real active-stereo camera's does; pixels beyond
//! the range, at grazing incidence or on the far side of a depth edge get no depth.

use crate::random::Random;
use crate::scene::{Scene, Surface};
use nalgebra::{Isometry3, Vector3};
use serde::{Deserialize, Serialize};

/// A pinhole camera without distortion (the simulator renders ideal images).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Default for Camera {
    /// A RealSense D435 colour stream at 640×480.
    fn default() -> Self {
        Self {
            width: 640,
            height: 480,
            fx: 605.86,
            fy: 606.27,
            cx: 325.02,
            cy: 244.76,
        }
    }
}

impl Camera {
    /// Direction through pixel (x, y) with unit depth (z = 1), camera frame.
    pub fn ray(&self, x: f64, y: f64) -> Vector3<f64> {
        Vector3::new((x - self.cx) / self.fx, (y - self.cy) / self.fy, 1.0)
    }
}

/// The depth sensor's model. Defaults follow a D435 at 640×480.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DepthSensor {
    /// Stereo baseline, metres.
    pub baseline: f64,
    /// Standard deviation of the disparity, pixels: σ_z = z² σ_d / (f B).
    pub disparity_sigma: f64,
    /// Disparity quantisation step, pixels (0 = none).
    pub disparity_step: f64,
    /// Nearest and farthest depth returned, metres.
    pub min_range: f64,
    pub max_range: f64,
    /// Beyond this angle between ray and surface normal, no depth, degrees.
    pub grazing_limit_deg: f64,
    /// A pixel whose neighbour is nearer by more than this fraction of its depth lies in the
    /// stereo shadow of an edge and gets no depth.
    pub edge_jump: f64,
    /// Fraction of pixels that randomly return nothing.
    pub dropout: f64,
}

impl Default for DepthSensor {
    fn default() -> Self {
        Self {
            baseline: 0.05,
            disparity_sigma: 0.08,
            disparity_step: 1.0 / 32.0,
            min_range: 0.2,
            max_range: 8.0,
            grazing_limit_deg: 80.0,
            edge_jump: 0.05,
            dropout: 0.002,
        }
    }
}

impl DepthSensor {
    /// Standard deviation of depth at `z` metres for focal length `f` pixels.
    pub fn sigma_at(&self, z: f64, f: f64) -> f64 {
        z * z * self.disparity_sigma / (f * self.baseline)
    }

    /// Largest depth change the quantisation makes at `z` (half a step).
    pub fn quantisation_at(&self, z: f64, f: f64) -> f64 {
        0.5 * z * z * self.disparity_step / (f * self.baseline)
    }
}

/// What is rendered besides geometry.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RenderOptions {
    pub camera: Camera,
    pub depth: DepthSensor,
    /// Relative amplitude of the slow exposure drift (auto-exposure, daylight), 0–1.
    pub exposure_variation: f64,
    /// Grey-level standard deviation of the colour sensor's noise.
    pub image_noise: f64,
    /// Brightness lost at the image corners to vignetting, 0–1.
    pub vignetting: f64,
    /// Renders averaged over the exposure for motion blur (1 = none).
    pub blur_samples: u32,
    /// Exposure time for motion blur, seconds.
    pub exposure_s: f64,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            camera: Camera::default(),
            depth: DepthSensor::default(),
            exposure_variation: 0.12,
            image_noise: 2.0,
            vignetting: 0.25,
            blur_samples: 1,
            exposure_s: 0.012,
        }
    }
}

/// A rendered frame: RGB8 row-major, and depth in metres (0 = no return).
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
    pub depth: Vec<f32>,
    /// Pixels whose ray met no surface (none, in a closed building with the camera inside).
    pub misses: usize,
}

impl Frame {
    /// Depth as 16-bit units of `1 / scale` metres (5000 for TUM, 1000 for millimetres).
    pub fn depth_units(&self, scale: f64) -> Vec<u16> {
        self.depth
            .iter()
            .map(|&z| (f64::from(z) * scale).round().clamp(0.0, 65535.0) as u16)
            .collect()
    }

    /// Luma (BT.601) of the colour image.
    pub fn grey(&self) -> Vec<u8> {
        self.rgb
            .chunks_exact(3)
            .map(|p| {
                ((299 * u32::from(p[0]) + 587 * u32::from(p[1]) + 114 * u32::from(p[2]) + 500)
                    / 1000) as u8
            })
            .collect()
    }
}

/// Mean grey level auto-exposure aims for.
const AUTO_EXPOSURE_TARGET: f64 = 115.0;
/// Pixels per side of a culling tile.
const TILE: usize = 16;
/// Supersampling of marker pixels, per axis.
const MARKER_SAMPLES: usize = 4;

/// Renders one building.
pub struct Renderer {
    scene: Scene,
    options: RenderOptions,
    vignette: Vec<f32>,
    seed: u64,
}

/// Where one pixel's ray lands.
#[derive(Clone, Copy)]
struct Hit {
    /// Index of the surface, [`Hit::NONE`] when the ray met nothing.
    surface: u16,
    /// Depth along the optical axis, metres.
    z: f32,
}

impl Hit {
    const NONE: u16 = u16::MAX;
    const MISS: Hit = Hit {
        surface: Self::NONE,
        z: 0.0,
    };

    fn get(self) -> Option<Hit> {
        (self.surface != Self::NONE).then_some(self)
    }
}

/// The rays through a frame's pixels, `base + x·along_x + y·along_y` (camera z = 1), in the
/// world frame: three vectors per frame instead of a rotation per pixel.
struct Rays {
    base: Vector3<f64>,
    along_x: Vector3<f64>,
    along_y: Vector3<f64>,
}

impl Rays {
    fn new(camera: &Camera, world_from_camera: &Isometry3<f64>) -> Self {
        let r = world_from_camera.rotation;
        Self {
            base: r * Vector3::new(-camera.cx / camera.fx, -camera.cy / camera.fy, 1.0),
            along_x: r * Vector3::new(1.0 / camera.fx, 0.0, 0.0),
            along_y: r * Vector3::new(0.0, 1.0 / camera.fy, 0.0),
        }
    }

    #[inline]
    fn at(&self, x: f64, y: f64) -> Vector3<f64> {
        self.base + self.along_x * x + self.along_y * y
    }
}

impl Renderer {
    /// `seed` picks the textures and the noise; the same seed renders the same images.
    pub fn new(
        plan: &crate::FloorPlan,
        building: &crate::Building,
        options: RenderOptions,
        seed: u64,
    ) -> Self {
        let camera = &options.camera;
        let (w, h) = (camera.width as usize, camera.height as usize);
        let half_diagonal = (camera.cx.powi(2) + camera.cy.powi(2)).sqrt();
        let mut vignette = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let r = ((x as f64 - camera.cx).powi(2) + (y as f64 - camera.cy).powi(2)).sqrt()
                    / half_diagonal;
                vignette.push((1.0 - options.vignetting * r * r) as f32);
            }
        }
        Self {
            scene: Scene::new(plan, building, seed),
            options,
            vignette,
            seed,
        }
    }

    pub fn options(&self) -> &RenderOptions {
        &self.options
    }

    /// Renders frame `index` at `time_s`. `poses` are `world_from_camera` over the exposure
    /// (one pose: no blur); depth comes from the middle one.
    pub fn render(&self, index: u64, time_s: f64, poses: &[Isometry3<f64>]) -> Frame {
        assert!(!poses.is_empty(), "a frame needs a camera pose");
        let camera = &self.options.camera;
        let (w, h) = (camera.width as usize, camera.height as usize);
        let middle = poses[poses.len() / 2];
        let mut grey = vec![0f32; w * h];
        let mut hits = vec![Hit::MISS; w * h];
        if let [pose] = poses {
            self.cast(pose, &mut grey, &mut hits);
        } else {
            let mut shade = vec![0f32; w * h];
            let mut pose_hits = vec![Hit::MISS; w * h];
            for (k, pose) in poses.iter().enumerate() {
                self.cast(pose, &mut shade, &mut pose_hits);
                for (g, s) in grey.iter_mut().zip(&shade) {
                    *g += s / poses.len() as f32;
                }
                if k == poses.len() / 2 {
                    hits.copy_from_slice(&pose_hits);
                }
            }
        }
        // Auto-exposure brings the mean grey to a set level, but lags and hunts: a slow drift
        // around the ideal gain remains.
        let mean = grey.iter().map(|&g| f64::from(g)).sum::<f64>() / grey.len() as f64;
        let drift = self.options.exposure_variation
            * (0.7 * (time_s * std::f64::consts::TAU / 9.0).sin()
                + 0.3 * (time_s * std::f64::consts::TAU / 2.3 + 1.0).sin());
        let exposure = (AUTO_EXPOSURE_TARGET / mean.max(1.0)).clamp(0.5, 2.0) * (1.0 + drift);
        let mut random = Random::derive(self.seed, 0xC010_0000 ^ index);
        let noise = self.options.image_noise as f32;
        let surfaces = &self.scene.surfaces;
        let mut rgb = vec![0u8; w * h * 3];
        for (((out, g), hit), vignette) in rgb
            .chunks_exact_mut(3)
            .zip(&grey)
            .zip(&hits)
            .zip(&self.vignette)
        {
            let value = g * exposure as f32 * vignette;
            let tint = surfaces
                .get(hit.surface as usize)
                .map_or(&[1.0; 3], |s| &s.tint);
            let noises = random.fast_normals3();
            for k in 0..3 {
                out[k] = (value * tint[k] + noise * noises[k]).clamp(0.0, 255.0) as u8;
            }
        }
        Frame {
            width: camera.width,
            height: camera.height,
            misses: hits.iter().filter(|h| h.get().is_none()).count(),
            rgb,
            depth: self.sense_depth(index, &middle, &hits),
        }
    }

    /// Casts every pixel's ray from `world_from_camera`: albedo × light into `shade`, the hit
    /// into `hits`.
    fn cast(&self, world_from_camera: &Isometry3<f64>, shade: &mut [f32], hits: &mut [Hit]) {
        let camera = &self.options.camera;
        let (w, h) = (camera.width as usize, camera.height as usize);
        let origin = world_from_camera.translation.vector;
        let rays = Rays::new(camera, world_from_camera);
        let ray = |x: f64, y: f64| rays.at(x, y);
        // Back-face culling: only sides the camera is in front of.
        let facing: Vec<usize> = self
            .scene
            .surfaces
            .iter()
            .enumerate()
            .filter(|(_, s)| s.facing * (origin[s.axis] - s.at) > 1e-9)
            .map(|(i, _)| i)
            .collect();
        let corners: Vec<[Vector3<f64>; 4]> = facing
            .iter()
            .map(|&i| self.scene.surfaces[i].corners().map(|c| c - origin))
            .collect();
        let mut candidates = Vec::with_capacity(facing.len());
        for ty in (0..h).step_by(TILE) {
            for tx in (0..w).step_by(TILE) {
                let (x1, y1) = ((tx + TILE).min(w), (ty + TILE).min(h));
                // The tile's frustum: four planes through the camera centre, normals inward.
                let edge = [
                    ray(tx as f64 - 0.5, ty as f64 - 0.5),
                    ray(x1 as f64 - 0.5, ty as f64 - 0.5),
                    ray(x1 as f64 - 0.5, y1 as f64 - 0.5),
                    ray(tx as f64 - 0.5, y1 as f64 - 0.5),
                ];
                let planes = [0, 1, 2, 3].map(|k| edge[k].cross(&edge[(k + 1) % 4]));
                candidates.clear();
                for (c, &i) in corners.iter().zip(&facing) {
                    let outside = planes.iter().any(|n| c.iter().all(|p| n.dot(p) < 0.0));
                    if !outside {
                        candidates.push(i);
                    }
                }
                for y in ty..y1 {
                    for x in tx..x1 {
                        let d = ray(x as f64, y as f64);
                        let pixel = y * w + x;
                        match self.first_hit(&candidates, &origin, &d) {
                            Some((surface, z)) => {
                                hits[pixel] = Hit {
                                    surface: surface as u16,
                                    z: z as f32,
                                };
                                shade[pixel] =
                                    self.shade_pixel(surface, z, &origin, &ray, x as f64, y as f64);
                            }
                            None => {
                                hits[pixel] = Hit::MISS;
                                shade[pixel] = 0.0;
                            }
                        }
                    }
                }
            }
        }
    }

    /// The nearest surface among `candidates` along direction `d` (camera z = 1) from `origin`,
    /// and its depth.
    #[inline]
    fn first_hit(
        &self,
        candidates: &[usize],
        origin: &Vector3<f64>,
        d: &Vector3<f64>,
    ) -> Option<(usize, f64)> {
        let mut best: Option<(usize, f64)> = None;
        let mut nearest = f64::INFINITY;
        for &i in candidates {
            let s = &self.scene.surfaces[i];
            let t = (s.at - origin[s.axis]) / d[s.axis];
            if !(t > 0.0 && t < nearest) {
                continue;
            }
            let u = origin[s.u_axis] + t * d[s.u_axis];
            let v = origin[s.v_axis] + t * d[s.v_axis];
            if s.contains(u, v) {
                best = Some((i, t));
                nearest = t;
            }
        }
        best
    }

    /// Albedo × light seen through pixel (x, y), supersampled near markers.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    fn shade_pixel(
        &self,
        surface: usize,
        z: f64,
        origin: &Vector3<f64>,
        ray: &impl Fn(f64, f64) -> Vector3<f64>,
        x: f64,
        y: f64,
    ) -> f32 {
        let s: &Surface = &self.scene.surfaces[surface];
        let local = |d: &Vector3<f64>| {
            let t = (s.at - origin[s.axis]) / d[s.axis];
            (
                origin[s.u_axis] + t * d[s.u_axis],
                origin[s.v_axis] + t * d[s.v_axis],
            )
        };
        let (u, v) = local(&ray(x, y));
        // A pixel's footprint at this depth, to catch pixels that straddle a marker's edge.
        let footprint = 2.0 * z / self.options.camera.fx;
        if s.markers.is_empty() || !s.marker_near(u, v, footprint) {
            return s.shade(u, v);
        }
        let n = MARKER_SAMPLES;
        let mut sum = 0.0;
        // Stratified in both axes at once ("n-rooks" inside an n×n grid): n² distinct offsets
        // per axis, so edges along the pixel grid are not quantised to 1/n of a pixel.
        for j in 0..n {
            for i in 0..n {
                let dx = (i as f64 + (j as f64 + 0.5) / n as f64) / n as f64 - 0.5;
                let dy = (j as f64 + (i as f64 + 0.5) / n as f64) / n as f64 - 0.5;
                let (u, v) = local(&ray(x + dx, y + dy));
                sum += s.shade(u, v);
            }
        }
        sum / (n * n) as f32
    }

    /// Markers a detector would find from `world_from_camera`: wholly in the image, facing the
    /// camera within `max_angle_deg`, no farther than `max_distance`, and not hidden behind
    /// another surface. (A geometric stand-in for detection, for planning and checking routes.)
    pub fn visible_markers(
        &self,
        building: &crate::Building,
        world_from_camera: &Isometry3<f64>,
        max_distance: f64,
        max_angle_deg: f64,
    ) -> Vec<u32> {
        let camera = &self.options.camera;
        let origin = world_from_camera.translation.vector;
        let camera_from_world = world_from_camera.inverse();
        let all: Vec<usize> = (0..self.scene.surfaces.len()).collect();
        let margin = 4.0;
        building
            .markers
            .iter()
            .filter(|m| {
                let centre = m.world_from_marker.translation.vector;
                let to_camera = origin - centre;
                let normal = m.world_from_marker.rotation * Vector3::z();
                let distance = to_camera.norm();
                if distance > max_distance
                    || normal.dot(&to_camera) < distance * max_angle_deg.to_radians().cos()
                {
                    return false;
                }
                let h = m.side / 2.0;
                let in_image = [(-h, h), (h, h), (h, -h), (-h, -h)].iter().all(|&(x, y)| {
                    let p = camera_from_world
                        * (m.world_from_marker * nalgebra::Point3::new(x, y, 0.0));
                    let (u, v) = (
                        camera.fx * p.x / p.z + camera.cx,
                        camera.fy * p.y / p.z + camera.cy,
                    );
                    p.z > 0.0
                        && u >= margin
                        && v >= margin
                        && u <= f64::from(camera.width) - margin
                        && v <= f64::from(camera.height) - margin
                });
                if !in_image {
                    return false;
                }
                let in_camera = camera_from_world * nalgebra::Point3::from(centre);
                let d = world_from_camera.rotation * (in_camera.coords / in_camera.z);
                self.first_hit(&all, &origin, &d)
                    .is_some_and(|(_, z)| (z - in_camera.z).abs() < 1e-3)
            })
            .map(|m| m.id)
            .collect()
    }

    /// The depth sensor's reading of the true hits.
    fn sense_depth(
        &self,
        index: u64,
        world_from_camera: &Isometry3<f64>,
        hits: &[Hit],
    ) -> Vec<f32> {
        let camera = &self.options.camera;
        let sensor = &self.options.depth;
        let (w, h) = (camera.width as usize, camera.height as usize);
        let rays = Rays::new(camera, world_from_camera);
        let cos_limit = sensor.grazing_limit_deg.to_radians().cos();
        let focal_baseline = camera.fx * sensor.baseline;
        let z_of = |i: usize| hits[i].get().map_or(f32::INFINITY, |h| h.z);
        let mut random = Random::derive(self.seed, 0xDE97_0000 ^ index);
        let dropout_above = irwin_hall3_quantile(1.0 - sensor.dropout);
        let mut depth = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let Some(hit) = hits[i].get() else { continue };
                let z = f64::from(hit.z);
                if z < sensor.min_range || z > sensor.max_range {
                    continue;
                }
                let s = &self.scene.surfaces[hit.surface as usize];
                let d = rays.at(x as f64, y as f64);
                if d[s.axis] * d[s.axis] < cos_limit * cos_limit * d.norm_squared() {
                    continue;
                }
                let jump = (sensor.edge_jump * z) as f32;
                let shadowed = [
                    (x > 0, i.wrapping_sub(1)),
                    (x + 1 < w, i + 1),
                    (y > 0, i.wrapping_sub(w)),
                    (y + 1 < h, i + w),
                ]
                .iter()
                .any(|&(inside, j)| inside && hit.z - z_of(j) > jump);
                // One draw: the dropout from its first channel, the noise from the second.
                let [drop, noise, _] = random.fast_normals3();
                if shadowed || drop > dropout_above {
                    continue;
                }
                let mut disparity = focal_baseline / z + sensor.disparity_sigma * f64::from(noise);
                if sensor.disparity_step > 0.0 && disparity > 0.0 {
                    // Round half up by truncation (a positive value): `round` is a libm call
                    // on baseline x86-64, and this runs per pixel.
                    let steps = (disparity / sensor.disparity_step + 0.5) as u64;
                    disparity = steps as f64 * sensor.disparity_step;
                }
                let measured = focal_baseline / disparity;
                if disparity > 0.0 && (sensor.min_range..=sensor.max_range).contains(&measured) {
                    depth[i] = measured as f32;
                }
            }
        }
        depth
    }
}

/// The value a [`Random::fast_normals3`] channel exceeds with probability `1 − p`, from the
/// Irwin–Hall distribution of three uniforms (exact for the continuous form).
fn irwin_hall3_quantile(p: f64) -> f32 {
    let p = p.clamp(0.0, 1.0);
    // CDF of the sum S of three U(0, 1) on its three pieces; invert by bisection.
    let cdf = |s: f64| {
        if s <= 0.0 {
            0.0
        } else if s <= 1.0 {
            s.powi(3) / 6.0
        } else if s <= 2.0 {
            (-2.0 * s.powi(3) + 9.0 * s * s - 9.0 * s + 3.0) / 6.0
        } else if s <= 3.0 {
            1.0 - (3.0 - s).powi(3) / 6.0
        } else {
            1.0
        }
    };
    let (mut lo, mut hi) = (0.0, 3.0);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if cdf(mid) < p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    // S has mean 1.5 and standard deviation 1/2; the channels are (S − 1.5) × 2.
    ((lo - 1.5) * 2.0) as f32
}
