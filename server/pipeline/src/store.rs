//! The maps' store: every map of the server in one redb file, written as it changes, read
//! back at start.
//!
//! Each map's writer works out which of its rows changed ([`vsgraphs_slam::archive::rows`])
//! at most [`Saver::every`] after mapping a keyframe (and at once after a merge, an import or
//! a flush) and hands them to the store's thread ([`Saver`]), which writes everything handed
//! to it since its last commit in one transaction and makes it durable before the next. A kill
//! loses at most the keyframes of that interval and of the commit in progress
//! ([`Saver::stored_keyframes`] says how far each map is). A merge's new rows and the removal of the map merged away go in one
//! transaction, so a restart never finds both.
//!
//! Tables: `meta` (the store's and the records' format), `maps` (each map's header row, by
//! map id), and `frames`, `states`, `words`, `points` (rows keyed by map id << 32 | index).
//! Reading refuses a store of another format and a map any of whose rows is missing, changed
//! (each row has its own CRC-32) or inconsistent with the rest, with what is wrong: a store is
//! loaded whole or not at all. A store whose records are of an older format still read is
//! upgraded when it is opened: every map read in the old format and written whole in the new,
//! with the format, in one transaction (so a kill leaves it old or new, never half).

use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{mpsc, Arc, Mutex};
use std::thread::JoinHandle;
use vsgraphs_slam::archive::rows::{self, Changes, RowKind, StoredRows};
use vsgraphs_slam::archive::{ArchiveError, FORMAT_VERSION, OLDEST_FORMAT};
use vsgraphs_slam::{Map, MapId};

/// The store's layout (tables and keys); a store of another is refused.
pub const STORE_FORMAT: u32 = 1;

const META: TableDefinition<&str, u32> = TableDefinition::new("meta");
const HEADERS: TableDefinition<u32, &[u8]> = TableDefinition::new("maps");
const FRAMES: TableDefinition<u64, &[u8]> = TableDefinition::new("frames");
const STATES: TableDefinition<u64, &[u8]> = TableDefinition::new("states");
const WORDS: TableDefinition<u64, &[u8]> = TableDefinition::new("words");
const POINTS: TableDefinition<u64, &[u8]> = TableDefinition::new("points");

fn table(kind: RowKind) -> TableDefinition<'static, u64, &'static [u8]> {
    match kind {
        RowKind::Frame => FRAMES,
        RowKind::State => STATES,
        RowKind::Words => WORDS,
        RowKind::Point => POINTS,
    }
}

fn key(map: MapId, index: u32) -> u64 {
    (u64::from(map.0) << 32) | u64::from(index)
}

/// The keys of one map's rows.
fn keys_of(map: MapId) -> std::ops::Range<u64> {
    key(map, 0)..key(map, 0) + (1 << 32)
}

/// Why the store cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{}: cannot open the map store: {reason}", path.display())]
    Open { path: PathBuf, reason: String },
    #[error("{}: the map store is format {found} with records of format {records}; this server reads format {STORE_FORMAT} with records of formats {OLDEST_FORMAT} to {FORMAT_VERSION}", path.display())]
    Version {
        path: PathBuf,
        found: u32,
        records: u32,
    },
    #[error("{}: map {map} in the store cannot be read: {error}", path.display())]
    Map {
        path: PathBuf,
        map: u32,
        error: ArchiveError,
    },
    #[error("{}: {reason}", path.display())]
    Database { path: PathBuf, reason: String },
}

/// What one map's writer hands the store after a keyframe: its changed rows, and the maps
/// merged into it since, whose rows go.
#[derive(Debug)]
pub struct Save {
    pub map: MapId,
    pub changes: Changes,
    pub retire: Vec<MapId>,
}

/// The most memory redb keeps of the file. Its default (a gigabyte) fills as the file grows,
/// so a server that maps for days would grow towards it; the store reads a map back whole only
/// at start and otherwise writes, which a small cache serves as well.
pub const CACHE_BYTES: usize = 64 << 20;

