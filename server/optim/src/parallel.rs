//! Fork–join over a fixed set of jobs on scoped threads.
//!
//! The work is split the same way on every run (by the analysis, not by work stealing), so a
//! solve gives bit-identical results for a given thread count.

/// Runs `f` on every job, the first on the calling thread and the rest on scoped threads, and
/// returns the results in job order. A panic in any job is resumed on the caller.
pub(crate) fn run<J: Send, R: Send>(jobs: Vec<J>, f: impl Fn(J) -> R + Sync) -> Vec<R> {
    let mut jobs = jobs.into_iter();
    let Some(first) = jobs.next() else {
        return Vec::new();
    };
    if jobs.len() == 0 {
        return vec![f(first)];
    }
    std::thread::scope(|scope| {
        let f = &f;
        let handles: Vec<_> = jobs.map(|job| scope.spawn(move || f(job))).collect();
        let mut results = vec![f(first)];
        for handle in handles {
            match handle.join() {
                Ok(r) => results.push(r),
                Err(panic) => std::panic::resume_unwind(panic),
            }
        }
        results
    })
}

/// Splits `slice` into consecutive parts of the given lengths, which must add up to its length.
pub(crate) fn split_lengths<T>(
    mut slice: &mut [T],
    lengths: impl IntoIterator<Item = usize>,
) -> Vec<&mut [T]> {
    let mut parts = Vec::new();
    for len in lengths {
        let (head, tail) = std::mem::take(&mut slice).split_at_mut(len);
        parts.push(head);
        slice = tail;
    }
    debug_assert!(slice.is_empty(), "lengths must cover the slice");
    parts
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_come_back_in_job_order() {
        let out = run((0..5).collect(), |i: i32| i * i);
        assert_eq!(out, vec![0, 1, 4, 9, 16]);
    }

    #[test]
    fn parts_have_the_given_lengths() {
        let mut v: Vec<i32> = (0..6).collect();
        let parts = split_lengths(&mut v, [1, 0, 3, 2]);
        let lens: Vec<usize> = parts.iter().map(|p| p.len()).collect();
        assert_eq!(lens, vec![1, 0, 3, 2]);
        assert_eq!(parts[2], &mut [1, 2, 3][..]);
    }
}
