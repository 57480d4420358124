//! The service's configuration (edge layer): TOML with every key documented in
//! `config/clearview.toml`, parsed into raw serde structs that refuse unknown keys, then
//! [`RawConfig::validate`]d into checked types the daemon can trust.

use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;
use thiserror::Error;

/// Why a configuration was refused. Every variant is the operator's to fix.
#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("{path}: cannot read: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("{key}: {message}")]
    Invalid { key: &'static str, message: String },
}

fn invalid(key: &'static str, message: impl Into<String>) -> ConfigError {
    ConfigError::Invalid { key, message: message.into() }
}

/// The file as written (see `config/clearview.toml` for what each key means).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawConfig {
    pub watch: RawWatch,
    pub output: RawOutput,
    pub state: RawState,
    pub session: RawSession,
    pub compute: RawCompute,
    pub http: RawHttp,
    /// `[nats]`: the NATS JetStream scale-out (`clearview ingest/worker/collect`).
    pub nats: RawNats,
    /// `[[video]]` tables: video stream sources (see [`RawVideo`]).
    pub video: Vec<RawVideo>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawWatch {
    pub enabled: bool,
    pub dir: PathBuf,
    pub mode: String,
    pub poll_interval_ms: u64,
    pub quiet_period_ms: u64,
    pub rescan_interval_s: u64,
    pub extensions: Vec<String>,
    pub max_pixels: u64,
    pub follow_symlinks: bool,
}

