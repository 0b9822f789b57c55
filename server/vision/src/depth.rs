//! Depth images and the depth check of marker distances.
//!
//! A marker's distance from its four corners is its weakest estimate: a corner error of a tenth
//! of a pixel on an 8 cm marker at 2 m moves it by centimetres. The depth image measures the
//! marker's plane directly, so the distance along the marker's centre ray is taken from a plane
//! fitted to the depth pixels inside the marker when they agree with the corners.

use nalgebra::{Matrix3, Point2, Vector3};

/// A row-major depth image in sensor units (`depth_scale` units per metre; 0 = no measurement).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u16>,
    pub depth_scale: f64,
    /// Aligned to the colour image pixel for pixel (see the wire's `DepthRegistration`).
    pub registered: bool,
}

impl DepthImage {
    /// Depth in metres at a pixel, if measured.
    pub fn metres_at(&self, x: u32, y: u32) -> Option<f64> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let raw = *self
            .data
            .get(y as usize * self.width as usize + x as usize)?;
        (raw != 0).then(|| f64::from(raw) / self.depth_scale)
    }
}

/// Fewest valid depth pixels inside a marker for the depth distance to be used.
pub const MIN_DEPTH_SAMPLES: usize = 12;
/// Sampling stride (pixels) inside large markers; small markers use every pixel.
const MAX_SAMPLES_PER_SIDE: f64 = 24.0;
/// Only the inner part of the marker is sampled, away from depth edges at its border.
const INNER_FRACTION: f64 = 0.8;

/// A plane n·p = d (|n| = 1) fitted to the depth pixels inside a quadrilateral.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthPlane {
    pub normal: Vector3<f64>,
    pub offset: f64,
    pub samples: usize,
}

impl DepthPlane {
    /// Distance along `ray` (any length) from the camera centre to the plane, in units of |ray|.
    pub fn ray_parameter(&self, ray: &Vector3<f64>) -> Option<f64> {
        let denominator = self.normal.dot(ray);
        (denominator.abs() > 1e-9).then(|| self.offset / denominator)
    }
}

