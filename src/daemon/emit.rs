//! The sinks (shell layer): result images, their history and `result.json` per session,
//! and the event log `events.jsonl`; every file written atomically.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, RwLock};
use std::time::SystemTime;

use thiserror::Error;

use super::DaemonError;
use super::event::Event;
use crate::config::{Config, OutputFormat};
use crate::fsio::{atomic_write, atomic_write_linked};
use crate::imaging::RgbF32;
use crate::imaging::encode::{EncodeOptions, Format, OutputSpace, encode};
use crate::imaging::meta::{Metadata, Provenance};

/// Removes temporaries a killed process left behind in `dir` and its sub-folders (two
/// levels: sessions and their history).
pub fn remove_stale_temporaries(dir: &Path) {
    fn walk(dir: &Path, depth: usize) {
        let Ok(entries) = std::fs::read_dir(dir) else { return };
        for e in entries.flatten() {
            let path = e.path();
            if e.file_type().is_ok_and(|t| t.is_dir()) {
                if depth > 0 {
                    walk(&path, depth - 1);
                }
            } else if e.file_name().to_string_lossy().contains(crate::fsio::TMP_MARK) {
                tracing::info!(file = %path.display(), "removing a temporary file left by an interrupted run");
                let _ = std::fs::remove_file(&path);
            }
        }
    }
    walk(dir, 2);
}

/// `2026-11-22T13:40:05.123Z` from a system time (UTC; civil-from-days, no time zone).
pub fn rfc3339(t: SystemTime) -> String {
    let d = t.duration_since(SystemTime::UNIX_EPOCH).unwrap_or_default();
    let secs = d.as_secs() as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60,
        d.subsec_millis()
    )
}

/// A result file that could not be written: which one, and the system's reason. The file
/// already there is untouched.
#[derive(Debug, Error)]
#[error("{}: {source}", path.display())]
pub struct WriteError {
    pub path: PathBuf,
    pub source: std::io::Error,
}

fn at(path: &Path) -> impl FnOnce(std::io::Error) -> WriteError + '_ {
    move |source| WriteError { path: path.to_owned(), source }
}

/// The maps a result may have beside it, written with it (see [`Emitter::write_result`]).
pub const MAPS: [&str; 3] = ["confidence.png", "surfaces.png", "provenance.png"];

/// Checks that a session's `result.json` describes the image beside it, and every map it
/// names (the size and digest it records for each); returns the result's number. They
/// are replaced one after the other, so a crash between two renames can leave them
/// disagreeing: the service then writes them all again rather than trust any.
pub fn check_result(dir: &Path) -> Result<u64, String> {
    let json = std::fs::read(dir.join("result.json")).map_err(|e| format!("result.json: {e}"))?;
    let report: serde_json::Value =
        serde_json::from_slice(&json).map_err(|e| format!("result.json does not parse: {e}"))?;
    let number = report["number"].as_u64().ok_or("result.json has no number")?;
    let image = &report["image"];
    let (Some(file), Some(size), Some(digest)) =
        (image["file"].as_str(), image["bytes"].as_u64(), image["fnv64"].as_str())
    else {
        return Err("result.json does not describe its image".into());
    };
    if file.contains(['/', '\\']) || file.starts_with('.') {
        return Err(format!("result.json names an odd image file {file:?}"));
    }
    let bytes = std::fs::read(dir.join(file)).map_err(|e| format!("{file}: {e}"))?;
    if bytes.len() as u64 != size || fnv64_hex(&bytes) != digest {
        return Err(format!("{file} is not the image result.json describes (result {number})"));
    }
    // A result written before its maps were listed (an older clearview) is taken as it is.
    let Some(maps) = report["maps"].as_object() else { return Ok(number) };
    for name in MAPS {
        let path = dir.join(name);
        match &maps.get(name).unwrap_or(&serde_json::Value::Null) {
            serde_json::Value::Null if path.exists() => {
                return Err(format!("{name} is there, and result {number} has none"));
            }
            serde_json::Value::Null => {}
            map => {
                let bytes = std::fs::read(&path).map_err(|e| format!("{name}: {e}"))?;
                if Some(bytes.len() as u64) != map["bytes"].as_u64()
                    || map["fnv64"].as_str() != Some(fnv64_hex(&bytes).as_str())
                {
                    return Err(format!("{name} is not the map result.json describes (result {number})"));
                }
            }
        }
    }
    Ok(number)
}

