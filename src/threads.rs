//! Jobs run side by side, each on a thread with a rayon pool of its own: for work that is
//! itself parallel inside (flex's matrix products and reductions, the grid lookup's plan), cut
//! into as many parts as there are cores. And the process's CPU time, which tells how many
//! cores a piece of work kept busy.
//!
//! Why not `par_iter` over the parts: a part's inner parallel loops then run in the shared pool
//! too, and a part that waits on such a loop sits idle while the other part's thread finishes a
//! chunk it stole, with its own part paused. A training step's render and the parts' backward
//! passes kept 1.3-1.6 of 2 cores busy that way; in pools of their own, 1.8-1.9.

use std::sync::{Arc, Mutex};

/// The one-thread pools handed out so far, the k-th to the k-th job of every call; kept for the
/// process, so a fit's thousands of steps do not build pools again.
static POOLS: Mutex<Vec<Arc<rayon::ThreadPool>>> = Mutex::new(Vec::new());

/// `count` one-thread pools, or none when one could not be built (the jobs then run one after
/// the other).
fn pools(count: usize) -> Option<Vec<Arc<rayon::ThreadPool>>> {
    let mut pools = POOLS.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    while pools.len() < count {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).thread_name(|_| "umbra-part".into()).build().ok()?;
        pools.push(Arc::new(pool));
    }
    Some(pools[..count].to_vec())
}

/// Runs every job at once, each in a one-thread pool of its own (nested rayon loops stay on its
/// thread), and returns their results in the jobs' order. A job's panic is raised again here,
/// as `par_iter` would.
pub fn on_own_threads<T: Send, F: FnOnce() -> T + Send>(jobs: Vec<F>) -> Vec<T> {
    let Some(pools) = (jobs.len() > 1).then(|| pools(jobs.len())).flatten() else {
        return jobs.into_iter().map(|job| job()).collect();
    };
    std::thread::scope(|scope| {
        let running: Vec<_> = jobs.into_iter().zip(pools).map(|(job, pool)| scope.spawn(move || pool.install(job))).collect();
        running.into_iter().map(|job| job.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))).collect()
    })
}

/// The CPU time every thread of the process has spent so far (s), to tell how many cores a part
/// of the work kept busy (its CPU time over its wall time); none where it cannot be read.
pub fn process_cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        let mut now = libc::timespec { tv_sec: 0, tv_nsec: 0 };
        // SAFETY: clock_gettime writes one timespec, which lives on this stack frame.
        let read = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut now) };
        (read == 0).then_some(now.tv_sec as f64 + now.tv_nsec as f64 * 1e-9)
    }
    #[cfg(not(unix))]
    {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jobs_come_back_in_order_each_on_a_pool_of_its_own() {
        let jobs: Vec<_> = (0..3).map(|k| move || (k, rayon::current_num_threads(), std::thread::current().id())).collect();
        let done = on_own_threads(jobs);
        assert_eq!(done.iter().map(|d| d.0).collect::<Vec<_>>(), vec![0, 1, 2]);
        // Each job's inner parallel loops see one thread: its own pool's.
        assert!(done.iter().all(|d| d.1 == 1), "{done:?}");
        // And the jobs ran on different threads.
        assert!(done[0].2 != done[1].2 && done[1].2 != done[2].2 && done[0].2 != done[2].2);
    }

    #[test]
    fn a_jobs_panic_is_raised_to_the_caller() {
        let jobs: Vec<Box<dyn FnOnce() -> usize + Send>> = vec![Box::new(|| 1), Box::new(|| panic!("part failed"))];
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| on_own_threads(jobs)));
        assert!(caught.is_err());
        // The pools still serve the next call.
        assert_eq!(on_own_threads((2..4).map(|k| move || k).collect()), vec![2, 3]);
    }

    #[test]
    fn two_busy_threads_count_twice_their_wall_time() {
        let Some(before) = process_cpu_seconds() else { return };
        let start = std::time::Instant::now();
        let spin = || {
            let until = std::time::Instant::now() + std::time::Duration::from_millis(200);
            let mut x = 0u64;
            while std::time::Instant::now() < until {
                x = std::hint::black_box(x.wrapping_add(1));
            }
            x
        };
        on_own_threads(vec![spin, spin]);
        let (cpu, wall) = (process_cpu_seconds().unwrap_or(before) - before, start.elapsed().as_secs_f64());
        // Each thread spun 0.2 s: at least 0.3 s of CPU (a loaded machine may not run both at
        // once, but the CPU time is still both threads'), and never more than the cores allow.
        assert!(cpu >= 0.3, "{cpu} s of CPU over {wall} s");
        assert!(cpu <= wall * std::thread::available_parallelism().map_or(64, |n| n.get()) as f64 + 0.05, "{cpu} over {wall}");
    }
}
