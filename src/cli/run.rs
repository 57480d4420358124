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
    #[command(flatten)]
    pub video: VideoArgs,
}

/// A video source from the command line (one `[[video]]` table).
#[derive(Debug, Args)]
pub struct VideoArgs {
    /// Read this video as one session: a file, rtsp://, http(s):// (MJPEG, HLS) or a
    /// device such as /dev/video0 (anything FFmpeg opens). Without --watch or --config no
    /// folder is watched, and for a file the service exits 0 after its final result.
    #[arg(long, value_name = "INPUT")]
    pub video: Option<String>,
    /// The video's mask: an image of the frame's size (white = remove) or `auto`.
    #[arg(long, value_name = "FILE|auto", requires = "video")]
    pub mask: Option<String>,
    /// The keyframe is the first frame at or after this time (seconds), exactly: paint the
    /// mask on it. A blurred one is refused (the session ends with the reason), never
    /// replaced by another. Without this or --keyframe-frame: frame 0, unless it is blurred.
    #[arg(long, value_name = "SECONDS", requires = "video", conflicts_with = "keyframe_frame")]
    pub keyframe_at: Option<f64>,
    /// The keyframe is this frame (from 0), exactly: paint the mask on it. A blurred one is
    /// refused (the session ends with the reason), never replaced by another.
    #[arg(long, value_name = "N", requires = "video")]
    pub keyframe_frame: Option<u64>,
    /// The video's session name (its folder in the output).
    #[arg(long, value_name = "NAME", requires = "video", default_value = "video")]
    pub session: String,
    /// Read a file at its own frame rate, dropping frames when the service is behind.
    #[arg(long, requires = "video")]
    pub realtime: bool,
}

impl VideoArgs {
    /// Adds the video source to `config`; `watch` tells whether a folder is to be watched too.
    fn apply(&self, config: &mut Config, watch: bool) -> Result<(), crate::config::ConfigError> {
        let Some(input) = &self.video else { return Ok(()) };
        let raw = crate::config::RawVideo {
            input: input.clone(),
            session: self.session.clone(),
            keyframe_at_s: self.keyframe_at,
            keyframe_frame: self.keyframe_frame,
            mask: self.mask.clone().unwrap_or_else(|| "auto".into()),
            realtime: self.realtime,
            ..Default::default()
        };
        config.videos.push(raw.validate()?);
        config.watch_enabled = watch;
        Ok(())
    }
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
    let watch = config.watch_enabled && (args.config.is_some() || args.watch.is_some());
    if let Err(e) = args.video.apply(&mut config, watch) {
        eprintln!("clearview run: {e}");
        return exit::USAGE;
    }
    if let Err(e) = http_overrides(&mut config, args.http.as_deref()) {
        eprintln!("clearview run: {e}");
        return exit::USAGE;
    }
    if let Err(e) = daemon::paths::check_apart(&config.folders()) {
        eprintln!("clearview run: {e}");
        return exit::USAGE;
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().worker_threads(2).build() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("clearview run: cannot start the runtime: {e}");
            return exit::FAILURE;
        }
    };
    // The signal handlers are installed inside the runtime, before anything starts.
    let outcome = runtime.block_on(async move { daemon::run(config, daemon::shutdown_signal()).await });
    // The grace period was spent inside `run`: a step still running past it (a worker
    // thread joined from a blocking task) is not waited for again here, as dropping the
    // runtime would; it has been told to stop and can write nothing more.
    runtime.shutdown_timeout(std::time::Duration::from_millis(100));
    match outcome {
        Ok(()) => exit::OK,
        Err(e) => {
            tracing::error!(error = %e, "service failed");
            eprintln!("clearview run: {e}");
            exit::FAILURE
        }
    }
}

/// `--http ADDR` and the `CLEARVIEW_HTTP_TOKEN` variable over the configuration's `[http]`.
pub(super) fn http_overrides(
    config: &mut Config,
    listen: Option<&str>,
) -> Result<(), crate::config::ConfigError> {
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