/// FNV-1a of `bytes`, as 16 hex digits (a check against mix-ups, not an adversary).
pub fn fnv64_hex(bytes: &[u8]) -> String {
    let mut h = crate::session::Fnv::new();
    h.write(bytes);
    format!("{:016x}", h.finish())
}

/// A second destination for every event line (the NATS roles publish them): called with
/// the session and the whole line, after it is appended to the log.
pub type Tee = std::sync::Arc<dyn Fn(Option<&str>, &str) + Send + Sync>;

/// Where results and events go.
pub struct Emitter {
    tee: Option<Tee>,
    out: PathBuf,
    format: OutputFormat,
    history: usize,
    /// The event log; `None` while it cannot be opened again.
    events: Mutex<Option<File>>,
    /// Closed (`true`) once the service has said `service_stopped`: from then on nothing
    /// is written, no event, no result. Writers hold it shared for the whole write, so the
    /// last line is written after every write in progress, never before one.
    closed: RwLock<bool>,
}

/// Opens the event log at `path` for appending, cutting off a last line left without its
/// newline (a crash or a full disk in an earlier run), so every line of the log is whole.
fn open_log(path: &Path) -> std::io::Result<File> {
    let events = OpenOptions::new().create(true).read(true).append(true).open(path)?;
    match cut_partial_line(&events) {
        Ok(0) => {}
        Ok(n) => {
            tracing::warn!(file = %path.display(), bytes = n, "removed a partial last line from the event log")
        }
        Err(e) => {
            tracing::warn!(file = %path.display(), error = %e, "cannot check the event log's last line")
        }
    }
    Ok(events)
}

/// Refuses a folder of the out tree that has been replaced by a symbolic link since the
/// start (the out folder was resolved then): results are not written through it to
/// wherever it points. A folder that does not exist yet is fine (it is made).
fn no_link(dir: &Path) -> std::io::Result<()> {
    match std::fs::symlink_metadata(dir) {
        Ok(m) if m.file_type().is_symlink() => Err(std::io::Error::other(
            "is a symbolic link (the folder was replaced by one since the start): results are not written through links",
        )),
        _ => Ok(()),
    }
}

/// One line of the event log: `time`, `event`, `session`, then `fields`' members.
fn line(time: String, kind: &str, session: Option<&str>, fields: serde_json::Value) -> String {
    let mut obj = serde_json::Map::new();
    obj.insert("time".into(), time.into());
    obj.insert("event".into(), kind.into());
    if let Some(s) = session {
        obj.insert("session".into(), s.into());
    }
    if let serde_json::Value::Object(m) = fields {
        obj.extend(m);
    }
    let mut line = serde_json::Value::Object(obj).to_string();
    line.push('\n');
    line
}

/// An event's kind (its `event` field) and its other fields.
fn split(event: &Event) -> (String, serde_json::Value) {
    match serde_json::to_value(event) {
        Ok(serde_json::Value::Object(mut m)) => {
            let kind = match m.remove("event") {
                Some(serde_json::Value::String(k)) => k,
                _ => String::new(),
            };
            (kind, serde_json::Value::Object(m))
        }
        _ => (String::new(), serde_json::Value::Null),
    }
}

/// Whether `path` still names the open file `f` (not deleted, not replaced).
fn still_names(path: &Path, f: &File) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (std::fs::metadata(path), f.metadata()) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        let _ = f;
        path.exists()
    }
}

