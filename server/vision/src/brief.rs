//! Rotated BRIEF, the descriptor of ORB: 256 comparisons of pixel pairs in a smoothed patch
//! around a keypoint, the pairs turned by the keypoint's orientation so that the bits do not
//! change when the image turns.
//!
//! Computed here rather than by OpenCV's `ORB::compute`, which builds its pyramid again and
//! goes through the bindings per keypoint: the extractor already holds the levels and the
//! corners. On the same level the bits equal OpenCV's (tested against it): the same pairs, the
//! same 7×7 Gaussian (σ = 2, by the same filter) and the same rounding of turned pairs.

use crate::CvError;
use opencv::core::{Mat, Rect, Scalar, Size, BORDER_REFLECT_101};
use opencv::imgproc;
use opencv::prelude::*;

/// A 256-bit descriptor; bit `i` (byte `i / 8`, bit `i % 8`) is pair `i`.
pub type Descriptor = [u8; 32];

/// Number of differing bits.
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    let mut distance = 0;
    for (x, y) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        let x = u64::from_le_bytes(x.try_into().expect("8 bytes"));
        let y = u64::from_le_bytes(y.try_into().expect("8 bytes"));
        distance += (x ^ y).count_ones();
    }
    distance
}

/// How far a turned pair reaches from its keypoint, pixels: the pairs lie within 13 px on
/// each axis, so a turn takes them at most 13·√2 ≈ 18.4 px away, rounded to 18.
pub const REACH: i32 = 18;

/// Half the side of the smoothing kernel.
const KERNEL_RADIUS: i32 = 3;

