//! The bulk of a bundle adjustment, four observations at a time.
//!
//! Reprojections of eliminated points with isotropic information and a Huber kernel or none
//! are copied at analysis into chunks of four observations of one point. The four lanes take
//! the same steps, so a chunk is a few hundred vector instructions (compiled for AVX2 + FMA and
//! picked at run time; the portable build takes the same steps in the same order, so both
//! give the same bits). A point's own block and gradient are summed in lanes over its chunks
//! and added to `V` and `g` once; its couplings `W` are written in the order they are laid out
//! (sequentially: `W` is megabytes, and scattered writes cost more than the arithmetic); each
//! lane adds its pose's block and gradient to a small per-pose sum, added to `H` at the end.
//!
//! The blocks are those of [`crate::bundle`] (`J = D·[P | R_cw]`, see there); a test checks
//! both against each other. Costs of the same observations come from here too, so a cost pass
//! and an assembly see the same numbers.

use super::assemble::Accumulators;
use super::{Coupling, Share};
use crate::bundle::{PoseViews, Reprojection};
use crate::camera::{DepthResidual, MIN_DEPTH};
use crate::factor::Kernel;
#[cfg(target_arch = "x86_64")]
use crate::four::{avx2_fma, Avx};
use crate::four::{Four, Portable};
use crate::problem::Entry;
use crate::values::{Values, VarId};
use nalgebra::Vector3;
use std::ops::Range;

const LANES: usize = 4;
type Lanes = [f64; LANES];

/// A lane without a pose block or a `W` block (a fixed pose, or padding).
const NONE: u32 = u32::MAX;

/// Per pose, what its observations add to its own block and gradient: `G`'s five entries
/// `(00, 02, 11, 12, 22)`, `N = G·[p]×` by column (nine), the six entries of `[p]×ᵀ·G·[p]×`
/// in the upper triangle, the gradient (six) and two unused, summed over observations.
pub(super) type PoseParts = [f64; 28];

/// Four observations of one point, each field by lane. A padding lane repeats a real lane's
/// pose with zero information, so it adds nothing and writes nowhere.
#[derive(Clone, Copy, Debug)]
struct Chunk {
    /// The pose's variable, for its view.
    pose: [u32; LANES],
    /// The pose's index in [`Observations::poses`] ([`NONE`]: fixed or padding).
    slot: [u32; LANES],
    /// Start of the lane's `W` block within the share's ([`NONE`]: fixed or padding).
    w_at: [u32; LANES],
    measured: [Lanes; 3],
    /// `s²` of the information `s·I` (0 in a padding lane).
    scale2: Lanes,
    /// Huber's `δ` (∞ without a kernel: every residual is then in the quadratic part).
    delta: Lanes,
    /// `bf` of an RGB-D observation `(u, v, u_r)`, 0 for a monocular one `(u, v)`.
    bf: Lanes,
    /// The camera's index in [`Observations::cameras`], with [`RGBD`] set for `(u, v, u_r)` and
    /// [`RIGHT_IMAGE`] as well when its depth is a right-image residual.
    camera: [u32; LANES],
}

/// Marks an RGB-D lane in [`Chunk::camera`].
const RGBD: u32 = 1 << 31;
/// Marks an RGB-D lane whose depth is [`DepthResidual::RightImage`]'s.
const RIGHT_IMAGE: u32 = 1 << 30;

/// One point's chunks.
#[derive(Clone, Debug)]
struct PointRun {
    point: VarId,
    /// Its index among the share's eliminated variables.
    elim: usize,
    chunks: Range<usize>,
}

/// A free pose the share's observations see: where column `k` of its own block starts in `H`
/// (rows `0..=k` follow), and its offset in `g`.
#[derive(Clone, Copy, Debug)]
struct PoseTarget {
    starts: [usize; 6],
    offset: usize,
}

/// One share's observations that take this path.
#[derive(Clone, Debug, Default)]
pub(super) struct Observations {
    points: Vec<PointRun>,
    chunks: Vec<Chunk>,
    poses: Vec<PoseTarget>,
    /// Every camera `(fx, fy, cx, cy)` the observations use (usually one).
    cameras: Vec<[f64; 4]>,
}

