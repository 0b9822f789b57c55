//! Rooms, corridors and doorways (paper eq. 4–11).
//!
//! Centres follow the frame-independent definition in the reference facts: a corridor's centre
//! is its markers' centre projected onto the mid-plane of its two walls; a room's centre is its
//! markers' centre projected onto the intersection line of its two mid-planes (one per pair of
//! facing walls). One factor takes all of a room's wall markers: eq. 6 sums one term per marker,
//! but a term that projects a single marker puts the centre at that marker's place along the
//! corridor, so terms of markers spread along it disagree and pull the walls askew (we measured
//! it: the S-Graph test's trajectory got worse than without semantics). The printed eq. 4–5 use
//! the world origin instead and are singular when the origin lies on a mid-plane; this form has
//! no such case and does not change when the map is moved.

use crate::factor::Factor;
use crate::lie::{hat, Se3};
use crate::plane::Plane;
use crate::values::{Key, Kind, Values, VarId};
use nalgebra::{DMatrixViewMut, SMatrix, SVector, Vector3};

/// The mid-plane `w·x + k = 0` of two facing walls (unnormalised; `w = n_a ± n_b`), and the sign
/// that turned wall `b` to face the same way as wall `a`.
fn mid_plane(a: &Plane, b: &Plane) -> (Vector3<f64>, f64, f64) {
    let s = if a.normal.dot(&b.normal) >= 0.0 {
        1.0
    } else {
        -1.0
    };
    (
        a.normal.into_inner() + b.normal.into_inner() * s,
        a.offset + b.offset * s,
        s,
    )
}

/// Projection of `anchor` onto the intersection of the planes `A·x + k = 0` (`P` of them), with
/// the multipliers `λ = (AAᵀ)⁻¹(A·anchor + k)` and `(AAᵀ)⁻¹`. `None` when the planes are parallel.
#[allow(clippy::type_complexity)]
fn project<const P: usize>(
    a: &SMatrix<f64, P, 3>,
    k: &SVector<f64, P>,
    anchor: &Vector3<f64>,
) -> Option<(Vector3<f64>, SVector<f64, P>, SMatrix<f64, P, P>)> {
    let g_inv = (a * a.transpose()).try_inverse()?;
    let lambda = g_inv * (a * anchor + k);
    Some((anchor - a.transpose() * lambda, lambda, g_inv))
}

/// The centre of a corridor (two facing walls) for markers centred at `anchor`.
pub fn corridor_centre(walls: [&Plane; 2], anchor: &Vector3<f64>) -> Option<Vector3<f64>> {
    let (w, k, _) = mid_plane(walls[0], walls[1]);
    project::<1>(&w.transpose(), &SVector::from([k]), anchor).map(|p| p.0)
}

/// The centre of a four-wall room (`[x_a, x_b, y_a, y_b]`: two pairs of facing walls) for markers
/// centred at `anchor`. `None` when the pairs are parallel to each other.
pub fn room_centre(walls: [&Plane; 4], anchor: &Vector3<f64>) -> Option<Vector3<f64>> {
    let (wx, kx, _) = mid_plane(walls[0], walls[1]);
    let (wy, ky, _) = mid_plane(walls[2], walls[3]);
    let a = SMatrix::<f64, 2, 3>::from_rows(&[wx.transpose(), wy.transpose()]);
    project::<2>(&a, &SVector::from([kx, ky]), anchor).map(|p| p.0)
}

/// `r = c − f(walls, t̄)`: a room's (`P = 2`) or corridor's (`P = 1`) centre `c` agrees with its
/// walls, given the mean position `t̄` of its markers (paper eq. 6 and 10).
#[derive(Clone, Debug)]
pub struct CentreFactor<const P: usize> {
    /// Centre, `2P` walls (facing pairs), then the markers.
    keys: Vec<VarId>,
    kinds: Vec<Kind>,
}

/// A corridor's centre and its two walls (eq. 4–6).
pub type CorridorFactor = CentreFactor<1>;
/// A four-wall room's centre and its walls (eq. 7–10).
pub type RoomFactor = CentreFactor<2>;

