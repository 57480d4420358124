//! Which files are candidates, and how they are noticed: the notify watcher and the full
//! scan (shell layer).
//!
//! A candidate is an image directly in the watched folder (session `_root`) or in one of
//! its sub-folders (the session is the sub-folder's name). Never candidates: names that
//! start with a dot, names of uploads in progress (`.part`, `.tmp`, `.crdownload`,
//! `.partial`, `.download`, `~`), other extensions, anything deeper.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use notify::{RecursiveMode, Watcher};
use tokio::sync::mpsc::Sender;
use tokio::sync::mpsc::error::TrySendError;

/// Notifications buffered between the watcher and the intake. When full, the watcher
/// raises the overflow flag and the intake rescans the whole folder instead: a burst of
/// events costs a scan, never memory, and no file is missed.
pub const HINT_QUEUE: usize = 1024;

/// The session of images directly in the watched folder.
pub const ROOT_SESSION: &str = "_root";

/// What a file is to its session.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Role {
    /// Named `key.<ext>`.
    Key,
    /// Named `mask.<ext>`, or `<stem>.mask.<ext>`, `<stem>_mask.<ext>`, `<stem>-mask.<ext>`
    /// (the mask of the image `<stem>`; see [`mask_owner`]). Never aligned as a view.
    Mask,
    /// Anything else: a view (or the keyframe, when the configuration names it or it is
    /// the first to arrive).
    View,
}

/// A candidate file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Candidate {
    pub session: String,
    pub role: Role,
}

/// Names of files still being written by common uploaders, or hidden.
pub fn is_partial_or_hidden(name: &str) -> bool {
    let lower = name.to_ascii_lowercase();
    name.starts_with('.')
        || name.ends_with('~')
        || [".part", ".tmp", ".crdownload", ".partial", ".download", ".filepart"]
            .iter()
            .any(|s| lower.ends_with(s))
}

/// What `path` (inside `root`) is, or `None` when it is not a candidate.
pub fn classify(root: &Path, path: &Path, extensions: &[String]) -> Option<Candidate> {
    let rel = path.strip_prefix(root).ok()?;
    // A file name that is not UTF-8 is read under its lossy name (U+FFFD for the bad
    // bytes); a session's folder name must be UTF-8 (it names an output folder).
    let parts: Vec<&std::ffi::OsStr> = rel.iter().collect();
    let lossy = |n: &std::ffi::OsStr| n.to_string_lossy().into_owned();
    let (session, name) = match parts.as_slice() {
        [name] => (ROOT_SESSION, lossy(name)),
        [dir, name] => match dir.to_str() {
            Some(dir) if !is_partial_or_hidden(dir) => (dir, lossy(name)),
            _ => return None,
        },
        _ => return None,
    };
    let name = name.as_str();
    if is_partial_or_hidden(name) {
        return None;
    }
    let (stem, ext) = name.rsplit_once('.')?;
    if stem.is_empty() || !extensions.iter().any(|e| e.eq_ignore_ascii_case(ext)) {
        return None;
    }
    Some(Candidate { session: session.to_owned(), role: role_of_stem(stem) })
}

/// What an image whose name's stem is `stem` is to its session.
pub fn role_of_stem(stem: &str) -> Role {
    if stem == "key" {
        Role::Key
    } else if mask_owner(stem).is_some() {
        Role::Mask
    } else {
        Role::View
    }
}

/// Whose mask a file whose stem is `stem` is: `Some("")` for the session's own `mask`,
/// `Some(owner)` for `<owner>.mask`, `<owner>_mask` and `<owner>-mask` (the word `mask` in
/// any case, as people and tools write it), `None` for anything else (an image).
pub fn mask_owner(stem: &str) -> Option<&str> {
    if stem.eq_ignore_ascii_case("mask") {
        return Some("");
    }
    let cut = stem.len().checked_sub(4)?;
    let (owner, word) = (stem.get(..cut)?, stem.get(cut..)?);
    let owner = owner.strip_suffix(['.', '_', '-'])?;
    (word.eq_ignore_ascii_case("mask") && !owner.is_empty()).then_some(owner)
}

/// The names a mask of the image whose stem is `owner` may have, most specific first, for
/// each extension in `extensions` (lower case, as configured).
pub fn mask_names(owner: &str, extensions: &[String]) -> Vec<String> {
    let bases = [format!("{owner}.mask"), format!("{owner}_mask"), format!("{owner}-mask")];
    bases.iter().flat_map(|b| extensions.iter().map(move |e| format!("{b}.{e}"))).collect()
}

