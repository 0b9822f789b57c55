//! The map service: every map of the server, each with one writer thread, and the latest
//! snapshot of each for readers.
//!
//! A map's writer is the only code that changes it. Robots' workers hand it what tracking
//! decided (a map to start, a keyframe to insert, work to land: [`MapRequest`]) and wait for the
//! answer, so a robot's frames are mapped in order and a run gives the same map live and
//! offline. The writer runs local mapping on the map now; loop closing and the S-Graph join it
//! there, and builds the map's semantic layer (walls, rooms and corridors: [`SemanticMap`]) from
//! its markers and the service's semantic dictionary. After each request it publishes a
//! snapshot ([`MapView`]) that readers (the API, the page, later the store) take without ever
//! waiting for a writer. Trackers read the map itself between requests ([`SharedMap`]).

use crate::model;
use crate::store::{Save, Saver, Store, StoreError};
use std::any::Any;
use std::collections::{BTreeMap, VecDeque};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{mpsc, Arc, Condvar, Mutex, MutexGuard, RwLock, Weak};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use vsgraphs_proto::api::{MapMarker, MapView};
use vsgraphs_semantics::{Dictionary, SemanticMap};
use vsgraphs_slam::archive::rows::Ledger;
use vsgraphs_slam::local_mapping::{MergeOutcome, PointStatistics};
use vsgraphs_slam::loops;
use vsgraphs_slam::merge::{self, Evidence, Place};
use vsgraphs_slam::walls::WallPrior;
use vsgraphs_slam::{
    KeyFrameId, LocalMapper, Map, MapId, MapMove, MapReply, MapRequest, MapWriter, MappingConfig,
    SharedMap, TrackError,
};

/// Every map of the server. Cloning gives another handle to the same service.
#[derive(Clone, Default)]
pub struct MapService {
    inner: Arc<Inner>,
}

#[derive(Default)]
struct Inner {
    next_id: AtomicU32,
    maps: Mutex<BTreeMap<MapId, Arc<MapEntry>>>,
    /// Maps merged into others, and where their keyframes went.
    merged: Mutex<BTreeMap<MapId, Merged>>,
    /// The same, with the map they went into, for robots still tracking in them.
    moves: Mutex<BTreeMap<MapId, MapMove>>,
    /// Every merge so far, oldest first.
    merge_log: Mutex<Vec<MergeReport>>,
    /// The last snapshots of the maps merged into others.
    retired: Mutex<BTreeMap<MapId, Snapshots>>,
    /// Merges run one at a time; held for the length of one.
    merging: Mutex<()>,
    /// Merge maps as soon as they share markers ([`MapService::merge_where_shared`]).
    merge_live: AtomicBool,
    /// Look for merges on the service's merge thread rather than the robot's worker
    /// ([`MapService::look_for_merges`]).
    background_merges: AtomicBool,
    looks: Arc<Looks>,
    looker: Mutex<Option<JoinHandle<()>>>,
    /// Pairs of maps tried, with what they shared then: a pair is tried again only once it
    /// shares more ([`Shared::grown_since`]).
    tried: Mutex<BTreeMap<(MapId, MapId), Shared>>,
    /// Merges refused, the newest [`KEPT_REFUSALS`].
    refused: Mutex<VecDeque<RefusedMerge>>,
    /// Places of another map a map's keyframes recognised, by (map, other map), until enough
    /// keyframes in a row agree.
    places_seen: Mutex<BTreeMap<(MapId, MapId), Sightings>>,
    semantics: Arc<RwLock<Semantics>>,
    /// How maps the service starts itself (imported, read from the store) are mapped; the
    /// default tracker's settings unless set ([`MapService::with_mapping`]).
    mapping: Mutex<Option<MappingConfig>>,
    /// Where maps are kept across restarts ([`MapService::with_store`]); none: in memory only.
    saver: Mutex<Option<Arc<Saver>>>,
}

/// Merge look-ups waiting for the service's merge thread.
#[derive(Default)]
struct Looks {
    pending: Mutex<Pending>,
    ready: Condvar,
}

#[derive(Default)]
struct Pending {
    /// The newest keyframe of each map not yet looked at: a newer one of the same map
    /// supersedes it, so a busy thread falls behind by no more than a look per map.
    keyframes: BTreeMap<MapId, KeyFrameId>,
    stop: bool,
}

/// Where a merged map went: its keyframe `k` is keyframe `k + keyframe_offset` of `into`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Merged {
    pub into: MapId,
    pub keyframe_offset: u32,
    pub into_from_merged: vsgraphs_slam::Se3,
}

/// How a map's recent keyframes saw a place of another map: the latest transform, how many
/// keyframes in a row agreed on it, and how many since did not see it.
#[derive(Clone, Copy, Debug)]
struct Sightings {
    other_from_here: vsgraphs_slam::Se3,
    agreeing: usize,
    missed: usize,
}

/// Why a map file did not become a map.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error(transparent)]
    File(#[from] vsgraphs_slam::archive::ArchiveError),
    #[error(transparent)]
    Writer(#[from] TrackError),
}

/// Two maps that looked like one place but were not merged, and why: a place recognised by
/// visual words, or markers of the same ids.
#[derive(Clone, Debug)]
pub struct RefusedMerge {
    pub target: MapId,
    pub source: MapId,
    /// The place the words recognised (`None`: shared markers).
    pub place: Option<Place>,
    pub reason: String,
}

/// What [`MapService::merge`] did.
#[derive(Clone, Debug)]
pub struct MergeReport {
    pub target: MapId,
    pub source: MapId,
    /// When it was made, ns since the Unix epoch.
    pub at_ns: u64,
    pub outcome: MergeOutcome,
}

impl MergeReport {
    /// As the API reports it.
    pub fn api(&self) -> vsgraphs_proto::api::MapMerge {
        let o = &self.outcome;
        let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
        vsgraphs_proto::api::MapMerge {
            target: self.target.0,
            source: self.source.0,
            at_ns: self.at_ns,
            markers: o.alignment.markers.clone(),
            turned: o.alignment.turned.clone(),
            disagreeing: o.alignment.disagreeing.iter().map(|&(id, _)| id).collect(),
            marker_rms_m: o.alignment.marker_rms_m,
            point_inliers: o.alignment.point_inliers as u64,
            place_keyframes: o
                .alignment
                .place
                .map(|p| [p.target_keyframe.0, p.source_keyframe.0]),
            target_keyframes: o.keyframes.0 as u64,
            source_keyframes: o.keyframes.1 as u64,
            moved_max_m: o
                .whole_map
                .as_ref()
                .filter(|w| w.applied)
                .map(|w| w.moved_max_m),
            duration_ms: ms(o.align_time) + ms(o.absorb_time) + ms(o.optimise_time),
        }
    }
}

/// The semantic layer's settings, which every writer reads at each request.
#[derive(Clone)]
struct Semantics {
    enabled: bool,
    dictionary: Option<Arc<Dictionary>>,
    /// Keyframes between whole-map optimisations of the S-Graph (0: none).
    optimise_every: usize,
    /// Close loops inside each map (through the whole-map optimisation).
    close_loops: bool,
}

impl Default for Semantics {
    fn default() -> Self {
        Self {
            enabled: true,
            dictionary: None,
            optimise_every: crate::config::DEFAULT_OPTIMISE_EVERY_KEYFRAMES,
            close_loops: true,
        }
    }
}

/// What a map's writer publishes: the snapshot, and the semantic layer its walls, doorways and
/// spaces come from (indices in one are ids in the other).
#[derive(Clone)]
pub struct Published {
    pub view: Arc<MapView>,
    pub semantics: Arc<SemanticMap>,
}

type Slot = Arc<Mutex<Published>>;

/// A map's snapshot slot, which its writer refills: readers that keep it see the map's newest
/// snapshot without asking the service.
#[derive(Clone)]
pub struct Snapshots(Slot);

impl Snapshots {
    pub fn latest(&self) -> Arc<MapView> {
        lock(&self.0).view.clone()
    }

    /// The latest snapshot with its semantic layer.
    pub fn published(&self) -> Published {
        lock(&self.0).clone()
    }
}

impl std::fmt::Debug for Snapshots {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("Snapshots")
            .field(&self.latest().map)
            .finish()
    }
}