/// An observation the analysis gives this path: its point's index among all eliminated
/// variables and its coupling's index ([`NONE`] when the pose is fixed).
#[derive(Clone, Copy, Debug)]
pub(super) struct Observed {
    pub elim: u32,
    pub coupling: u32,
}

impl Observed {
    /// Not an observation of this path.
    pub const NONE: Self = Self {
        elim: NONE,
        coupling: NONE,
    };
}

impl Observations {
    /// Whether an observation can take this path: its kernel is Huber or none.
    pub fn accepts(kernel: Option<Kernel>) -> bool {
        matches!(kernel, None | Some(Kernel::Huber(_)))
    }

    /// Lays out the share's observations (each accepted by [`Self::accepts`], onto one of
    /// the share's eliminated points) by point, each point's in the order of its couplings.
    /// `offset` gives each variable's place in the update vector, `diagonal(offset)` where a
    /// pose's own block starts in each of its columns of `H`.
    pub fn new(
        share: &Share,
        observed: &[(u32, Observed)],
        entries: &[Entry],
        couplings: &[Coupling],
        (offset, diagonal): (&[usize], &dyn Fn(usize) -> [usize; 6]),
    ) -> Self {
        // By point (a counting sort: points are many, a point's observations few), and each
        // point's by coupling, fixed poses (no coupling) last.
        let points = share.elim.len();
        let local = |o: &(u32, Observed)| o.1.elim as usize - share.elim.start;
        let mut start = vec![0; points + 1];
        for o in observed {
            start[local(o) + 1] += 1;
        }
        for e in 0..points {
            start[e + 1] += start[e];
        }
        let mut next = start.clone();
        let mut sorted = vec![0u32; observed.len()];
        for (i, o) in observed.iter().enumerate() {
            sorted[next[local(o)]] = i as u32;
            next[local(o)] += 1;
        }
        let mut out = Self {
            points: Vec::with_capacity(points),
            chunks: Vec::with_capacity(observed.len() / LANES + points),
            poses: Vec::new(),
            cameras: Vec::new(),
        };
        let mut slot_of = vec![NONE; offset.len()];
        for e in 0..points {
            let run = &mut sorted[start[e]..start[e + 1]];
            if run.is_empty() {
                continue;
            }
            run.sort_unstable_by_key(|&i| observed[i as usize].1.coupling);
            let first = out.chunks.len();
            for lanes in run.chunks(LANES) {
                let mut chunk = Chunk::PADDING;
                for l in 0..LANES {
                    let (factor, o) = observed[lanes[l.min(lanes.len() - 1)] as usize];
                    let e = &entries[factor as usize];
                    let fast = e.reprojection.as_ref().expect("a reprojection");
                    let camera = fast.camera();
                    let camera = [camera.fx, camera.fy, camera.cx, camera.cy];
                    let index = match out.cameras.iter().position(|c| *c == camera) {
                        Some(i) => i,
                        None => {
                            out.cameras.push(camera);
                            out.cameras.len() - 1
                        }
                    };
                    chunk.set(l, fast, e.kernel, index as u32);
                    if l >= lanes.len() {
                        continue;
                    }
                    chunk.scale2[l] = fast.scale() * fast.scale();
                    if o.coupling == NONE {
                        // A fixed pose: no pose block, no coupling.
                        continue;
                    }
                    chunk.w_at[l] = (couplings[o.coupling as usize].data - share.data.start) as u32;
                    let pose = fast.pose.index();
                    if slot_of[pose] == NONE {
                        slot_of[pose] = out.poses.len() as u32;
                        out.poses.push(PoseTarget {
                            starts: diagonal(offset[pose]),
                            offset: offset[pose],
                        });
                    }
                    chunk.slot[l] = slot_of[pose];
                }
                out.chunks.push(chunk);
            }
            let factor = observed[run[0] as usize].0;
            let fast = entries[factor as usize].reprojection.as_ref();
            out.points.push(PointRun {
                point: fast.expect("a reprojection").point,
                elim: e,
                chunks: first..out.chunks.len(),
            });
        }
        out
    }

