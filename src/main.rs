//! The `defvol` command line: the commands live in `cli/`.

mod cli;

fn main() -> anyhow::Result<()> {
    defvol::logging::init();
    cli::run(cli::parse())
}