/// One map: the map, its writer's queue and thread, its latest snapshot.
struct MapEntry {
    map: Arc<SharedMap>,
    commands: Mutex<Option<mpsc::Sender<Command>>>,
    snapshot: Slot,
    thread: Mutex<Option<JoinHandle<()>>>,
}

/// What a writer is asked to do.
// A writer's queue holds a request or two at a time: boxing the large variant would allocate on
// every request to save bytes on the rare refresh.
#[allow(clippy::large_enum_variant)]
enum Command {
    /// A tracker's request, with where to send its answer.
    Request {
        request: MapRequest,
        reply: mpsc::SyncSender<Result<MapReply, Failure>>,
    },
    /// Rebuild the semantic layer: its settings changed.
    Refresh,
    /// Wait, doing nothing, until told whether to stop (`true`: the map was merged into
    /// another) or to go on (`false`, or the sender gone: the merge failed). Acknowledged on
    /// `paused` once waiting.
    Pause {
        paused: mpsc::SyncSender<()>,
        until: mpsc::Receiver<bool>,
    },
    /// Join another map, whose writer is paused, to this one.
    Absorb {
        source: Arc<SharedMap>,
        evidence: Evidence,
        reply: mpsc::SyncSender<Result<MergeOutcome, Failure>>,
    },
}

/// Why a request has no reply: an error, or a panic in the writer, handed back to the robot's
/// worker so that it is counted there like any other panic in a frame's processing.
enum Failure {
    Error(TrackError),
    Panic(Box<dyn Any + Send>),
}

/// Refused places a service keeps for inspection: enough to show what fooled the words over a
/// session, bounded so that a look-alike seen for hours does not grow the server.
pub const KEPT_REFUSALS: usize = 256;

/// What two maps have in common for a merge on markers: ids both hold, and the keyframes of
/// both that saw those markers, which is what the points around them come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Shared {
    markers: usize,
    sightings: u64,
}

impl Shared {
    fn between(a: &[MapMarker], b: &[MapMarker]) -> Self {
        let seen: BTreeMap<i32, u64> = a
            .iter()
            .map(|m| (m.id, u64::from(m.observations)))
            .collect();
        let mut shared = Self {
            markers: 0,
            sightings: 0,
        };
        for marker in b {
            if let Some(&in_a) = seen.get(&marker.id) {
                shared.markers += 1;
                shared.sightings += in_a + u64::from(marker.observations);
            }
        }
        shared
    }