impl<const P: usize> CentreFactor<P> {
    fn with(centre: Key<Vector3<f64>>, walls: &[Key<Plane>], markers: &[Key<Se3>]) -> Option<Self> {
        if markers.is_empty() {
            return None;
        }
        let mut keys = vec![centre.id];
        keys.extend(walls.iter().map(|w| w.id));
        keys.extend(markers.iter().map(|m| m.id));
        let mut kinds = vec![Kind::Point];
        kinds.extend(std::iter::repeat_n(Kind::Plane, walls.len()));
        kinds.extend(std::iter::repeat_n(Kind::Pose, markers.len()));
        Some(Self { keys, kinds })
    }

    fn markers(&self) -> &[VarId] {
        &self.keys[1 + 2 * P..]
    }
}

impl CorridorFactor {
    /// `None` without markers: the centre's place along the corridor would be undefined.
    pub fn new(
        centre: Key<Vector3<f64>>,
        walls: [Key<Plane>; 2],
        markers: &[Key<Se3>],
    ) -> Option<Self> {
        Self::with(centre, &walls, markers)
    }
}

impl RoomFactor {
    /// `walls` are `[x_a, x_b, y_a, y_b]`: two pairs of facing walls. `None` without markers.
    pub fn new(
        centre: Key<Vector3<f64>>,
        walls: [Key<Plane>; 4],
        markers: &[Key<Se3>],
    ) -> Option<Self> {
        Self::with(centre, &walls, markers)
    }
}

impl<const P: usize> Factor for CentreFactor<P> {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &self.kinds
    }

    fn residual_dim(&self) -> usize {
        3
    }

    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        jacobian: Option<DMatrixViewMut<'_, f64>>,
    ) {
        let centre = values.at::<Vector3<f64>>(self.keys[0]);
        let count = self.markers().len() as f64;
        let wall = |j: usize| values.at::<Plane>(self.keys[1 + j]);
        let mut a = SMatrix::<f64, P, 3>::zeros();
        let mut k = SVector::<f64, P>::zeros();
        let mut signs = [1.0; 4];
        for p in 0..P {
            let (w, kp, s) = mid_plane(wall(2 * p), wall(2 * p + 1));
            a.set_row(p, &w.transpose());
            k[p] = kp;
            signs[2 * p + 1] = s;
        }
        let anchor = self
            .markers()
            .iter()
            .map(|&m| values.at::<Se3>(m).translation)
            .sum::<Vector3<f64>>()
            / count;
        let Some((f, lambda, g_inv)) = project::<P>(&a, &k, &anchor) else {
            // Parallel pairs: no centre exists. A non-finite cost makes the solver refuse the
            // values with an error instead of optimising nonsense.
            residual.fill(f64::NAN);
            return;
        };
        let r = centre - f;
        residual.copy_from_slice(r.as_slice());
        let Some(mut jac) = jacobian else { return };
        jac.fill(0.0);
        for i in 0..3 {
            jac[(i, i)] = 1.0;
        }
        // Directional derivatives of f: dλ = G⁻¹(dA·t + A·dt + dk − (dA·Aᵀ + A·dAᵀ)·λ),
        // df = dt − dAᵀ·λ − Aᵀ·dλ; the residual moves by −df.
        let mut column =
            |col: usize, da: SMatrix<f64, P, 3>, dk: SVector<f64, P>, dt: Vector3<f64>| {
                let dg = da * a.transpose() + a * da.transpose();
                let d_lambda = g_inv * (da * anchor + a * dt + dk - dg * lambda);
                let df = dt - da.transpose() * lambda - a.transpose() * d_lambda;
                for i in 0..3 {
                    jac[(i, col)] = -df[i];
                }
            };
        for j in 0..2 * P {
            let basis = Plane::tangent_basis(&wall(j).normal);
            let s = signs[j];
            for t in 0..3 {
                let mut da = SMatrix::<f64, P, 3>::zeros();
                let mut dk = SVector::<f64, P>::zeros();
                if t < 2 {
                    da.set_row(j / 2, &(basis.column(t) * s).transpose());
                } else {
                    dk[j / 2] = s;
                }
                column(3 + 3 * j + t, da, dk, Vector3::zeros());
            }
        }
        // A marker's position moves by R_M·ρ (the mean by 1/count of that); its rotation does
        // not enter.
        for (i, &m) in self.markers().iter().enumerate() {
            let r_m = values
                .at::<Se3>(m)
                .rotation
                .to_rotation_matrix()
                .into_inner();
            for t in 0..3 {
                column(
                    3 + 6 * P + 6 * i + t,
                    SMatrix::zeros(),
                    SVector::zeros(),
                    r_m.column(t) / count,
                );
            }
        }
    }
}

