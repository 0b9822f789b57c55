//! Four `f64` lanes, for kernels written once and compiled twice: on AVX2 + FMA (`Avx`, one
//! register) and portably (`Portable`, an array). Every operation rounds the same way on both
//! (`mul_add` is a fused multiply–add on both), so a kernel gives the same bits on every CPU.
//!
//! `Avx`'s methods are only called from functions compiled with `avx2,fma` and inlined into
//! them; they are `unsafe` to reach in any other way.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// Four lanes of `f64`.
pub(crate) trait Four:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    fn splat(x: f64) -> Self;
    fn from_array(a: [f64; 4]) -> Self;
    fn to_array(self) -> [f64; 4];
    /// `self·b + c`, rounded once.
    fn mul_add(self, b: Self, c: Self) -> Self;
    fn sqrt(self) -> Self;
    /// Lane by lane, `self` if `self > other`, else `other` (as `maxpd`: `other` when either is
    /// NaN).
    fn max(self, other: Self) -> Self;
    /// Lane by lane, `then` where `self > other`, else `otherwise`.
    fn select_gt(self, other: Self, then: Self, otherwise: Self) -> Self;
    /// Lane by lane, `then` where `self < other`, else `otherwise`.
    fn select_lt(self, other: Self, then: Self, otherwise: Self) -> Self {
        other.select_gt(self, then, otherwise)
    }
    /// `(a + b) + (c + d)` of the lanes.
    #[inline(always)]
    fn sum(self) -> f64 {
        let [a, b, c, d] = self.to_array();
        (a + b) + (c + d)
    }
    /// The 4 × 4 transpose: lane `l` of `out[k]` is lane `k` of `columns[l]`.
    #[inline(always)]
    fn transpose(columns: [Self; 4]) -> [Self; 4] {
        let [a, b, c, d] = columns;
        let (a, b, c, d) = (a.to_array(), b.to_array(), c.to_array(), d.to_array());
        [
            Self::from_array([a[0], b[0], c[0], d[0]]),
            Self::from_array([a[1], b[1], c[1], d[1]]),
            Self::from_array([a[2], b[2], c[2], d[2]]),
            Self::from_array([a[3], b[3], c[3], d[3]]),
        ]
    }

    /// [`Self::transpose`] as arrays: `out[l][k] = columns[k][l]`.
    #[inline(always)]
    fn transpose_to_arrays(columns: [Self; 4]) -> [[f64; 4]; 4] {
        let [a, b, c, d] = Self::transpose(columns);
        [a.to_array(), b.to_array(), c.to_array(), d.to_array()]
    }
}

/// The portable lanes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Portable(pub [f64; 4]);

macro_rules! portable_op {
    ($trait:ident, $method:ident, $op:tt) => {
        impl $trait for Portable {
            type Output = Self;
            #[inline(always)]
            fn $method(self, b: Self) -> Self {
                Self(std::array::from_fn(|l| self.0[l] $op b.0[l]))
            }
        }
    };
}
portable_op!(Add, add, +);
portable_op!(Sub, sub, -);
portable_op!(Mul, mul, *);
portable_op!(Div, div, /);

impl Neg for Portable {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Self(self.0.map(|x| -x))
    }
}

impl Four for Portable {
    #[inline(always)]
    fn splat(x: f64) -> Self {
        Self([x; 4])
    }
    #[inline(always)]
    fn from_array(a: [f64; 4]) -> Self {
        Self(a)
    }
    #[inline(always)]
    fn to_array(self) -> [f64; 4] {
        self.0
    }
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        Self(std::array::from_fn(|l| self.0[l].mul_add(b.0[l], c.0[l])))
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        Self(self.0.map(f64::sqrt))
    }
    #[inline(always)]
    fn max(self, other: Self) -> Self {
        Self(std::array::from_fn(|l| {
            if self.0[l] > other.0[l] {
                self.0[l]
            } else {
                other.0[l]
            }
        }))
    }
    #[inline(always)]
    fn select_gt(self, other: Self, then: Self, otherwise: Self) -> Self {
        Self(std::array::from_fn(|l| {
            if self.0[l] > other.0[l] {
                then.0[l]
            } else {
                otherwise.0[l]
            }
        }))
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) use avx::Avx;