/// The 256 pairs `[x0, y0, x1, y1]` (pixels from the keypoint, y down): bit `i` is set when
/// the first pixel of pair `i` is darker than the second. These are the pairs Rublee et al.
/// learned for ORB (uncorrelated, high-variance tests in a 31 px patch), as OpenCV and
/// ORB-SLAM use them, so descriptors stay comparable with theirs.
const PAIRS: [[i8; 4]; 256] = [
    [8, -3, 9, 5],
    [4, 2, 7, -12],
    [-11, 9, -8, 2],
    [7, -12, 12, -13],
    [2, -13, 2, 12],
    [1, -7, 1, 6],
    [-2, -10, -2, -4],
    [-13, -13, -11, -8],
    [-13, -3, -12, -9],
    [10, 4, 11, 9],
    [-13, -8, -8, -9],
    [-11, 7, -9, 12],
    [7, 7, 12, 6],
    [-4, -5, -3, 0],
    [-13, 2, -12, -3],
    [-9, 0, -7, 5],
    [12, -6, 12, -1],
    [-3, 6, -2, 12],
    [-6, -13, -4, -8],
    [11, -13, 12, -8],
    [4, 7, 5, 1],
    [5, -3, 10, -3],
    [3, -7, 6, 12],
    [-8, -7, -6, -2],
    [-2, 11, -1, -10],
    [-13, 12, -8, 10],
    [-7, 3, -5, -3],
    [-4, 2, -3, 7],
    [-10, -12, -6, 11],
    [5, -12, 6, -7],
    [5, -6, 7, -1],
    [1, 0, 4, -5],
    [9, 11, 11, -13],
    [4, 7, 4, 12],
    [2, -1, 4, 4],
    [-4, -12, -2, 7],
    [-8, -5, -7, -10],
    [4, 11, 9, 12],
    [0, -8, 1, -13],
    [-13, -2, -8, 2],
    [-3, -2, -2, 3],
    [-6, 9, -4, -9],
    [8, 12, 10, 7],
    [0, 9, 1, 3],
    [7, -5, 11, -10],
    [-13, -6, -11, 0],
    [10, 7, 12, 1],
    [-6, -3, -6, 12],
    [10, -9, 12, -4],
    [-13, 8, -8, -12],
    [-13, 0, -8, -4],
    [3, 3, 7, 8],
    [5, 7, 10, -7],
    [-1, 7, 1, -12],
    [3, -10, 5, 6],
    [2, -4, 3, -10],
    [-13, 0, -13, 5],
    [-13, -7, -12, 12],
    [-13, 3, -11, 8],
    [-7, 12, -4, 7],
    [6, -10, 12, 8],
    [-9, -1, -7, -6],
    [-2, -5, 0, 12],
    [-12, 5, -7, 5],
    [3, -10, 8, -13],
    [-7, -7, -4, 5],
    [-3, -2, -1, -7],
    [2, 9, 5, -11],
    [-11, -13, -5, -13],
    [-1, 6, 0, -1],
    [5, -3, 5, 2],
    [-4, -13, -4, 12],
    [-9, -6, -9, 6],
    [-12, -10, -8, -4],
    [10, 2, 12, -3],
    [7, 12, 12, 12],
    [-7, -13, -6, 5],
    [-4, 9, -3, 4],
    [7, -1, 12, 2],
    [-7, 6, -5, 1],
    [-13, 11, -12, 5],
    [-3, 7, -2, -6],
    [7, -8, 12, -7],
    [-13, -7, -11, -12],
    [1, -3, 12, 12],
    [2, -6, 3, 0],
    [-4, 3, -2, -13],
    [-1, -13, 1, 9],
    [7, 1, 8, -6],
    [1, -1, 3, 12],
    [9, 1, 12, 6],
    [-1, -9, -1, 3],
    [-13, -13, -10, 5],
    [7, 7, 10, 12],
    [12, -5, 12, 9],
    [6, 3, 7, 11],
    [5, -13, 6, 10],
    [2, -12, 2, 3],
    [3, 8, 4, -6],
    [2, 6, 12, -13],
    [9, -12, 10, 3],
    [-8, 4, -7, 9],
    [-11, 12, -4, -6],
    [1, 12, 2, -8],
    [6, -9, 7, -4],
    [2, 3, 3, -2],
    [6, 3, 11, 0],
    [3, -3, 8, -8],
    [7, 8, 9, 3],
    [-11, -5, -6, -4],
    [-10, 11, -5, 10],
    [-5, -8, -3, 12],
    [-10, 5, -9, 0],
    [8, -1, 12, -6],
    [4, -6, 6, -11],
    [-10, 12, -8, 7],
    [4, -2, 6, 7],
    [-2, 0, -2, 12],
    [-5, -8, -5, 2],
    [7, -6, 10, 12],
    [-9, -13, -8, -8],
    [-5, -13, -5, -2],
    [8, -8, 9, -13],
    [-9, -11, -9, 0],
    [1, -8, 1, -2],
    [7, -4, 9, 1],
    [-2, 1, -1, -4],
    [11, -6, 12, -11],
    [-12, -9, -6, 4],
    [3, 7, 7, 12],
    [5, 5, 10, 8],
    [0, -4, 2, 8],
    [-9, 12, -5, -13],
    [0, 7, 2, 12],
    [-1, 2, 1, 7],
    [5, 11, 7, -9],
    [3, 5, 6, -8],
    [-13, -4, -8, 9],
    [-5, 9, -3, -3],
    [-4, -7, -3, -12],
    [6, 5, 8, 0],
    [-7, 6, -6, 12],
    [-13, 6, -5, -2],
    [1, -10, 3, 10],
    [4, 1, 8, -4],
    [-2, -2, 2, -13],
    [2, -12, 12, 12],
    [-2, -13, 0, -6],
    [4, 1, 9, 3],
    [-6, -10, -3, -5],
    [-3, -13, -1, 1],
    [7, 5, 12, -11],
    [4, -2, 5, -7],
    [-13, 9, -9, -5],
    [7, 1, 8, 6],
    [7, -8, 7, 6],
    [-7, -4, -7, 1],
    [-8, 11, -7, -8],
    [-13, 6, -12, -8],
    [2, 4, 3, 9],
    [10, -5, 12, 3],
    [-6, -5, -6, 7],
    [8, -3, 9, -8],
    [2, -12, 2, 8],
    [-11, -2, -10, 3],
    [-12, -13, -7, -9],
    [-11, 0, -10, -5],
    [5, -3, 11, 8],
    [-2, -13, -1, 12],
    [-1, -8, 0, 9],
    [-13, -11, -12, -5],
    [-10, -2, -10, 11],
    [-3, 9, -2, -13],
    [2, -3, 3, 2],
    [-9, -13, -4, 0],
    [-4, 6, -3, -10],
    [-4, 12, -2, -7],
    [-6, -11, -4, 9],
    [6, -3, 6, 11],
    [-13, 11, -5, 5],
    [11, 11, 12, 6],
    [7, -5, 12, -2],
    [-1, 12, 0, 7],
    [-4, -8, -3, -2],
    [-7, 1, -6, 7],
    [-13, -12, -8, -13],
    [-7, -2, -6, -8],
    [-8, 5, -6, -9],
    [-5, -1, -4, 5],
    [-13, 7, -8, 10],
    [1, 5, 5, -13],
    [1, 0, 10, -13],
    [9, 12, 10, -1],
    [5, -8, 10, -9],
    [-1, 11, 1, -13],
    [-9, -3, -6, 2],
    [-1, -10, 1, 12],
    [-13, 1, -8, -10],
    [8, -11, 10, -6],
    [2, -13, 3, -6],
    [7, -13, 12, -9],
    [-10, -10, -5, -7],
    [-10, -8, -8, -13],
    [4, -6, 8, 5],
    [3, 12, 8, -13],
    [-4, 2, -3, -3],
    [5, -13, 10, -12],
    [4, -13, 5, -1],
    [-9, 9, -4, 3],
    [0, 3, 3, -9],
    [-12, 1, -6, 1],
    [3, 2, 4, -8],
    [-10, -10, -10, 9],
    [8, -13, 12, 12],
    [-8, -12, -6, -5],
    [2, 2, 3, 7],
    [10, 6, 11, -8],
    [6, 8, 8, -12],
    [-7, 10, -6, 5],
    [-3, -9, -3, 9],
    [-1, -13, -1, 5],
    [-3, -7, -3, 4],
    [-8, -2, -8, 3],
    [4, 2, 12, 12],
    [2, -5, 3, 11],
    [6, -9, 11, -13],
    [3, -1, 7, 12],
    [11, -1, 12, 4],
    [-3, 0, -3, 6],
    [4, -11, 4, 12],
    [2, -4, 2, 1],
    [-10, -6, -8, 1],
    [-13, 7, -11, 1],
    [-13, 12, -11, -13],
    [6, 0, 11, -13],
    [0, -1, 1, 4],
    [-13, 3, -9, -2],
    [-9, 8, -6, -3],
    [-13, -6, -8, -2],
    [5, -9, 8, 10],
    [2, 7, 3, -9],
    [-1, -6, -1, -1],
    [9, 5, 11, -2],
    [11, -3, 12, -8],
    [3, 0, 3, 5],
    [-1, 4, 0, 10],
    [3, -6, 4, 5],
    [-13, 0, -10, 5],
    [5, 8, 12, 11],
    [8, 9, 9, -6],
    [7, -4, 8, -12],
    [-10, 4, -10, 9],
    [7, 3, 12, 4],
    [9, -7, 10, -2],
    [7, 0, 12, -2],
    [-1, -6, 0, -11],
];