impl Default for RawWatch {
    fn default() -> Self {
        Self {
            enabled: true,
            dir: PathBuf::from("./inbox"),
            mode: "notify".into(),
            poll_interval_ms: 2000,
            quiet_period_ms: 2000,
            rescan_interval_s: 300,
            extensions: ["jpg", "jpeg", "png", "tif", "tiff", "webp", "heic", "heif", "avif"]
                .map(String::from)
                .to_vec(),
            max_pixels: 100_000_000,
            follow_symlinks: false,
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawOutput {
    pub dir: PathBuf,
    pub format: String,
    pub jpeg_quality: u8,
    pub history: usize,
}

impl Default for RawOutput {
    fn default() -> Self {
        Self { dir: PathBuf::from("./outbox"), format: "png".into(), jpeg_quality: 92, history: 20 }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawState {
    pub dir: PathBuf,
}

impl Default for RawState {
    fn default() -> Self {
        Self { dir: PathBuf::from("./.clearview") }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawSession {
    pub keyframe: String,
    pub mask: String,
    pub buffer: usize,
    pub min_new_pixels: usize,
    pub witnesses: usize,
    pub batch_max: usize,
    pub margin_px: usize,
    pub auto_mask_views: usize,
    pub seed: u64,
    pub planes: bool,
}

impl Default for RawSession {
    fn default() -> Self {
        let p = crate::session::SessionParams::default();
        Self {
            keyframe: "first".into(),
            mask: "file".into(),
            buffer: p.buffer,
            min_new_pixels: p.min_new_pixels,
            witnesses: p.witnesses,
            batch_max: 8,
            margin_px: p.margin_px,
            auto_mask_views: 2,
            seed: p.seed,
            planes: p.sweep.is_some(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawCompute {
    pub workers: usize,
    pub queue: usize,
    pub decoders: usize,
    pub grace_period_ms: u64,
    pub resident_sessions: usize,
}

impl Default for RawCompute {
    fn default() -> Self {
        Self { workers: 0, queue: 4, decoders: 2, grace_period_ms: 20_000, resident_sessions: 4 }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawHttp {
    pub listen: String,
    pub token: String,
    pub max_body_bytes: usize,
}

impl Default for RawHttp {
    fn default() -> Self {
        Self { listen: String::new(), token: String::new(), max_body_bytes: 16 << 20 }
    }
}

/// `[nats]` as written (see `config/clearview.toml`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawNats {
    pub servers: Vec<String>,
    pub stream: String,
    pub results_stream: String,
    pub consumer: String,
    pub objects: String,
    pub sessions: String,
    pub leases: String,
    pub replicas: usize,
    pub credentials: PathBuf,
    pub tls_ca: PathBuf,
    pub tls_cert: PathBuf,
    pub tls_key: PathBuf,
    pub max_deliver: i64,
    pub ack_wait_ms: u64,
    pub lease_ttl_ms: u64,
    pub duplicate_window_s: u64,
}

impl Default for RawNats {
    fn default() -> Self {
        Self {
            servers: Vec::new(),
            stream: "CLEARVIEW_IN".into(),
            results_stream: "CLEARVIEW_OUT".into(),
            consumer: "clearview-workers".into(),
            objects: "clearview-files".into(),
            sessions: "clearview-sessions".into(),
            leases: "clearview-leases".into(),
            replicas: 1,
            credentials: PathBuf::new(),
            tls_ca: PathBuf::new(),
            tls_cert: PathBuf::new(),
            tls_key: PathBuf::new(),
            max_deliver: 5,
            ack_wait_ms: 30_000,
            lease_ttl_ms: 10_000,
            duplicate_window_s: 600,
        }
    }
}

/// The checked `[nats]` section: where the cluster is and what its streams and buckets are
/// called (see [`crate::daemon::cluster`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NatsConfig {
    /// Server URLs (`nats://host:4222`, `tls://…`); empty until `--nats` gives some.
    pub servers: Vec<String>,
    /// The work-queue stream of files (`clearview.in.<session>`).
    pub stream: String,
    /// The stream of results, events and dead letters (`clearview.out|events|dead.<session>`).
    pub results_stream: String,
    /// The workers' durable pull consumer.
    pub consumer: String,
    /// Object store bucket: files by content digest, results by input digest.
    pub objects: String,
    /// Key-value bucket: each session's listing and state.
    pub sessions: String,
    /// Key-value bucket of session leases (its max age is the lease's time to live).
    pub leases: String,
    /// Replicas of every stream and bucket (3 on a 3-server cluster; 1 on one server).
    pub replicas: usize,
    pub credentials: Option<PathBuf>,
    pub tls_ca: Option<PathBuf>,
    /// Client certificate and key (mutual TLS), both or neither.
    pub tls_client: Option<(PathBuf, PathBuf)>,
    /// Deliveries of a message before it is a poison message (dead-lettered).
    pub max_deliver: i64,
    pub ack_wait: Duration,
    pub lease_ttl: Duration,
    pub duplicate_window: Duration,
}

impl Default for NatsConfig {
    fn default() -> Self {
        RawNats::default().validate().expect("the built-in [nats] section is valid")
    }
}

impl NatsConfig {
    /// Replaces the servers by a comma-separated list (`--nats URLS`).
    pub fn set_servers(&mut self, urls: &str) -> Result<(), ConfigError> {
        self.servers = parse_servers(urls.split(','))?;
        if self.servers.is_empty() {
            return Err(invalid("nats.servers", "--nats names no server"));
        }
        Ok(())
    }
}

fn parse_servers<'a>(urls: impl Iterator<Item = &'a str>) -> Result<Vec<String>, ConfigError> {
    let mut out = Vec::new();
    for u in urls.map(str::trim).filter(|u| !u.is_empty()) {
        let rest = u.split_once("://").map_or(u, |(scheme, rest)| {
            if matches!(scheme, "nats" | "tls" | "ws" | "wss") { rest } else { "" }
        });
        if rest.is_empty() || rest.contains(char::is_whitespace) {
            return Err(invalid("nats.servers", format!("{u:?} is not a server URL (nats://host:4222)")));
        }
        out.push(u.to_owned());
    }
    Ok(out)
}

impl RawNats {
    pub fn validate(self) -> Result<NatsConfig, ConfigError> {
        let servers = parse_servers(self.servers.iter().map(String::as_str))?;
        for (key, name) in [("nats.stream", &self.stream), ("nats.results_stream", &self.results_stream)] {
            if name.is_empty() || name.contains(['.', '*', '>', ' ', '\t', '/', '\\']) {
                return Err(invalid(key, format!("{name:?}: a stream name, without . * > / or spaces")));
            }
        }
        if self.stream == self.results_stream {
            return Err(invalid("nats.results_stream", "must differ from nats.stream"));
        }
        let bucket_ok =
            |b: &str| !b.is_empty() && b.bytes().all(|c| c.is_ascii_alphanumeric() || c == b'-' || c == b'_');
        for (key, name) in [
            ("nats.consumer", &self.consumer),
            ("nats.objects", &self.objects),
            ("nats.sessions", &self.sessions),
            ("nats.leases", &self.leases),
        ] {
            if !bucket_ok(name) {
                return Err(invalid(key, format!("{name:?}: letters, digits, - and _ only")));
            }
        }
        if self.sessions == self.leases {
            return Err(invalid("nats.leases", "must differ from nats.sessions"));
        }
        if !(1..=5).contains(&self.replicas) {
            return Err(invalid("nats.replicas", "must be within 1..=5 (JetStream's limit)"));
        }
        if self.max_deliver < 1 {
            return Err(invalid("nats.max_deliver", "must be at least 1"));
        }
        if self.ack_wait_ms < 1000 {
            return Err(invalid("nats.ack_wait_ms", "must be at least 1000"));
        }
        if self.lease_ttl_ms < 1000 {
            return Err(invalid("nats.lease_ttl_ms", "must be at least 1000"));
        }
        if self.duplicate_window_s == 0 {
            return Err(invalid("nats.duplicate_window_s", "must be at least 1"));
        }
        let path = |p: PathBuf| (!p.as_os_str().is_empty()).then_some(p);
        let tls_client = match (path(self.tls_cert), path(self.tls_key)) {
            (Some(c), Some(k)) => Some((c, k)),
            (None, None) => None,
            _ => return Err(invalid("nats.tls_cert", "tls_cert and tls_key go together")),
        };
        Ok(NatsConfig {
            servers,
            stream: self.stream,
            results_stream: self.results_stream,
            consumer: self.consumer,
            objects: self.objects,
            sessions: self.sessions,
            leases: self.leases,
            replicas: self.replicas,
            credentials: path(self.credentials),
            tls_ca: path(self.tls_ca),
            tls_client,
            max_deliver: self.max_deliver,
            ack_wait: Duration::from_millis(self.ack_wait_ms),
            lease_ttl: Duration::from_millis(self.lease_ttl_ms),
            duplicate_window: Duration::from_secs(self.duplicate_window_s),
        })
    }
}

/// The status API and preview page (`[http]`), when on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HttpConfig {
    pub listen: std::net::SocketAddr,
    /// The access token; `None`: one is generated at start and printed in the page's URL.
    pub token: Option<String>,
    /// Largest request body accepted (a painted mask); larger ones get 413.
    pub max_body_bytes: usize,
}

impl HttpConfig {
    /// Checks a listen address and token: binding beyond the loopback needs a token.
    pub fn new(listen: &str, token: Option<String>, max_body_bytes: usize) -> Result<Self, ConfigError> {
        let listen: std::net::SocketAddr = listen.trim().parse().map_err(|e| {
            invalid("http.listen", format!("{listen:?}: {e} (expected e.g. \"127.0.0.1:8080\")"))
        })?;
        let token = token.filter(|t| !t.is_empty());
        if let Some(t) = &token
            && (t.len() < 16 || !t.bytes().all(|b| b.is_ascii_graphic()))
        {
            return Err(invalid("http.token", "at least 16 printable ASCII characters, no spaces"));
        }
        if !listen.ip().is_loopback() && token.is_none() {
            return Err(invalid(
                "http.token",
                format!(
                    "listening on {listen} (beyond this machine) requires a token (http.token or CLEARVIEW_HTTP_TOKEN)"
                ),
            ));
        }
        if max_body_bytes < 1024 {
            return Err(invalid("http.max_body_bytes", "must be at least 1024"));
        }
        Ok(Self { listen, token, max_body_bytes })
    }
}

/// How new files are noticed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WatchMode {
    /// Kernel notifications (inotify and the like), plus a full scan every
    /// `rescan_interval` as a safety net.
    Notify,
    /// A full scan every `interval`: for network shares, where notifications do not arrive.
    Poll { interval: Duration },
}

/// Result image format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputFormat {
    Png,
    Jpeg { quality: u8 },
}

impl OutputFormat {
    pub fn extension(self) -> &'static str {
        match self {
            Self::Png => "png",
            Self::Jpeg { .. } => "jpg",
        }
    }
}

/// Which image of a session is the keyframe when none is called `key`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum KeyframeRule {
    /// The first image to arrive (by modification time, then name, within a batch).
    First,
    /// The image with this file stem.
    Named(String),
}

/// Where a session's mask comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MaskRule {
    /// `<key stem>.mask.<ext>` or `mask.<ext>` beside the keyframe.
    File,
    /// Computed from the consensus of the first `views` accepted views.
    Auto { views: usize },
}

/// A checked configuration: everything the daemon needs, nothing it must re-check.
#[derive(Debug, Clone)]
pub struct Config {
    /// Whether the folder is watched at all (a video-only service does not need it).
    pub watch_enabled: bool,
    pub watch_dir: PathBuf,
    pub watch_mode: WatchMode,
    pub rescan_interval: Duration,
    pub quiet_period: Duration,
    /// Lower-case extensions without the dot.
    pub extensions: Vec<String>,
    pub max_pixels: u64,
    /// Whether symbolic links in the watched folder are followed (see
    /// [`crate::daemon::paths`]); off, every link is refused and reported.
    pub follow_symlinks: bool,
    pub out_dir: PathBuf,
    pub format: OutputFormat,
    /// Numbered results kept in `history/` (0: none).
    pub history: usize,
    pub state_dir: PathBuf,
    pub keyframe: KeyframeRule,
    pub mask: MaskRule,
    pub session: crate::session::SessionParams,
    /// Views admitted to a session before a fill runs even though more are waiting.
    pub batch_max: NonZeroUsize,
    pub workers: NonZeroUsize,
    /// Jobs each worker's queue holds.
    pub queue: NonZeroUsize,
    pub decoders: NonZeroUsize,
    pub grace_period: Duration,
    /// The HTTP server, `None` when off.
    pub http: Option<HttpConfig>,
    /// Video stream sources, each one session.
    pub videos: Vec<VideoSource>,
    /// The NATS JetStream scale-out (`[nats]`).
    pub nats: NatsConfig,
    /// Sessions each worker keeps in memory; the least recently used idle one beyond this
    /// is put to sleep (saved state, no pixels) and rebuilt from disk when a file arrives.
    pub resident_sessions: NonZeroUsize,
}

impl Default for Config {
    fn default() -> Self {
        RawConfig::default().validate().expect("the built-in configuration is valid")
    }
}

impl Config {
    /// Reads and validates `path`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| ConfigError::Read { path: path.to_owned(), source })?;
        Self::parse(&text, path)
    }

    /// Parses and validates TOML text; `path` only names it in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self, ConfigError> {
        let raw: RawConfig = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_owned(),
            message: e.to_string().trim().to_owned(),
        })?;
        raw.validate()
    }
}

