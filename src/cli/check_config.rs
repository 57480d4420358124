//! `clearview check-config [FILE]`: validates a service configuration without starting
//! anything, for operators and for systemd's `ExecStartPre` (edge layer).

use std::path::PathBuf;

use clap::Args;

use super::exit;
use crate::config::Config;

#[derive(Debug, Args)]
pub struct CheckConfigArgs {
    /// The configuration file (default: the built-in configuration, which is always valid).
    pub file: Option<PathBuf>,
}

pub fn run(args: &CheckConfigArgs) -> u8 {
    let Some(path) = &args.file else {
        println!("built-in configuration: valid");
        return exit::OK;
    };
    let checked = Config::load(path).map_err(|e| e.to_string()).and_then(|c| {
        crate::daemon::paths::check_apart(&c.folders()).map_err(|e| e.to_string())?;
        Ok(c)
    });
    match checked {
        Ok(c) => {
            println!(
                "{}: valid (watch {}, out {}, state {})",
                path.display(),
                c.watch_dir.display(),
                c.out_dir.display(),
                c.state_dir.display()
            );
            exit::OK
        }
        Err(e) => {
            eprintln!("clearview check-config: {e}");
            exit::USAGE
        }
    }
}
