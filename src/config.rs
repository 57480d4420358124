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
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawWatch {
    pub dir: PathBuf,
    pub mode: String,
    pub poll_interval_ms: u64,
    pub quiet_period_ms: u64,
    pub rescan_interval_s: u64,
    pub extensions: Vec<String>,
    pub max_pixels: u64,
}

impl Default for RawWatch {
    fn default() -> Self {
        Self {
            dir: PathBuf::from("./inbox"),
            mode: "notify".into(),
            poll_interval_ms: 2000,
            quiet_period_ms: 2000,
            rescan_interval_s: 300,
            extensions: ["jpg", "jpeg", "png", "tif", "tiff", "webp"].map(String::from).to_vec(),
            max_pixels: 100_000_000,
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
            seed: 1,
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
    pub watch_dir: PathBuf,
    pub watch_mode: WatchMode,
    pub rescan_interval: Duration,
    pub quiet_period: Duration,
    /// Lower-case extensions without the dot.
    pub extensions: Vec<String>,
    pub max_pixels: u64,
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
        Ok(Config {
            watch_dir: w.dir,
            watch_mode,
            rescan_interval: Duration::from_secs(w.rescan_interval_s),
            quiet_period: Duration::from_millis(w.quiet_period_ms),
            extensions,
            max_pixels: w.max_pixels,
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
    }
}
