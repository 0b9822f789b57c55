//! The renderable building: every side of every space (corridor ends too, so that no ray
//! escapes), floors and ceilings, as axis-aligned rectangles with door openings cut out, each
//! with its baked texture and the markers that hang on it.
//!
//! All sides face into their space, and a camera inside a space can only see front faces: its
//! rays leave the space through its own sides or through a door, which opens in both spaces'
//! sides. So back faces are culled, which also settles the tie between two spaces' coplanar
//! sides of one wall.

use crate::aruco::{Dictionary, MarkerBits};
use crate::building::Building;
use crate::plan::FloorPlan;
use crate::plan::{all_sides, shared_wall};
use crate::texture::{self, Canvas, Keepout, Lighting, Pattern, Texture};
use nalgebra::{Isometry3, Vector3};

/// A marker hung on a surface, in that surface's (u, v) coordinates.
#[derive(Clone, Debug)]
pub(crate) struct SurfaceMarker {
    pub bits: MarkerBits,
    /// Centre, surface-local (u, v), metres.
    pub centre: [f64; 2],
    /// +1 when the marker's x axis runs along +u, −1 along −u (its y axis is always +v).
    pub u_sign: f64,
    /// Side of one cell (bit) of the marker, metres.
    pub cell: f64,
    /// Half the side of the marker with its one-cell white quiet zone.
    pub padded_half: f64,
    /// Lamp light at the marker.
    pub light: f32,
}

impl SurfaceMarker {
    /// Albedo at surface-local (u, v), or `None` outside the marker and its quiet zone.
    #[inline]
    pub fn albedo(&self, u: f64, v: f64) -> Option<f32> {
        let x = self.u_sign * (u - self.centre[0]) + self.padded_half;
        let y = self.padded_half - (v - self.centre[1]);
        let extent = 2.0 * self.padded_half;
        if !(0.0..extent).contains(&x) || !(0.0..extent).contains(&y) {
            return None;
        }
        let (col, row) = ((x / self.cell) as usize, (y / self.cell) as usize);
        let cells = self.bits.bits + 4;
        let white = row == 0
            || col == 0
            || row == cells - 1
            || col == cells - 1
            || self.bits.white(row - 1, col - 1);
        Some(if white { 215.0 } else { 25.0 } * self.light)
    }
}

/// An axis-aligned rectangle facing `facing` along `axis` at `x[axis] = at`.
#[derive(Clone, Debug)]
pub(crate) struct Surface {
    pub axis: usize,
    pub at: f64,
    pub facing: f64,
    /// The in-plane axes: u and v (v is z for walls).
    pub u_axis: usize,
    pub v_axis: usize,
    pub u: [f64; 2],
    pub v: [f64; 2],
    /// Door openings, `[u0, u1, v0, v1]`.
    pub holes: Vec<Keepout>,
    pub texture: Texture,
    /// Colour of its paint, multiplied with the grey texture.
    pub tint: [f32; 3],
    pub markers: Vec<SurfaceMarker>,
}

impl Surface {
    pub fn normal(&self) -> Vector3<f64> {
        let mut n = Vector3::zeros();
        n[self.axis] = self.facing;
        n
    }

    pub fn corners(&self) -> [Vector3<f64>; 4] {
        let point = |u: f64, v: f64| {
            let mut p = Vector3::zeros();
            p[self.axis] = self.at;
            p[self.u_axis] = u;
            p[self.v_axis] = v;
            p
        };
        [
            point(self.u[0], self.v[0]),
            point(self.u[1], self.v[0]),
            point(self.u[1], self.v[1]),
            point(self.u[0], self.v[1]),
        ]
    }

    /// Whether surface-local coordinates are on the surface (not in a hole).
    #[inline]
    pub fn contains(&self, u: f64, v: f64) -> bool {
        u >= self.u[0]
            && u <= self.u[1]
            && v >= self.v[0]
            && v <= self.v[1]
            && !self
                .holes
                .iter()
                .any(|h| u > h[0] && u < h[1] && v > h[2] && v < h[3])
    }

    /// Albedo × light at (u, v): a marker's cell or the texture.
    #[inline]
    pub fn shade(&self, u: f64, v: f64) -> f32 {
        for marker in &self.markers {
            if let Some(value) = marker.albedo(u, v) {
                return value;
            }
        }
        self.texture.sample(u - self.u[0], v - self.v[0])
    }

    /// The marker whose quiet zone, grown by `margin` metres, holds (u, v).
    #[inline]
    pub fn marker_near(&self, u: f64, v: f64, margin: f64) -> bool {
        self.markers.iter().any(|m| {
            let reach = m.padded_half + margin;
            (u - m.centre[0]).abs() < reach && (v - m.centre[1]).abs() < reach
        })
    }
}