/// The store's file.
pub struct Store {
    db: Database,
    path: PathBuf,
}

impl Store {
    /// Opens the store at `path`, made empty if there is no file there.
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        let fail = |reason: String| StoreError::Open {
            path: path.to_owned(),
            reason,
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| fail(format!("creating its folder: {e}")))?;
        }
        let db = redb::Builder::new()
            .set_cache_size(CACHE_BYTES)
            .create(path)
            .map_err(|e| fail(e.to_string()))?;
        let store = Self {
            db,
            path: path.to_owned(),
        };
        let records = store.check_format()?;
        if records != FORMAT_VERSION {
            store.upgrade(records)?;
        }
        Ok(store)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn database(&self, error: impl std::fmt::Display) -> StoreError {
        StoreError::Database {
            path: self.path.clone(),
            reason: error.to_string(),
        }
    }

    /// Sets a new store's format, or checks an old one's: the format its records are in.
    fn check_format(&self) -> Result<u32, StoreError> {
        let e = |e: redb::Error| self.database(e);
        let txn = self.db.begin_write().map_err(|x| e(x.into()))?;
        let records = {
            let mut meta = txn.open_table(META).map_err(|x| e(x.into()))?;
            let found = meta
                .get("store")
                .map_err(|x| e(x.into()))?
                .map(|v| v.value());
            let records = meta
                .get("records")
                .map_err(|x| e(x.into()))?
                .map(|v| v.value());
            match (found, records) {
                (Some(STORE_FORMAT), Some(records))
                    if (OLDEST_FORMAT..=FORMAT_VERSION).contains(&records) =>
                {
                    records
                }
                (None, None) => {
                    meta.insert("store", STORE_FORMAT)
                        .map_err(|x| e(x.into()))?;
                    meta.insert("records", FORMAT_VERSION)
                        .map_err(|x| e(x.into()))?;
                    FORMAT_VERSION
                }
                (found, records) => {
                    return Err(StoreError::Version {
                        path: self.path.clone(),
                        found: found.unwrap_or(0),
                        records: records.unwrap_or(0),
                    })
                }
            }
        };
        txn.commit().map_err(|x| e(x.into()))?;
        Ok(records)
    }

    /// Rewrites a store whose records are of the older format `records`: every map read in it
    /// and written whole in today's, in one transaction with the new format.
    fn upgrade(&self, records: u32) -> Result<(), StoreError> {
        let maps = self.maps_in(records)?;
        let saves: Vec<Save> = maps
            .iter()
            .map(|(id, map)| Save {
                map: *id,
                changes: rows::Ledger::new().changes(map),
                retire: Vec::new(),
            })
            .collect();
        let e = |e: redb::Error| self.database(e);
        let txn = self.db.begin_write().map_err(|x| e(x.into()))?;
        put(&txn, &saves).map_err(e)?;
        {
            let mut meta = txn.open_table(META).map_err(|x| e(x.into()))?;
            meta.insert("records", FORMAT_VERSION)
                .map_err(|x| e(x.into()))?;
        }
        txn.commit().map_err(|x| e(x.into()))?;
        tracing::info!(
            path = %self.path.display(),
            maps = maps.len(),
            from = records,
            to = FORMAT_VERSION,
            "map store's records upgraded"
        );
        Ok(())
    }

    /// Every map in the store, each read whole and checked.
    pub fn maps(&self) -> Result<Vec<(MapId, Map)>, StoreError> {
        self.maps_in(FORMAT_VERSION)
    }

    /// Every map in the store, its records read as of format `records`.
    fn maps_in(&self, records: u32) -> Result<Vec<(MapId, Map)>, StoreError> {
        let e = |e: redb::Error| self.database(e);
        let txn = self.db.begin_read().map_err(|x| e(x.into()))?;
        let headers = match txn.open_table(HEADERS) {
            Ok(t) => t,
            Err(redb::TableError::TableDoesNotExist(_)) => return Ok(Vec::new()),
            Err(x) => return Err(e(x.into())),
        };
        let mut maps = Vec::new();
        for entry in headers.iter().map_err(|x| e(x.into()))? {
            let (id, header) = entry.map_err(|x| e(x.into()))?;
            let id = MapId(id.value());
            let header = header.value().to_vec();
            let refused = |error| StoreError::Map {
                path: self.path.clone(),
                map: id.0,
                error,
            };
            let (keyframes, points) = rows::counts(&header).map_err(refused)?;
            let read = |kind: RowKind, count: u32| -> Result<Vec<Option<Vec<u8>>>, StoreError> {
                let mut rows = vec![None; count as usize];
                let table = match txn.open_table(table(kind)) {
                    Ok(t) => t,
                    Err(redb::TableError::TableDoesNotExist(_)) => return Ok(rows),
                    Err(x) => return Err(e(x.into())),
                };
                for entry in table.range(keys_of(id)).map_err(|x| e(x.into()))? {
                    let (k, v) = entry.map_err(|x| e(x.into()))?;
                    let index = (k.value() & u64::from(u32::MAX)) as usize;
                    match rows.get_mut(index) {
                        Some(row) => *row = Some(v.value().to_vec()),
                        None => {
                            return Err(refused(ArchiveError::Inconsistent(format!(
                                "a {kind:?} row for index {index} of {count}"
                            ))))
                        }
                    }
                }
                Ok(rows)
            };
            let whole = |kind: RowKind, count: u32| -> Result<Vec<Vec<u8>>, StoreError> {
                read(kind, count)?
                    .into_iter()
                    .enumerate()
                    .map(|(i, row)| {
                        row.ok_or_else(|| {
                            refused(ArchiveError::Inconsistent(format!(
                                "its {kind:?} row {i} is missing"
                            )))
                        })
                    })
                    .collect()
            };
            let stored = StoredRows {
                format: records,
                header,
                frames: whole(RowKind::Frame, keyframes)?,
                states: whole(RowKind::State, keyframes)?,
                words: read(RowKind::Words, keyframes)?,
                points: whole(RowKind::Point, points)?,
            };
            maps.push((id, rows::assemble(stored).map_err(refused)?));
        }
        Ok(maps)
    }

    /// Writes `saves` in one durable transaction.
    pub fn write(&self, saves: &[Save]) -> Result<(), StoreError> {
        let e = |e: redb::Error| self.database(e);
        let txn = self.db.begin_write().map_err(|x| e(x.into()))?;
        put(&txn, saves).map_err(e)?;
        txn.commit().map_err(|x| e(x.into()))
    }
}