/// Whether this CPU runs [`Avx`].
#[cfg(target_arch = "x86_64")]
pub(crate) fn avx2_fma() -> bool {
    std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
}

#[cfg(target_arch = "x86_64")]
mod avx {
    use super::Four;
    use std::arch::x86_64::*;
    use std::ops::{Add, Div, Mul, Neg, Sub};

    /// The AVX2 + FMA lanes.
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Avx(__m256d);

    // Every `unsafe` block below calls an AVX2 or FMA intrinsic. They run only inlined into
    // functions compiled with `avx2,fma`, which callers pick after detecting both features
    // (module doc); `Avx` is private to the crate, so nothing else reaches them.
    macro_rules! avx_op {
        ($trait:ident, $method:ident, $intrinsic:ident) => {
            impl $trait for Avx {
                type Output = Self;
                #[inline(always)]
                fn $method(self, b: Self) -> Self {
                    // SAFETY: AVX2 is present (see above).
                    Self(unsafe { $intrinsic(self.0, b.0) })
                }
            }
        };
    }
    avx_op!(Add, add, _mm256_add_pd);
    avx_op!(Sub, sub, _mm256_sub_pd);
    avx_op!(Mul, mul, _mm256_mul_pd);
    avx_op!(Div, div, _mm256_div_pd);

    impl Neg for Avx {
        type Output = Self;
        #[inline(always)]
        fn neg(self) -> Self {
            // SAFETY: AVX2 is present (see above).
            Self(unsafe { _mm256_xor_pd(self.0, _mm256_set1_pd(-0.0)) })
        }
    }