    /// Whether a pair is worth a (new) try: markers in common, and since the last try more of
    /// them, or twice the sightings. Maps first tried while young have too few points around
    /// their markers to confirm them; the doubling tries them again as their robots add views,
    /// while a pair that never aligns (an id printed twice) costs only a try per doubling.
    fn grown_since(self, before: Option<Shared>) -> bool {
        match before {
            None => self.markers > 0,
            Some(before) => {
                self.markers > before.markers || self.sightings >= 2 * before.sightings.max(1)
            }
        }
    }
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic elsewhere must not take the service down with it.
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl MapService {
    /// A service whose maps get walls from their markers, without a semantic dictionary.
    pub fn new() -> Self {
        Self::default()
    }

    /// A service with its semantic layer `enabled` or not, reading markers by `dictionary`.
    pub fn with_semantics(enabled: bool, dictionary: Option<Dictionary>) -> Self {
        let service = Self::default();
        *service
            .inner
            .semantics
            .write()
            .unwrap_or_else(|p| p.into_inner()) = Semantics {
            enabled,
            dictionary: dictionary.map(Arc::new),
            ..Semantics::default()
        };
        service
    }

    /// Optimises each map's whole S-Graph every `every` keyframes (0: never), when the semantic
    /// layer is enabled.
    pub fn with_whole_map_optimisation(self, every: usize) -> Self {
        self.inner
            .semantics
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .optimise_every = every;
        self
    }

    /// Closes loops inside each map ([`vsgraphs_slam::loops`]) when the whole-map
    /// optimisation runs.
    pub fn with_loop_closing(self, close_loops: bool) -> Self {
        self.inner
            .semantics
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .close_loops = close_loops;
        self
    }

    /// Where a map's snapshots appear: [`Snapshots::latest`] is always its newest.
    pub fn snapshots(&self, id: MapId) -> Option<Snapshots> {
        let entry = lock(&self.inner.maps).get(&id).cloned()?;
        Some(Snapshots(entry.snapshot.clone()))
    }

    /// The latest snapshot of a map.
    pub fn snapshot(&self, id: MapId) -> Option<Arc<MapView>> {
        self.snapshots(id).map(|s| s.latest())
    }

    /// The latest snapshot of a map, or the last one of a map merged into another (as it was
    /// before the merge, in its own frame; [`MapService::resolve`] finds its keyframes since).
    pub fn last_snapshot(&self, id: MapId) -> Option<Arc<MapView>> {
        self.snapshot(id)
            .or_else(|| lock(&self.inner.retired).get(&id).map(Snapshots::latest))
    }

    /// Every map's snapshots, by id.
    pub fn all(&self) -> Vec<(MapId, Snapshots)> {
        lock(&self.inner.maps)
            .iter()
            .map(|(&id, entry)| (id, Snapshots(entry.snapshot.clone())))
            .collect()
    }

    /// Replaces the semantic dictionary (`None`: none) of every map, the ones to come and the
    /// ones there are: each writer rebuilds its map's layer with it next, robots or not.
    pub fn set_dictionary(&self, dictionary: Option<Dictionary>) {
        self.inner
            .semantics
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .dictionary = dictionary.map(Arc::new);
        let entries: Vec<_> = lock(&self.inner.maps).values().cloned().collect();
        for entry in entries {
            if let Some(commands) = lock(&entry.commands).as_ref() {
                // A stopped writer has nothing left to publish.
                let _ = commands.send(Command::Refresh);
            }
        }
    }

    /// The semantic dictionary the maps read now.
    pub fn dictionary(&self) -> Option<Arc<Dictionary>> {
        self.inner
            .semantics
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .dictionary
            .clone()
    }

    /// How many maps the server holds.
    pub fn len(&self) -> usize {
        lock(&self.inner.maps).len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Stops every writer once it has answered what is queued, and waits for it. Maps stay
    /// readable; requests made afterwards fail.
    pub fn stop(&self) {
        self.inner.stop_looking();
        let entries: Vec<_> = lock(&self.inner.maps).values().cloned().collect();
        for entry in &entries {
            lock(&entry.commands).take();
        }
        for entry in entries {
            if let Some(thread) = lock(&entry.thread).take() {
                let _ = thread.join();
            }
        }
        // The writers' last changes are handed over: write them.
        if let Some(saver) = lock(&self.inner.saver).as_ref() {
            saver.stop();
        }
    }

    /// Joins map `source` to map `target`, when the markers both hold agree on where one lies in
    /// the other ([`vsgraphs_slam::merge`]): `source`'s writer lands what it has pending and
    /// stops, `target`'s moves its keyframes, points and markers in and optimises the whole
    /// map, and `source` leaves the service ([`MapService::merged`] says where it went). Maps
    /// that do not align are left as they were. A robot tracking in `source` follows it into
    /// `target` at its next frame ([`MapWriter::moved`]).
    pub fn merge(&self, target: MapId, source: MapId) -> Result<MergeReport, TrackError> {
        let _one_at_a_time = lock(&self.inner.merging);
        self.merge_now(target, source, Evidence::Markers)
    }

    /// [`MapService::merge`] by what `evidence` names, with the service's merge lock held.
    fn merge_now(
        &self,
        target: MapId,
        source: MapId,
        evidence: Evidence,
    ) -> Result<MergeReport, TrackError> {
        if target == source {
            return Err(TrackError::Writer(format!(
                "map {} cannot be merged into itself",
                source.0
            )));
        }
        let (into, from) = (self.entry(target)?, self.entry(source)?);
        // Checked before anything waits, so that maps that do not align stay as they are.
        merge::align(&into.map.read(), &from.map.read(), &evidence)?;
        // The source's writer lands what it has pending and waits while the target takes the
        // source in: it ends if that succeeds and goes on if not (an alignment can fail the
        // second time, on the map as the pending work left it), so a failed merge loses nothing.
        Self::ask(&from, MapRequest::Flush(PointStatistics::default()))?;
        let (paused, is_paused) = mpsc::sync_channel(1);
        let (resume, until) = mpsc::sync_channel(1);
        let sent = lock(&from.commands)
            .as_ref()
            .is_some_and(|commands| commands.send(Command::Pause { paused, until }).is_ok());
        if !sent || is_paused.recv().is_err() {
            return Err(TrackError::Writer(
                "the source map's writer has stopped".into(),
            ));
        }
        let outcome = self.absorb_into(&into, &from, evidence)?;
        // Recorded before the source's writer ends: a request it leaves unanswered then finds
        // the map moved, and its tracker follows the merge instead of losing the frame.
        let report = self.record_merge(target, source, (&into, &from), outcome);
        let _ = resume.send(true);
        lock(&from.commands).take();
        if let Some(thread) = lock(&from.thread).take() {
            let _ = thread.join();
        }
        Ok(report)
    }

    /// Has `into`'s writer take `from` in; `from`'s writer is paused.
    fn absorb_into(
        &self,
        into: &MapEntry,
        from: &MapEntry,
        evidence: Evidence,
    ) -> Result<MergeOutcome, TrackError> {
        let (reply, answer) = mpsc::sync_channel(1);
        let sent = lock(&into.commands).as_ref().is_some_and(|commands| {
            commands
                .send(Command::Absorb {
                    source: from.map.clone(),
                    evidence,
                    reply,
                })
                .is_ok()
        });
        if !sent {
            return Err(TrackError::Writer(
                "the target map's writer has stopped".into(),
            ));
        }
        match answer.recv() {
            Ok(Ok(outcome)) => Ok(outcome),
            Ok(Err(Failure::Error(e))) => Err(e),
            Ok(Err(Failure::Panic(payload))) => std::panic::resume_unwind(payload),
            Err(_) => Err(TrackError::Writer(
                "the target map's writer stopped before answering".into(),
            )),
        }
    }

    /// Records a merge made: where the source went, for readers and for its robots.
    fn record_merge(
        &self,
        target: MapId,
        source: MapId,
        (into, from): (&MapEntry, &MapEntry),
        outcome: MergeOutcome,
    ) -> MergeReport {
        let record = Merged {
            into: target,
            keyframe_offset: outcome.absorbed.keyframe_offset,
            into_from_merged: outcome.absorbed.target_from_source,
        };
        lock(&self.inner.merged).insert(source, record);
        lock(&self.inner.moves).insert(
            source,
            MapMove {
                into: into.map.clone(),
                keyframe_offset: outcome.absorbed.keyframe_offset,
                point_offset: outcome.absorbed.point_offset,
                into_from_merged: outcome.absorbed.target_from_source,
            },
        );
        lock(&self.inner.retired).insert(source, Snapshots(from.snapshot.clone()));
        lock(&self.inner.maps).remove(&source);
        tracing::info!(
            target = target.0,
            source = source.0,
            markers = ?outcome.alignment.markers,
            marker_rms_m = outcome.alignment.marker_rms_m,
            point_inliers = outcome.alignment.point_inliers,
            "maps merged"
        );
        let report = MergeReport {
            target,
            source,
            at_ns: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as u64),
            outcome,
        };
        lock(&self.inner.merge_log).push(report.clone());
        report
    }

    /// Merges maps as soon as they share markers (see [`MapService::merge_where_shared`]), or
    /// only when asked ([`MapService::merge`]).
    pub fn with_live_merges(self, live: bool) -> Self {
        self.inner.merge_live.store(live, Ordering::Relaxed);
        self
    }

    /// Looks for merges on a thread of the service's own (`true`), so that a robot's worker
    /// never waits for a merge, or on the calling robot's worker (`false`: an offline run then
    /// makes the same merges every time).
    pub fn with_background_merges(self, background: bool) -> Self {
        self.inner
            .background_merges
            .store(background, Ordering::Relaxed);
        self
    }

    /// Keyframe `keyframe` is new in map `map`: looks for the maps it shows one place with
    /// ([`MapService::merge_where_recognised`]), now or on the service's merge thread
    /// ([`MapService::with_background_merges`]).
    pub fn look_for_merges(&self, map: MapId, keyframe: KeyFrameId) {
        if !self.inner.merge_live.load(Ordering::Relaxed) {
            return;
        }
        if !self.inner.background_merges.load(Ordering::Relaxed) {
            self.merge_where_recognised(map, keyframe);
            return;
        }
        {
            let mut pending = lock(&self.inner.looks.pending);
            if pending.stop {
                return;
            }
            pending.keyframes.insert(map, keyframe);
        }
        self.inner.looks.ready.notify_one();
        let mut looker = lock(&self.inner.looker);
        if looker.is_none() {
            let looks = self.inner.looks.clone();
            let service = Arc::downgrade(&self.inner);
            match std::thread::Builder::new()
                .name("atlas-merges".into())
                .spawn(move || look_in_background(&looks, &service))
            {
                Ok(thread) => *looker = Some(thread),
                Err(e) => tracing::error!(error = %e, "cannot start the merge thread"),
            }
        }
    }

    /// Map `id` as the bytes of a map file ([`vsgraphs_slam::archive`]): as its writer left
    /// it after its last request (the map is read between two).
    pub fn export(&self, id: MapId) -> Result<Vec<u8>, TrackError> {
        let entry = self.entry(id)?;
        let map = entry.map.read();
        Ok(vsgraphs_slam::archive::encode(&map))
    }

    /// Every point of map `id` (not the snapshot's, which are thinned beyond
    /// [`crate::model::SNAPSHOT_POINTS`]), metres in its frame; read under the map's lock, as an
    /// export is.
    pub fn points(&self, id: MapId) -> Result<Vec<[f32; 3]>, TrackError> {
        let entry = self.entry(id)?;
        let map = entry.map.read();
        Ok(crate::model::point_positions(&map))
    }

    /// How the maps the service starts itself (imported ones) are mapped: as the server's
    /// robots map theirs.
    pub fn with_mapping(self, settings: MappingConfig) -> Self {
        *lock(&self.inner.mapping) = Some(settings);
        self
    }

    /// Keeps the maps in the store at `path` (made if absent): the maps in it are read back now,
    /// whole and checked, with their ids, and mapped like the rest; every map's changes are
    /// written to it at most `every` after they were made ([`crate::store`]). Call after
    /// [`MapService::with_mapping`]. A store that cannot be read is refused whole, with what
    /// is wrong.
    pub fn with_store(self, path: &std::path::Path, every: Duration) -> Result<Self, StoreError> {
        let store = Store::open(path)?;
        let started = Instant::now();
        let maps = store.maps()?;
        let saver = Saver::start(store, &maps, every).map_err(|e| StoreError::Open {
            path: path.to_owned(),
            reason: format!("cannot start its thread: {e}"),
        })?;
        *lock(&self.inner.saver) = Some(Arc::new(saver));
        let settings = lock(&self.inner.mapping)
            .clone()
            .unwrap_or_else(|| vsgraphs_slam::TrackerConfig::default().mapping());
        let count = maps.len();
        for (id, map) in maps {
            let keyframes = map.live_keyframes();
            self.start_map(map, &settings, 0, Some(id))
                .map_err(|e| StoreError::Open {
                    path: path.to_owned(),
                    reason: e.to_string(),
                })?;
            tracing::info!(map = id.0, keyframes, "map read from the store");
        }
        tracing::info!(
            path = %path.display(),
            maps = count,
            ms = started.elapsed().as_secs_f64() * 1e3,
            "map store opened"
        );
        Ok(self)
    }

    /// Keyframes of map `id` (culled ones included) written to the store, which a kill of
    /// the server would not lose; `None` without a store or for a map not yet written.
    pub fn stored_keyframes(&self, id: MapId) -> Option<u32> {
        lock(&self.inner.saver).as_ref()?.stored_keyframes(id)
    }

    /// What the store has cost so far (`None` without a store).
    pub fn store_stats(&self) -> Option<crate::store::StoreStats> {
        Some(lock(&self.inner.saver).as_ref()?.stats())
    }

    /// A map file read back as a new map of the service (its id is returned), mapped from
    /// then on like any other: robots that lose track relocalise in it and maps that show its
    /// places merge with it.
    pub fn import(&self, bytes: &[u8]) -> Result<MapId, ImportError> {
        let map = vsgraphs_slam::archive::decode(bytes)?;
        let keyframes = map.live_keyframes();
        let settings = lock(&self.inner.mapping)
            .clone()
            .unwrap_or_else(|| vsgraphs_slam::TrackerConfig::default().mapping());
        let shared = self.start_map(map, &settings, 0, None)?;
        tracing::info!(map = shared.id().0, keyframes, "map imported");
        Ok(shared.id())
    }

    /// Every merge so far, oldest first.
    pub fn merges(&self) -> Vec<MergeReport> {
        lock(&self.inner.merge_log).clone()
    }

    /// Merges map `map`, whose keyframe `keyframe` is new, with the maps it shows one place
    /// with, when live merges are on: first every map that holds a marker it holds
    /// ([`MapService::merge_where_shared`]); then, if none did, the first map that shows the
    /// place the keyframe shows by visual words ([`MapService::merge_where_seen`]). The map
    /// with more keyframes takes the other in (the older on a tie). Returns the merges made.
    pub fn merge_where_recognised(&self, map: MapId, keyframe: KeyFrameId) -> Vec<MergeReport> {
        if !self.inner.merge_live.load(Ordering::Relaxed) {
            return Vec::new();
        }
        let made = self.merge_where_shared(map);
        if !made.is_empty() {
            return made;
        }
        self.merge_where_seen(map, keyframe).into_iter().collect()
    }

    /// Merges map `map` with the first other map that shows the place its keyframe
    /// `keyframe` shows ([`vsgraphs_slam::loops::recognise_in`], then
    /// [`merge::align_by_place`]), when live merges are on. A map alone costs nothing; each
    /// other map, a look-up in its index of words and at most three verifications, on the
    /// calling robot's worker (so an offline run makes the same merges every time). A place
    /// recognised but refused (too few points around it, a marker that says the place is
    /// another) is logged and counted ([`MapService::refused_merges`]).
    pub fn merge_where_seen(&self, map: MapId, keyframe: KeyFrameId) -> Option<MergeReport> {
        if !self.inner.merge_live.load(Ordering::Relaxed) {
            return None;
        }
        let _one_at_a_time = lock(&self.inner.merging);
        let here = self.entry(map).ok()?;
        let others: Vec<(MapId, Arc<MapEntry>)> = lock(&self.inner.maps)
            .iter()
            .filter(|(&id, _)| id != map)
            .map(|(&id, entry)| (id, entry.clone()))
            .collect();
        for (other, entry) in others {
            let found = {
                let own = here.map.read();
                let (Some(rig), Some(k)) =
                    (own.rig.clone(), own.keyframes.get(keyframe.0 as usize))
                else {
                    return None;
                };
                if k.is_culled() {
                    return None;
                }
                let old = entry.map.read();
                loops::recognise_in(&own, &rig, keyframe, &old)
                    .map(|found| (found, k.world_from_camera))
            };
            let pair = (map, other);
            let Some((found, world_from_keyframe)) = found else {
                // A place seen once is forgotten after a few keyframes that do not see it.
                let mut seen = lock(&self.inner.places_seen);
                if let Some(sightings) = seen.get_mut(&pair) {
                    sightings.missed += 1;
                    if sightings.missed > merge::PLACE_MISSES {
                        seen.remove(&pair);
                    }
                }
                continue;
            };
            let other_from_here = found
                .world_from_camera
                .compose(&world_from_keyframe.inverse());
            let agreeing = {
                let mut seen = lock(&self.inner.places_seen);
                let sightings = seen.entry(pair).or_insert(Sightings {
                    other_from_here,
                    agreeing: 0,
                    missed: 0,
                });
                let at = world_from_keyframe.translation;
                if merge::places_agree(&sightings.other_from_here, &other_from_here, &at) {
                    sightings.agreeing += 1;
                } else {
                    sightings.agreeing = 1;
                }
                sightings.other_from_here = other_from_here;
                sightings.missed = 0;
                sightings.agreeing
            };
            tracing::debug!(
                map = map.0,
                other = other.0,
                keyframe = keyframe.0,
                other_keyframe = found.keyframe.0,
                inliers = found.inliers,
                agreeing,
                "a place of another map recognised"
            );
            if agreeing < merge::PLACE_AGREEMENTS {
                continue;
            }
            lock(&self.inner.places_seen).remove(&pair);
            let size = |entry: &MapEntry, id: MapId| {
                let view = lock(&entry.snapshot).view.clone();
                (view.keyframe_count, std::cmp::Reverse(id))
            };
            let (target, source, place) = if size(&entry, other) >= size(&here, map) {
                let place = Place {
                    target_keyframe: found.keyframe,
                    source_keyframe: keyframe,
                    target_from_source: other_from_here,
                };
                (other, map, place)
            } else {
                let place = Place {
                    target_keyframe: keyframe,
                    source_keyframe: found.keyframe,
                    target_from_source: other_from_here.inverse(),
                };
                (map, other, place)
            };
            match self.merge_now(target, source, Evidence::Place(place)) {
                Ok(report) => return Some(report),
                Err(error) => {
                    tracing::info!(
                        target = target.0,
                        source = source.0,
                        target_keyframe = place.target_keyframe.0,
                        source_keyframe = place.source_keyframe.0,
                        inliers = found.inliers,
                        %error,
                        "a place recognised in two maps was not merged"
                    );
                    self.refuse(RefusedMerge {
                        target,
                        source,
                        place: Some(place),
                        reason: error.to_string(),
                    });
                }
            }
        }
        None
    }

    /// Merges refused, oldest first (the newest [`KEPT_REFUSALS`]: a look-alike place refuses
    /// again each time it is seen): places recognised by visual words, and maps sharing
    /// markers that do not join them (an id printed twice).
    pub fn refused_merges(&self) -> Vec<RefusedMerge> {
        lock(&self.inner.refused).iter().cloned().collect()
    }

    fn refuse(&self, refusal: RefusedMerge) {
        let mut refused = lock(&self.inner.refused);
        if refused.len() == KEPT_REFUSALS {
            refused.pop_front();
        }
        refused.push_back(refusal);
    }

    /// Merges map `map` with every other map that holds a marker it holds, when live merges
    /// are on: the map with more keyframes takes the other in (the older on a tie). Called
    /// after a keyframe changed `map`; a pair that did not align is tried again only once it
    /// shares more markers, or its shared markers have been seen from at least twice as many
    /// keyframes ([`Shared::grown_since`]), so a map that keeps mapping costs a look at each
    /// map's marker ids. Returns the merges made.
    pub fn merge_where_shared(&self, map: MapId) -> Vec<MergeReport> {
        if !self.inner.merge_live.load(Ordering::Relaxed) {
            return Vec::new();
        }
        let _one_at_a_time = lock(&self.inner.merging);
        let mut made = Vec::new();
        let mut current = map;
        'again: loop {
            let views: Vec<(MapId, Arc<MapView>)> = self
                .all()
                .into_iter()
                .map(|(id, s)| (id, s.latest()))
                .collect();
            let Some(here) = views.iter().find(|(id, _)| *id == current) else {
                break;
            };
            for (other, view) in &views {
                if *other == current {
                    continue;
                }
                let shared = Shared::between(&here.1.markers, &view.markers);
                let pair = (current.min(*other), current.max(*other));
                let before = lock(&self.inner.tried).get(&pair).copied();
                if !shared.grown_since(before) {
                    continue;
                }
                lock(&self.inner.tried).insert(pair, shared);
                let larger = |a: &MapView, b: &MapView| {
                    (a.keyframe_count, std::cmp::Reverse(a.id))
                        > (b.keyframe_count, std::cmp::Reverse(b.id))
                };
                let (target, source) = if larger(&here.1, view) {
                    (current, *other)
                } else {
                    (*other, current)
                };
                match self.merge_now(target, source, Evidence::Markers) {
                    Ok(report) => {
                        made.push(report);
                        current = target;
                        continue 'again;
                    }
                    // Shared markers that do not join the maps yet, or ever (an id printed
                    // twice): tried again, and reported again, only with more in common.
                    Err(error) => {
                        tracing::info!(
                            target = target.0,
                            source = source.0,
                            shared = shared.markers,
                            sightings = shared.sightings,
                            %error,
                            "maps that share markers were not merged"
                        );
                        self.refuse(RefusedMerge {
                            target,
                            source,
                            place: None,
                            reason: error.to_string(),
                        });
                    }
                }
            }
            break;
        }
        made
    }

