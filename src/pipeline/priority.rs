//! Thread priorities: a haptic device expects an answer every millisecond, so the force
//! loop's thread asks for more than the rest (a negative nice value, which needs
//! CAP_SYS_NICE) and the threads that only need throughput (the solver's, the warp and
//! raycast workers', the recorder's) take less (a positive one, which needs no privilege).
//! On two cores this is what keeps an answer's p99 under a millisecond while they all run.

/// The force loop's nice value.
pub const FORCE_LOOP_NICE: i32 = -10;
/// The solver's, the frame workers' and the recorder's.
pub const BACKGROUND_NICE: i32 = 5;

/// Sets the calling thread's nice value (Linux: per thread).
#[cfg(target_os = "linux")]
pub fn set_thread_nice(nice: i32) -> std::io::Result<()> {
    // SAFETY: gettid has no preconditions; setpriority with PRIO_PROCESS and a thread id
    // changes that thread alone and touches no memory of ours.
    let done = unsafe { libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, nice) };
    match done {
        0 => Ok(()),
        _ => Err(std::io::Error::last_os_error()),
    }
}

#[cfg(not(target_os = "linux"))]
pub fn set_thread_nice(_nice: i32) -> std::io::Result<()> {
    Err(std::io::Error::new(std::io::ErrorKind::Unsupported, "thread priorities are set on Linux only"))
}

/// Lowers the calling thread to [`BACKGROUND_NICE`]; `what` names it in the debug log if
/// that fails.
pub fn into_background(what: &str) {
    if let Err(e) = set_thread_nice(BACKGROUND_NICE) {
        tracing::debug!("{what} keeps the default priority ({e})");
    }
}
