//! How the binaries log: to stderr, so that stdout carries only the data a user pipes
//! (benchmark rows, JSON); colours only on a terminal and never under `NO_COLOR`;
//! dependencies quiet unless `RUST_LOG` (or `IOX2_LOG_LEVEL`) asks for them.

use std::io::IsTerminal;

/// What is logged when `RUST_LOG` is unset. ros2-client warns at every start that
/// `ROS_DISTRO` is unset (it is, outside a sourced ROS workspace, and the wire format does not
/// depend on it); a distribution that does not match still shows, as an error.
pub const DEFAULT_FILTER: &str = "info,rustdds=error,ros2_client=warn,ros2_client::distributions=error";

/// Installs the log for a binary; call once, first.
pub fn init() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| DEFAULT_FILTER.into());
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_target(false)
        .with_writer(std::io::stderr)
        .with_ansi(colour(std::io::stderr().is_terminal(), std::env::var_os("NO_COLOR").as_deref()))
        .init();
    // iceoryx2 logs on its own (a warning at every start that no config file was read).
    #[cfg(feature = "shm")]
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
}

/// Colours on a terminal, unless `NO_COLOR` is set to anything but the empty string
/// (no-color.org).
fn colour(terminal: bool, no_color: Option<&std::ffi::OsStr>) -> bool {
    terminal && no_color.is_none_or(|v| v.is_empty())
}

/// A vector as a user reads it: `[0, -0.012, 26.7]`, rounded to `decimals`, no `-0`.
pub fn vector(v: [f64; 3], decimals: i32) -> String {
    let scale = 10f64.powi(decimals);
    let shown: Vec<String> = v.iter().map(|x| format!("{}", (x * scale).round() / scale + 0.0)).collect();
    format!("[{}]", shown.join(", "))
}

/// An error and its causes on one line, each cause once: a library error that already
/// quotes its source (`organ.vtu: No such file or directory`) does not repeat it.
pub fn error_chain(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(e) = cause {
        let message = e.to_string();
        if !text.contains(&message) {
            text = format!("{text}: {message}");
        }
        cause = e.source();
    }
    text
}

/// Grid dimensions as `nx x ny x nz`.
pub fn dims(d: [usize; 3]) -> String {
    format!("{}x{}x{}", d[0], d[1], d[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_needs_a_terminal_and_no_no_color() {
        use std::ffi::OsStr;
        assert!(colour(true, None));
        assert!(colour(true, Some(OsStr::new(""))));
        assert!(!colour(true, Some(OsStr::new("1"))));
        assert!(!colour(false, None));
    }

    #[test]
    fn an_error_chain_names_each_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "No such file");
        let quoted = crate::io::IoError::Io { path: "organ.vtu".into(), source: io };
        assert_eq!(error_chain(&quoted), "organ.vtu: No such file");
        #[derive(Debug, thiserror::Error)]
        #[error("loading the scene")]
        struct Context(#[source] crate::io::IoError);
        let context = Context(crate::io::IoError::MissingFolder { path: "a/b.nrrd".into(), folder: "a".into() });
        assert_eq!(error_chain(&context), "loading the scene: a/b.nrrd: the folder a does not exist");
    }

    #[test]
    fn vectors_print_rounded_without_negative_zero() {
        assert_eq!(vector([0.0, -0.0004, 26.691_4], 3), "[0, 0, 26.691]");
        assert_eq!(vector([-1.5, 2.0, -0.0], 1), "[-1.5, 2, 0]");
        assert_eq!(dims([20, 12, 9]), "20x12x9");
    }
}