/// `r = R_Dᵀ·(c − t_D) − δ`: a room's centre seen from one of its doorways stays where it was
/// measured (eq. 11). The centre is a point, so the relation is 3-D, not the reference's 6-D
/// pose; expressing it in the doorway's frame keeps it unchanged when the whole map turns.
#[derive(Clone, Debug)]
pub struct DoorwayRoomFactor {
    keys: [VarId; 2],
    /// The centre in the doorway's frame.
    pub measured: Vector3<f64>,
}

impl DoorwayRoomFactor {
    pub fn new(
        world_from_doorway: Key<Se3>,
        centre: Key<Vector3<f64>>,
        measured: Vector3<f64>,
    ) -> Self {
        Self {
            keys: [world_from_doorway.id, centre.id],
            measured,
        }
    }
}

impl Factor for DoorwayRoomFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &[Kind::Pose, Kind::Point]
    }

    fn residual_dim(&self) -> usize {
        3
    }

    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        jacobian: Option<DMatrixViewMut<'_, f64>>,
    ) {
        let d = values.at::<Se3>(self.keys[0]);
        let c = values.at::<Vector3<f64>>(self.keys[1]);
        let doorway_from_world = d.rotation.to_rotation_matrix().into_inner().transpose();
        let v = doorway_from_world * (c - d.translation);
        residual.copy_from_slice((v - self.measured).as_slice());
        if let Some(mut jac) = jacobian {
            jac.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(-nalgebra::Matrix3::identity()));
            jac.fixed_view_mut::<3, 3>(0, 3).copy_from(&hat(&v));
            jac.fixed_view_mut::<3, 3>(0, 6)
                .copy_from(&doorway_from_world);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{jacobian_error, random_se3, Rng};
    use nalgebra::UnitQuaternion;
    use proptest::prelude::*;

    /// A box room `[x0, x1] × [y0, y1]` turned by `yaw` and moved by `shift`; walls in the
    /// order `[x_a, x_b, y_a, y_b]` with normals that face every which way.
    fn box_walls(x: (f64, f64), y: (f64, f64), pose: &Se3, flips: [bool; 4]) -> [Plane; 4] {
        let raw = [
            Plane::new(Vector3::x(), -x.0).unwrap(),
            Plane::new(Vector3::x(), -x.1).unwrap(),
            Plane::new(Vector3::y(), -y.0).unwrap(),
            Plane::new(Vector3::y(), -y.1).unwrap(),
        ];
        std::array::from_fn(|i| {
            let p = raw[i].transformed(pose);
            if flips[i] {
                p.flipped()
            } else {
                p
            }
        })
    }

    #[test]
    fn centres_are_where_the_geometry_says() {
        let yaw = UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7);
        let pose = Se3::new(yaw, Vector3::new(3.0, -2.0, 0.4));
        for flips in [
            [false; 4],
            [true, false, false, true],
            [false, true, true, false],
        ] {
            let walls = box_walls((-1.0, 3.0), (0.5, 2.5), &pose, flips);
            // Markers' centre at (0.2, 2.5, 1.3) in the room frame: the room's centre is
            // (1, 1.5) at the markers' height; the corridor of the x walls keeps y.
            let anchor = pose.transform_point(&Vector3::new(0.2, 2.5, 1.3));
            let room = room_centre([&walls[0], &walls[1], &walls[2], &walls[3]], &anchor).unwrap();
            assert!((room - pose.transform_point(&Vector3::new(1.0, 1.5, 1.3))).norm() < 1e-12);
            let corridor = corridor_centre([&walls[0], &walls[1]], &anchor).unwrap();
            assert!((corridor - pose.transform_point(&Vector3::new(1.0, 2.5, 1.3))).norm() < 1e-12);
        }
        // The reference's documented formula for an axis-aligned room around the origin at
        // floor height: v = ½(|d1|·n1 − |d2|·n2) + |d2|·n2 per pair, centre = v_x + v_y.
        let walls = box_walls((-1.0, 3.0), (-0.5, 2.5), &Se3::identity(), [false; 4]);
        let flip = |p: &Plane| if p.offset > 0.0 { p.flipped() } else { *p };
        let half = |a: &Plane, b: &Plane| {
            let (a, b) = (flip(a), flip(b));
            let (a, b) = if a.offset.abs() > b.offset.abs() {
                (a, b)
            } else {
                (b, a)
            };
            (a.normal.into_inner() * a.offset.abs() - b.normal.into_inner() * b.offset.abs()) * 0.5
                + b.normal.into_inner() * b.offset.abs()
        };
        let reference = half(&walls[0], &walls[1]) + half(&walls[2], &walls[3]);
        let ours = room_centre(
            [&walls[0], &walls[1], &walls[2], &walls[3]],
            &Vector3::new(7.0, -3.0, 0.0),
        )
        .unwrap();
        assert!((ours - reference).norm() < 1e-12, "{ours} vs {reference}");
    }

    #[test]
    fn parallel_pairs_have_no_centre() {
        let walls = box_walls((-1.0, 3.0), (0.5, 2.5), &Se3::identity(), [false; 4]);
        assert!(room_centre(
            [&walls[0], &walls[1], &walls[0].flipped(), &walls[1]],
            &Vector3::zeros()
        )
        .is_none());
    }

    type Room = (Values, Key<Vector3<f64>>, [Key<Plane>; 4], Vec<Key<Se3>>);

    fn random_room(seed: u64, noise: f64) -> Room {
        let mut rng = Rng::new(seed);
        let pose = random_se3(seed);
        let flips = std::array::from_fn(|_| rng.uniform() < 0.5);
        let walls = box_walls(
            (rng.range(-4.0, -0.5), rng.range(0.5, 4.0)),
            (rng.range(-4.0, -0.5), rng.range(0.5, 4.0)),
            &pose,
            flips,
        );
        let mut values = Values::new();
        let centre = values.add(pose.transform_point(&rng.vector3(1.0)));
        // Walls a little off parallel and perpendicular, as estimates are.
        let walls = walls.map(|w| values.add(w.retract(&(rng.vector3(noise)))));
        let markers = (1..=3).map(|i| values.add(random_se3(seed + i))).collect();
        (values, centre, walls, markers)
    }

    proptest! {
        #[test]
        fn room_jacobians_match_differences(seed in any::<u64>(), noise in prop::sample::select(vec![0.0, 0.05])) {
            let (values, centre, walls, markers) = random_room(seed, noise);
            let f = RoomFactor::new(centre, walls, &markers).unwrap();
            prop_assert!(jacobian_error(&f, &values) < 1e-6);
        }

        #[test]
        fn corridor_jacobians_match_differences(seed in any::<u64>(), noise in prop::sample::select(vec![0.0, 0.05])) {
            let (values, centre, walls, markers) = random_room(seed, noise);
            let f = CorridorFactor::new(centre, [walls[2], walls[3]], &markers[..1]).unwrap();
            prop_assert!(jacobian_error(&f, &values) < 1e-6);
        }

        #[test]
        fn doorway_room_jacobians_match_differences(seed in any::<u64>()) {
            let mut values = Values::new();
            let d = values.add(random_se3(seed));
            let c = values.add(Rng::new(seed).vector3(3.0));
            let f = DoorwayRoomFactor::new(d, c, Vector3::new(0.3, -1.0, 2.0));
            prop_assert!(jacobian_error(&f, &values) < 1e-6);
        }
    }

    #[test]
    fn a_centre_on_its_walls_has_zero_residual() {
        let (mut values, centre, walls, markers) = random_room(5, 0.0);
        let w = walls.map(|k| *values.get(k));
        let mean = markers
            .iter()
            .map(|m| values.get(*m).translation)
            .sum::<Vector3<f64>>()
            / 3.0;
        let c = room_centre([&w[0], &w[1], &w[2], &w[3]], &mean).unwrap();
        values.set(centre, c);
        let mut r = [1.0; 3];
        RoomFactor::new(centre, walls, &markers)
            .unwrap()
            .evaluate(&values, &mut r, None);
        assert!(r.iter().all(|v| v.abs() < 1e-12));
        assert!(RoomFactor::new(centre, walls, &[]).is_none());
    }
}