/// One pyramid level smoothed for descriptors, with a margin so that every pair of a keypoint
/// at least `REACH − margin` pixels inside the level stays in the image.
pub struct Smoothed {
    image: Mat,
    margin: i32,
    width: i32,
    height: i32,
}

impl Smoothed {
    /// Smooths `level` (8-bit grey) by the 7×7 Gaussian of σ = 2 that BRIEF's tests are made
    /// on, into an image with `margin` pixels of border (at least the kernel's 3). The border
    /// holds the level's pixels mirrored (reflect-101) but not smoothed, as OpenCV's ORB has it.
    pub fn new(level: &Mat, margin: i32) -> Result<Self, CvError> {
        let margin = margin.max(KERNEL_RADIUS);
        let (width, height) = (level.cols(), level.rows());
        let mut image = Mat::default();
        opencv::core::copy_make_border(
            level,
            &mut image,
            margin,
            margin,
            margin,
            margin,
            BORDER_REFLECT_101,
            Scalar::default(),
        )?;
        // Smoothing the level as a sub-matrix of its mirrored copy reads the border around it
        // (the same values reflect-101 gives) and takes OpenCV's floating-point filter, half
        // the instructions of the bit-exact one a whole image gets, and what OpenCV's ORB does.
        let inner = Rect::new(margin, margin, width, height);
        let mut smoothed = Mat::default();
        imgproc::gaussian_blur(
            &Mat::roi(&image, inner)?,
            &mut smoothed,
            Size::new(2 * KERNEL_RADIUS + 1, 2 * KERNEL_RADIUS + 1),
            2.0,
            2.0,
            BORDER_REFLECT_101,
        )?;
        smoothed.copy_to(&mut Mat::roi_mut(&mut image, inner)?)?;
        Ok(Self {
            image,
            margin,
            width,
            height,
        })
    }

