//! What can go wrong in tracking and mapping, for a robot's frame to report.

use crate::map::MapId;
use thiserror::Error;
use vsgraphs_vision::CvError;

#[derive(Debug, Error)]
pub enum TrackError {
    #[error(transparent)]
    Features(#[from] CvError),
    #[error("local bundle adjustment failed: {0}")]
    LocalBa(#[from] vsgraphs_optim::SolveError),
    #[error("whole-map optimisation failed: {0}")]
    WholeMap(vsgraphs_optim::SolveError),
    #[error("a background optimisation thread of the map stopped")]
    WorkerStopped,
    #[error("map {0:?} has no writer")]
    UnknownMap(MapId),
    #[error("the map's writer: {0}")]
    Writer(String),
    /// The map was merged into another while the request waited: the tracker follows it and
    /// tracks the frame again there.
    #[error("map {} was merged into map {} during the frame", .from.0, .into.0)]
    MapMerged { from: MapId, into: MapId },
    #[error("the maps were not merged: {0}")]
    Merge(#[from] crate::merge::NoAlignment),
}