/// Puts `saves` into the transaction `txn`.
fn put(txn: &redb::WriteTransaction, saves: &[Save]) -> Result<(), redb::Error> {
    let mut headers = txn.open_table(HEADERS)?;
    let mut tables = [
        txn.open_table(FRAMES)?,
        txn.open_table(STATES)?,
        txn.open_table(WORDS)?,
        txn.open_table(POINTS)?,
    ];
    let index = |kind: RowKind| match kind {
        RowKind::Frame => 0,
        RowKind::State => 1,
        RowKind::Words => 2,
        RowKind::Point => 3,
    };
    for save in saves {
        for &gone in &save.retire {
            headers.remove(gone.0)?;
            for table in &mut tables {
                table.retain_in(keys_of(gone), |_, _| false)?;
            }
        }
        if let Some(header) = &save.changes.header {
            headers.insert(save.map.0, header.as_slice())?;
        }
        for (kind, i, bytes) in &save.changes.rows {
            tables[index(*kind)].insert(key(save.map, *i), bytes.as_slice())?;
        }
        for (kind, i) in &save.changes.removed {
            tables[index(*kind)].remove(key(save.map, *i))?;
        }
    }
    Ok(())
}

/// The store's thread and what it has made durable.
pub struct Saver {
    sender: Mutex<Option<mpsc::Sender<Save>>>,
    thread: Mutex<Option<JoinHandle<()>>>,
    state: Arc<SaverState>,
    path: PathBuf,
    every: std::time::Duration,
}