    /// `Σ ρ(s)` of the observations at `values`.
    pub fn cost(&self, values: &Values, views: &PoseViews) -> f64 {
        #[cfg(target_arch = "x86_64")]
        if avx2_fma() {
            // SAFETY: the CPU has just been found to support AVX2 and FMA.
            return unsafe { self.cost_avx2(values, views) };
        }
        self.cost_with::<Portable>(values, views)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn cost_avx2(&self, values: &Values, views: &PoseViews) -> f64 {
        self.cost_with::<Avx>(values, views)
    }

    #[inline(always)]
    fn cost_with<F: Four>(&self, values: &Values, views: &PoseViews) -> f64 {
        let mut sum = F::splat(0.0);
        for run in &self.points {
            let point = values.at::<Vector3<f64>>(run.point);
            for c in &self.chunks[run.chunks.clone()] {
                sum = sum + c.evaluate::<F>(point, views, &self.cameras).cost;
            }
        }
        sum.sum()
    }

    /// Adds the observations' blocks to `H` (the poses' own, upper triangle), `g`, `V` and
    /// `W` (stored when each coupling has one factor, `w_single`, else added), and returns
    /// their cost. `g_l`, `v` and `w` are the share's slices; `parts` is scratch.
    pub fn assemble(
        &self,
        (values, views): (&Values, &PoseViews),
        out: &mut Accumulators<'_>,
        w_single: bool,
        parts: &mut Vec<PoseParts>,
    ) -> f64 {
        parts.clear();
        parts.resize(self.poses.len(), [0.0; 28]);
        #[cfg(target_arch = "x86_64")]
        if avx2_fma() {
            // SAFETY: the CPU has just been found to support AVX2 and FMA.
            return unsafe { self.assemble_avx2((values, views), out, w_single, parts) };
        }
        self.assemble_with::<Portable>((values, views), out, w_single, parts)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn assemble_avx2(
        &self,
        (values, views): (&Values, &PoseViews),
        out: &mut Accumulators<'_>,
        w_single: bool,
        parts: &mut [PoseParts],
    ) -> f64 {
        self.assemble_with::<Avx>((values, views), out, w_single, parts)
    }

    #[inline(always)]
    fn assemble_with<F: Four>(
        &self,
        (values, views): (&Values, &PoseViews),
        out: &mut Accumulators<'_>,
        w_single: bool,
        parts: &mut [PoseParts],
    ) -> f64 {
        let zero = F::splat(0.0);
        let mut cost = zero;
        for run in &self.points {
            let point = values.at::<Vector3<f64>>(run.point);
            // The point's own block (upper triangle) and gradient, summed by lane.
            let mut own = [zero; 9];
            for c in &self.chunks[run.chunks.clone()] {
                let e = c.evaluate::<F>(point, views, &self.cameras);
                cost = cost + e.cost;
                let b = e.blocks();
                for (o, x) in own.iter_mut().zip(b.point.iter().chain(&b.g_point)) {
                    *o = *o + *x;
                }
                c.scatter(&b, out, w_single, parts);
            }
            let v = &mut out.v[run.elim];
            let mut sums = [0.0; 9];
            for (s, x) in sums.iter_mut().zip(&own) {
                *s = x.sum();
            }
            let [v00, v11, v22, v01, v02, v12, g0, g1, g2] = sums;
            for (i, j, x) in [(0, 0, v00), (1, 1, v11), (2, 2, v22)] {
                v[(i, j)] += x;
            }
            for (i, j, x) in [(0, 1, v01), (0, 2, v02), (1, 2, v12)] {
                v[(i, j)] += x;
                v[(j, i)] += x;
            }
            let g = &mut out.g_l[3 * run.elim..3 * run.elim + 3];
            g[0] += g0;
            g[1] += g1;
            g[2] += g2;
        }
        for (pose, parts) in self.poses.iter().zip(parts.iter()) {
            pose.add(parts, out.h, out.g_r);
        }
        cost.sum()
    }
}

impl PoseTarget {
    /// Adds a pose's summed parts to its block's upper triangle in `h` and its gradient in `g`.
    fn add(&self, parts: &PoseParts, h: &mut [f64], g: &mut [f64]) {
        let [g00, g02, g11, g12, g22] = [parts[0], parts[1], parts[2], parts[3], parts[4]];
        let n = &parts[5..14];
        let x = &parts[14..20];
        // Pᵀ·G·P = [[G, −N], [−Nᵀ, X]]: column 3 + j holds −n_j, then x_j's upper part.
        let columns: [&[f64]; 6] = [
            &[g00],
            &[0.0, g11],
            &[g02, g12, g22],
            &[-n[0], -n[1], -n[2], x[0]],
            &[-n[3], -n[4], -n[5], x[1], x[2]],
            &[-n[6], -n[7], -n[8], x[3], x[4], x[5]],
        ];
        for (start, column) in self.starts.iter().zip(columns) {
            for (h, x) in h[*start..*start + column.len()].iter_mut().zip(column) {
                *h += x;
            }
        }
        for (g, s) in g[self.offset..self.offset + 6]
            .iter_mut()
            .zip(&parts[20..26])
        {
            *g += s;
        }
    }
}

impl Chunk {
    /// Lanes that add nothing and write nowhere.
    const PADDING: Self = Self {
        pose: [0; LANES],
        slot: [NONE; LANES],
        w_at: [NONE; LANES],
        measured: [[0.0; LANES]; 3],
        scale2: [0.0; LANES],
        delta: [f64::INFINITY; LANES],
        bf: [0.0; LANES],
        camera: [0; LANES],
    };

    /// Lane `l`'s pose and measurement (its information, pose slot and `W` block are set by
    /// the caller; a padding lane keeps zero information).
    fn set(&mut self, l: usize, fast: &Reprojection, kernel: Option<Kernel>, camera: u32) {
        self.pose[l] = fast.pose.0;
        for (m, x) in self.measured.iter_mut().zip(fast.measured()) {
            m[l] = x;
        }
        self.delta[l] = match kernel {
            Some(Kernel::Huber(delta)) => delta,
            _ => f64::INFINITY,
        };
        let stereo = fast.stereo();
        self.bf[l] = stereo.map_or(0.0, |s| s.bf);
        self.camera[l] = camera
            | match stereo.map(|s| s.residual) {
                None => 0,
                Some(DepthResidual::Disparity) => RGBD,
                Some(DepthResidual::RightImage) => RGBD | RIGHT_IMAGE,
            };
    }

    /// Residuals, costs and robust weights of the four lanes, for the point at `point`.
    #[inline(always)]
    fn evaluate<F: Four>(
        &self,
        point: &Vector3<f64>,
        views: &PoseViews,
        cameras: &[[f64; 4]],
    ) -> Evaluated<'_, F> {
        // Each lane's pose: `R_cw` and the centre, gathered. (No closures over lanes in this
        // kernel: in the AVX2 build they would be compiled apart, without AVX2.)
        let [p0, p1, p2, p3] = self.pose;
        let v = [
            views.get(VarId(p0)),
            views.get(VarId(p1)),
            views.get(VarId(p2)),
            views.get(VarId(p3)),
        ];
        let mut rot = [[F::splat(0.0); 3]; 3];
        for (i, row) in rot.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x = F::from_array([
                    v[0].rotation[(i, j)],
                    v[1].rotation[(i, j)],
                    v[2].rotation[(i, j)],
                    v[3].rotation[(i, j)],
                ]);
            }
        }
        let mut d = [F::splat(0.0); 3];
        for (k, d) in d.iter_mut().enumerate() {
            let centre = [
                v[0].centre[k],
                v[1].centre[k],
                v[2].centre[k],
                v[3].centre[k],
            ];
            *d = F::splat(point[k]) - F::from_array(centre);
        }
        let p = rotate(&rot, &d);
        let load = F::from_array;
        let iz = F::splat(1.0) / p[2].max(F::splat(MIN_DEPTH));
        // Each lane's camera, 1 for RGB-D (0 for monocular) and 1 for a right-image residual.
        let mut k = [[0.0; LANES]; 6];
        for (l, &c) in self.camera.iter().enumerate() {
            let camera = &cameras[(c & !(RGBD | RIGHT_IMAGE)) as usize];
            for (k, x) in k.iter_mut().zip(camera) {
                k[l] = *x;
            }
            k[4][l] = if c & RGBD != 0 { 1.0 } else { 0.0 };
            k[5][l] = if c & RIGHT_IMAGE != 0 { 1.0 } else { 0.0 };
        }
        let [fx, fy, cx, cy, stereo, right] = [
            F::from_array(k[0]),
            F::from_array(k[1]),
            F::from_array(k[2]),
            F::from_array(k[3]),
            F::from_array(k[4]),
            F::from_array(k[5]),
        ];
        let u = (fx * p[0]).mul_add(iz, cx);
        let v = (fy * p[1]).mul_add(iz, cy);
        let m = [
            load(self.measured[0]),
            load(self.measured[1]),
            load(self.measured[2]),
        ];
        let bf = load(self.bf);
        // The third entry as `pixel_residual`'s, in the same order of operations.
        let disparity = bf * iz;
        let depth = right.select_gt(
            F::splat(0.5),
            (u - disparity) - m[2],
            (m[0] - m[2]) - disparity,
        );
        let r = [u - m[0], v - m[1], stereo * depth];
        let scale2 = load(self.scale2);
        let s = scale2 * r[2].mul_add(r[2], r[1].mul_add(r[1], r[0] * r[0]));
        // Huber: both branches computed and one kept per lane.
        let delta = load(self.delta);
        let d2 = delta * delta;
        let root = s.sqrt();
        let linear = (F::splat(2.0) * delta).mul_add(root, -d2);
        Evaluated {
            chunk: self,
            fx,
            fy,
            stereo,
            right,
            rot,
            p,
            r,
            iz,
            cost: s.select_gt(d2, linear, s),
            w2: scale2 * s.select_gt(d2, delta / root, F::splat(1.0)),
        }
    }

    /// Adds each real lane's pose parts to its pose's sums and writes its coupling to `W`.
    #[inline(always)]
    fn scatter<F: Four>(
        &self,
        b: &Blocks<F>,
        out: &mut Accumulators<'_>,
        w_single: bool,
        parts: &mut [PoseParts],
    ) {
        let (g, n, x, gp) = (&b.g, &b.n, &b.x, &b.g_pose);
        let zero = F::splat(0.0);
        let quads = [
            F::transpose_to_arrays([g[0], g[1], g[2], g[3]]),
            F::transpose_to_arrays([g[4], n[0], n[1], n[2]]),
            F::transpose_to_arrays([n[3], n[4], n[5], n[6]]),
            F::transpose_to_arrays([n[7], n[8], x[0], x[1]]),
            F::transpose_to_arrays([x[2], x[3], x[4], x[5]]),
            F::transpose_to_arrays([gp[0], gp[1], gp[2], gp[3]]),
            F::transpose_to_arrays([gp[4], gp[5], zero, zero]),
        ];
        for l in 0..LANES {
            if self.slot[l] == NONE {
                continue;
            }
            let sums = &mut parts[self.slot[l] as usize];
            for (q, quad) in quads.iter().enumerate() {
                for (s, x) in sums[4 * q..4 * q + 4].iter_mut().zip(&quad[l]) {
                    *s += x;
                }
            }
        }
        let c = &b.coupling;
        let quads = [
            F::transpose_to_arrays([c[0], c[1], c[2], c[3]]),
            F::transpose_to_arrays([c[4], c[5], c[6], c[7]]),
            F::transpose_to_arrays([c[8], c[9], c[10], c[11]]),
            F::transpose_to_arrays([c[12], c[13], c[14], c[15]]),
        ];
        let (c16, c17) = (c[16].to_array(), c[17].to_array());
        for l in 0..LANES {
            if self.w_at[l] == NONE {
                continue;
            }
            let at = self.w_at[l] as usize;
            let mut lane = [0.0; 18];
            for (q, quad) in quads.iter().enumerate() {
                lane[4 * q..4 * q + 4].copy_from_slice(&quad[l]);
            }
            lane[16] = c16[l];
            lane[17] = c17[l];
            let w: &mut [f64; 18] = (&mut out.w[at..at + 18]).try_into().expect("6 × 3");
            if w_single {
                *w = lane;
            } else {
                for (x, y) in w.iter_mut().zip(&lane) {
                    *x += y;
                }
            }
        }
    }
}

