//! The map's points by place, for the searches of one build of the semantic layer. Each search
//! wants the points near one marker or one wall (a metre or two around it) out of a map of a
//! hundred thousand; a grid of cells hands it the few cells that can hold them, and the search
//! tests only their points, so it answers exactly what a scan of every point would.

use nalgebra::Vector3;
use rustc_hash::FxHashMap;

/// A map point as the semantic layer takes it.
#[derive(Clone, Debug, PartialEq)]
pub struct MapPoint {
    pub position: Vector3<f64>,
    /// The mean direction from the point to the cameras that saw it (unit).
    pub toward_cameras: Vector3<f64>,
    /// The cameras that saw it, as indices into the map's camera centres.
    pub cameras: Vec<u32>,
}

/// The map's points, gridded by place.
#[derive(Clone, Debug)]
pub struct Cloud<'a> {
    points: &'a [MapPoint],
    cells: Vec<Cell>,
}

/// One cube of the grid with the points in it.
#[derive(Clone, Debug)]
pub struct Cell {
    /// The cube's centre.
    pub centre: Vector3<f64>,
    /// The smallest and largest coordinates of its points and of the cameras that saw them:
    /// every ray from a point to its cameras lies in this box.
    pub rays_min: Vector3<f64>,
    pub rays_max: Vector3<f64>,
    /// Where the cell is in the grid.
    key: [i64; 3],
    /// Indices of its points, ascending.
    indices: Vec<u32>,
}

impl Cell {
    /// A ball of this radius round the centre holds the whole cube (a hair more, for rounding).
    pub const RADIUS_M: f64 = CELL_M * 0.866_026;

    /// How far the box of the cell's rays reaches along `direction` (unit) from `origin`: the
    /// least and greatest of `direction · (x - origin)` over the box.
    pub fn rays_along(&self, origin: &Vector3<f64>, direction: &Vector3<f64>) -> (f64, f64) {
        let middle = (self.rays_min + self.rays_max) * 0.5 - origin;
        let half = (self.rays_max - self.rays_min) * 0.5;
        let reach =
            half.x * direction.x.abs() + half.y * direction.y.abs() + half.z * direction.z.abs();
        let at = middle.dot(direction);
        (at - reach, at + reach)
    }
}

/// A cell's side. The searches reach 5 cm to 2.5 m; half a metre keeps the cells a search
/// touches few and the points it tests mostly the ones it wants.
const CELL_M: f64 = 0.5;

impl<'a> Cloud<'a> {
    /// `cameras` are the map's camera centres, which points name by index.
    pub fn new(points: &'a [MapPoint], cameras: &[Vector3<f64>]) -> Self {
        let mut by_key: FxHashMap<[i64; 3], Cell> = FxHashMap::default();
        for (i, point) in points.iter().enumerate() {
            let key = point.position.map(|x| (x / CELL_M).floor() as i64);
            let cell = by_key.entry(key.into()).or_insert_with(|| Cell {
                centre: key.map(|k| (k as f64 + 0.5) * CELL_M),
                rays_min: point.position,
                rays_max: point.position,
                key: key.into(),
                indices: Vec::new(),
            });
            cell.indices.push(i as u32);
            let seen_from = point
                .cameras
                .iter()
                .filter_map(|&c| cameras.get(c as usize));
            for x in std::iter::once(&point.position).chain(seen_from) {
                cell.rays_min = cell.rays_min.inf(x);
                cell.rays_max = cell.rays_max.sup(x);
            }
        }
        // In the grid's order: searches come out the same in every run.
        let mut cells: Vec<Cell> = by_key.into_values().collect();
        cells.sort_unstable_by_key(|cell| cell.key);
        Self { points, cells }
    }