/// Fits a plane to the valid depth pixels inside the (undistorted) corner quadrilateral, with one
/// round of outlier rejection. None when too few pixels carry depth.
/// `rays` maps pixels to their viewing rays with z = 1 (undistorting them if the lens needs it).
pub fn fit_plane_in_quad(
    depth: &DepthImage,
    corners: &[Point2<f64>; 4],
    rays: impl Fn(&[Point2<f64>]) -> Vec<Vector3<f64>>,
) -> Option<DepthPlane> {
    let centre = corners
        .iter()
        .fold(Point2::origin(), |acc, c| acc + c.coords / 4.0);
    let inner: Vec<Point2<f64>> = corners
        .iter()
        .map(|c| centre + (c - centre) * INNER_FRACTION)
        .collect();
    let (min_x, max_x, min_y, max_y) = inner.iter().fold(
        (f64::MAX, f64::MIN, f64::MAX, f64::MIN),
        |(a, b, c, d), p| (a.min(p.x), b.max(p.x), c.min(p.y), d.max(p.y)),
    );
    let x0 = min_x.floor().max(0.0) as u32;
    let y0 = min_y.floor().max(0.0) as u32;
    let x1 = (max_x.ceil().max(0.0) as u32).min(depth.width.saturating_sub(1));
    let y1 = (max_y.ceil().max(0.0) as u32).min(depth.height.saturating_sub(1));
    if x0 > x1 || y0 > y1 {
        return None;
    }
    let stride = (((max_x - min_x).max(max_y - min_y)) / MAX_SAMPLES_PER_SIDE).max(1.0) as usize;
    let mut pixels = Vec::new();
    let mut depths = Vec::new();
    for y in (y0..=y1).step_by(stride) {
        for x in (x0..=x1).step_by(stride) {
            let pixel = Point2::new(f64::from(x), f64::from(y));
            if !inside_convex(&inner, pixel) {
                continue;
            }
            if let Some(z) = depth.metres_at(x, y) {
                pixels.push(pixel);
                depths.push(z);
            }
        }
    }
    if pixels.len() < MIN_DEPTH_SAMPLES {
        return None;
    }
    // Depth edges and holes filled by the background give samples far from the marker: drop
    // them by their distance to the median depth before fitting (robust to a tilted marker).
    let median_z = median(depths.clone());
    let spread = 1.4826 * median(depths.iter().map(|z| (z - median_z).abs()).collect());
    let keep_z = (3.0 * spread).max(0.01 * median_z);
    let mut points: Vec<Vector3<f64>> = rays(&pixels)
        .into_iter()
        .zip(depths)
        .filter(|(_, z)| (z - median_z).abs() <= keep_z)
        .map(|(ray, z)| ray * z)
        .collect();
    let plane = fit_plane(&points)?;
    // Drop points far from the first fit (depth edges, holes filled by the background), refit.
    let mut residuals: Vec<f64> = points
        .iter()
        .map(|p| (plane.normal.dot(p) - plane.offset).abs())
        .collect();
    residuals.sort_by(f64::total_cmp);
    let limit = (3.0 * residuals[residuals.len() / 2]).max(0.005);
    points.retain(|p| (plane.normal.dot(p) - plane.offset).abs() <= limit);
    fit_plane(&points)
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn fit_plane(points: &[Vector3<f64>]) -> Option<DepthPlane> {
    if points.len() < MIN_DEPTH_SAMPLES {
        return None;
    }
    let n = points.len() as f64;
    let mean = points.iter().sum::<Vector3<f64>>() / n;
    let scatter = points
        .iter()
        .map(|p| (p - mean) * (p - mean).transpose())
        .sum::<Matrix3<f64>>();
    let eigen = scatter.symmetric_eigen();
    let smallest = eigen.eigenvalues.imin();
    let mut normal: Vector3<f64> = eigen.eigenvectors.column(smallest).into_owned();
    // Orient the normal away from the camera so that the offset is positive.
    if normal.dot(&mean) < 0.0 {
        normal = -normal;
    }
    Some(DepthPlane {
        normal,
        offset: normal.dot(&mean),
        samples: points.len(),
    })
}

fn inside_convex(polygon: &[Point2<f64>], p: Point2<f64>) -> bool {
    let mut sign = 0.0;
    for i in 0..polygon.len() {
        let a = polygon[i];
        let b = polygon[(i + 1) % polygon.len()];
        let cross = (b - a).perp(&(p - a));
        if cross != 0.0 {
            if sign != 0.0 && cross.signum() != sign {
                return false;
            }
            sign = cross.signum();
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::PinholeCamera;

    fn rays(camera: &PinholeCamera) -> impl Fn(&[Point2<f64>]) -> Vec<Vector3<f64>> + '_ {
        move |pixels| pixels.iter().map(|p| camera.ray(*p)).collect()
    }

    fn camera() -> PinholeCamera {
        PinholeCamera::new(64, 48, [60.0, 60.0, 32.0, 24.0], vec![]).unwrap()
    }

    /// Depth of the plane n·p = d seen by `camera`, quantised to millimetres.
    fn plane_depth(camera: &PinholeCamera, normal: Vector3<f64>, offset: f64) -> DepthImage {
        let mut data = Vec::new();
        for y in 0..camera.height {
            for x in 0..camera.width {
                let ray = camera.ray(Point2::new(f64::from(x), f64::from(y)));
                let z = offset / normal.dot(&ray);
                data.push((z * 1000.0).round() as u16);
            }
        }
        DepthImage {
            width: camera.width,
            height: camera.height,
            data,
            depth_scale: 1000.0,
            registered: true,
        }
    }

    #[test]
    fn recovers_a_slanted_plane() {
        let camera = camera();
        let normal = Vector3::new(0.3, -0.2, 1.0).normalize();
        let depth = plane_depth(&camera, normal, 1.5);
        let quad =
            [(10.0, 8.0), (50.0, 10.0), (52.0, 40.0), (12.0, 38.0)].map(|(x, y)| Point2::new(x, y));
        let plane = fit_plane_in_quad(&depth, &quad, rays(&camera)).unwrap();
        assert!(plane.normal.angle(&normal) < 0.01, "{}", plane.normal);
        assert!((plane.offset - 1.5).abs() < 0.002, "{}", plane.offset);
        let ray = camera.ray(Point2::new(30.0, 24.0));
        let t = plane.ray_parameter(&ray).unwrap();
        assert!((t - 1.5 / normal.dot(&ray)).abs() < 0.003);
    }

    #[test]
    fn holes_leave_too_few_samples() {
        let camera = camera();
        let mut depth = plane_depth(&camera, Vector3::z(), 2.0);
        depth.data.iter_mut().for_each(|d| *d = 0);
        let quad =
            [(10.0, 8.0), (50.0, 10.0), (52.0, 40.0), (12.0, 38.0)].map(|(x, y)| Point2::new(x, y));
        assert_eq!(fit_plane_in_quad(&depth, &quad, rays(&camera)), None);
        let off_image = [
            (100.0, 100.0),
            (120.0, 100.0),
            (120.0, 120.0),
            (100.0, 120.0),
        ]
        .map(|(x, y)| Point2::new(x, y));
        assert_eq!(fit_plane_in_quad(&depth, &off_image, rays(&camera)), None);
    }

    #[test]
    fn outliers_from_the_background_are_rejected() {
        let camera = camera();
        let mut depth = plane_depth(&camera, Vector3::z(), 1.0);
        // A stripe of background at 3 m through the marker.
        for y in 0..camera.height {
            depth.data[(y * camera.width + 30) as usize] = 3000;
        }
        let quad =
            [(10.0, 8.0), (50.0, 8.0), (50.0, 40.0), (10.0, 40.0)].map(|(x, y)| Point2::new(x, y));
        let plane = fit_plane_in_quad(&depth, &quad, rays(&camera)).unwrap();
        assert!((plane.offset - 1.0).abs() < 0.002, "{}", plane.offset);
    }
}