/// A file name as the log shows it: control characters (a newline…) escaped, so that a
/// name cannot break or forge a log line. Events carry the name itself (JSON escapes it).
pub fn shown(name: &str) -> std::borrow::Cow<'_, str> {
    if !name.chars().any(char::is_control) {
        return name.into();
    }
    name.chars()
        .flat_map(|c| {
            let escaped: Vec<char> = if c.is_control() { c.escape_default().collect() } else { vec![c] };
            escaped
        })
        .collect::<String>()
        .into()
}

/// [`shown`] for a whole path.
pub fn shown_path(path: &Path) -> String {
    shown(&path.to_string_lossy()).into_owned()
}

/// The stem of a file name (`IMG_1.jpg` → `IMG_1`, `key.mask.png` → `key.mask`).
pub fn stem(name: &str) -> &str {
    name.rsplit_once('.').map_or(name, |(s, _)| s)
}

/// Every entry directly in `root` or one level below (the candidates among them are
/// decided by [`classify`]), symbolic links, special files and folders inside sessions
/// included: the intake refuses them, so each is reported rather than silently missed. A linked folder is entered only when links
/// are followed; otherwise the link itself is listed. Unreadable folders are logged and
/// skipped.
pub fn scan(root: &Path, follow_symlinks: bool) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let entries = match std::fs::read_dir(root) {
        Ok(e) => e,
        Err(e) => {
            tracing::warn!(dir = %root.display(), error = %e, "cannot scan");
            return out;
        }
    };
    // In a session folder everything is listed (a FIFO or a folder under an image's name
    // is reported, not silently missed); directly in the root, everything but folders
    // (which are sessions).
    for entry in entries.flatten() {
        let Ok(kind) = entry.file_type() else { continue };
        let is_dir = kind.is_dir()
            || (follow_symlinks
                && kind.is_symlink()
                && std::fs::metadata(entry.path()).is_ok_and(|m| m.is_dir()));
        if is_dir {
            if let Ok(inner) = std::fs::read_dir(entry.path()) {
                out.extend(inner.flatten().map(|e| e.path()));
            }
        } else {
            out.push(entry.path());
        }
    }
    out.sort();
    out
}

/// Whether a notification can mean that a file appeared, changed, moved, went or became
/// readable: everything but reads. Opening and closing a file without writing it says
/// nothing new, and the service's own reads of the folder (the intake's listing and
/// decoding, the HTTP thumbnails) raise exactly those: taken as hints, each read led to
/// another, and an idle service spun a core forever. A change of permissions (`chmod`,
/// an attribute event) stays a hint: a file that could not be read may now be.
pub fn changes_content(kind: &notify::EventKind) -> bool {
    use notify::event::{AccessKind, AccessMode, EventKind};
    match kind {
        EventKind::Access(AccessKind::Close(AccessMode::Write)) => true,
        EventKind::Access(_) => false,
        EventKind::Any
        | EventKind::Create(_)
        | EventKind::Modify(_)
        | EventKind::Remove(_)
        | EventKind::Other => true,
    }
}