impl Emitter {
    /// Opens the event log for appending. A last line left without its newline (a crash
    /// or a full disk in an earlier run) is cut off, so every line of the log is whole.
    pub fn open(config: &Config) -> Result<Self, DaemonError> {
        let path = config.out_dir.join("events.jsonl");
        let events =
            open_log(&path).map_err(|source| DaemonError::EventLog { path: path.clone(), source })?;
        Ok(Self {
            tee: None,
            out: config.out_dir.clone(),
            format: config.format,
            history: config.history,
            events: Mutex::new(Some(events)),
            closed: RwLock::new(false),
        })
    }

    /// Also hands every event line to `tee` (after the log has it).
    pub fn with_tee(mut self, tee: Tee) -> Self {
        self.tee = Some(tee);
        self
    }

    /// The folder of a session's results: always one plain folder directly in the out
    /// folder, whatever the session's name ([`super::paths::session_dir_name`]).
    pub fn session_dir(&self, session: &str) -> PathBuf {
        self.out.join(super::paths::session_dir_name(session))
    }

    /// The latest result's file name.
    pub fn result_name(&self) -> String {
        format!("result.{}", self.format.extension())
    }

    /// Appends one event, a JSON object on one line: `time`, `event`, `session`, then
    /// the event's fields ([`Event`]). A failure to log is itself logged, never fatal.
    pub fn emit(&self, session: Option<&str>, event: &Event) {
        let (kind, fields) = split(event);
        let line = line(rfc3339(SystemTime::now()), &kind, session, fields);
        let kind = kind.as_str();
        let closed = self.closed.read().expect("emitter gate");
        if *closed {
            tracing::debug!(event = kind, "after service_stopped: not logged");
            return;
        }
        self.append(kind, &line);
        if let Some(tee) = &self.tee {
            tee(session, &line);
        }
    }

    /// Writes the run's last event, `service_stopped`, once every write in progress has
    /// ended; nothing is written after it.
    pub fn close(&self, clean: bool) {
        let mut closed = self.closed.write().expect("emitter gate");
        if *closed {
            return;
        }
        *closed = true;
        let (kind, fields) = split(&Event::ServiceStopped { clean });
        self.append(&kind, &line(rfc3339(SystemTime::now()), &kind, None, fields));
    }

    /// Whether the service has said `service_stopped` (then nothing more is written).
    pub fn is_closed(&self) -> bool {
        *self.closed.read().expect("emitter gate")
    }

    fn append(&self, kind: &str, line: &str) {
        let mut guard = self.events.lock().expect("event log lock");
        let Some(f) = self.log_file(&mut guard, kind) else { return };
        // One write per line: appends of a line are not interleaved with other writers. A
        // line that does not fit (full disk: a short write, then an error) is taken back,
        // so the log never holds half a line that would break its readers.
        let before = f.metadata().map(|m| m.len());
        if let Err(e) = f.write_all(line.as_bytes()).and_then(|()| f.flush()) {
            let taken_back = before.and_then(|len| f.set_len(len));
            tracing::error!(
                file = %self.out.join("events.jsonl").display(),
                error = %e,
                event = kind,
                taken_back = taken_back.is_ok(),
                "cannot append to the event log: event lost"
            );
        }
    }