    /// The descriptor of the keypoint at pixel `(x, y)` of the level, oriented `angle` degrees
    /// (OpenCV's convention: from +x toward +y). `None` when a pair would leave the image.
    pub fn describe(&self, x: i32, y: i32, angle: f32) -> Option<Descriptor> {
        let patch = self.patch(x, y, angle)?;
        // Turn all 512 points first (a loop that vectorises), then read and compare.
        let mut offsets = [0i32; 512];
        for ((o, &px), &py) in offsets.iter_mut().zip(&POINTS_X).zip(&POINTS_Y) {
            *o = patch.offset(px, py);
        }
        let mut descriptor = [0u8; 32];
        for (byte, pairs) in descriptor.iter_mut().zip(offsets.chunks_exact(16)) {
            for (bit, pair) in pairs.chunks_exact(2).enumerate() {
                let (first, second) = (patch.at(pair[0]), patch.at(pair[1]));
                *byte |= u8::from(first < second) << bit;
            }
        }
        Some(descriptor)
    }

    fn patch(&self, x: i32, y: i32, angle: f32) -> Option<Patch<'_>> {
        let reach = REACH - self.margin;
        if x < reach || y < reach || x >= self.width - reach || y >= self.height - reach {
            return None;
        }
        let pixels = self.image.data_bytes().ok()?;
        let step = self.image.step1(0).ok()? as i32;
        // OpenCV turns the pairs in single precision from an angle in single precision; so do
        // we, so that a pair rounds to the same pixel.
        let radians = angle * (std::f64::consts::PI / 180.0) as f32;
        Some(Patch {
            pixels,
            step,
            centre: (y + self.margin) as usize * step as usize + (x + self.margin) as usize,
            sin: radians.sin(),
            cos: radians.cos(),
        })
    }
}

/// The pairs' points one after the other (first, second, first, second, …), x and y apart.
const POINTS_X: [f32; 512] = points(0);
const POINTS_Y: [f32; 512] = points(1);

const fn points(axis: usize) -> [f32; 512] {
    let mut out = [0.0; 512];
    let mut i = 0;
    while i < 256 {
        out[2 * i] = PAIRS[i][axis] as f32;
        out[2 * i + 1] = PAIRS[i][2 + axis] as f32;
        i += 1;
    }
    out
}

/// The smoothed pixels around one keypoint, and its orientation.
struct Patch<'a> {
    pixels: &'a [u8],
    step: i32,
    centre: usize,
    sin: f32,
    cos: f32,
}

impl Patch<'_> {
    /// Where the point `(px, py)` of the pattern falls once turned, from the centre.
    #[inline(always)]
    fn offset(&self, px: f32, py: f32) -> i32 {
        let column = round_half_even(px * self.cos - py * self.sin);
        let row = round_half_even(px * self.sin + py * self.cos);
        row * self.step + column
    }

    #[inline(always)]
    fn at(&self, offset: i32) -> u8 {
        self.pixels[self.centre.wrapping_add_signed(offset as isize)]
    }
}

