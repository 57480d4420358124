//! The command line (edge layer): argument types, and one module per subcommand that
//! reads files, calls the core and prints.

pub mod align;
pub mod check_config;
pub mod cluster;
pub mod demo;
pub mod fill;
pub mod load;
pub mod run;
pub mod save;

use std::path::PathBuf;

use clap::{Parser, Subcommand};

/// Exit codes shared by every subcommand (STYLE.md).
pub mod exit {
    pub const OK: u8 = 0;
    /// A runtime failure: a file could not be read, decoded or written.
    pub const FAILURE: u8 = 1;
    /// The view was rejected (align), or every view was (fill).
    pub const REJECTED: u8 = 3;
    /// Bad usage or configuration.
    pub const USAGE: u8 = 64;
}

#[derive(Debug, Parser)]
#[command(name = "clearview", version, about = "Clears trees, cars and people from photographs of buildings")]
pub struct Cli {
    /// Log as JSON lines instead of human-readable text.
    #[arg(long, global = true)]
    pub log_json: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Estimate the homography that maps KEY's pixels to VIEW's, and say whether to trust it.
    Align(align::AlignArgs),
    /// Clear the keyframe's masked region with what the other views saw there.
    Fill(fill::FillArgs),
    /// Run the capture service: watch a folder of sessions, align each new view and
    /// re-inpaint the keyframe whenever it can improve the result.
    Run(run::RunArgs),
    /// NATS JetStream scale-out: watch a folder and send each complete file to the cluster.
    Ingest(cluster::IngestArgs),
    /// NATS JetStream scale-out: take files from the cluster, one session at a time, and
    /// publish results and events.
    Worker(cluster::WorkerArgs),
    /// NATS JetStream scale-out: write the cluster's results and events to a folder, with
    /// the layout of `clearview run`.
    Collect(cluster::CollectArgs),
    /// Validate a service configuration file: exit 0 when valid, 64 when not.
    CheckConfig(check_config::CheckConfigArgs),
    /// Play a capture session of a rendered facade into the service, running in-process,
    /// and watch the result improve view by view: a tour that needs no files.
    Demo {
        /// The demo's folder (inbox, outbox and state are created inside).
        #[arg(default_value = "clearview-demo")]
        dir: PathBuf,
    },
}
