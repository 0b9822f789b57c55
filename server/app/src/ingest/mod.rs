//! Ingest: zenoh subscriptions for frames and robot presence, one bounded queue and one worker
//! thread per robot.
//!
//! The zenoh callbacks only look up the robot and enqueue bytes, so a slow or hostile robot can
//! never stall zenoh's threads or another robot. Workers decode and detect (see `pipeline`).
//! ROS 2 robots' topics ([`ros`]) become frames on a thread of their own and join the same
//! queues.

mod pairing;
pub mod ros;

use crate::config::Config;
use crate::queue::{Arrival, Pushed};
use crate::robots::{now_ns, ProcessingTimes, Registry, RobotEntry};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::Ordering;
use std::sync::{mpsc, Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;
use vsgraphs_pipeline::MapService;
use vsgraphs_pipeline::{FrameHeader, FrameProcessor};
use vsgraphs_proto::api::{self, FrameDetections, Presence};
use vsgraphs_proto::keys;
use zenoh::sample::SampleKind;

/// The running ingest: subscriptions, worker threads, and the thread that forgets robots that
/// left.
pub struct Ingest {
    _frames: zenoh::pubsub::Subscriber<()>,
    _presence: zenoh::pubsub::Subscriber<()>,
    ros: Option<ros::RosIngest>,
    workers: Arc<Workers>,
    sweeper: Option<(mpsc::Sender<()>, JoinHandle<()>)>,
}

struct Workers {
    registry: Arc<Registry>,
    config: Arc<Config>,
    maps: MapService,
    /// Each worker with the entry it serves (an id that comes back is a new entry).
    handles: Mutex<Vec<(Arc<RobotEntry>, JoinHandle<()>)>>,
}

impl Workers {
    /// The robot's entry, with its worker started when it is new.
    fn robot(self: &Arc<Self>, robot_id: &str) -> Option<Arc<RobotEntry>> {
        if keys::validate_robot_id(robot_id).is_err() {
            return None;
        }
        let (entry, created) = self.registry.get_or_insert(robot_id).ok()?;
        if created {
            let worker_entry = entry.clone();
            let config = self.config.clone();
            let maps = self.maps.clone();
            let spawned = std::thread::Builder::new()
                .name(format!("robot-{robot_id}"))
                .spawn(move || run_worker(worker_entry, &config, maps));
            match spawned {
                Ok(handle) => self
                    .handles
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .push((entry.clone(), handle)),
                Err(e) => {
                    tracing::error!(robot_id, error = %e, "cannot start the robot's worker thread")
                }
            }
        }
        Some(entry)
    }

    /// Queues a frame's bytes for `robot`, unless it is over its rate; a full queue drops one.
    fn enqueue(&self, robot: &RobotEntry, bytes: Vec<u8>) {
        robot.record_arrival();
        if !robot.admit(std::time::Instant::now()) {
            return;
        }
        let arrival = Arrival {
            bytes,
            received_ns: now_ns(),
            dropped_before: 0,
        };
        if robot.queue.push(arrival) == Pushed::DroppedOne {
            robot.record_dropped();
        }
    }

    /// Forgets the robots idle for longer than the configuration allows and waits for their
    /// workers to finish what was queued.
    fn forget_idle(&self) {
        let after_ns = (self.config.ingest.forget_after_s * 1e9) as u64;
        let forgotten = self.registry.forget_idle(now_ns(), after_ns);
        if forgotten.is_empty() {
            return;
        }
        let finished: Vec<JoinHandle<()>> = {
            let mut handles = self.handles.lock().unwrap_or_else(|p| p.into_inner());
            let (gone, kept) = std::mem::take(&mut *handles)
                .into_iter()
                .partition(|(entry, _)| forgotten.iter().any(|f| Arc::ptr_eq(f, entry)));
            *handles = kept;
            gone.into_iter().map(|(_, handle)| handle).collect()
        };
        for handle in finished {
            let _ = handle.join();
        }
        for robot in forgotten {
            tracing::info!(
                robot_id = robot.robot_id,
                idle_s = self.config.ingest.forget_after_s,
                "robot forgotten: neither online nor heard from; its maps stay"
            );
        }
    }
}

/// How often the sweeper looks for robots to forget: a tenth of the idle time allowed, at
/// most every 10 s, so a robot is forgotten at most 10 % late.
fn sweep_period(forget_after_s: f64) -> Duration {
    Duration::from_secs_f64((forget_after_s / 10.0).clamp(0.05, 10.0))
}

impl Ingest {
    /// Subscribes to every robot's frames and liveliness on `session`; robots' maps go to
    /// `maps`.
    pub async fn start(
        session: &zenoh::Session,
        registry: Arc<Registry>,
        config: Arc<Config>,
        maps: MapService,
    ) -> zenoh::Result<Self> {
        let workers = Arc::new(Workers {
            registry: registry.clone(),
            config,
            maps,
            handles: Mutex::new(Vec::new()),
        });
        let frame_workers = workers.clone();
        let frames = session
            .declare_subscriber(keys::ALL_FRAMES)
            .callback(move |sample| {
                let robot = keys::robot_id_of(sample.key_expr().as_str())
                    .and_then(|id| frame_workers.robot(id));
                let Some(robot) = robot else {
                    frame_workers
                        .registry
                        .frames_on_bad_keys
                        .fetch_add(1, Ordering::Relaxed);
                    return;
                };
                frame_workers.enqueue(&robot, sample.payload().to_bytes().into_owned());
            })
            .await?;
        let presence_workers = workers.clone();
        let presence = session
            .liveliness()
            .declare_subscriber(keys::ALL_ALIVE)
            .history(true)
            .callback(move |sample| {
                let key = sample.key_expr().as_str();
                let Some(robot) = keys::robot_id_of(key).and_then(|id| presence_workers.robot(id))
                else {
                    tracing::warn!(key, "liveliness token with an unusable robot id");
                    return;
                };
                let presence = match sample.kind() {
                    SampleKind::Put => Presence::Online,
                    SampleKind::Delete => Presence::Offline,
                };
                tracing::info!(robot_id = robot.robot_id, ?presence, "presence changed");
                robot.set_presence(presence);
            })
            .await?;
        let ros = ros::RosIngest::start(session, &workers, &workers.config.ros.robots).await?;
        let (stop, stopped) = mpsc::channel::<()>();
        let sweeping = workers.clone();
        let period = sweep_period(workers.config.ingest.forget_after_s);
        let sweeper = std::thread::Builder::new()
            .name("robot-sweeper".into())
            .spawn(move || {
                while let Err(mpsc::RecvTimeoutError::Timeout) = stopped.recv_timeout(period) {
                    sweeping.forget_idle();
                }
            })
            .map_err(|e| format!("cannot start the robot sweeper: {e}"))?;
        Ok(Self {
            _frames: frames,
            _presence: presence,
            ros: Some(ros),
            workers,
            sweeper: Some((stop, sweeper)),
        })
    }

    /// Stops accepting frames, lets workers finish what is queued, and joins them.
    pub fn stop(mut self) {
        // ROS robots' threads hand their last frames to the queues before those close.
        if let Some(ros) = self.ros.take() {
            ros.stop();
        }
        if let Some((stop, sweeper)) = self.sweeper.take() {
            drop(stop);
            let _ = sweeper.join();
        }
        for robot in self.workers.registry.all() {
            robot.queue.close();
        }
        let handles = std::mem::take(
            &mut *self
                .workers
                .handles
                .lock()
                .unwrap_or_else(|p| p.into_inner()),
        );
        for (_, handle) in handles {
            let _ = handle.join();
        }
    }
}

/// Per-robot bookkeeping of the worker: the last accepted frame and frames with no readable
/// sequence number since, to tell losses in transit from frames accounted for here.
#[derive(Default)]
struct Continuity {
    previous: Option<FrameHeader>,
    unsequenced_since: u64,
    dropped_since: u64,
}

impl Continuity {
    /// Accounts for a frame with a readable sequence number (of the previous frame's session
    /// when `session_id` is None) and returns how many frames before it never arrived.
    fn advance(&mut self, session_id: Option<&str>, sequence: u64) -> u64 {
        let Some(previous) = self.previous.as_mut() else {
            return 0;
        };
        let same_session = session_id.is_none_or(|s| s == previous.session_id);
        if !same_session || sequence <= previous.sequence {
            return 0;
        }
        let lost = (sequence - previous.sequence - 1)
            .saturating_sub(self.dropped_since + self.unsequenced_since);
        previous.sequence = sequence;
        self.dropped_since = 0;
        self.unsequenced_since = 0;
        lost
    }
}

fn run_worker(robot: Arc<RobotEntry>, config: &Config, maps: MapService) {
    let span = tracing::info_span!("robot", robot_id = robot.robot_id);
    let _entered = span.enter();
    let new_processor = || {
        FrameProcessor::new(
            &config.markers,
            &config.tracking,
            config.ingest.max_frame_bytes,
            maps.clone(),
        )
    };
    let mut processor = match new_processor() {
        Ok(processor) => processor,
        Err(e) => {
            // The configuration was checked at start-up, so this is not expected; say so loudly.
            tracing::error!(error = %e, "cannot set up frame processing; this robot's frames are dropped");
            return;
        }
    };
    let mut continuity = Continuity::default();
    loop {
        let Some(arrival) = robot.queue.pop(Duration::from_millis(250)) else {
            if robot.queue.is_closed() {
                break;
            }
            continue;
        };
        continuity.dropped_since += arrival.dropped_before;
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            processor.process(
                &robot.robot_id,
                &arrival.bytes,
                continuity.previous.as_ref(),
            )
        }));
        match outcome {
            Ok(Ok(processed)) => {
                let lost = continuity.advance(Some(&processed.session_id), processed.sequence);
                if lost > 0 {
                    tracing::warn!(
                        lost,
                        sequence = processed.sequence,
                        "frames lost in transit"
                    );
                    robot.record_lost(lost);
                }
                robot.record_session(&processed.session_id);
                continuity.previous = Some(FrameHeader {
                    session_id: processed.session_id.clone(),
                    sequence: processed.sequence,
                    timestamp_ns: processed.timestamp_ns,
                    accepted: Some(std::time::Instant::now()),
                });
                continuity.dropped_since = 0;
                continuity.unsequenced_since = 0;
                if let Some(tracking) = &processed.tracking {
                    if let Some(event) = tracking.result.as_ref().and_then(|r| r.event.as_ref()) {
                        tracing::info!(event, "tracking");
                    }
                    robot.record_tracking(processed.timestamp_ns, tracking);
                }
                robot.record_processed(
                    FrameDetections {
                        robot_id: robot.robot_id.clone(),
                        session_id: processed.session_id,
                        sequence: processed.sequence,
                        timestamp_ns: processed.timestamp_ns,
                        image_width: processed.image_width,
                        image_height: processed.image_height,
                        markers: processed.markers,
                    },
                    ProcessingTimes {
                        total: processed.processing,
                        decode: processed.decode,
                        detection: processed.detection,
                    },
                );
            }
            Ok(Err(rejection)) => {
                tracing::debug!(
                    reason = rejection.reason.code(),
                    message = rejection.message,
                    "frame rejected"
                );
                // A rejected frame with a sequence number still fills its place in the sequence.
                match rejection.sequence {
                    Some(sequence) => robot.record_lost(continuity.advance(None, sequence)),
                    None => continuity.unsequenced_since += 1,
                }
                robot.record_rejection(api::Rejection {
                    reason: rejection.reason.code().into(),
                    message: rejection.message,
                    sequence: rejection.sequence,
                    at_ns: now_ns(),
                });
            }
            Err(panic) => {
                let message = panic
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| panic.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into());
                tracing::error!(
                    message,
                    "frame processing panicked; frame rejected, and the robot's tracker starts \
                     afresh (it relocalises in the maps)"
                );
                // The panic may have left the tracker half-updated; a new one knows only the
                // maps, which their writers keep.
                match new_processor() {
                    Ok(fresh) => processor = fresh,
                    Err(e) => tracing::error!(error = %e, "cannot set up frame processing again"),
                }
                continuity.unsequenced_since += 1;
                robot.record_rejection(api::Rejection {
                    reason: "internal".into(),
                    message: format!("internal error while processing: {message}"),
                    sequence: None,
                    at_ns: now_ns(),
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(session: &str, sequence: u64) -> Option<FrameHeader> {
        Some(FrameHeader {
            session_id: session.into(),
            sequence,
            timestamp_ns: 1,
            accepted: None,
        })
    }

    #[test]
    fn gaps_not_explained_by_drops_are_lost() {
        let mut c = Continuity {
            previous: header("s", 10),
            ..Default::default()
        };
        assert_eq!(c.advance(Some("s"), 11), 0);
        c.dropped_since = 2;
        assert_eq!(c.advance(Some("s"), 15), 1);
        c.unsequenced_since = 1;
        assert_eq!(c.advance(None, 17), 0);
        // A new session restarts the count; an old sequence number is ignored.
        assert_eq!(c.advance(Some("t"), 5), 0);
        assert_eq!(c.advance(Some("s"), 3), 0);
        assert_eq!(Continuity::default().advance(Some("s"), 100), 0);
    }
}