    /// Where a merged map went (`None` for a map that was not merged).
    pub fn merged(&self, id: MapId) -> Option<Merged> {
        lock(&self.inner.merged).get(&id).copied()
    }

    /// The map and keyframe that keyframe `keyframe` of map `map` is now, following merges.
    pub fn resolve(&self, mut map: MapId, mut keyframe: KeyFrameId) -> (MapId, KeyFrameId) {
        let merged = lock(&self.inner.merged);
        while let Some(m) = merged.get(&map) {
            map = m.into;
            keyframe = KeyFrameId(keyframe.0 + m.keyframe_offset);
        }
        (map, keyframe)
    }

    /// Runs `request` on `entry`'s writer and waits for the answer.
    fn ask(entry: &MapEntry, request: MapRequest) -> Result<MapReply, TrackError> {
        let (reply, answer) = mpsc::sync_channel(1);
        let sent = lock(&entry.commands)
            .as_ref()
            .is_some_and(|commands| commands.send(Command::Request { request, reply }).is_ok());
        if !sent {
            return Err(TrackError::Writer("the map's writer has stopped".into()));
        }
        match answer.recv() {
            Ok(Ok(reply)) => Ok(reply),
            Ok(Err(Failure::Error(e))) => Err(e),
            Ok(Err(Failure::Panic(payload))) => std::panic::resume_unwind(payload),
            Err(_) => Err(TrackError::Writer(
                "the map's writer stopped before answering".into(),
            )),
        }
    }

