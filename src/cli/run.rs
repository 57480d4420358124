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
    /// Serve the status API, /metrics and the preview page on ADDR (e.g. 127.0.0.1:8080;
    /// port 0 picks a free one). The URL with its token is printed at start.
    #[arg(long, value_name = "ADDR")]
    pub http: Option<String>,
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
    if let Err(e) = http_overrides(&mut config, args.http.as_deref()) {
        eprintln!("clearview run: {e}");
        return exit::USAGE;
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

/// `--http ADDR` and the `CLEARVIEW_HTTP_TOKEN` variable over the configuration's `[http]`.
fn http_overrides(config: &mut Config, listen: Option<&str>) -> Result<(), crate::config::ConfigError> {
    let env_token = std::env::var("CLEARVIEW_HTTP_TOKEN").ok().filter(|t| !t.is_empty());
    let current = config.http.clone();
    let Some(listen) = listen.map(str::to_owned).or_else(|| current.as_ref().map(|h| h.listen.to_string()))
    else {
        return Ok(());
    };
    let token = env_token.or_else(|| current.as_ref().and_then(|h| h.token.clone()));
    let max_body = current.map_or(crate::config::RawHttp::default().max_body_bytes, |h| h.max_body_bytes);
    config.http = Some(crate::config::HttpConfig::new(&listen, token, max_body)?);
    Ok(())
}