/// What the store has cost, for benchmarks and logs: the newest [`KEPT_TIMES`] times of each.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct StoreStats {
    pub commits: u64,
    /// Commits that failed (each logged; the writers then hand over every row again).
    pub failures: u64,
    /// Bytes of rows committed.
    pub bytes: u64,
    /// Each commit, ms (the store's thread).
    pub commit_ms: VecDeque<f64>,
    /// Each hand-over on a map's writer (hashing the map's rows, serialising the changed
    /// ones), ms.
    pub hand_over_ms: VecDeque<f64>,
}

/// Times kept per kind in [`StoreStats`], so a long run does not grow the server.
pub const KEPT_TIMES: usize = 4096;

fn keep(times: &mut VecDeque<f64>, ms: f64) {
    if times.len() == KEPT_TIMES {
        times.pop_front();
    }
    times.push_back(ms);
}

#[derive(Default)]
struct SaverState {
    /// Keyframes of each map as of its last commit.
    stored: Mutex<BTreeMap<MapId, u32>>,
    /// Maps whose last rows were not written: their writers hand over every row again, with
    /// the maps merged into them whose removal was in the commit that failed.
    rewrite: Mutex<BTreeMap<MapId, Vec<MapId>>>,
    stats: Mutex<StoreStats>,
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Saver {
    /// Starts the thread that writes to `store`, whose maps as read are `maps`.
    /// Writers hand their changes over at most `every` after making them.
    pub fn start(
        store: Store,
        maps: &[(MapId, Map)],
        every: std::time::Duration,
    ) -> std::io::Result<Self> {
        let state = Arc::new(SaverState::default());
        *lock(&state.stored) = maps
            .iter()
            .map(|(id, map)| (*id, map.keyframes.len() as u32))
            .collect();
        let (sender, saves) = mpsc::channel();
        let path = store.path().to_owned();
        let thread_state = state.clone();
        let thread = std::thread::Builder::new()
            .name("map-store".into())
            .spawn(move || save(&store, &saves, &thread_state))?;
        Ok(Self {
            sender: Mutex::new(Some(sender)),
            thread: Mutex::new(Some(thread)),
            state,
            path,
            every,
        })
    }

    /// How long a writer may keep changes before handing them over.
    pub fn every(&self) -> std::time::Duration {
        self.every
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Hands a map's changes over; they are written with the next commit.
    pub fn send(&self, save: Save) {
        if let Some(sender) = lock(&self.sender).as_ref() {
            let _ = sender.send(save);
        }
    }

    /// Whether `map`'s writer must hand over all its rows again (a write of them failed), and
    /// if so the maps merged into it to remove in the same commit (their removal failed too).
    pub fn take_rewrite(&self, map: MapId) -> Option<Vec<MapId>> {
        lock(&self.state.rewrite).remove(&map)
    }

    /// Keyframes of `map` (culled ones included) that a kill would not lose.
    pub fn stored_keyframes(&self, map: MapId) -> Option<u32> {
        lock(&self.state.stored).get(&map).copied()
    }

    /// A writer's hand-over took `ms`.
    pub fn record_hand_over(&self, ms: f64) {
        keep(&mut lock(&self.state.stats).hand_over_ms, ms);
    }

    pub fn stats(&self) -> StoreStats {
        lock(&self.state.stats).clone()
    }

    /// Writes what was handed over and ends the thread.
    pub fn stop(&self) {
        lock(&self.sender).take();
        if let Some(thread) = lock(&self.thread).take() {
            let _ = thread.join();
        }
    }
}

impl Drop for Saver {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The store's thread: waits for changes, then commits everything handed over meanwhile.
fn save(store: &Store, saves: &mpsc::Receiver<Save>, state: &SaverState) {
    while let Ok(first) = saves.recv() {
        let mut batch = vec![first];
        batch.extend(saves.try_iter());
        let started = std::time::Instant::now();
        match store.write(&batch) {
            Ok(()) => {
                let mut stored = lock(&state.stored);
                for save in &batch {
                    for gone in &save.retire {
                        stored.remove(gone);
                    }
                    stored.insert(save.map, save.changes.keyframes);
                }
                drop(stored);
                let bytes = batch.iter().map(|s| s.changes.bytes()).sum::<usize>();
                let ms = started.elapsed().as_secs_f64() * 1e3;
                let mut stats = lock(&state.stats);
                stats.commits += 1;
                stats.bytes += bytes as u64;
                keep(&mut stats.commit_ms, ms);
                tracing::debug!(saves = batch.len(), bytes, ms, "store committed");
            }
            Err(error) => {
                tracing::error!(%error, "the map store could not be written; the maps will be written whole again");
                state.failed(&batch);
            }
        }
    }
}

impl SaverState {
    /// A commit of `batch` failed: each map in it is to be written whole again, together with
    /// the removal of the maps merged into it (so that a restart never finds a merged map
    /// without what was merged into it, nor both).
    fn failed(&self, batch: &[Save]) {
        lock(&self.stats).failures += 1;
        let mut rewrite = lock(&self.rewrite);
        for save in batch {
            rewrite
                .entry(save.map)
                .or_default()
                .extend(save.retire.iter().copied());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The format of the records in the store at `path`.
    fn records_format(store: &Store) -> Option<u32> {
        let txn = store.db.begin_read().unwrap();
        let meta = txn.open_table(META).unwrap();
        meta.get("records").unwrap().map(|v| v.value())
    }

    #[test]
    fn a_store_of_format_1_records_is_upgraded_as_it_opens() {
        // Written by format 1's code: the map of `testdata/format1.map` (the slam crate's) as
        // map 3, whose keyframes recorded no `previous`.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("maps.redb");
        let testdata = concat!(env!("CARGO_MANIFEST_DIR"), "/testdata/format1.redb");
        std::fs::copy(testdata, &path).unwrap();
        let file = include_bytes!("../../slam/testdata/format1.map");
        let want = format!("{:?}", vsgraphs_slam::archive::decode(file).unwrap());

        let store = Store::open(&path).unwrap();
        assert_eq!(records_format(&store), Some(FORMAT_VERSION));
        let maps = store.maps().unwrap();
        assert_eq!(maps.len(), 1);
        assert_eq!(maps[0].0, MapId(3));
        assert_eq!(format!("{:?}", maps[0].1), want);
        drop(store);
        // Opened again, the rows are read in today's format: the same map.
        let store = Store::open(&path).unwrap();
        let maps = store.maps().unwrap();
        assert_eq!(format!("{:?}", maps[0].1), want);
    }

    #[test]
    fn a_failed_merge_commit_is_redone_whole_with_its_removal() {
        let state = SaverState::default();
        let save = |map, retire: Vec<MapId>| Save {
            map: MapId(map),
            changes: Changes::default(),
            retire,
        };
        // Map 1 took map 7 in; map 2 only added rows. The commit fails.
        state.failed(&[save(1, vec![MapId(7)]), save(2, vec![])]);
        assert_eq!(state.stats.lock().unwrap().failures, 1);
        let take_rewrite = |map| state.rewrite.lock().unwrap().remove(&MapId(map));
        // Map 1's writer writes it whole and removes map 7 in the same commit; map 2 whole.
        assert_eq!(take_rewrite(1), Some(vec![MapId(7)]));
        assert_eq!(take_rewrite(2), Some(vec![]));
        assert_eq!(take_rewrite(3), None);
    }
}