/// Surfaces each space drafts: four sides, a floor and a ceiling.
const SURFACES_PER_SPACE: usize = 6;
/// Texel sides: finer on walls, which the camera sees closest and where markers hang.
const WALL_TEXEL: f64 = 0.005;
const FLOOR_TEXEL: f64 = 0.01;

/// Paint colours (multiplied with grey): warm white walls, brownish floors, white ceilings.
const WALL_TINTS: [[f32; 3]; 4] = [
    [1.0, 0.97, 0.9],
    [0.92, 0.97, 1.0],
    [1.0, 0.93, 0.88],
    [0.95, 1.0, 0.93],
];
const FLOOR_TINT: [f32; 3] = [0.95, 0.85, 0.72];
const CEILING_TINT: [f32; 3] = [1.0, 1.0, 0.98];

/// The building as the renderer sees it.
pub(crate) struct Scene {
    pub surfaces: Vec<Surface>,
}

impl Scene {
    pub fn new(plan: &FloorPlan, building: &Building, seed: u64) -> Self {
        let dictionary =
            Dictionary::by_name(&plan.markers.dictionary).expect("the plan was validated");
        let height = plan.wall_height;
        // Lamps under each space's ceiling, about one per 3.5 m along it.
        let lamps: Vec<Vec<[f64; 3]>> = plan
            .spaces
            .iter()
            .map(|s| {
                let count = |k: usize| ((s.max[k] - s.min[k]) / 3.5).ceil().max(1.0) as usize;
                let (nx, ny) = (count(0), count(1));
                let mut lamps = Vec::new();
                for i in 0..nx {
                    for j in 0..ny {
                        let at = |k: usize, i: usize, n: usize| {
                            s.min[k] + (s.max[k] - s.min[k]) * (i as f64 + 0.5) / n as f64
                        };
                        lamps.push([at(0, i, nx), at(1, j, ny), height - 0.05]);
                    }
                }
                lamps
            })
            .collect();
        struct Draft {
            space: usize,
            surface: Surface,
            pattern: Pattern,
            texel: f64,
            /// Which surface's texture this one draws (its own index, or the same surface of
            /// the space it looks like).
            look: usize,
        }
        let mut drafts = Vec::new();
        for (si, space) in plan.spaces.iter().enumerate() {
            // Each space drafts its four sides, then its floor and its ceiling.
            let look_of = space
                .looks_like
                .as_ref()
                .and_then(|name| plan.spaces.iter().position(|s| &s.name == name))
                .unwrap_or(si);
            let mut next_look = SURFACES_PER_SPACE * look_of;
            let mut look = || {
                next_look += 1;
                next_look - 1
            };
            for side in all_sides(plan, si) {
                let holes = plan
                    .doors
                    .iter()
                    .filter_map(|door| {
                        let (a, b) = shared_wall(plan, door)?;
                        let along = door.at[1 - side.axis];
                        (a == side || b == side).then_some([
                            along - door.width / 2.0,
                            along + door.width / 2.0,
                            -1.0,
                            door.height,
                        ])
                    })
                    .collect();
                drafts.push(Draft {
                    space: si,
                    surface: Surface {
                        axis: side.axis,
                        at: side.at,
                        facing: side.facing,
                        u_axis: 1 - side.axis,
                        v_axis: 2,
                        u: [side.from, side.to],
                        v: [0.0, height],
                        holes,
                        texture: placeholder(),
                        tint: WALL_TINTS[(look_of + side.axis) % WALL_TINTS.len()],
                        markers: Vec::new(),
                    },
                    pattern: Pattern::Wall,
                    texel: WALL_TEXEL,
                    look: look(),
                });
            }
            for (at, facing, pattern, tint) in [
                (0.0, 1.0, Pattern::Floor, FLOOR_TINT),
                (height, -1.0, Pattern::Ceiling, CEILING_TINT),
            ] {
                drafts.push(Draft {
                    space: si,
                    surface: Surface {
                        axis: 2,
                        at,
                        facing,
                        u_axis: 0,
                        v_axis: 1,
                        u: [space.min[0], space.max[0]],
                        v: [space.min[1], space.max[1]],
                        holes: Vec::new(),
                        texture: placeholder(),
                        tint,
                        markers: Vec::new(),
                    },
                    pattern,
                    texel: FLOOR_TEXEL,
                    look: look(),
                });
            }
        }
        for marker in &building.markers {
            let (surface, hung) = hang(
                &drafts.iter().map(|d| &d.surface).collect::<Vec<_>>(),
                marker.world_from_marker,
                marker.side,
                dictionary
                    .marker(plan.printed_id(marker.id))
                    .expect("the plan was validated"),
            );
            let lighting = Lighting {
                lamps: &lamps[drafts[surface].space],
                ambient: AMBIENT,
                gain: LAMP_GAIN,
            };
            let p = marker.world_from_marker.translation.vector;
            let n = drafts[surface].surface.normal();
            let light = lighting.at(p.into(), n.into()) as f32;
            drafts[surface]
                .surface
                .markers
                .push(SurfaceMarker { light, ..hung });
        }
        // Texture generation dominates building a scene: spread the surfaces over the cores.
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        let textures: Vec<Texture> = std::thread::scope(|scope| {
            let jobs: Vec<_> = (0..threads)
                .map(|t| {
                    let drafts = &drafts;
                    let lamps = &lamps;
                    scope.spawn(move || {
                        (t..drafts.len())
                            .step_by(threads)
                            .map(|i| (i, texture_of(&drafts[i], lamps, seed, drafts[i].look)))
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            let mut all: Vec<(usize, Texture)> = jobs
                .into_iter()
                .flat_map(|j| j.join().expect("texture generation does not panic"))
                .collect();
            all.sort_by_key(|(i, _)| *i);
            all.into_iter().map(|(_, t)| t).collect()
        });
        fn texture_of(draft: &Draft, lamps: &[Vec<[f64; 3]>], seed: u64, index: usize) -> Texture {
            let s = &draft.surface;
            let keepout: Vec<Keepout> = s
                .markers
                .iter()
                .map(|m| {
                    [
                        m.centre[0] - s.u[0] - m.padded_half,
                        m.centre[0] - s.u[0] + m.padded_half,
                        m.centre[1] - s.v[0] - m.padded_half,
                        m.centre[1] - s.v[0] + m.padded_half,
                    ]
                })
                .collect();
            let world = |u: f64, v: f64| -> [f64; 3] {
                let mut p = [0.0; 3];
                p[s.axis] = s.at;
                p[s.u_axis] = s.u[0] + u;
                p[s.v_axis] = s.v[0] + v;
                p
            };
            texture::generate(
                &Canvas {
                    size: [s.u[1] - s.u[0], s.v[1] - s.v[0]],
                    texel: draft.texel,
                    pattern: draft.pattern,
                    keepout: &keepout,
                    world: &world,
                    normal: s.normal().into(),
                    seed: seed ^ (index as u64 + 1).wrapping_mul(0x2545_F491_4F6C_DD1D),
                },
                &Lighting {
                    lamps: &lamps[draft.space],
                    ambient: AMBIENT,
                    gain: LAMP_GAIN,
                },
            )
        }
        let surfaces = drafts
            .into_iter()
            .zip(textures)
            .map(|(draft, texture)| Surface {
                texture,
                ..draft.surface
            })
            .collect();
        Self { surfaces }
    }
}

/// Light that reaches every surface, and the lamps' strength (see [`Lighting::at`]).
const AMBIENT: f64 = 0.5;
const LAMP_GAIN: f64 = 2.5;

fn placeholder() -> Texture {
    Texture {
        width: 0,
        height: 0,
        texel: 1.0,
        data: Vec::new(),
    }
}

/// The surface a marker hangs on (the wall side it faces out of, holding its centre), and the
/// marker in that surface's coordinates.
fn hang(
    surfaces: &[&Surface],
    world_from_marker: Isometry3<f64>,
    side: f64,
    bits: MarkerBits,
) -> (usize, SurfaceMarker) {
    let normal = world_from_marker.rotation * Vector3::z();
    let x_axis = world_from_marker.rotation * Vector3::x();
    let centre = world_from_marker.translation.vector;
    let index = surfaces
        .iter()
        .position(|s| {
            s.axis != 2
                && (s.normal() - normal).norm() < 1e-9
                && (centre[s.axis] - s.at).abs() < 1e-9
                && centre[s.u_axis] >= s.u[0]
                && centre[s.u_axis] <= s.u[1]
        })
        .expect("every marker of a building hangs on a wall side");
    let s = surfaces[index];
    let cell = side / (bits.bits + 2) as f64;
    (
        index,
        SurfaceMarker {
            bits,
            centre: [centre[s.u_axis], centre[s.v_axis]],
            u_sign: x_axis[s.u_axis].signum(),
            cell,
            padded_half: cell * (bits.bits + 4) as f64 / 2.0,
            light: 1.0,
        },
    )
}