    /// The open event log, opened again when its path no longer leads to it (the out
    /// folder or the log was deleted or replaced: appends to the old file would be lost
    /// without a word); `None` (the event is lost, and that is logged) when it cannot be.
    fn log_file<'a>(&self, slot: &'a mut Option<File>, kind: &str) -> Option<&'a mut File> {
        let path = self.out.join("events.jsonl");
        if slot.as_ref().is_some_and(|f| still_names(&path, f)) {
            return slot.as_mut();
        }
        let reopened = no_link(&self.out)
            .and_then(|()| std::fs::create_dir_all(&self.out))
            .and_then(|()| open_log(&path));
        match reopened {
            Ok(f) => {
                tracing::warn!(file = %path.display(), "the event log was deleted or replaced: writing to a new one");
                *slot = Some(f);
            }
            Err(e) => {
                tracing::error!(file = %path.display(), error = %e, event = kind, "cannot open the event log: event lost");
                *slot = None;
            }
        }
        slot.as_mut()
    }

    /// Writes result number `number` of `session`: the history copy, then `result.<ext>`,
    /// then its maps (each of [`MAPS`]: `Some`, the PNG to write; `None`, the result has
    /// none and one left by an earlier result goes), then `result.json` (to which the
    /// image's and the maps' sizes and digests are added, see [`check_result`]), each
    /// atomically; prunes the history. The image goes first (the largest: where a full disk
    /// stops the write, nothing has changed); `result.json` last, naming only what was
    /// written for it, so it never describes a map of another result. Returns the result's
    /// path.
    /// The image is written in the keyframe's colour space with its metadata (`key`; none:
    /// sRGB, and only clearview's own XMP), its XMP naming `result.json` and the views the
    /// report says filled it. On failure the files already there are left whole and the
    /// error names the file.
    pub fn write_result(
        &self,
        session: &str,
        number: u64,
        image: &RgbF32,
        key: Option<&Metadata>,
        report: &mut serde_json::Value,
        maps: &[(&str, Option<Vec<u8>>)],
    ) -> Result<PathBuf, WriteError> {
        let dir = self.session_dir(session);
        let closed = self.closed.read().expect("emitter gate");
        if *closed {
            let e = std::io::Error::other("the service has stopped: nothing more is written");
            return Err(WriteError { path: dir, source: e });
        }
        no_link(&self.out).map_err(at(&self.out))?;
        no_link(&dir).map_err(at(&dir))?;
        std::fs::create_dir_all(&dir).map_err(at(&dir))?;
        let path = dir.join(self.result_name());
        let bytes = self.encode(image, key, report).map_err(at(&path))?;
        let ext = self.format.extension();
        let history = (self.history > 0).then(|| dir.join("history"));
        if let Some(hist) = &history {
            no_link(hist).map_err(at(hist))?;
            std::fs::create_dir_all(hist).map_err(at(hist))?;
        }
        // Written once; the history entry is a second name for the same file (a hard link
        // made before the rename), so the bytes hit the disk once.
        let hist_path = history.as_ref().map(|h| h.join(format!("result-{number:04}.{ext}")));
        atomic_write_linked(&path, &bytes, hist_path.as_deref()).map_err(at(&path))?;
        if let Some(hist) = &history {
            prune_history(hist, self.history);
        }
        let mut written = serde_json::Map::new();
        for (name, png) in maps {
            debug_assert!(MAPS.contains(name), "{name} is not a result's map");
            let map_path = dir.join(name);
            match png {
                Some(png) => {
                    atomic_write(&map_path, png).map_err(at(&map_path))?;
                    let entry = serde_json::json!({ "bytes": png.len(), "fnv64": fnv64_hex(png) });
                    written.insert((*name).to_owned(), entry);
                }
                None => match std::fs::remove_file(&map_path) {
                    Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(at(&map_path)(e)),
                    _ => {}
                },
            }
        }
        if let serde_json::Value::Object(m) = report {
            m.insert(
                "image".into(),
                serde_json::json!({ "file": self.result_name(), "bytes": bytes.len(), "fnv64": fnv64_hex(&bytes) }),
            );
            m.insert("maps".into(), serde_json::Value::Object(written));
        }
        let json_path = dir.join("result.json");
        let mut json =
            serde_json::to_vec_pretty(report).map_err(|e| at(&json_path)(std::io::Error::other(e)))?;
        json.push(b'\n');
        atomic_write(&json_path, &json).map_err(at(&json_path))?;
        Ok(path)
    }

    fn encode(
        &self,
        image: &RgbF32,
        key: Option<&Metadata>,
        report: &serde_json::Value,
    ) -> std::io::Result<Vec<u8>> {
        let (format, quality) = match self.format {
            OutputFormat::Png => (Format::Png, None),
            OutputFormat::Jpeg { quality } => (Format::Jpeg, Some(quality)),
        };
        let filled_by =
            report["views"].as_array().into_iter().flatten().filter(|v| v["filled"].as_u64() > Some(0));
        let provenance = Provenance {
            report: Some("result.json".into()),
            views: filled_by.filter_map(|v| v["file"].as_str().map(str::to_owned)).collect(),
        };
        let fallback = Metadata::default();
        let opts = EncodeOptions { quality, space: OutputSpace::Keyframe };
        let encoded = encode(image, format, &opts, key.unwrap_or(&fallback), &provenance)
            .map_err(std::io::Error::other)?;
        for w in &encoded.warnings {
            tracing::warn!(warning = %w, "result written without part of the keyframe's metadata");
        }
        Ok(encoded.bytes)
    }
}