/// Rounds to the nearest integer, halves to even (as OpenCV's `cvRound`), for |v| < 2²²:
/// after adding 1.5·2²³ no fraction bits are left, so the addition itself rounds, and the
/// mantissa then holds 2²² plus the result. Branch-free, and vectorises (x86-64's baseline has
/// no rounding instruction, and `as` would check for overflow).
#[inline(always)]
fn round_half_even(v: f32) -> i32 {
    const SHIFT: f32 = 12_582_912.0;
    (v + SHIFT).to_bits() as i32 - SHIFT.to_bits() as i32
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{KeyPoint, Vector, CV_8UC1};
    use opencv::features2d::{ORB_ScoreType, ORB};

    #[test]
    fn rounding_is_half_to_even() {
        for (v, r) in [
            (0.5, 0),
            (1.5, 2),
            (2.5, 2),
            (-0.5, 0),
            (-1.5, -2),
            (17.49, 17),
            (-18.2, -18),
        ] {
            assert_eq!(round_half_even(v), r, "{v}");
        }
    }

    #[test]
    fn every_pair_stays_within_reach() {
        for p in PAIRS {
            for (x, y) in [(p[0], p[1]), (p[2], p[3])] {
                assert!((-13..=13).contains(&x) && (-13..=13).contains(&y));
                // The farthest a turn can take the point, rounded as a pixel would be.
                let r = (f32::from(x).powi(2) + f32::from(y).powi(2)).sqrt();
                assert!(r.round() as i32 <= REACH);
            }
        }
    }

    /// A deterministic grey texture with structure at several scales.
    fn texture(width: i32, height: i32) -> Mat {
        let mut image = Mat::new_rows_cols_with_default(height, width, CV_8UC1, 0.into()).unwrap();
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        for y in 0..height {
            for x in 0..width {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let (fx, fy) = (f64::from(x), f64::from(y));
                let smooth =
                    80.0 * ((fx / 17.0).sin() * (fy / 23.0).cos() + (fx * fy / 900.0).sin());
                let noise = (state % 60) as f64;
                *image.at_2d_mut::<u8>(y, x).unwrap() =
                    (110.0 + smooth + noise).clamp(0.0, 255.0) as u8;
            }
        }
        image
    }

    #[test]
    fn descriptors_equal_opencvs_on_the_same_pixels() {
        let image = texture(320, 240);
        let smoothed = Smoothed::new(&image, 3).unwrap();
        let mut keypoints = Vector::<KeyPoint>::new();
        let mut ours = Vec::new();
        let mut n = 0;
        for y in (16..224).step_by(13) {
            for x in (16..304).step_by(11) {
                // Angles all round, and every seventh on a multiple of 90°, where turned pairs
                // land on exact halves less often but sine and cosine are at their extremes.
                let angle = if n % 7 == 0 {
                    90.0 * (n % 4) as f32
                } else {
                    (n as f32 * 37.3) % 360.0
                };
                n += 1;
                keypoints.push(
                    KeyPoint::new_coords(x as f32, y as f32, 31.0, angle, 1.0, 0, -1).unwrap(),
                );
                ours.push(smoothed.describe(x, y, angle).expect("inside"));
            }
        }
        let mut orb =
            ORB::create(500, 1.2, 1, 16, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20).unwrap();
        let mut theirs = Mat::default();
        let given = keypoints.len();
        orb.compute(&image, &mut keypoints, &mut theirs).unwrap();
        assert_eq!(keypoints.len(), given, "OpenCV kept every keypoint");
        let mut differing_bits = 0;
        for (i, d) in ours.iter().enumerate() {
            let row = theirs.at_row::<u8>(i as i32).unwrap();
            differing_bits += d
                .iter()
                .zip(row)
                .map(|(a, b)| (a ^ b).count_ones())
                .sum::<u32>();
        }
        assert_eq!(
            differing_bits,
            0,
            "bits differing from OpenCV's over {} descriptors",
            ours.len()
        );
    }

    #[test]
    fn a_keypoint_too_near_the_edge_has_no_descriptor() {
        let smoothed = Smoothed::new(&texture(64, 64), 3).unwrap();
        assert!(smoothed.describe(15, 32, 0.0).is_some());
        assert!(smoothed.describe(14, 32, 0.0).is_none());
        assert!(smoothed.describe(32, 64 - 15, 0.0).is_none());
    }
}
