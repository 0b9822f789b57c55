//! Background threads of a map's work: a [`Worker`] takes jobs of one kind and returns their
//! results in order, at a priority of its own (a solve whose result is not needed at once can
//! yield the cores to tracking).

use crate::error::TrackError;
use std::sync::mpsc;

/// A thread that does one kind of a map's work in the background (named after the calling
/// thread and `suffix`), one job at a time.
pub struct Worker<J, R> {
    jobs: mpsc::Sender<J>,
    /// What the thread returns, one per job, in order.
    pub results: mpsc::Receiver<R>,
}

impl<J: Send + 'static, R: Send + 'static> Worker<J, R> {
    /// A worker whose thread runs at `nice` (0: the normal priority; more: yields the cores to
    /// threads at the normal priority).
    pub fn spawn(suffix: &str, nice: i32, solve: fn(J) -> R) -> std::io::Result<Self> {
        let (jobs, job_receiver) = mpsc::channel::<J>();
        let (result_sender, results) = mpsc::channel();
        let name = std::thread::current()
            .name()
            .map_or_else(|| format!("map-{suffix}"), |n| format!("{n}-{suffix}"));
        std::thread::Builder::new().name(name).spawn(move || {
            if nice != 0 {
                lower_priority(nice);
            }
            for job in job_receiver {
                if result_sender.send(solve(job)).is_err() {
                    return;
                }
            }
        })?;
        Ok(Self { jobs, results })
    }

    /// Hands `job` to the worker in `slot`, starting one on first use (or after one stopped).
    pub fn submit(
        slot: &mut Option<Self>,
        suffix: &str,
        nice: i32,
        solve: fn(J) -> R,
        job: J,
    ) -> Result<(), TrackError> {
        if slot.is_none() {
            let worker = Self::spawn(suffix, nice, solve).map_err(|_| TrackError::WorkerStopped)?;
            *slot = Some(worker);
        }
        let worker = slot.as_ref().expect("started above");
        if worker.jobs.send(job).is_err() {
            *slot = None;
            return Err(TrackError::WorkerStopped);
        }
        Ok(())
    }
}

/// Lowers the calling thread's priority by `nice` (on Linux a nice value is the thread's own).
/// Where that fails or is not supported the thread runs at the normal priority: the results
/// are the same, only their timing differs.
fn lower_priority(nice: i32) {
    #[cfg(target_os = "linux")]
    if let Err(error) = rustix::process::nice(nice) {
        tracing::debug!(%error, "a worker runs at the normal priority");
    }
    #[cfg(not(target_os = "linux"))]
    let _ = nice;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The calling thread's nice value.
    #[cfg(target_os = "linux")]
    fn own_nice(_: ()) -> i32 {
        rustix::process::getpriority_process(None).expect("a thread may read its priority")
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_background_worker_yields_and_the_caller_keeps_its_priority() {
        let before = own_nice(());
        let mut slot = None;
        Worker::submit(&mut slot, "test", 10, own_nice, ()).unwrap();
        let worker_nice = slot.as_ref().unwrap().results.recv().unwrap();
        assert_eq!(worker_nice, (before + 10).min(19));
        assert_eq!(own_nice(()), before);
        // At the normal priority a worker runs as its caller does.
        let mut normal = None;
        Worker::submit(&mut normal, "test", 0, own_nice, ()).unwrap();
        assert_eq!(normal.as_ref().unwrap().results.recv().unwrap(), before);
    }
}