/// Cuts `file` back to just after its last newline; returns the bytes removed.
fn cut_partial_line(file: &File) -> std::io::Result<u64> {
    use std::io::{Read, Seek, SeekFrom};
    let len = file.metadata()?.len();
    let mut f = file;
    let mut end = len;
    let mut buf = vec![0u8; 64 * 1024];
    while end > 0 {
        let start = end.saturating_sub(buf.len() as u64);
        let chunk = &mut buf[..(end - start) as usize];
        f.seek(SeekFrom::Start(start))?;
        f.read_exact(chunk)?;
        if let Some(i) = chunk.iter().rposition(|&b| b == b'\n') {
            end = start + i as u64 + 1;
            break;
        }
        end = start;
    }
    if end < len {
        file.set_len(end)?;
    }
    Ok(len - end)
}

/// Keeps the `keep` highest-numbered `result-NNNN.*` files.
pub(crate) fn prune_history(dir: &Path, keep: usize) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    let mut numbered: Vec<(u64, PathBuf)> = entries
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_str()?.to_owned();
            let n = name.strip_prefix("result-")?.split('.').next()?.parse().ok()?;
            Some((n, e.path()))
        })
        .collect();
    numbered.sort();
    let excess = numbered.len().saturating_sub(keep);
    for (_, path) in numbered.into_iter().take(excess) {
        let _ = std::fs::remove_file(path);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn rfc3339_dates() {
        assert_eq!(rfc3339(SystemTime::UNIX_EPOCH), "1970-01-01T00:00:00.000Z");
        let t = SystemTime::UNIX_EPOCH + Duration::from_millis(1_709_210_096_789);
        assert_eq!(rfc3339(t), "2024-02-29T12:34:56.789Z");
    }

    #[test]
    fn a_partial_last_line_is_cut_back_to_the_last_newline() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("events.jsonl");
        for (text, want) in [
            (&b"{\"a\":1}\n{\"b\":"[..], &b"{\"a\":1}\n"[..]),
            (b"{\"a\":1}\n", b"{\"a\":1}\n"),
            (b"half", b""),
            (b"", b""),
        ] {
            std::fs::write(&p, text).unwrap();
            let f = OpenOptions::new().read(true).append(true).open(&p).unwrap();
            assert_eq!(cut_partial_line(&f).unwrap(), (text.len() - want.len()) as u64);
            assert_eq!(std::fs::read(&p).unwrap(), want);
        }
    }

    #[test]
    fn history_keeps_the_newest() {
        let dir = tempfile::tempdir().unwrap();
        for n in 1..=5 {
            std::fs::write(dir.path().join(format!("result-{n:04}.png")), b"x").unwrap();
        }
        prune_history(dir.path(), 2);
        let mut left: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        left.sort();
        assert_eq!(left, ["result-0004.png", "result-0005.png"]);
    }
}
