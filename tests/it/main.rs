//! The integration tests, one binary so that a change links once: each module is one area,
//! and `cargo test --test it <module>::` (or `cargo nextest run -E 'test(/^<module>::/)'`)
//! runs that area alone. The tests that need process-wide state are safe side by side:
//! the fuzzers keep their panics on their own threads, and the DDS tests re-run themselves
//! in their own process inside a private network namespace.

mod bench_report;
mod cli;
mod dicom;
mod dpcm;
mod dpcm_markers;
mod file_interop;
mod fuzz_loaders;
mod haptic;
mod layers;
mod mixed_cells;
#[cfg(feature = "ros")]
mod node_dds;
#[cfg(all(feature = "ros", feature = "mcap", feature = "shm"))]
mod readme;
mod render;
mod scenes;
#[cfg(feature = "mcap")]
mod session;
#[cfg(feature = "shm")]
mod shm_interop;
mod solver;
mod tool_contact;
mod warp;

/// Runs the test `name` (its path in this binary) again with /dev/shm a 1 MiB tmpfs, in a
/// private mount namespace (`unshare --mount`, mapping root where the user is not), through
/// `wrapper` (tests/netns-run, say) when given. False when already there: run the body.
#[cfg(any(feature = "shm", feature = "ros"))]
pub(crate) fn rerun_under_tiny_dev_shm(name: &str, wrapper: Option<&std::path::Path>) -> bool {
    const INSIDE: &str = "DEFVOL_TEST_IN_TINY_SHM";
    if std::env::var_os(INSIDE).is_some() {
        return false;
    }
    let mount = "mount -t tmpfs -o size=1m defvol-test-shm /dev/shm && exec \"$0\" \"$@\"";
    let mut command = std::process::Command::new("unshare");
    // /proc/self belongs to the process's effective user.
    if std::os::unix::fs::MetadataExt::uid(&std::fs::metadata("/proc/self").unwrap()) != 0 {
        command.arg("--map-root-user");
    }
    command.args(["--mount", "--", "sh", "-c", mount]);
    if let Some(wrapper) = wrapper {
        command.arg(wrapper);
    }
    let out = command
        .arg(std::env::current_exe().unwrap())
        .args(["--exact", name, "--nocapture", "--test-threads", "1"])
        .env(INSIDE, "1")
        .env("DEFVOL_NETNS_RERUN", "1")
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success() && text.contains("1 passed"), "{name} under a 1 MiB /dev/shm:\n{text}");
    true
}