/// A chunk evaluated at a set of values.
struct Evaluated<'a, F> {
    chunk: &'a Chunk,
    fx: F,
    fy: F,
    /// 1 for RGB-D, 0 for monocular.
    stereo: F,
    /// 1 for a right-image residual, else 0.
    right: F,
    /// Each lane's `R_cw`.
    rot: [[F; 3]; 3],
    /// The points in the camera.
    p: [F; 3],
    r: [F; 3],
    /// `1 / max(z, MIN_DEPTH)`.
    iz: F,
    cost: F,
    /// `s²·ρ'`.
    w2: F,
}

/// Four lanes' blocks: the pose block's parts (see [`PoseParts`]), the point block's upper
/// triangle `(00, 11, 22, 01, 02, 12)`, the coupling `W` (6 × 3 by column) and both gradients.
struct Blocks<F> {
    g: [F; 5],
    n: [F; 9],
    x: [F; 6],
    g_pose: [F; 6],
    point: [F; 6],
    coupling: [F; 18],
    g_point: [F; 3],
}

impl<F: Four> Evaluated<'_, F> {
    #[inline(always)]
    fn blocks(&self) -> Blocks<F> {
        let c = self.chunk;
        let load = F::from_array;
        let (p, r, iz) = (&self.p, &self.r, self.iz);
        // D's entries: u's row [a, 0, b], v's [0, cc, d], the disparity's [0, 0, e] or the right
        // image's [a, 0, e] with e holding b as well; the depth column is zero where the depth is
        // clamped. A disparity lane adds zeros where a right-image lane adds its u terms, so
        // both keep `gauss_newton_terms`' bits.
        let zero = F::splat(0.0);
        let a = self.fx * iz;
        let cc = self.fy * iz;
        let min = F::splat(MIN_DEPTH);
        let b = p[2].select_lt(min, zero, -(a * p[0] * iz));
        let d = p[2].select_lt(min, zero, -(cc * p[1] * iz));
        let lever = self.right * b;
        let e = p[2].select_lt(min, lever, (load(c.bf) * iz).mul_add(iz, lever));
        let (st, w2) = (self.stereo, self.w2);
        let ra = self.right * a;
        let g00 = a.mul_add(a, ra * a) * w2;
        let g02 = a.mul_add(b, ra * e) * w2;
        let g11 = cc * cc * w2;
        let g12 = cc * d * w2;
        let g22 = b.mul_add(b, d.mul_add(d, st * e * e)) * w2;
        // r's third entry is 0 for a monocular lane.
        let h = [
            a * (r[0] + self.right * r[2]) * w2,
            cc * r[1] * w2,
            b.mul_add(r[0], d.mul_add(r[1], e * r[2])) * w2,
        ];
        let [px, py, pz] = *p;
        // N = G·[p]× by column: n_j = G·(p × e_j).
        let n = [
            -(g02 * py),
            g11.mul_add(pz, -(g12 * py)),
            g12.mul_add(pz, -(g22 * py)),
            g02.mul_add(px, -(g00 * pz)),
            g12 * px,
            g22.mul_add(px, -(g02 * pz)),
            g00 * py,
            -(g11 * px),
            g02.mul_add(py, -(g12 * px)),
        ];
        // x_j = n_j × p, of which the pose block keeps (x_0[0], x_1[0..2], x_2[0..3]).
        let x0 = cross([n[0], n[1], n[2]], *p);
        let x1 = cross([n[3], n[4], n[5]], *p);
        let x2 = cross([n[6], n[7], n[8]], *p);
        let hx = cross(h, *p);
        // G·R_cw by column, then the coupling Pᵀ·(G·R) and the point block Rᵀ·(G·R).
        let rot = &self.rot;
        let mut gr = [[zero; 3]; 3];
        let mut coupling = [zero; 18];
        for k in 0..3 {
            let (r0, r1, r2) = (rot[0][k], rot[1][k], rot[2][k]);
            gr[k] = [
                g00.mul_add(r0, g02 * r2),
                g11.mul_add(r1, g12 * r2),
                g02.mul_add(r0, g12.mul_add(r1, g22 * r2)),
            ];
            let x = cross(gr[k], *p);
            for i in 0..3 {
                coupling[6 * k + i] = -gr[k][i];
                coupling[6 * k + 3 + i] = x[i];
            }
        }
        Blocks {
            g: [g00, g02, g11, g12, g22],
            n,
            x: [x0[0], x1[0], x1[1], x2[0], x2[1], x2[2]],
            g_pose: [-h[0], -h[1], -h[2], hx[0], hx[1], hx[2]],
            point: [
                dot_column(rot, 0, &gr[0]),
                dot_column(rot, 1, &gr[1]),
                dot_column(rot, 2, &gr[2]),
                dot_column(rot, 0, &gr[1]),
                dot_column(rot, 0, &gr[2]),
                dot_column(rot, 1, &gr[2]),
            ],
            coupling,
            g_point: [
                dot_column(rot, 0, &h),
                dot_column(rot, 1, &h),
                dot_column(rot, 2, &h),
            ],
        }
    }
}