/// Starts kernel notifications on `root` (recursive); every path a change touched becomes
/// a hint ([`changes_content`]: reads are not changes).
/// Linked folders are watched through only when links are followed.
pub fn start_notify(
    root: &Path,
    follow_symlinks: bool,
    hints: Sender<PathBuf>,
    overflow: Arc<AtomicBool>,
) -> notify::Result<notify::RecommendedWatcher> {
    let handler = move |res: notify::Result<notify::Event>| match res {
        Ok(event) if !changes_content(&event.kind) => {}
        Ok(event) => {
            for path in event.paths {
                match hints.try_send(path) {
                    Ok(()) => {}
                    Err(TrySendError::Full(_)) => overflow.store(true, Ordering::Relaxed),
                    Err(TrySendError::Closed(_)) => return,
                }
            }
        }
        Err(e) => {
            tracing::warn!(error = %e, "file notification error: rescanning");
            overflow.store(true, Ordering::Relaxed);
        }
    };
    let config = notify::Config::default().with_follow_symlinks(follow_symlinks);
    let mut watcher = notify::RecommendedWatcher::new(handler, config)?;
    watcher.watch(root, RecursiveMode::Recursive)?;
    Ok(watcher)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn exts() -> Vec<String> {
        vec!["jpg".into(), "png".into()]
    }

    #[test]
    fn sessions_roles_and_ignored_names() {
        let root = Path::new("/in");
        let c = |p: &str| classify(root, &root.join(p), &exts());
        assert_eq!(c("a.JPG"), Some(Candidate { session: ROOT_SESSION.into(), role: Role::View }));
        assert_eq!(c("s1/key.png"), Some(Candidate { session: "s1".into(), role: Role::Key }));
        assert_eq!(c("s1/key.mask.png"), Some(Candidate { session: "s1".into(), role: Role::Mask }));
        assert_eq!(c("s1/mask.png"), Some(Candidate { session: "s1".into(), role: Role::Mask }));
        for ignored in [
            "s1/a.jpg.part",
            "s1/.a.jpg",
            "s1/a.jpg~",
            "s1/a.tmp",
            "s1/a.crdownload",
            "a.txt",
            "s1/x/a.jpg",
            ".s/a.jpg",
        ] {
            assert_eq!(c(ignored), None, "{ignored}");
        }
        assert_eq!(classify(root, Path::new("/elsewhere/a.jpg"), &exts()), None);
        assert_eq!(c("../a.jpg"), None);
        use std::os::unix::ffi::OsStrExt;
        let odd = root.join("s1").join(std::ffi::OsStr::from_bytes(b"caf\xe9.png"));
        assert_eq!(classify(root, &odd, &exts()), Some(Candidate { session: "s1".into(), role: Role::View }));
        let odd_dir = root.join(std::ffi::OsStr::from_bytes(b"s\xff")).join("a.png");
        assert_eq!(classify(root, &odd_dir, &exts()), None);
    }

    #[test]
    fn masks_are_named_in_the_ways_people_name_them() {
        assert_eq!(mask_owner("mask"), Some(""));
        assert_eq!(mask_owner("MASK"), Some(""));
        for (stem, owner) in [
            ("hunt3.mask", "hunt3"),
            ("hunt3_mask", "hunt3"),
            ("hunt3-mask", "hunt3"),
            ("IMG_1.MASK", "IMG_1"),
            ("a.b_Mask", "a.b"),
        ] {
            assert_eq!(mask_owner(stem), Some(owner), "{stem}");
        }
        for stem in
            ["hunt3", "masked", "unmask", "_mask", ".mask", "mask2", "hunt3mask", "hunt3.masks", "aééx", "é"]
        {
            assert_eq!(mask_owner(stem), None, "{stem}");
        }
        let root = Path::new("/in");
        for name in ["s/hunt3_mask.png", "s/hunt3-mask.jpg", "s/hunt3.mask.png"] {
            assert_eq!(classify(root, &root.join(name), &exts()).unwrap().role, Role::Mask, "{name}");
        }
        assert_eq!(
            mask_names("k", &exts()),
            ["k.mask.jpg", "k.mask.png", "k_mask.jpg", "k_mask.png", "k-mask.jpg", "k-mask.png"]
        );
    }

    #[test]
    fn reads_are_not_hints_and_writes_moves_removals_and_chmods_are() {
        use notify::event::*;
        for quiet in [
            EventKind::Access(AccessKind::Open(AccessMode::Any)),
            EventKind::Access(AccessKind::Close(AccessMode::Read)),
            EventKind::Access(AccessKind::Read),
            EventKind::Access(AccessKind::Any),
        ] {
            assert!(!changes_content(&quiet), "{quiet:?}");
        }
        for change in [
            EventKind::Access(AccessKind::Close(AccessMode::Write)),
            EventKind::Create(CreateKind::File),
            EventKind::Modify(ModifyKind::Data(DataChange::Any)),
            EventKind::Modify(ModifyKind::Metadata(MetadataKind::Permissions)),
            EventKind::Modify(ModifyKind::Name(RenameMode::To)),
            EventKind::Remove(RemoveKind::File),
            EventKind::Any,
        ] {
            assert!(changes_content(&change), "{change:?}");
        }
    }

    #[test]
    fn log_names_escape_control_characters() {
        assert_eq!(shown("a b.png"), "a b.png");
        assert_eq!(shown("new\nline\t.png"), "new\\nline\\t.png");
    }

    #[cfg(unix)]
    #[test]
    fn scans_list_links_and_enter_linked_folders_only_when_following() {
        use std::os::unix::fs::symlink;
        let tmp = tempfile::tempdir().unwrap();
        let (root, outside) = (tmp.path().join("in"), tmp.path().join("out"));
        std::fs::create_dir_all(root.join("s1")).unwrap();
        std::fs::create_dir_all(&outside).unwrap();
        std::fs::write(outside.join("o.jpg"), b"x").unwrap();
        std::fs::write(root.join("s1/a.jpg"), b"x").unwrap();
        symlink(outside.join("o.jpg"), root.join("s1/l.jpg")).unwrap();
        symlink(&outside, root.join("s2")).unwrap();
        let rel = |v: Vec<PathBuf>| -> Vec<String> {
            v.iter().map(|p| p.strip_prefix(&root).unwrap().to_string_lossy().into_owned()).collect()
        };
        assert_eq!(rel(scan(&root, false)), ["s1/a.jpg", "s1/l.jpg", "s2"]);
        assert_eq!(rel(scan(&root, true)), ["s1/a.jpg", "s1/l.jpg", "s2/o.jpg"]);
    }
}