    /// Adds `map` under a new id, with a writer that maps with `settings`; a map with
    /// keyframes is published at once, its semantic layer moments later. A map read from the
    /// store keeps its id (`stored`), which later maps' ids follow.
    fn start_map(
        &self,
        map: Map,
        settings: &MappingConfig,
        label: usize,
        stored: Option<MapId>,
    ) -> Result<Arc<SharedMap>, TrackError> {
        let id = match stored {
            Some(id) => {
                self.inner
                    .next_id
                    .fetch_max(id.0.saturating_add(1), Ordering::Relaxed);
                id
            }
            None => MapId(self.inner.next_id.fetch_add(1, Ordering::Relaxed)),
        };
        let saver = lock(&self.inner.saver).clone();
        let ledger = match stored {
            Some(_) => Ledger::synced(&map),
            None => Ledger::new(),
        };
        // A map read back or imported was last changed by its newest keyframe.
        let updated_ns = map
            .keyframes
            .iter()
            .map(|k| k.frame.timestamp_ns)
            .max()
            .unwrap_or(0);
        let view = model::map_view(&map, id, label, updated_ns, None, None);
        let filled = !map.keyframes.is_empty();
        let map = Arc::new(SharedMap::with_map(id, map));
        let snapshot = Arc::new(Mutex::new(Published {
            view: Arc::new(view),
            semantics: Arc::default(),
        }));
        let (sender, commands) = mpsc::channel();
        let writer = Writer {
            map: map.clone(),
            mapper: LocalMapper::new(settings.clone()),
            label,
            snapshot: snapshot.clone(),
            semantics: self.inner.semantics.clone(),
            layer_behind: 0,
            save_every: saver.as_ref().map_or(Duration::ZERO, |s| s.every()),
            saver,
            ledger,
            unsaved: false,
            saved_at: Instant::now(),
        };
        let thread = std::thread::Builder::new()
            .name(format!("map-{}", id.0))
            .spawn(move || writer.run(commands))
            .map_err(|e| TrackError::Writer(format!("cannot start the map's writer: {e}")))?;
        if filled {
            let _ = sender.send(Command::Refresh);
        }
        let entry = MapEntry {
            map: map.clone(),
            commands: Mutex::new(Some(sender)),
            snapshot,
            thread: Mutex::new(Some(thread)),
        };
        lock(&self.inner.maps).insert(id, Arc::new(entry));
        Ok(map)
    }

