//! Trajectories in the TUM RGB-D text format: one pose per line, `t tx ty tz qx qy qz qw`
//! (seconds, metres, a unit quaternion with its scalar last), `#` starts a comment line.
//!
//! A pose is `world_from_camera`. Quaternions are normalised on reading, as evo does, so a file
//! written with few digits still gives rotations.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum TrajectoryError {
    #[error("cannot read {path}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {path}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("line {line}: {message}")]
    Parse { line: usize, message: String },
    #[error("the trajectory has no poses")]
    Empty,
}

/// Timestamps (seconds) and `world_from_camera` poses, in file order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trajectory {
    pub stamps: Vec<f64>,
    pub poses: Vec<Isometry3<f64>>,
}

impl Trajectory {
    pub fn len(&self) -> usize {
        self.stamps.len()
    }

    pub fn is_empty(&self) -> bool {
        self.stamps.is_empty()
    }

    pub fn push(&mut self, stamp: f64, world_from_camera: Isometry3<f64>) {
        self.stamps.push(stamp);
        self.poses.push(world_from_camera);
    }

    /// Length of the path through the positions, metres.
    pub fn path_length(&self) -> f64 {
        self.poses
            .windows(2)
            .map(|w| (w[1].translation.vector - w[0].translation.vector).norm())
            .sum()
    }

    /// Parses TUM text. Fields are separated by spaces, tabs or commas.
    pub fn parse_tum(text: &str) -> Result<Self, TrajectoryError> {
        let mut out = Trajectory::default();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let parse = |message: String| TrajectoryError::Parse {
                line: i + 1,
                message,
            };
            let fields: Vec<&str> = line
                .split(|c: char| c.is_whitespace() || c == ',')
                .filter(|f| !f.is_empty())
                .collect();
            if fields.len() != 8 {
                return Err(parse(format!(
                    "expected 8 fields (t tx ty tz qx qy qz qw), found {}",
                    fields.len()
                )));
            }
            let mut v = [0.0; 8];
            for (k, (x, f)) in v.iter_mut().zip(&fields).enumerate() {
                *x = f
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| {
                        parse(format!("field {} ({f:?}) is not a finite number", k + 1))
                    })?;
            }
            let q = Quaternion::new(v[7], v[4], v[5], v[6]);
            if q.norm() < 1e-9 {
                return Err(parse("the quaternion is zero".into()));
            }
            let pose = Isometry3::from_parts(
                Translation3::new(v[1], v[2], v[3]),
                UnitQuaternion::from_quaternion(q),
            );
            out.push(v[0], pose);
        }
        if out.is_empty() {
            return Err(TrajectoryError::Empty);
        }
        Ok(out)
    }

    pub fn read_tum(path: &Path) -> Result<Self, TrajectoryError> {
        let text = std::fs::read_to_string(path).map_err(|source| TrajectoryError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse_tum(&text)
    }

    /// TUM text with microsecond timestamps and 9 decimals elsewhere (below a nanometre).
    pub fn to_tum(&self) -> String {
        let mut s = String::with_capacity(self.len() * 100);
        for (t, p) in self.stamps.iter().zip(&self.poses) {
            let (x, q) = (p.translation.vector, p.rotation.quaternion());
            let _ = writeln!(
                s,
                "{t:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
                x.x, x.y, x.z, q.i, q.j, q.k, q.w
            );
        }
        s
    }

    pub fn write_tum(&self, path: &Path) -> Result<(), TrajectoryError> {
        std::fs::write(path, self.to_tum()).map_err(|source| TrajectoryError::Write {
            path: path.to_path_buf(),
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn text_round_trips_and_comments_are_skipped() {
        let mut t = Trajectory::default();
        let q = UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3);
        t.push(
            1.5,
            Isometry3::from_parts(Translation3::new(1.0, -2.0, 0.5), q),
        );
        t.push(1.6, Isometry3::identity());
        let text = format!("# a comment\n\n{}", t.to_tum());
        let back = Trajectory::parse_tum(&text).unwrap();
        assert_eq!(back.stamps, t.stamps);
        for (a, b) in back.poses.iter().zip(&t.poses) {
            assert!((a.translation.vector - b.translation.vector).norm() < 1e-9);
            assert!(a.rotation.angle_to(&b.rotation) < 1e-8);
        }
        assert!((t.path_length() - Vector3::<f64>::new(1.0, -2.0, 0.5).norm()).abs() < 1e-12);
    }

    #[test]
    fn bad_lines_are_named() {
        let err = Trajectory::parse_tum("0 1 2 3 0 0 0 1\n1 2 3\n").unwrap_err();
        assert_eq!(
            err.to_string(),
            "line 2: expected 8 fields (t tx ty tz qx qy qz qw), found 3"
        );
        let err = Trajectory::parse_tum("0 1 2 x 0 0 0 1\n").unwrap_err();
        assert!(err.to_string().starts_with("line 1: field 4"), "{err}");
        let err = Trajectory::parse_tum("0 1 2 3 0 0 0 0\n").unwrap_err();
        assert!(err.to_string().contains("zero"), "{err}");
        assert!(matches!(
            Trajectory::parse_tum("# nothing\n"),
            Err(TrajectoryError::Empty)
        ));
    }

    #[test]
    fn quaternions_are_normalised() {
        let t = Trajectory::parse_tum("0 0 0 0 0 0 0 2\n").unwrap();
        assert!(t.poses[0].rotation.angle() < 1e-12);
    }
}