    impl Four for Avx {
        #[inline(always)]
        fn splat(x: f64) -> Self {
            // SAFETY: AVX2 is present (see above).
            Self(unsafe { _mm256_set1_pd(x) })
        }
        #[inline(always)]
        fn from_array(a: [f64; 4]) -> Self {
            // SAFETY: AVX2 is present (see above); `a` holds the four doubles read.
            Self(unsafe { _mm256_loadu_pd(a.as_ptr()) })
        }
        #[inline(always)]
        fn to_array(self) -> [f64; 4] {
            let mut a = [0.0; 4];
            // SAFETY: AVX2 is present (see above); `a` holds the four doubles written.
            unsafe { _mm256_storeu_pd(a.as_mut_ptr(), self.0) };
            a
        }
        #[inline(always)]
        fn mul_add(self, b: Self, c: Self) -> Self {
            // SAFETY: FMA is present (see above).
            Self(unsafe { _mm256_fmadd_pd(self.0, b.0, c.0) })
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            // SAFETY: AVX2 is present (see above).
            Self(unsafe { _mm256_sqrt_pd(self.0) })
        }
        #[inline(always)]
        fn max(self, other: Self) -> Self {
            // SAFETY: AVX2 is present (see above).
            Self(unsafe { _mm256_max_pd(self.0, other.0) })
        }
        #[inline(always)]
        fn select_gt(self, other: Self, then: Self, otherwise: Self) -> Self {
            // SAFETY: AVX2 is present (see above).
            unsafe {
                let mask = _mm256_cmp_pd::<_CMP_GT_OQ>(self.0, other.0);
                Self(_mm256_blendv_pd(otherwise.0, then.0, mask))
            }
        }
        #[inline(always)]
        fn transpose(columns: [Self; 4]) -> [Self; 4] {
            // SAFETY: AVX2 is present (see above).
            unsafe {
                let [a, b, c, d] = columns.map(|x| x.0);
                // Pairs of lanes (0, 1) and (2, 3) interleaved, then halves swapped across.
                let ab_lo = _mm256_unpacklo_pd(a, b); // a0 b0 a2 b2
                let ab_hi = _mm256_unpackhi_pd(a, b); // a1 b1 a3 b3
                let cd_lo = _mm256_unpacklo_pd(c, d); // c0 d0 c2 d2
                let cd_hi = _mm256_unpackhi_pd(c, d); // c1 d1 c3 d3
                let rows = [
                    _mm256_permute2f128_pd::<0x20>(ab_lo, cd_lo), // a0 b0 c0 d0
                    _mm256_permute2f128_pd::<0x20>(ab_hi, cd_hi), // a1 b1 c1 d1
                    _mm256_permute2f128_pd::<0x31>(ab_lo, cd_lo), // a2 b2 c2 d2
                    _mm256_permute2f128_pd::<0x31>(ab_hi, cd_hi), // a3 b3 c3 d3
                ];
                let [r0, r1, r2, r3] = rows;
                [Avx(r0), Avx(r1), Avx(r2), Avx(r3)]
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values that exercise rounding, signs, zeros, infinities and NaN.
    fn samples() -> Vec<[f64; 4]> {
        let odd = [0.1, -1.0 / 3.0, 2.0f64.sqrt(), 1e-300];
        vec![
            odd,
            [1e300, -0.0, 0.0, f64::INFINITY],
            [f64::NAN, 7.0, -7.5, 3.25],
            [5e-324, -2.5, 1.0 + f64::EPSILON, -1e-3],
        ]
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn avx_results(a: [f64; 4], b: [f64; 4], c: [f64; 4]) -> Vec<[f64; 4]> {
        let (x, y, z) = (Avx::from_array(a), Avx::from_array(b), Avx::from_array(c));
        let mut out = vec![
            (x + y).to_array(),
            (x - y).to_array(),
            (x * y).to_array(),
            (x / y).to_array(),
            (-x).to_array(),
            x.mul_add(y, z).to_array(),
            x.sqrt().to_array(),
            x.max(y).to_array(),
            x.select_gt(y, z, y).to_array(),
            x.select_lt(y, z, y).to_array(),
            [x.sum(), 0.0, 0.0, 0.0],
        ];
        out.extend(Avx::transpose_to_arrays([x, y, z, x * z]));
        out
    }

    fn portable_results(a: [f64; 4], b: [f64; 4], c: [f64; 4]) -> Vec<[f64; 4]> {
        let (x, y, z) = (Portable(a), Portable(b), Portable(c));
        let mut out = vec![
            (x + y).0,
            (x - y).0,
            (x * y).0,
            (x / y).0,
            (-x).0,
            x.mul_add(y, z).0,
            x.sqrt().0,
            x.max(y).0,
            x.select_gt(y, z, y).0,
            x.select_lt(y, z, y).0,
            [x.sum(), 0.0, 0.0, 0.0],
        ];
        out.extend(Portable::transpose_to_arrays([x, y, z, x * z]));
        out
    }

    #[test]
    fn portable_lanes_compute_lane_by_lane() {
        let [a, b, c, _] = samples()[..] else {
            unreachable!()
        };
        let out = portable_results(a, b, c);
        for l in 0..4 {
            assert_eq!(out[2][l].to_bits(), (a[l] * b[l]).to_bits());
            assert_eq!(out[5][l].to_bits(), a[l].mul_add(b[l], c[l]).to_bits());
        }
        // Transposed: row l holds lane l of each column.
        assert_eq!(out[11][1].to_bits(), b[0].to_bits());
        assert_eq!(out[13][2].to_bits(), c[2].to_bits());
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx_and_portable_lanes_give_the_same_bits() {
        if !avx2_fma() {
            return;
        }
        let s = samples();
        for (i, a) in s.iter().enumerate() {
            for b in &s {
                let c = s[(i + 1) % s.len()];
                // SAFETY: the CPU supports AVX2 and FMA (checked above).
                let avx = unsafe { avx_results(*a, *b, c) };
                let portable = portable_results(*a, *b, c);
                let bits = |v: &Vec<[f64; 4]>| -> Vec<u64> {
                    v.iter().flatten().map(|x| x.to_bits()).collect()
                };
                assert_eq!(bits(&avx), bits(&portable), "{a:?} {b:?} {c:?}");
            }
        }
    }
}