    fn entry(&self, id: MapId) -> Result<Arc<MapEntry>, TrackError> {
        lock(&self.inner.maps)
            .get(&id)
            .cloned()
            .ok_or(TrackError::UnknownMap(id))
    }
}

/// The service's merge thread: each map's newest keyframe in turn, until told to stop or the
/// service is gone. It holds the service only while looking, so that dropping the last
/// handle elsewhere ends it.
fn look_in_background(looks: &Looks, service: &Weak<Inner>) {
    loop {
        let (map, keyframe) = {
            let mut pending = lock(&looks.pending);
            loop {
                if pending.stop {
                    return;
                }
                if let Some((map, keyframe)) = pending.keyframes.pop_first() {
                    break (map, keyframe);
                }
                pending = looks
                    .ready
                    .wait(pending)
                    .unwrap_or_else(|poisoned| poisoned.into_inner());
            }
        };
        let Some(inner) = service.upgrade() else {
            return;
        };
        let service = MapService { inner };
        let looked = catch_unwind(AssertUnwindSafe(|| {
            service.merge_where_recognised(map, keyframe)
        }));
        if looked.is_err() {
            tracing::error!(
                map = map.0,
                keyframe = keyframe.0,
                "looking for merges panicked; the maps stay as they were"
            );
        }
    }
}

impl Inner {
    /// Ends the merge thread once its current look is done (not waiting for itself: the last
    /// handle of the service may be the one it holds).
    fn stop_looking(&self) {
        lock(&self.looks.pending).stop = true;
        self.looks.ready.notify_all();
        let looker = lock(&self.looker).take();
        if let Some(thread) = looker {
            if thread.thread().id() != std::thread::current().id() {
                let _ = thread.join();
            }
        }
    }
}

impl Drop for Inner {
    fn drop(&mut self) {
        self.stop_looking();
        // The last handle is gone: writers finish what is queued and end.
        let maps = std::mem::take(self.maps.get_mut().unwrap_or_else(|p| p.into_inner()));
        for entry in maps.values() {
            lock(&entry.commands).take();
        }
        for entry in maps.values() {
            if let Some(thread) = lock(&entry.thread).take() {
                let _ = thread.join();
            }
        }
    }
}

impl MapWriter for MapService {
    fn moved(&self, map: &SharedMap) -> Option<MapMove> {
        lock(&self.inner.moves).get(&map.id()).cloned()
    }

    fn maps(&self) -> Vec<Arc<SharedMap>> {
        lock(&self.inner.maps)
            .values()
            .map(|entry| entry.map.clone())
            .collect()
    }

    fn create_map(
        &mut self,
        settings: &MappingConfig,
        label: usize,
    ) -> Result<Arc<SharedMap>, TrackError> {
        self.start_map(Map::default(), settings, label, None)
    }

    fn request(&mut self, map: &SharedMap, request: MapRequest) -> Result<MapReply, TrackError> {
        let merged = |service: &Self| {
            service.moved(map).map(|moved| TrackError::MapMerged {
                from: map.id(),
                into: moved.into.id(),
            })
        };
        // A merge raced the robot's frame: the tracker follows the map and tracks it again.
        if let Some(e) = merged(self) {
            return Err(e);
        }
        let entry = self.entry(map.id())?;
        if !std::ptr::eq(entry.map.as_ref(), map) {
            // A map of another service that happens to share the id.
            return Err(TrackError::UnknownMap(map.id()));
        }
        // A map merged away stops its writer with the request unanswered.
        Self::ask(&entry, request).map_err(|e| merged(self).unwrap_or(e))
    }
}

/// A map's writer thread: its local mapping and where it publishes snapshots.
struct Writer {
    map: Arc<SharedMap>,
    mapper: LocalMapper,
    label: usize,
    snapshot: Slot,
    semantics: Arc<RwLock<Semantics>>,
    /// Keyframes mapped since the semantic layer was last published.
    layer_behind: usize,
    /// The store, and what of this map was last handed to it.
    saver: Option<Arc<Saver>>,
    ledger: Ledger,
    /// Keyframes were mapped since the last hand-over, made at `saved_at`; the next is due
    /// `save_every` after it.
    unsaved: bool,
    saved_at: Instant,
    save_every: Duration,
}

/// The map's walls are rebuilt after every keyframe, as local BA uses them; the rest of the
/// semantic layer (doorways, rooms, corridors, and the walls as published), which nothing in the
/// map's optimisation reads and which costs most (doorways read every point with the cameras
/// that saw it), after this many keyframes, at a flush, and when no keyframe has come for
/// [`LAYER_IDLE`]. A robot maps a keyframe every 0.1–0.3 s at walking pace, so the published
/// layer trails the map by a second at most.
const LAYER_EVERY_KEYFRAMES: usize = 5;
const LAYER_IDLE: std::time::Duration = std::time::Duration::from_millis(500);

