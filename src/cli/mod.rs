//! The `defvol` subcommands: their arguments, the mapping onto the library's types
//! (`choices.rs`), and their bodies, one file each.

#[cfg(feature = "mcap")]
mod bag;
mod bench;
mod bench_report;
mod checks;
mod choices;
mod demo;
mod dpcm;
mod info;
mod render;
#[cfg(feature = "mcap")]
mod replay;
mod simulate;
mod warp;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "defvol",
    version,
    about = "Deformable volumes: implicit mass-spring meshes, grid warps, DPCM surfaces and raycast images on the GPU and the CPU"
)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a mesh for N steps with a scripted tool; write the final mesh and a per-step CSV.
    Simulate(simulate::SimulateArgs),
    /// Warp a volume through a deformed mesh and/or displacement volumes; with no files,
    /// the phantom through a generated bend and press.
    Warp(warp::WarpArgs),
    /// Run a DPCM surface (phyxels engraved by markers) and write its renderings.
    Dpcm(dpcm::DpcmArgs),
    /// A raycast image of a volume (the phantom when no file is given).
    Render(render::RenderArgs),
    /// What a volume or mesh file holds: geometry, values, DICOM series; mesh quality.
    Info(info::InfoArgs),
    /// The node's pipeline on a scene with its scripted tool path, no DDS: writes
    /// DIR/demo.mcap (a rosbag2 MCAP) and DIR/demo.rrd (a rerun log).
    Demo(demo::DemoArgs),
    /// Run the pipeline from the tool poses and wrenches of a recorded bag.
    #[cfg(feature = "mcap")]
    Replay(replay::ReplayArgs),
    /// Work on recorded bags: `defvol bag recover PATH` rebuilds one cut short.
    #[cfg(feature = "mcap")]
    Bag {
        #[command(subcommand)]
        command: bag::BagCommand,
    },
    /// The ROS 2 node (as `defvol_node`): `defvol node [--record F.mcap] --ros-args -p …`.
    #[cfg(feature = "ros")]
    #[command(disable_help_flag = true)]
    Node {
        /// The node's options and its ROS arguments, as `defvol_node` takes them.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Measure a stage: run time against error.
    Bench {
        #[command(subcommand)]
        stage: bench::BenchStage,
    },
}

/// The command line, parsed: negative numbers are values everywhere (`--dt -0.01`,
/// `--background -1000`), not flags; a choice may be spelt as the scene files spell it
/// (`implicit_euler`, `red_blue`) or as the flags list it (`implicit-euler`, `red-blue`).
pub fn parse() -> Cli {
    use clap::{CommandFactory, FromArgMatches};
    fn negatives(command: clap::Command) -> clap::Command {
        command.allow_negative_numbers(true).mut_subcommands(negatives)
    }
    let command = negatives(Cli::command());
    let args = kebab_choices(&command, std::env::args_os().collect());
    let matches = command.get_matches_from(args);
    Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit())
}

/// `--flag snake_value` (or `--flag=a_b,c_d`) rewritten with dashes where that spelling is
/// one of the flag's listed choices.
fn kebab_choices(command: &clap::Command, args: Vec<std::ffi::OsString>) -> Vec<std::ffi::OsString> {
    let mut at = command;
    let mut out = Vec::with_capacity(args.len());
    let mut choices: Vec<String> = Vec::new();
    let fix = |value: &str, choices: &[String]| {
        let items: Vec<String> = value
            .split(',')
            .map(|v| match v.replace('_', "-") {
                kebab if choices.contains(&kebab) => kebab,
                _ => v.to_owned(),
            })
            .collect();
        items.join(",")
    };
    let listed = |arg: &clap::Arg| arg.get_possible_values().iter().map(|v| v.get_name().to_owned()).collect();
    for arg in args {
        let Some(text) = arg.to_str() else {
            out.push(arg);
            choices.clear();
            continue;
        };
        if !choices.is_empty() && !text.starts_with("--") {
            out.push(fix(text, &choices).into());
        } else if let Some((flag, value)) = text.strip_prefix("--").and_then(|t| t.split_once('=')) {
            let known: Vec<String> = at.get_arguments().find(|a| a.get_long() == Some(flag)).map_or(Vec::new(), listed);
            out.push(format!("--{flag}={}", fix(value, &known)).into());
        } else {
            out.push(arg.clone());
        }
        choices = match text.strip_prefix("--") {
            Some(flag) => at.get_arguments().find(|a| a.get_long() == Some(flag)).map_or(Vec::new(), listed),
            None => Vec::new(),
        };
        if let Some(sub) = at.find_subcommand(text) {
            at = sub;
        }
    }
    out
}

pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Simulate(args) => simulate::run(args),
        Command::Warp(args) => warp::run(args),
        Command::Dpcm(args) => dpcm::run(args),
        Command::Render(args) => render::run(args),
        Command::Info(args) => info::run(args),
        Command::Demo(args) => demo::run(args),
        #[cfg(feature = "mcap")]
        Command::Replay(args) => replay::run(args),
        #[cfg(feature = "mcap")]
        Command::Bag { command } => bag::run(command),
        #[cfg(feature = "ros")]
        Command::Node { args } => Ok(defvol::ros::node::run_from_args(&args)?),
        Command::Bench { stage } => bench::run(stage),
    }
}
