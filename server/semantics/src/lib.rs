//! The S-Graph's semantic layer: what the markers of a building mean. [`dictionary`] reads the
//! semantic dictionary (the reference implementation's "env database"), which says which marker
//! ids bound which room or corridor and which open which door.
//!
//! Walls, doorways, rooms and corridors, built from a map's marker landmarks and optimised with
//! it, join this crate with the rest of the S-Graph issue. Must not depend on zenoh, tokio or the
//! pipeline: the pipeline runs it on each map's writer.

pub mod dictionary;

pub use dictionary::{Dictionary, DictionaryError, MarkerRole, SpaceKind};