impl RawConfig {
    /// Checks every value and turns it into the types the daemon uses.
    pub fn validate(self) -> Result<Config, ConfigError> {
        let w = self.watch;
        let watch_mode = match w.mode.as_str() {
            "notify" => WatchMode::Notify,
            "poll" => {
                if w.poll_interval_ms < 50 {
                    return Err(invalid("watch.poll_interval_ms", "must be at least 50"));
                }
                WatchMode::Poll { interval: Duration::from_millis(w.poll_interval_ms) }
            }
            other => {
                return Err(invalid("watch.mode", format!("{other:?}: expected \"notify\" or \"poll\"")));
            }
        };
        if w.quiet_period_ms > 3_600_000 {
            return Err(invalid("watch.quiet_period_ms", "more than an hour"));
        }
        if w.rescan_interval_s == 0 {
            return Err(invalid("watch.rescan_interval_s", "must be at least 1"));
        }
        if w.extensions.is_empty() {
            return Err(invalid("watch.extensions", "no extension: nothing would ever be read"));
        }
        let mut extensions = Vec::new();
        for e in &w.extensions {
            let e = e.trim_start_matches('.').to_ascii_lowercase();
            if e.is_empty() || e.contains(['/', '.']) {
                return Err(invalid("watch.extensions", format!("{e:?} is not a file extension")));
            }
            extensions.push(e);
        }
        if w.max_pixels < 64 * 64 {
            return Err(invalid("watch.max_pixels", "must allow at least 64x64 pixels"));
        }
        let o = self.output;
        let format = match o.format.as_str() {
            "png" => OutputFormat::Png,
            "jpg" | "jpeg" => {
                if !(1..=100).contains(&o.jpeg_quality) {
                    return Err(invalid("output.jpeg_quality", "must be within 1..=100"));
                }
                OutputFormat::Jpeg { quality: o.jpeg_quality }
            }
            other => return Err(invalid("output.format", format!("{other:?}: expected \"png\" or \"jpg\""))),
        };
        for (key, dir) in [("watch.dir", &w.dir), ("output.dir", &o.dir), ("state.dir", &self.state.dir)] {
            if dir.as_os_str().is_empty() {
                return Err(invalid(key, "empty path"));
            }
        }
        if o.dir == w.dir || self.state.dir == w.dir {
            return Err(invalid(
                "output.dir",
                "the output and state folders must differ from the watched one",
            ));
        }
        let s = self.session;
        let keyframe = match s.keyframe.trim() {
            "" => return Err(invalid("session.keyframe", "empty")),
            "first" => KeyframeRule::First,
            name if name.contains('/') => {
                return Err(invalid("session.keyframe", "a file stem, not a path"));
            }
            name => KeyframeRule::Named(name.to_owned()),
        };
        let mask = match s.mask.as_str() {
            "file" => MaskRule::File,
            "auto" => {
                if s.auto_mask_views == 0 {
                    return Err(invalid("session.auto_mask_views", "must be at least 1"));
                }
                MaskRule::Auto { views: s.auto_mask_views }
            }
            other => {
                return Err(invalid("session.mask", format!("{other:?}: expected \"file\" or \"auto\"")));
            }
        };
        if !(1..=256).contains(&s.buffer) {
            return Err(invalid("session.buffer", "must be within 1..=256"));
        }
        if s.witnesses == 0 {
            return Err(invalid("session.witnesses", "must be at least 1"));
        }
        let batch_max = NonZeroUsize::new(s.batch_max)
            .ok_or_else(|| invalid("session.batch_max", "must be at least 1"))?;
        let session = crate::session::SessionParams {
            buffer: s.buffer,
            min_new_pixels: s.min_new_pixels,
            witnesses: s.witnesses,
            margin_px: s.margin_px,
            seed: s.seed,
            sweep: s.planes.then(crate::inpaint::parallax::SweepParams::default),
            ..crate::session::SessionParams::default()
        };
        let c = self.compute;
        let workers = match c.workers {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 4),
            n if n > 64 => return Err(invalid("compute.workers", "more than 64")),
            n => n,
        };
        let queue =
            NonZeroUsize::new(c.queue).ok_or_else(|| invalid("compute.queue", "must be at least 1"))?;
        if c.queue > 64 {
            return Err(invalid("compute.queue", "more than 64 decoded images waiting is a memory hazard"));
        }
        let decoders =
            NonZeroUsize::new(c.decoders).ok_or_else(|| invalid("compute.decoders", "must be at least 1"))?;
        let h = self.http;
        let http = if h.listen.trim().is_empty() {
            None
        } else {
            Some(HttpConfig::new(&h.listen, Some(h.token), h.max_body_bytes)?)
        };
        let videos = self.video.into_iter().map(RawVideo::validate).collect::<Result<Vec<_>, _>>()?;
        let nats = self.nats.validate()?;
        Ok(Config {
            watch_enabled: w.enabled,
            watch_dir: w.dir,
            watch_mode,
            rescan_interval: Duration::from_secs(w.rescan_interval_s),
            quiet_period: Duration::from_millis(w.quiet_period_ms),
            extensions,
            max_pixels: w.max_pixels,
            follow_symlinks: w.follow_symlinks,
            out_dir: o.dir,
            format,
            history: o.history,
            state_dir: self.state.dir,
            keyframe,
            mask,
            session,
            batch_max,
            workers: NonZeroUsize::new(workers).expect("clamped to at least 1"),
            queue,
            decoders,
            grace_period: Duration::from_millis(c.grace_period_ms),
            resident_sessions: NonZeroUsize::new(c.resident_sessions)
                .ok_or_else(|| invalid("compute.resident_sessions", "must be at least 1"))?,
            http,
            videos,
            nats,
        })
    }
}

