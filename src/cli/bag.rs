//! `defvol bag`: work on recorded bags.

use std::path::PathBuf;

use anyhow::Result;

use defvol::record::recover::{recover, FileOutcome};

#[derive(clap::Subcommand)]
pub enum BagCommand {
    /// Rebuild a recording cut short (a crash, `kill -9`, a full disk) up to its last whole
    /// record into a complete MCAP every reader opens; for a bag directory, each cut split,
    /// then its metadata.yaml from the splits. The cut file is kept as `NAME.mcap.cut`.
    Recover {
        /// An MCAP file or a rosbag2 bag directory.
        path: PathBuf,
    },
}

pub fn run(command: BagCommand) -> Result<()> {
    match command {
        BagCommand::Recover { path } => {
            let recovery = recover(&path)?;
            for (file, outcome) in &recovery.files {
                match outcome {
                    FileOutcome::Intact { messages } => {
                        println!("{}: intact, {messages} messages (left as it was)", file.display());
                    }
                    FileOutcome::Rebuilt { messages, kept } => println!(
                        "{}: rebuilt with {messages} messages (the cut original kept as {})",
                        file.display(),
                        kept.display()
                    ),
                }
            }
            if let Some(metadata) = &recovery.metadata {
                println!("{}: regenerated from the splits", metadata.display());
            }
            Ok(())
        }
    }
}
