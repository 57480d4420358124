//! `clearview ingest`, `clearview worker`, `clearview collect`: the NATS JetStream roles
//! (edge layer). Each loads the configuration (its `[nats]` section, `--nats` over it),
//! runs its role until SIGTERM or SIGINT, and exits 0 (64 on bad usage or configuration,
//! 1 when the cluster cannot be reached or set up).

use std::path::PathBuf;

use clap::Args;

use super::exit;
use crate::config::Config;
use crate::daemon::{self, cluster};

/// What every role takes.
#[derive(Debug, Args)]
pub struct NatsArgs {
    /// NATS servers, comma-separated (nats://host:4222,...); replaces `[nats].servers`.
    #[arg(long, value_name = "URLS")]
    pub nats: Option<String>,
    /// Configuration file (TOML, see config/clearview.toml; its `[nats]` section).
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct IngestArgs {
    #[command(flatten)]
    pub nats: NatsArgs,
    /// The folder of sessions to watch (instead of the configuration's).
    #[arg(long)]
    pub watch: Option<PathBuf>,
    /// Local folder of the ingest's own event log (default: the configuration's state
    /// folder, `ingest/` in it).
    #[arg(long)]
    pub state: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct WorkerArgs {
    #[command(flatten)]
    pub nats: NatsArgs,
    /// This worker's name in leases and records (default: host name and process id).
    #[arg(long)]
    pub id: Option<String>,
    /// Scratch folder: copies of the sessions in hand (a cache, emptied at start; default:
    /// the configuration's state folder, `worker-<id>/` in it).
    #[arg(long)]
    pub scratch: Option<PathBuf>,
    /// Serve Prometheus /metrics on ADDR (e.g. 127.0.0.1:9101; port 0 picks one).
    #[arg(long, value_name = "ADDR")]
    pub metrics: Option<std::net::SocketAddr>,
}

#[derive(Debug, Args)]
pub struct CollectArgs {
    #[command(flatten)]
    pub nats: NatsArgs,
    /// Write results and events here (instead of the configuration's output folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// The collector's durable consumer (one per collected folder).
    #[arg(long, default_value = "clearview-collect")]
    pub consumer: String,
    /// Serve the preview page of the collected folder on ADDR (read-only: no mask painting,
    /// no keyframe choice). The token and body limit are `[http]`'s and
    /// CLEARVIEW_HTTP_TOKEN's, as for `clearview run --http`.
    #[arg(long, value_name = "ADDR")]
    pub http: Option<String>,
    /// The collector's own folder: the sessions' snapshots and, with --http, copies of
    /// their keyframes and views (default: the configuration's state folder, `collect/` in it).
    #[arg(long)]
    pub state: Option<PathBuf>,
}

fn load(cmd: &str, args: &NatsArgs) -> Result<Config, u8> {
    let mut config = match &args.config {
        Some(path) => Config::load(path).map_err(|e| {
            eprintln!("clearview {cmd}: {e}");
            exit::USAGE
        })?,
        None => Config::default(),
    };
    if let Some(urls) = &args.nats
        && let Err(e) = config.nats.set_servers(urls)
    {
        eprintln!("clearview {cmd}: {e}");
        return Err(exit::USAGE);
    }
    if config.nats.servers.is_empty() {
        eprintln!("clearview {cmd}: no NATS server: give --nats URL[,URL...] or [nats].servers");
        return Err(exit::USAGE);
    }
    Ok(config)
}

fn block_on(cmd: &str, f: impl std::future::Future<Output = Result<(), cluster::ClusterError>>) -> u8 {
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().worker_threads(2).build() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("clearview {cmd}: cannot start the runtime: {e}");
            return exit::FAILURE;
        }
    };
    let outcome = runtime.block_on(f);
    runtime.shutdown_timeout(std::time::Duration::from_millis(500));
    match outcome {
        Ok(()) => exit::OK,
        Err(e) => {
            tracing::error!(error = %e, "{cmd} failed");
            eprintln!("clearview {cmd}: {e}");
            exit::FAILURE
        }
    }
}

pub fn ingest(args: &IngestArgs) -> u8 {
    let mut config = match load("ingest", &args.nats) {
        Ok(c) => c,
        Err(code) => return code,
    };
    if let Some(d) = &args.watch {
        config.watch_dir = d.clone();
    }
    config.out_dir = args.state.clone().unwrap_or_else(|| config.state_dir.join("ingest"));
    if let Err(e) =
        daemon::paths::check_apart(&[("watch.dir", &config.watch_dir), ("--state", &config.out_dir)])
    {
        eprintln!("clearview ingest: {e}");
        return exit::USAGE;
    }
    block_on("ingest", async move { cluster::ingest::run(config, daemon::shutdown_signal()).await })
}

pub fn worker(args: &WorkerArgs) -> u8 {
    let config = match load("worker", &args.nats) {
        Ok(c) => c,
        Err(code) => return code,
    };
    let id = args.id.clone().unwrap_or_else(|| {
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
        format!("{}-{}", host.trim(), std::process::id())
    });
    if id.is_empty() || id.contains(char::is_whitespace) {
        eprintln!("clearview worker: --id {id:?}: a name without spaces");
        return exit::USAGE;
    }
    let scratch = args.scratch.clone().unwrap_or_else(|| config.state_dir.join(format!("worker-{id}")));
    let opts = cluster::worker::WorkerOptions { id, scratch, metrics: args.metrics };
    block_on("worker", async move { cluster::worker::run(config, opts, daemon::shutdown_signal()).await })
}

pub fn collect(args: &CollectArgs) -> u8 {
    let mut config = match load("collect", &args.nats) {
        Ok(c) => c,
        Err(code) => return code,
    };
    if let Some(d) = &args.out {
        config.out_dir = d.clone();
    }
    // Only `--http` serves the page: a configuration shared with `run` may name its
    // `[http] listen`, which is `run`'s.
    let listen = args.http.as_deref();
    let served = listen.map_or(Ok(()), |l| super::run::http_overrides(&mut config, Some(l)));
    if listen.is_none() {
        config.http = None;
    }
    if let Err(e) = served {
        eprintln!("clearview collect: {e}");
        return exit::USAGE;
    }
    let state = args.state.clone().unwrap_or_else(|| config.state_dir.join("collect"));
    if let Err(e) = daemon::paths::check_apart(&[("--out", &config.out_dir), ("--state", &state)]) {
        eprintln!("clearview collect: {e}");
        return exit::USAGE;
    }
    let opts = cluster::collect::CollectOptions { consumer: args.consumer.clone(), state };
    block_on("collect", async move { cluster::collect::run(config, opts, daemon::shutdown_signal()).await })
}