impl Config {
    /// The folders the service reads and writes, by their configuration keys: the watched
    /// one (when a folder is watched), the output and the state folders. They must be
    /// apart (`daemon::paths::check_apart`, which needs the file system).
    pub fn folders(&self) -> Vec<(&'static str, &Path)> {
        let mut v = Vec::with_capacity(3);
        if self.watch_enabled {
            v.push(("watch.dir", self.watch_dir.as_path()));
        }
        v.push(("output.dir", self.out_dir.as_path()));
        v.push(("state.dir", self.state_dir.as_path()));
        v
    }
}

// ---------------------------------------------------------------------------------------
// Video sources (`[[video]]` tables).

/// One `[[video]]` table as written (see `config/clearview.toml`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawVideo {
    pub input: String,
    pub session: String,
    pub keyframe_at_s: Option<f64>,
    pub keyframe_frame: Option<u64>,
    pub mask: String,
    pub auto_mask_views: usize,
    pub live: Option<bool>,
    pub realtime: bool,
    pub min_sharpness: f32,
    pub min_motion: f32,
    pub max_kept_fps: f32,
    pub warmup_frames: usize,
    pub queue: usize,
    pub reconnect_min_ms: u64,
    pub reconnect_max_ms: u64,
    pub ffmpeg: PathBuf,
    pub ffprobe: PathBuf,
}