impl Writer {
    fn run(mut self, commands: mpsc::Receiver<Command>) {
        let span = tracing::info_span!("map", id = self.map.id().0);
        let _entered = span.enter();
        // An imported map is written whole before anything else.
        self.guarded("the map's store", |w| w.save(Vec::new()));
        let mut idle_since = Instant::now();
        loop {
            // Waits for a command, or until the semantic layer or the store is due.
            let layer_due =
                (self.layer_behind > 0).then(|| LAYER_IDLE.saturating_sub(idle_since.elapsed()));
            let save_due = self
                .unsaved
                .then(|| self.save_every.saturating_sub(self.saved_at.elapsed()));
            let command = match layer_due.into_iter().chain(save_due).min() {
                Some(wait) => match commands.recv_timeout(wait) {
                    Ok(command) => command,
                    Err(mpsc::RecvTimeoutError::Timeout) => {
                        if self.unsaved && self.saved_at.elapsed() >= self.save_every {
                            self.guarded("the map's store", |w| w.save(Vec::new()));
                        }
                        if self.layer_behind > 0 && idle_since.elapsed() >= LAYER_IDLE {
                            self.guarded("the map's semantic layer", Self::publish_semantics);
                            // A layer that failed is tried again after another idle spell,
                            // not at once.
                            idle_since = Instant::now();
                        }
                        continue;
                    }
                    Err(mpsc::RecvTimeoutError::Disconnected) => break,
                },
                None => match commands.recv() {
                    Ok(command) => command,
                    Err(_) => break,
                },
            };
            idle_since = Instant::now();
            let (request, reply) = match command {
                Command::Request { request, reply } => (request, reply),
                Command::Refresh => {
                    self.guarded("the map's semantic layer", Self::publish_semantics);
                    continue;
                }
                Command::Pause { paused, until } => {
                    let _ = paused.send(());
                    if until.recv() == Ok(true) {
                        break;
                    }
                    continue;
                }
                Command::Absorb {
                    source,
                    evidence,
                    reply,
                } => {
                    let outcome = catch_unwind(AssertUnwindSafe(|| {
                        let source = source.read();
                        self.mapper
                            .absorb(&mut self.map.write(), &source, &evidence)
                    }));
                    let answer = match outcome {
                        Ok(Ok(outcome)) => Ok(outcome),
                        Ok(Err(error)) => Err(Failure::Error(error)),
                        Err(payload) => Err(Failure::Panic(payload)),
                    };
                    self.guarded("the map's snapshot", |w| w.publish_geometry(None));
                    self.guarded("the map's semantic layer", Self::publish_semantics);
                    // The merged map's rows go with this map's new ones, in one commit.
                    let merged = answer.is_ok().then(|| source.id());
                    self.guarded("the map's store", |w| w.save(merged.into_iter().collect()));
                    let _ = reply.send(answer);
                    continue;
                }
            };
            let outcome = catch_unwind(AssertUnwindSafe(|| self.handle(request)));
            let (answer, stamp) = match outcome {
                Ok(Ok((done, stamp))) => (Ok(done), Some(stamp)),
                Ok(Err(error)) => (Err(Failure::Error(error)), None),
                Err(payload) => {
                    tracing::error!("mapping panicked; the request is answered with the panic");
                    (Err(Failure::Panic(payload)), None)
                }
            };
            // The map's geometry is published before the answer (the trajectory and the API
            // read keyframe poses from it: cheap), its semantic layer after (milliseconds to
            // tens of them on a large map), so the tracker goes on meanwhile; the map cannot
            // change under it, this thread being its only writer. A flush publishes both first:
            // whoever flushes reads the final snapshot next.
            let flush = matches!(stamp, Some(None));
            if let Some(stamp) = stamp {
                self.guarded("the map's snapshot", |w| w.publish_geometry(stamp));
                if flush {
                    self.guarded("the map's semantic layer", Self::publish_semantics);
                }
            }
            // The robot's worker may have gone (the server stopping): nobody to tell.
            let _ = reply.send(answer);
            if flush {
                self.guarded("the map's store", |w| w.save(Vec::new()));
            }
            if stamp.is_some() && !flush {
                self.guarded("loop closing", |w| {
                    w.mapper.look_for_pending_loop(&mut w.map.write())
                });
                self.layer_behind += 1;
                if self.layer_behind >= LAYER_EVERY_KEYFRAMES {
                    self.guarded("the map's semantic layer", Self::publish_semantics);
                } else {
                    self.guarded("the map's walls", Self::update_walls);
                }
                self.unsaved = true;
                if self.saved_at.elapsed() >= self.save_every {
                    self.guarded("the map's store", |w| w.save(Vec::new()));
                }
            }
        }
        // The service is stopping: what is left goes to the store.
        if self.unsaved {
            self.guarded("the map's store", |w| w.save(Vec::new()));
        }
    }

    /// Hands the rows changed since the last save to the store (if any), with the maps merged
    /// into this one since, whose rows go in the same commit.
    fn save(&mut self, mut retire: Vec<MapId>) {
        // Cleared with no store too: the writer's wait for the next save ends on it.
        self.unsaved = false;
        self.saved_at = Instant::now();
        let Some(saver) = self.saver.clone() else {
            return;
        };
        let started = Instant::now();
        if let Some(again) = saver.take_rewrite(self.map.id()) {
            self.ledger = Ledger::new();
            retire.extend(again);
        }
        let changes = {
            let map = self.map.read();
            if map.keyframes.is_empty() {
                return;
            }
            self.ledger.changes(&map)
        };
        if changes.is_empty() && retire.is_empty() {
            return;
        }
        saver.send(Save {
            map: self.map.id(),
            changes,
            retire,
        });
        saver.record_hand_over(started.elapsed().as_secs_f64() * 1e3);
    }

    /// Runs one request; returns its answer and the stamp the map is now at.
    fn handle(&mut self, request: MapRequest) -> Result<(MapReply, Option<u64>), TrackError> {
        let stamp = match &request {
            MapRequest::Start { frame, .. } => Some(frame.timestamp_ns),
            MapRequest::Insert(insert) => Some(insert.frame.timestamp_ns),
            MapRequest::Flush(_) => None,
        };
        let settings = self.settings();
        let every = if settings.enabled {
            settings.optimise_every
        } else {
            0
        };
        self.mapper.set_whole_map_every(every);
        self.mapper
            .set_close_loops(settings.close_loops && every > 0);
        let reply = self.mapper.handle(&mut self.map.write(), request)?;
        Ok((reply, stamp))
    }

    /// Runs `publish`, a panic in it logged: the last snapshot stays.
    fn guarded(&mut self, what: &str, publish: impl FnOnce(&mut Self)) {
        if catch_unwind(AssertUnwindSafe(|| publish(self))).is_err() {
            tracing::error!("building {what} panicked; the last snapshot stays");
        }
    }

    /// Publishes the map as the last request left it (stamped `stamp`, else as before), with
    /// the semantic layer of the snapshot before.
    fn publish_geometry(&mut self, stamp: Option<u64>) {
        let map = self.map.read();
        let last = lock(&self.snapshot).view.clone();
        let updated_ns = stamp.unwrap_or(last.updated_ns);
        let mut view = model::map_view(&map, self.map.id(), self.label, updated_ns, None, None);
        view.walls = last.walls.clone();
        view.doorways = last.doorways.clone();
        view.spaces = last.spaces.clone();
        view.missing_spaces = last.missing_spaces.clone();
        lock(&self.snapshot).view = Arc::new(view);
    }

