//! The `defvol` command line: the commands live in `cli/`.

mod cli;

/// Errors print as one line with each cause once (`RUST_LOG=debug` adds the backtrace).
fn main() -> std::process::ExitCode {
    defvol::logging::init();
    match cli::run(cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            tracing::debug!("{e:?}");
            eprintln!("Error: {}", defvol::logging::error_chain(e.as_ref()));
            std::process::ExitCode::FAILURE
        }
    }
}