impl Default for RawVideo {
    fn default() -> Self {
        let s = crate::imaging::sharpness::SelectParams::default();
        Self {
            input: String::new(),
            session: "video".into(),
            keyframe_at_s: None,
            keyframe_frame: None,
            mask: "auto".into(),
            auto_mask_views: 2,
            live: None,
            realtime: false,
            min_sharpness: s.min_sharpness,
            min_motion: s.min_motion,
            max_kept_fps: s.max_kept_fps,
            warmup_frames: s.warmup_frames,
            queue: 4,
            reconnect_min_ms: 500,
            reconnect_max_ms: 30_000,
            ffmpeg: PathBuf::from("ffmpeg"),
            ffprobe: PathBuf::from("ffprobe"),
        }
    }
}

/// Which frame of a video is the keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum VideoKeyframe {
    /// Frame 0, or the next sharp frame when it is blurred.
    First,
    /// The first frame at or after this stream time (seconds), exactly (refused when blurred).
    AtSeconds(f64),
    /// This frame number (0-based), exactly (refused when blurred).
    AtFrame(u64),
}

/// Where a video session's mask comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum VideoMask {
    /// A mask image of the frame's size (white = remove).
    File(PathBuf),
    /// The consensus of the first `views` accepted frames.
    Auto { views: usize },
}

