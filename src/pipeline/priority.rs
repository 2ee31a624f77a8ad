//! Thread priorities: a haptic device expects an answer every millisecond, so the force
//! loop's thread, and the DDS threads that carry its poses in and its forces out, run as
//! haptic frameworks run their loops: real-time (`SCHED_FIFO`), where the process may
//! (CAP_SYS_NICE or an rtprio limit), else at a negative nice value, else as they are. The
//! threads that only need throughput (the solver's, the warp and raycast workers', the
//! recorder's) take a positive nice value and ordinary scheduling, which needs no
//! privilege. On two cores, with every stage and the recorder beside it, this is what keeps
//! an answer's p99 under a millisecond (see docs/perf/journal.md#a-core-for-the-force-loop).

/// The force loop's real-time priority (1-99): above ordinary threads, below the kernel's
/// own real-time work.
pub const FORCE_LOOP_RT_PRIORITY: i32 = 10;
/// The force loop's nice value where real-time scheduling is not allowed.
pub const FORCE_LOOP_NICE: i32 = -10;
/// The solver's, the frame workers' and the recorder's.
pub const BACKGROUND_NICE: i32 = 5;

/// How a thread is scheduled: its policy with its real-time priority, and its nice value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Scheduling {
    pub policy: i32,
    pub rt_priority: i32,
    pub nice: i32,
}

/// The calling thread's scheduling (Linux: per thread).
#[cfg(target_os = "linux")]
pub fn current() -> std::io::Result<Scheduling> {
    let mut policy = 0;
    let mut param = libc::sched_param { sched_priority: 0 };
    // SAFETY: pthread_self is always valid for the calling thread, and both out-pointers
    // point at locals that live across the call. errno is cleared first because -1 is a
    // valid nice value.
    let (got, nice) = unsafe {
        let got = libc::pthread_getschedparam(libc::pthread_self(), &mut policy, &mut param);
        *libc::__errno_location() = 0;
        (got, libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t))
    };
    if got != 0 {
        return Err(std::io::Error::from_raw_os_error(got));
    }
    match std::io::Error::last_os_error() {
        e if nice == -1 && e.raw_os_error().is_some_and(|code| code != 0) => Err(e),
        _ => Ok(Scheduling { policy, rt_priority: param.sched_priority, nice }),
    }
}

/// Sets the calling thread's scheduling: its policy first, then its nice value.
#[cfg(target_os = "linux")]
pub fn set(scheduling: Scheduling) -> std::io::Result<()> {
    let param = libc::sched_param { sched_priority: scheduling.rt_priority };
    // SAFETY: pthread_self is valid for the calling thread and `param` outlives the call;
    // setpriority with PRIO_PROCESS and a thread id changes that thread alone.
    let (policy, nice) = unsafe {
        let policy = libc::pthread_setschedparam(libc::pthread_self(), scheduling.policy, &param);
        (policy, libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, scheduling.nice))
    };
    match (policy, nice) {
        (0, 0) => Ok(()),
        (0, _) => Err(std::io::Error::last_os_error()),
        (code, _) => Err(std::io::Error::from_raw_os_error(code)),
    }
}

#[cfg(not(target_os = "linux"))]
pub fn current() -> std::io::Result<Scheduling> {
    Err(std::io::Error::new(std::io::ErrorKind::Unsupported, "thread priorities are read on Linux only"))
}

#[cfg(not(target_os = "linux"))]
pub fn set(_scheduling: Scheduling) -> std::io::Result<()> {
    Err(std::io::Error::new(std::io::ErrorKind::Unsupported, "thread priorities are set on Linux only"))
}

/// Raises the calling thread to the force loop's priority: real-time where allowed, else
/// the nice value. `what` names it in the debug log when neither is.
pub fn into_force_loop(what: &str) {
    let real_time = Scheduling { policy: libc::SCHED_FIFO, rt_priority: FORCE_LOOP_RT_PRIORITY, nice: 0 };
    let raised = Scheduling { policy: libc::SCHED_OTHER, rt_priority: 0, nice: FORCE_LOOP_NICE };
    if set(real_time).is_err() {
        if let Err(e) = set(raised) {
            tracing::debug!("{what} keeps the default priority ({e}); CAP_SYS_NICE would raise it");
        }
    }
}

/// Runs `work` with the calling thread at the force loop's priority, then puts the thread
/// back. The threads `work` starts keep it (a Linux thread begins with its creator's
/// scheduling): the DDS threads that carry poses in and forces out wait on nothing else.
pub fn at_force_loop_priority<R>(what: &str, work: impl FnOnce() -> R) -> R {
    let before = current();
    into_force_loop(what);
    let done = work();
    if let Err(e) = before.and_then(set) {
        tracing::warn!("the thread that ran {what} stays at the force loop's priority: {e}");
    }
    done
}

/// Lowers the calling thread to ordinary scheduling at [`BACKGROUND_NICE`], even when it
/// was started by a real-time one; `what` names it in the debug log if that fails.
pub fn into_background(what: &str) {
    if let Err(e) = set(Scheduling { policy: libc::SCHED_OTHER, rt_priority: 0, nice: BACKGROUND_NICE }) {
        tracing::debug!("{what} keeps the default priority ({e})");
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    // By its full path: `super` would read, to the layer check, as the pipeline's module.
    use crate::pipeline::priority::*;

    /// A thread run at the force loop's priority is put back as it was, whichever of
    /// real-time, a raised nice value or nothing the process was allowed; the threads it
    /// starts meanwhile begin at the raised priority, and a background thread started from
    /// there is ordinary again.
    #[test]
    fn the_force_loop_priority_is_lent_and_given_back() {
        std::thread::spawn(|| {
            let before = current().unwrap();
            let (inside, child, background) = at_force_loop_priority("the test", || {
                let child = std::thread::spawn(|| current().unwrap()).join().unwrap();
                let background = std::thread::spawn(|| {
                    into_background("the test's worker");
                    current().unwrap()
                });
                (current().unwrap(), child, background.join().unwrap())
            });
            assert_eq!(current().unwrap(), before);
            assert_eq!(child, inside, "a thread begins with its creator's scheduling");
            let real_time = inside.policy == libc::SCHED_FIFO && inside.rt_priority == FORCE_LOOP_RT_PRIORITY;
            let raised = inside.policy == before.policy && inside.nice == FORCE_LOOP_NICE;
            assert!(real_time || raised || inside == before, "{inside:?} from {before:?}");
            assert_eq!((background.policy, background.rt_priority), (libc::SCHED_OTHER, 0));
            assert!(background.nice == BACKGROUND_NICE || background.nice == before.nice, "{background:?}");
        })
        .join()
        .unwrap();
    }
}