    /// Local BA adjusts the walls with their markers and points from the next keyframe on.
    fn set_walls(&mut self, walls: &[vsgraphs_semantics::Wall]) {
        self.mapper.set_walls(
            walls
                .iter()
                .map(|w| WallPrior {
                    plane: w.plane,
                    markers: w.markers.clone(),
                })
                .collect(),
        );
    }

    /// The semantic layer's settings now.
    fn settings(&self) -> Semantics {
        self.semantics
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// `build` run on what the semantic layer reads of the map (with the cameras that saw each
    /// point when `with_cameras`).
    fn read_map<T>(
        &self,
        with_cameras: bool,
        build: impl FnOnce(&vsgraphs_semantics::MapInput<'_>) -> T,
    ) -> T {
        let map = self.map.read();
        let (points, cameras) = model::live_points(&map, with_cameras);
        build(&vsgraphs_semantics::MapInput {
            markers: &model::marker_poses(&map),
            points: &points,
            cameras: &cameras,
        })
    }

    /// Rebuilds the map's walls for local BA alone (as the whole layer would make them).
    fn update_walls(&mut self) {
        let started = std::time::Instant::now();
        let settings = self.settings();
        let walls = settings.enabled.then(|| {
            self.read_map(false, |input| {
                vsgraphs_semantics::walls(input, settings.dictionary.as_deref())
            })
        });
        self.set_walls(walls.as_deref().unwrap_or(&[]));
        tracing::debug!(ms = started.elapsed().as_secs_f64() * 1e3, "walls rebuilt");
    }

    /// Rebuilds the map's semantic layer and publishes it in the latest snapshot.
    fn publish_semantics(&mut self) {
        // Due no more even if the build panics: an idle map does not retry it every half second.
        self.layer_behind = 0;
        let started = std::time::Instant::now();
        let settings = self.settings();
        let dictionary = settings.dictionary.as_deref();
        let mut read_ms = 0.0;
        let semantic = settings.enabled.then(|| {
            self.read_map(true, |input| {
                read_ms = started.elapsed().as_secs_f64() * 1e3;
                SemanticMap::build(input, dictionary)
            })
        });
        self.set_walls(semantic.as_ref().map_or(&[], |s| &s.walls));
        let built = std::time::Instant::now();
        let mut view = (*lock(&self.snapshot).view).clone();
        model::set_semantics(&mut view, semantic.as_ref(), dictionary);
        tracing::debug!(
            ms = started.elapsed().as_secs_f64() * 1e3,
            read_ms,
            snapshot_ms = built.elapsed().as_secs_f64() * 1e3,
            walls = view.walls.len(),
            doorways = view.doorways.len(),
            "semantic layer published"
        );
        *lock(&self.snapshot) = Published {
            view: Arc::new(view),
            semantics: Arc::new(semantic.unwrap_or_default()),
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vsgraphs_slam::local_mapping::PointStatistics;

    fn settings() -> MappingConfig {
        MappingConfig {
            local_ba_iterations: 0,
            local_ba_threads: 1,
            background_ba: false,
            triangulate_points: false,
            cull_keyframes: false,
        }
    }

    #[test]
    fn each_map_has_its_own_writer_and_snapshot() {
        let mut service = MapService::new();
        let a = service.create_map(&settings(), 0).unwrap();
        let b = service.create_map(&settings(), 1).unwrap();
        assert_ne!(a.id(), b.id());
        assert_eq!(service.len(), 2);
        let reply = service
            .request(&b, MapRequest::Flush(PointStatistics::default()))
            .unwrap();
        assert!(matches!(reply, MapReply::Flushed { .. }));
        let view = service.snapshot(b.id()).unwrap();
        assert_eq!((view.map, view.keyframe_count), (1, 0));
        service.stop();
        let stopped = service.request(&a, MapRequest::Flush(PointStatistics::default()));
        assert!(matches!(stopped, Err(TrackError::Writer(_))), "{stopped:?}");
    }

    #[test]
    fn a_panic_in_a_writer_reaches_the_requester_and_the_writer_goes_on() {
        let mut service = MapService::new();
        let map = service.create_map(&settings(), 0).unwrap();
        // Statistics of a point the map does not hold: the writer panics on the index.
        let mut bad = PointStatistics::default();
        bad.seen(vsgraphs_slam::MapPointId(99));
        let request = std::panic::AssertUnwindSafe(|| {
            let _ = service.clone().request(&map, MapRequest::Flush(bad));
        });
        assert!(std::panic::catch_unwind(request).is_err());
        let next = service.request(&map, MapRequest::Flush(PointStatistics::default()));
        assert!(matches!(next, Ok(MapReply::Flushed { .. })), "{next:?}");
    }

    #[test]
    fn a_map_of_another_service_is_refused() {
        let mut ours = MapService::new();
        let mut theirs = MapService::new();
        ours.create_map(&settings(), 0).unwrap();
        let same_id = theirs.create_map(&settings(), 0).unwrap();
        let flush = || MapRequest::Flush(PointStatistics::default());
        assert!(matches!(
            ours.request(&same_id, flush()),
            Err(TrackError::UnknownMap(MapId(0)))
        ));
        let unknown = SharedMap::new(MapId(7));
        assert!(matches!(
            ours.request(&unknown, flush()),
            Err(TrackError::UnknownMap(MapId(7)))
        ));
    }

    fn markers(seen: &[(i32, u32)]) -> Vec<MapMarker> {
        let pose = vsgraphs_proto::api::Pose {
            translation_m: [0.0; 3],
            rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
        };
        seen.iter()
            .map(|&(id, observations)| MapMarker {
                id,
                side_m: 0.2,
                world_from_marker: pose,
                observations,
                keyframes: Vec::new(),
            })
            .collect()
    }

    #[test]
    fn a_refused_pair_is_tried_again_once_its_shared_markers_are_seen_twice_as_often() {
        // Marker 0 in both (2 + 1 keyframes), 5 and 6 in one map each.
        let young = Shared::between(&markers(&[(0, 2), (5, 9)]), &markers(&[(0, 1), (6, 4)]));
        assert_eq!((young.markers, young.sightings), (1, 3));
        assert!(young.grown_since(None));
        let apart = Shared::between(&markers(&[(5, 9)]), &markers(&[(6, 9)]));
        assert!(!apart.grown_since(None));
        // The same marker, seen more but not yet twice as often: not tried again.
        let older = Shared::between(&markers(&[(0, 3)]), &markers(&[(0, 2)]));
        assert!(!older.grown_since(Some(young)));
        let twice = Shared::between(&markers(&[(0, 4)]), &markers(&[(0, 2)]));
        assert!(twice.grown_since(Some(young)));
        // Another marker in common is worth a try at once.
        let more = Shared::between(&markers(&[(0, 2), (7, 1)]), &markers(&[(0, 1), (7, 1)]));
        assert!(more.grown_since(Some(young)));
    }
}