/// `R·d`, lane by lane.
#[inline(always)]
fn rotate<F: Four>(rot: &[[F; 3]; 3], d: &[F; 3]) -> [F; 3] {
    [
        rot[0][2].mul_add(d[2], rot[0][1].mul_add(d[1], rot[0][0] * d[0])),
        rot[1][2].mul_add(d[2], rot[1][1].mul_add(d[1], rot[1][0] * d[0])),
        rot[2][2].mul_add(d[2], rot[2][1].mul_add(d[1], rot[2][0] * d[0])),
    ]
}

/// Column `i` of `R` dotted with `v` (`(Rᵀ·v)_i`), lane by lane.
#[inline(always)]
fn dot_column<F: Four>(rot: &[[F; 3]; 3], i: usize, v: &[F; 3]) -> F {
    rot[2][i].mul_add(v[2], rot[1][i].mul_add(v[1], rot[0][i] * v[0]))
}

/// `a × b`, lane by lane.
#[inline(always)]
fn cross<F: Four>(a: [F; 3], b: [F; 3]) -> [F; 3] {
    [
        a[1].mul_add(b[2], -(a[2] * b[1])),
        a[2].mul_add(b[0], -(a[0] * b[2])),
        a[0].mul_add(b[1], -(a[1] * b[0])),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{ProjectionFactor, StereoProjectionFactor};
    use crate::normal::NormalEquations;
    use crate::testing::{bundle_scene, BundleConfig, Rng};
    use crate::{Information, Pinhole, Problem};
    use nalgebra::Vector2;

    /// A bundle adjustment with everything the four-lane path must get right: RGB-D (depth as
    /// a disparity and as a right-image coordinate) and monocular observations, Huber kernels and none, two cameras, fixed poses, points behind
    /// a camera (their depth clamped), residuals in both parts of the Huber kernel, and a
    /// Cauchy factor, which stays on the one-at-a-time path.
    fn varied_problem() -> Problem {
        let config = BundleConfig {
            keyframes: 8,
            points: 300,
            observations_per_point: 5,
            ..BundleConfig::default()
        };
        let mut problem = bundle_scene(&config, 3).problem;
        let values = problem.values().clone();
        let poses: Vec<VarId> = values
            .ids()
            .filter(|&id| values.variable(id).unwrap().kind() == crate::Kind::Pose)
            .collect();
        let points: Vec<VarId> = values
            .ids()
            .filter(|&id| values.variable(id).unwrap().kind() == crate::Kind::Point)
            .collect();
        let other = Pinhole::new(520.0, 515.0, 330.0, 250.0);
        let mut rng = Rng::new(9);
        for (i, &point) in points.iter().enumerate().step_by(7) {
            let pose = values.key(poses[i % poses.len()]).unwrap();
            let point = values.key(point).unwrap();
            let measured = Vector2::new(rng.range(0.0, 640.0), rng.range(0.0, 480.0));
            let info = Information::isotropic(2, 1.0 + (i % 3) as f64).unwrap();
            let kernel = [None, Some(Kernel::Huber(0.5)), Some(Kernel::Huber(50.0))][i % 3];
            let mono = ProjectionFactor::new(pose, point, other, measured);
            problem.add(mono, info, kernel).unwrap();
            if i % 2 == 0 {
                let m = nalgebra::Vector3::new(measured.x, measured.y, measured.x - 20.0);
                let stereo = StereoProjectionFactor::new(pose, point, other, 25.0, m);
                let info = Information::isotropic(3, 1.5).unwrap();
                problem
                    .add(stereo, info, Some(Kernel::Cauchy(2.0)))
                    .unwrap();
            } else {
                // ORB-SLAM's right-image form, on the four-lane path.
                let m = nalgebra::Vector3::new(measured.x, measured.y, measured.x - 15.0);
                let right = StereoProjectionFactor::new(pose, point, other, 25.0, m)
                    .with_residual(DepthResidual::RightImage);
                let info = Information::isotropic(3, 1.2).unwrap();
                problem.add(right, info, kernel).unwrap();
            }
        }
        // A few points behind the first free camera.
        let camera = *problem
            .values()
            .get(values.key::<crate::Se3>(poses[3]).unwrap());
        for &point in points.iter().take(4) {
            let key = values.key(point).unwrap();
            let behind = camera.transform_point(&nalgebra::Vector3::new(0.1, 0.2, -1.0));
            problem.values_mut().set(key, behind);
        }
        problem
    }

    fn relative_difference(a: &[f64], b: &[f64]) -> f64 {
        let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-300);
        a.iter()
            .zip(b)
            .fold(0.0, |m, (x, y)| m.max((x - y).abs() / scale))
    }

    #[test]
    fn four_lanes_assemble_what_one_at_a_time_does() {
        let problem = varied_problem();
        for threads in [1, 3] {
            let mut lanes = NormalEquations::analyse_with(&problem, true, threads, true).unwrap();
            let mut single = NormalEquations::analyse_with(&problem, true, threads, false).unwrap();
            let taken: usize = lanes.st.shares.iter().map(|s| s.factors.len()).sum();
            let all: usize = single.st.shares.iter().map(|s| s.factors.len()).sum();
            assert!(
                taken < all / 2,
                "{taken} of {all} factors left one at a time"
            );
            assert!(lanes
                .st
                .shares
                .iter()
                .any(|s| !s.observations.cameras.is_empty()));
            let views = problem.pose_views(problem.values());
            let cost_lanes = lanes.linearize(&problem.entries, problem.values(), &views);
            let cost_single = single.linearize(&problem.entries, problem.values(), &views);
            assert!((cost_lanes - cost_single).abs() <= 1e-12 * cost_single);
            let cost = lanes.cost(&problem.entries, problem.values(), &views);
            assert!((cost - cost_single).abs() <= 1e-12 * cost_single);
            assert!(relative_difference(&lanes.h, &single.h) < 1e-12);
            assert!(relative_difference(&lanes.g, &single.g) < 1e-12);
            assert!(relative_difference(&lanes.w, &single.w) < 1e-12);
            let flat = |v: &[nalgebra::Matrix3<f64>]| -> Vec<f64> {
                v.iter().flat_map(|m| m.iter().copied()).collect()
            };
            assert!(relative_difference(&flat(&lanes.v), &flat(&single.v)) < 1e-12);
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn portable_and_avx_lanes_give_the_same_bits() {
        if !avx2_fma() {
            return;
        }
        let problem = varied_problem();
        let system = NormalEquations::analyse(&problem, true, 1).unwrap();
        let (st, share) = (&system.st, &system.st.shares[0]);
        let observations = &share.observations;
        let (values, views) = (problem.values(), &problem.pose_views(problem.values()));
        let run = |avx: bool| {
            let (mut h, mut g) = (vec![0.0; system.h.len()], vec![0.0; system.g.len()]);
            let mut v = vec![nalgebra::Matrix3::zeros(); system.v.len()];
            let mut w = vec![0.0; system.w.len()];
            let (g_r, g_l) = g.split_at_mut(st.n_reduced);
            let mut out = Accumulators {
                h: &mut h,
                g_r,
                g_l,
                v: &mut v,
                w: &mut w,
            };
            let mut parts = vec![[0.0; 28]; observations.poses.len()];
            let (cost, total) = if avx {
                // SAFETY: the CPU supports AVX2 and FMA (checked above).
                unsafe {
                    let c = observations.assemble_avx2((values, views), &mut out, true, &mut parts);
                    (c, observations.cost_avx2(values, views))
                }
            } else {
                let c = observations.assemble_with::<Portable>(
                    (values, views),
                    &mut out,
                    true,
                    &mut parts,
                );
                (c, observations.cost_with::<Portable>(values, views))
            };
            let mut bits: Vec<u64> = [cost, total].iter().map(|x| x.to_bits()).collect();
            let v: Vec<f64> = v.iter().flat_map(|m| m.iter().copied()).collect();
            for x in h.iter().chain(&g).chain(&v).chain(&w) {
                bits.push(x.to_bits());
            }
            bits
        };
        let (avx, portable) = (run(true), run(false));
        assert!(avx.iter().filter(|&&b| b != 0).count() > 1000);
        assert_eq!(avx, portable);
    }
}
