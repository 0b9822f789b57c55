//! The variables of a problem, in one arena addressed by typed keys.
//!
//! A `Key<Se3>` can only name a pose, so passing a point where a factor expects a pose is a
//! compile error. Keys are only made by [`Values`], which checks them again when a factor is
//! added to a problem (a key from another `Values` is an error there, not a panic later).

use crate::lie::Se3;
use crate::plane::Plane;
use nalgebra::{Vector3, Vector6};
use std::marker::PhantomData;

/// Untyped index of a variable in its [`Values`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VarId(pub u32);

impl VarId {
    pub fn index(self) -> usize {
        self.0 as usize
    }
}

/// Typed handle of a variable.
#[derive(Debug, PartialEq, Eq, Hash)]
pub struct Key<T> {
    pub id: VarId,
    kind: PhantomData<fn() -> T>,
}

impl<T> Clone for Key<T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for Key<T> {}

impl<T> Key<T> {
    fn new(id: VarId) -> Self {
        Self {
            id,
            kind: PhantomData,
        }
    }
}

/// What kind of manifold a variable lives on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// SE(3): keyframes, markers, doorways. Tangent `[ρ; φ]`.
    Pose,
    /// R³: map points, room and corridor centres.
    Point,
    /// Planes (walls), see [`Plane`].
    Plane,
}

impl Kind {
    /// Dimension of the tangent space.
    pub const fn dim(self) -> usize {
        match self {
            Kind::Pose => 6,
            Kind::Point | Kind::Plane => 3,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Variable {
    Pose(Se3),
    Point(Vector3<f64>),
    Plane(Plane),
}

impl Variable {
    pub fn kind(&self) -> Kind {
        match self {
            Variable::Pose(_) => Kind::Pose,
            Variable::Point(_) => Kind::Point,
            Variable::Plane(_) => Kind::Plane,
        }
    }

    /// `self ⊕ delta`, with `delta.len() == self.kind().dim()`.
    pub fn retract(&self, delta: &[f64]) -> Variable {
        match self {
            Variable::Pose(x) => Variable::Pose(x.retract(&Vector6::from_column_slice(delta))),
            Variable::Point(p) => Variable::Point(p + Vector3::from_column_slice(delta)),
            Variable::Plane(q) => Variable::Plane(q.retract(&Vector3::from_column_slice(delta))),
        }
    }
}

/// A type that can be stored in [`Values`].
pub trait VariableType: Sized + Copy {
    const KIND: Kind;
    fn wrap(self) -> Variable;
    fn unwrap(v: &Variable) -> Option<&Self>;
}

impl VariableType for Se3 {
    const KIND: Kind = Kind::Pose;
    fn wrap(self) -> Variable {
        Variable::Pose(self)
    }
    fn unwrap(v: &Variable) -> Option<&Self> {
        match v {
            Variable::Pose(x) => Some(x),
            _ => None,
        }
    }
}

impl VariableType for Vector3<f64> {
    const KIND: Kind = Kind::Point;
    fn wrap(self) -> Variable {
        Variable::Point(self)
    }
    fn unwrap(v: &Variable) -> Option<&Self> {
        match v {
            Variable::Point(x) => Some(x),
            _ => None,
        }
    }
}

impl VariableType for Plane {
    const KIND: Kind = Kind::Plane;
    fn wrap(self) -> Variable {
        Variable::Plane(self)
    }
    fn unwrap(v: &Variable) -> Option<&Self> {
        match v {
            Variable::Plane(x) => Some(x),
            _ => None,
        }
    }
}

/// The variables of a problem and which of them are held fixed.
#[derive(Clone, Debug, Default)]
pub struct Values {
    variables: Vec<Variable>,
    fixed: Vec<bool>,
    /// Counts changes of the fixed set (they change the normal equations' layout).
    fixed_changes: u64,
}

impl Values {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn add<T: VariableType>(&mut self, value: T) -> Key<T> {
        let id = VarId(self.variables.len() as u32);
        self.variables.push(value.wrap());
        self.fixed.push(false);
        Key::new(id)
    }

    /// The value behind a key made by this `Values`.
    ///
    /// # Panics
    /// On a key made by another `Values` of a different layout; problems check keys on entry.
    pub fn get<T: VariableType>(&self, key: Key<T>) -> &T {
        self.variables
            .get(key.id.index())
            .and_then(T::unwrap)
            .expect("a key made by this Values")
    }

    /// The value of variable `id`, which a factor's checked keys guarantee to be a `T`.
    ///
    /// # Panics
    /// When `id` is not a `T` of this `Values` (problems check every factor's keys on entry).
    pub fn at<T: VariableType>(&self, id: VarId) -> &T {
        self.variables
            .get(id.index())
            .and_then(T::unwrap)
            .expect("a checked key")
    }

    pub fn set<T: VariableType>(&mut self, key: Key<T>, value: T) {
        if let Some(slot) = self.variables.get_mut(key.id.index()) {
            if slot.kind() == T::KIND {
                *slot = value.wrap();
            }
        }
    }

    /// The key of variable `id` if it has type `T`.
    pub fn key<T: VariableType>(&self, id: VarId) -> Option<Key<T>> {
        let v = self.variables.get(id.index())?;
        (v.kind() == T::KIND).then(|| Key::new(id))
    }

    pub fn variable(&self, id: VarId) -> Option<&Variable> {
        self.variables.get(id.index())
    }

    pub(crate) fn variable_mut(&mut self, id: VarId) -> &mut Variable {
        &mut self.variables[id.index()]
    }

    /// Holds a variable constant in optimisation (e.g. the first keyframe, the gauge).
    pub fn set_fixed(&mut self, id: VarId, fixed: bool) {
        if let Some(f) = self.fixed.get_mut(id.index()) {
            if *f != fixed {
                *f = fixed;
                self.fixed_changes += 1;
            }
        }
    }

    pub(crate) fn fixed_changes(&self) -> u64 {
        self.fixed_changes
    }

    pub fn is_fixed(&self, id: VarId) -> bool {
        self.fixed.get(id.index()).copied().unwrap_or(false)
    }

    pub fn len(&self) -> usize {
        self.variables.len()
    }

    pub fn is_empty(&self) -> bool {
        self.variables.is_empty()
    }

    pub fn ids(&self) -> impl Iterator<Item = VarId> {
        (0..self.variables.len() as u32).map(VarId)
    }
}
