//! `clearview run`: loads and validates the configuration, applies the command line's
//! overrides, and runs the service until SIGTERM or SIGINT (edge layer).

use std::path::PathBuf;

use clap::Args;

use super::exit;
use crate::config::Config;
use crate::daemon;

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Configuration file (TOML, see config/clearview.toml); without it the built-in
    /// configuration is used (watch ./inbox, write ./outbox, state in ./.clearview).
    #[arg(long, short)]
    pub config: Option<PathBuf>,
    /// Watch this folder instead of the configuration's.
    #[arg(long)]
    pub watch: Option<PathBuf>,
    /// Write results to this folder instead of the configuration's.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Keep state in this folder instead of the configuration's.
    #[arg(long)]
    pub state: Option<PathBuf>,
}

pub fn run(args: &RunArgs) -> u8 {
    let mut config = match &args.config {
        Some(path) => match Config::load(path) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("clearview run: {e}");
                return exit::USAGE;
            }
        },
        None => Config::default(),
    };
    if let Some(d) = &args.watch {
        config.watch_dir = d.clone();
    }
    if let Some(d) = &args.out {
        config.out_dir = d.clone();
    }
    if let Some(d) = &args.state {
        config.state_dir = d.clone();
    }
    if config.out_dir == config.watch_dir || config.state_dir == config.watch_dir {
        eprintln!("clearview run: the output and state folders must differ from the watched one");
        return exit::USAGE;
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().worker_threads(2).build() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("clearview run: cannot start the runtime: {e}");
            return exit::FAILURE;
        }
    };
    match runtime.block_on(daemon::run(config, daemon::shutdown_signal())) {
        Ok(()) => exit::OK,
        Err(e) => {
            tracing::error!(error = %e, "service failed");
            eprintln!("clearview run: {e}");
            exit::FAILURE
        }
    }
}
