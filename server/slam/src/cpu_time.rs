//! CPU time, the measure of work that waits for a core do not inflate: what a stage costs on a
//! machine shared by several robots, read from the kernel's per-thread and per-process clocks.

use std::time::Duration;

/// The calling thread's CPU time so far.
pub fn thread() -> Duration {
    read(rustix::time::ClockId::ThreadCPUTime)
}

/// The whole process's CPU time so far: every thread's, living or ended.
pub fn process() -> Duration {
    read(rustix::time::ClockId::ProcessCPUTime)
}

fn read(clock: rustix::time::ClockId) -> Duration {
    let t = rustix::time::clock_gettime(clock);
    Duration::new(
        t.tv_sec.max(0) as u64,
        t.tv_nsec.clamp(0, 999_999_999) as u32,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Work on a second thread shows in the process's clock and not in this thread's.
    #[test]
    fn process_time_counts_other_threads() {
        let (thread_before, process_before) = (thread(), process());
        let spun = std::thread::spawn(|| {
            let started = thread();
            let mut x = 1u64;
            while thread() - started < Duration::from_millis(50) {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            }
            x
        })
        .join()
        .unwrap();
        std::hint::black_box(spun);
        let (thread_spent, process_spent) = (thread() - thread_before, process() - process_before);
        assert!(
            process_spent >= Duration::from_millis(50),
            "{process_spent:?}"
        );
        assert!(thread_spent < Duration::from_millis(50), "{thread_spent:?}");
    }
}