    /// The points of the cells `may_hold` keeps, cell by cell. It must keep every cell that
    /// can hold a point the search wants (the points are tested again after).
    pub fn within<'s>(
        &'s self,
        may_hold: impl Fn(&Cell) -> bool + 's,
    ) -> impl Iterator<Item = &'a MapPoint> + 's {
        let points = self.points;
        self.cells
            .iter()
            .filter(move |cell| may_hold(cell))
            .flat_map(move |cell| cell.indices.iter().map(move |&i| &points[i as usize]))
    }

    /// The points of the cells that can hold a point within `radius_m` of `centre`, in the
    /// map's order (for searches whose answer depends on the order, as a fit's sums do).
    pub fn near(&self, centre: &Vector3<f64>, radius_m: f64) -> Vec<&'a MapPoint> {
        let mut indices: Vec<u32> = self
            .cells
            .iter()
            .filter(|cell| (cell.centre - centre).norm() <= radius_m + Cell::RADIUS_M)
            .flat_map(|cell| cell.indices.iter().copied())
            .collect();
        indices.sort_unstable();
        indices
            .into_iter()
            .map(|i| &self.points[i as usize])
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points scattered over a few metres, seen from two cameras.
    fn scattered() -> (Vec<MapPoint>, Vec<Vector3<f64>>) {
        let cameras = vec![Vector3::new(-1.0, 0.5, 1.2), Vector3::new(6.0, 4.0, 1.0)];
        let mut random = crate::wall_points::SplitMix(7);
        let mut next = || random.below(1_000_000) as f64 / 1e6;
        let points = (0..4000)
            .map(|i| MapPoint {
                position: Vector3::new(next() * 5.0 - 0.2, next() * 4.0 - 1.0, next() * 2.5),
                toward_cameras: Vector3::z(),
                cameras: vec![(i % 2) as u32],
            })
            .collect();
        (points, cameras)
    }

    #[test]
    fn a_search_near_a_place_finds_what_a_scan_of_every_point_finds() {
        let (points, cameras) = scattered();
        let cloud = Cloud::new(&points, &cameras);
        for (centre, radius) in [
            ([1.0, 1.0, 1.0], 1.0),
            ([4.9, -0.9, 0.1], 0.3),
            ([9.0, 9.0, 9.0], 2.0),
        ] {
            let centre = Vector3::from(centre);
            let wanted = |p: &&MapPoint| (p.position - centre).norm() <= radius;
            let scanned: Vec<&MapPoint> = points.iter().filter(wanted).collect();
            let searched: Vec<&MapPoint> = cloud
                .near(&centre, radius)
                .into_iter()
                .filter(wanted)
                .collect();
            assert_eq!(searched, scanned);
            // And it tests far fewer points than there are.
            assert!(cloud.near(&centre, radius).len() < points.len() / 2);
            // A search by any test of whole cells finds the same points, in another order.
            let address = |p: &MapPoint| p as *const MapPoint as usize;
            let mut within: Vec<usize> = cloud
                .within(|cell| (cell.centre - centre).norm() <= radius + Cell::RADIUS_M)
                .filter(wanted)
                .map(address)
                .collect();
            within.sort_unstable();
            assert_eq!(
                within,
                scanned.iter().map(|p| address(p)).collect::<Vec<_>>()
            );
        }
    }

    #[test]
    fn a_cell_s_box_holds_the_rays_of_its_points() {
        let (points, cameras) = scattered();
        let cloud = Cloud::new(&points, &cameras);
        let direction = Vector3::new(0.6, 0.0, 0.8);
        let origin = Vector3::new(1.0, 2.0, 0.0);
        for cell in &cloud.cells {
            let (low, high) = cell.rays_along(&origin, &direction);
            for &i in &cell.indices {
                let p = &points[i as usize];
                for c in &p.cameras {
                    for t in [0.0, 0.3, 1.0] {
                        let x = p.position + (cameras[*c as usize] - p.position) * t;
                        let at = (x - origin).dot(&direction);
                        assert!(low - 1e-9 <= at && at <= high + 1e-9);
                    }
                }
                assert!((p.position - cell.centre).norm() <= Cell::RADIUS_M);
            }
        }
    }
}