/// A checked video source.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoSource {
    /// Anything FFmpeg opens: a file, `rtsp://`, `http(s)://` (MJPEG, HLS), `/dev/video0`.
    pub input: String,
    /// The session's name: results go to `<output.dir>/<session>/`.
    pub session: String,
    pub keyframe: VideoKeyframe,
    pub mask: VideoMask,
    /// A live stream is reconnected when it drops; a file ends the session.
    pub live: bool,
    /// Frames are read at the stream's pace and dropped when the service is behind (always
    /// so for live streams). Otherwise a file is read as fast as it is processed.
    pub realtime: bool,
    pub select: crate::imaging::sharpness::SelectParams,
    /// Selected frames waiting for alignment at most.
    pub queue: NonZeroUsize,
    pub reconnect_min: Duration,
    pub reconnect_max: Duration,
    pub ffmpeg: PathBuf,
    pub ffprobe: PathBuf,
}

/// Whether FFmpeg input `input` is a live stream (a URL other than `file:`, or a device).
pub fn is_live_input(input: &str) -> bool {
    (input.contains("://") && !input.starts_with("file:")) || input.starts_with("/dev/")
}

impl RawVideo {
    pub fn validate(self) -> Result<VideoSource, ConfigError> {
        if self.input.trim().is_empty() {
            return Err(invalid("video.input", "empty: a file, URL or device FFmpeg can open"));
        }
        let session = self.session.trim().to_owned();
        if session.is_empty()
            || session.contains(['/', '\\'])
            || session.starts_with('.')
            || session.chars().any(char::is_control)
        {
            return Err(invalid("video.session", format!("{session:?} is not a folder name")));
        }
        let keyframe = match (self.keyframe_at_s, self.keyframe_frame) {
            (Some(_), Some(_)) => {
                return Err(invalid("video.keyframe_at_s", "give keyframe_at_s or keyframe_frame, not both"));
            }
            (Some(t), None) if !(t.is_finite() && t >= 0.0) => {
                return Err(invalid("video.keyframe_at_s", "must be a time in seconds, 0 or more"));
            }
            (Some(t), None) => VideoKeyframe::AtSeconds(t),
            (None, Some(n)) => VideoKeyframe::AtFrame(n),
            (None, None) => VideoKeyframe::First,
        };
        let mask = match self.mask.as_str() {
            "" => return Err(invalid("video.mask", "empty: \"auto\" or a mask image")),
            "auto" => {
                if self.auto_mask_views == 0 {
                    return Err(invalid("video.auto_mask_views", "must be at least 1"));
                }
                VideoMask::Auto { views: self.auto_mask_views }
            }
            path => VideoMask::File(PathBuf::from(path)),
        };
        if !(0.0..=1.0).contains(&self.min_sharpness) {
            return Err(invalid("video.min_sharpness", "must be within 0..=1"));
        }
        if !(0.0..=1.0).contains(&self.min_motion) {
            return Err(invalid("video.min_motion", "must be within 0..=1"));
        }
        if !(self.max_kept_fps.is_finite() && self.max_kept_fps >= 0.0) {
            return Err(invalid("video.max_kept_fps", "must be 0 (no cap) or more"));
        }
        let queue =
            NonZeroUsize::new(self.queue).ok_or_else(|| invalid("video.queue", "must be at least 1"))?;
        if self.queue > 64 {
            return Err(invalid("video.queue", "more than 64 frames waiting is a memory hazard"));
        }
        if self.reconnect_min_ms == 0 || self.reconnect_max_ms < self.reconnect_min_ms {
            return Err(invalid("video.reconnect_max_ms", "need 0 < reconnect_min_ms <= reconnect_max_ms"));
        }
        let live = self.live.unwrap_or_else(|| is_live_input(&self.input));
        Ok(VideoSource {
            live,
            realtime: self.realtime || live,
            input: self.input,
            session,
            keyframe,
            mask,
            select: crate::imaging::sharpness::SelectParams {
                min_sharpness: self.min_sharpness,
                min_motion: self.min_motion,
                max_kept_fps: self.max_kept_fps,
                warmup_frames: self.warmup_frames,
                ..Default::default()
            },
            queue,
            reconnect_min: Duration::from_millis(self.reconnect_min_ms),
            reconnect_max: Duration::from_millis(self.reconnect_max_ms),
            ffmpeg: self.ffmpeg,
            ffprobe: self.ffprobe,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Config, ConfigError> {
        Config::parse(text, Path::new("test.toml"))
    }

    #[test]
    fn the_shipped_file_is_valid_and_says_what_the_defaults_say() {
        let text = include_str!("../config/clearview.toml");
        let shipped = parse(text).unwrap();
        let builtin = Config::default();
        assert_eq!(shipped.watch_dir, builtin.watch_dir);
        assert_eq!(shipped.quiet_period, builtin.quiet_period);
        assert_eq!(shipped.session, builtin.session);
        assert_eq!(shipped.format, builtin.format);
        assert_eq!(shipped.keyframe, builtin.keyframe);
        assert_eq!(shipped.follow_symlinks, builtin.follow_symlinks);
    }

    #[test]
    fn symbolic_links_are_not_followed_unless_asked() {
        assert!(!parse("").unwrap().follow_symlinks);
        assert!(parse("[watch]\nfollow_symlinks = true\n").unwrap().follow_symlinks);
        let e = parse("[watch]\nfollow_symlinks = \"yes\"\n").unwrap_err();
        assert!(e.to_string().contains("follow_symlinks"), "{e}");
    }

    #[test]
    fn empty_file_is_the_builtin_default() {
        let c = parse("").unwrap();
        assert_eq!(c.watch_dir, PathBuf::from("./inbox"));
        assert_eq!(c.out_dir, PathBuf::from("./outbox"));
        assert_eq!(c.state_dir, PathBuf::from("./.clearview"));
        assert_eq!(c.keyframe, KeyframeRule::First);
        assert_eq!(c.mask, MaskRule::File);
        assert_eq!(c.session.buffer, 16);
    }

    #[test]
    fn unknown_keys_are_errors() {
        let e = parse("[watch]\ndirectory = \"x\"\n").unwrap_err();
        assert!(e.to_string().contains("directory"), "{e}");
        assert!(parse("colour = 1\n").is_err());
    }

    #[test]
    fn bad_values_name_their_key() {
        for (text, key) in [
            ("[watch]\nmode = \"inotify\"\n", "watch.mode"),
            ("[output]\nformat = \"gif\"\n", "output.format"),
            ("[session]\nbuffer = 0\n", "session.buffer"),
            ("[session]\nmask = \"magic\"\n", "session.mask"),
            ("[compute]\nqueue = 0\n", "compute.queue"),
            ("[output]\ndir = \"./inbox\"\n", "output.dir"),
            ("[http]\nlisten = \"nowhere\"\n", "http.listen"),
            ("[http]\nlisten = \"0.0.0.0:8080\"\n", "http.token"),
            ("[http]\nlisten = \"127.0.0.1:8080\"\ntoken = \"short\"\n", "http.token"),
        ] {
            let e = parse(text).unwrap_err();
            assert!(e.to_string().starts_with(key), "{text}: {e}");
        }
    }

    #[test]
    fn values_become_checked_types() {
        let c = parse(
            "[watch]\nmode = \"poll\"\npoll_interval_ms = 500\nextensions = [\".JPG\"]\n\
             [output]\nformat = \"jpg\"\njpeg_quality = 80\n[session]\nkeyframe = \"IMG_0001\"\nmask = \"auto\"\n",
        )
        .unwrap();
        assert_eq!(c.watch_mode, WatchMode::Poll { interval: Duration::from_millis(500) });
        assert_eq!(c.extensions, vec!["jpg".to_owned()]);
        assert_eq!(c.format, OutputFormat::Jpeg { quality: 80 });
        assert_eq!(c.keyframe, KeyframeRule::Named("IMG_0001".into()));
        assert_eq!(c.mask, MaskRule::Auto { views: 2 });
        assert_eq!(c.http, None);
        let c = parse("[http]\nlisten = \"0.0.0.0:8080\"\ntoken = \"0123456789abcdef\"\n").unwrap();
        let h = c.http.unwrap();
        assert_eq!(h.listen.port(), 8080);
        assert_eq!(h.token.as_deref(), Some("0123456789abcdef"));
    }

    #[test]
    fn video_tables_become_sources() {
        let c = parse(
            "[[video]]\ninput = \"rtsp://cam/stream\"\nsession = \"cam1\"\nkeyframe_at_s = 2.5\n\
             [[video]]\ninput = \"walk.mp4\"\nmask = \"walk.mask.png\"\nkeyframe_frame = 10\nmax_kept_fps = 1\n",
        )
        .unwrap();
        assert_eq!(c.videos.len(), 2);
        let (a, b) = (&c.videos[0], &c.videos[1]);
        assert!(a.live && a.realtime, "a URL is live, and live means realtime");
        assert_eq!(a.keyframe, VideoKeyframe::AtSeconds(2.5));
        assert_eq!(a.mask, VideoMask::Auto { views: 2 });
        assert!(!b.live && !b.realtime);
        assert_eq!(b.keyframe, VideoKeyframe::AtFrame(10));
        assert_eq!(b.mask, VideoMask::File(PathBuf::from("walk.mask.png")));
        assert_eq!(b.select.max_kept_fps, 1.0);
        assert!(is_live_input("/dev/video0") && !is_live_input("file:a.mp4"));
        for (text, key) in [
            ("[[video]]\n", "video.input"),
            ("[[video]]\ninput = \"a\"\nkeyframe_at_s = 1\nkeyframe_frame = 1\n", "video.keyframe_at_s"),
            ("[[video]]\ninput = \"a\"\nsession = \"../x\"\n", "video.session"),
            ("[[video]]\ninput = \"a\"\nsession = \"a\\\\b\"\n", "video.session"),
            ("[[video]]\ninput = \"a\"\nsession = \"a\\nb\"\n", "video.session"),
            ("[[video]]\ninput = \"a\"\nmin_sharpness = 2\n", "video.min_sharpness"),
            ("[[video]]\ninput = \"a\"\nreconnect_min_ms = 0\n", "video.reconnect_max_ms"),
            ("[[video]]\ninput = \"a\"\nframerate = 3\n", "test.toml"),
        ] {
            let e = parse(text).unwrap_err();
            assert!(e.to_string().starts_with(key), "{text}: {e}");
        }
    }
}
