//! The service's boundary on disk (shell layer): the one place where a session's name
//! becomes a folder name, and the one way a file of the watched folder is opened.
//!
//! - **Names.** A session is named by a folder of the inbox, a `[[video]]` table or an
//!   HTTP path: none is ours to trust. [`session_dir_name`] turns any name into a single,
//!   ordinary path component (never empty, `.`, `..`, hidden, absolute, or holding a
//!   separator or a control character), and two different names never share a folder.
//!   Every path built from a session's name (its results, its saved state) goes through it.
//! - **Reads.** With `watch.follow_symlinks = false` (the default) [`Inbox::open`] refuses
//!   any symbolic link on the way from the watched folder to the file, whether it points
//!   outside or inside (a link that points inside today can point elsewhere between a
//!   check and a read; the file it names is in the folder anyway). The open itself walks
//!   the path with `openat(O_NOFOLLOW)` one component at a time from the watched folder,
//!   so a link swapped in after the checks is refused by the kernel, not raced.

use std::fs::File;
use std::path::{Component, Path, PathBuf};

use thiserror::Error;

use crate::config::Config;

/// Longest folder name [`session_dir_name`] returns, in bytes: leaves room under the
/// usual 255-byte limit for `<name>.json` and the atomic writer's temporary names.
pub const MAX_DIR_NAME: usize = 120;

/// The folder name of session `id` (below the out folder and the state folder): `id`
/// itself when it is an ordinary name, else an escaped form of it.
///
/// Escaped as `%XX` (each UTF-8 byte, upper-case hex): `%`, `/`, `\`, control characters,
/// and a leading `.` (so `.`, `..` and hidden names cannot come out). The empty name is
/// `%`. A name longer than [`MAX_DIR_NAME`] once escaped keeps its first part and ends
/// with `%~` and a 64-bit digest of the whole name. The mapping is one-to-one but for
/// digest collisions: a literal `%` is always escaped, so `%`, `%~` and `%XX` come only
/// from the rules above.
pub fn session_dir_name(id: &str) -> String {
    if id.is_empty() {
        return "%".into();
    }
    let mut out = String::with_capacity(id.len());
    for (i, c) in id.chars().enumerate() {
        let escape = matches!(c, '%' | '/' | '\\') || c.is_control() || (i == 0 && c == '.');
        if escape {
            let mut buf = [0u8; 4];
            for b in c.encode_utf8(&mut buf).bytes() {
                out.push_str(&format!("%{b:02X}"));
            }
        } else {
            out.push(c);
        }
    }
    if out.len() <= MAX_DIR_NAME {
        return out;
    }
    let mut h = crate::session::Fnv::new();
    h.write(id.as_bytes());
    let tail = format!("%~{:016x}", h.finish());
    let mut cut = MAX_DIR_NAME - tail.len();
    // Never cut a character or an escape in two.
    let b = out.as_bytes();
    while !out.is_char_boundary(cut) || b[cut - 1] == b'%' || b[cut - 2] == b'%' {
        cut -= 1;
    }
    out.truncate(cut);
    out.push_str(&tail);
    out
}

/// Why a file of the watched folder was not opened.
#[derive(Debug, Error)]
pub enum Refusal {
    #[error("{} is a symbolic link: links are not followed (watch.follow_symlinks = false)", .link.display())]
    Symlink { link: PathBuf },
    #[error("not inside the watched folder {}", .root.display())]
    Outside { root: PathBuf },
    #[error("not a regular file")]
    NotAFile,
    #[error("cannot read: {0}")]
    Io(std::io::Error),
}

/// The watched folder and how its files may be opened.
#[derive(Debug, Clone)]
pub struct Inbox {
    root: PathBuf,
    follow_symlinks: bool,
}

impl Inbox {
    /// `root` should be canonical (the service canonicalises its folders at start).
    pub fn new(root: impl Into<PathBuf>, follow_symlinks: bool) -> Self {
        Self { root: root.into(), follow_symlinks }
    }

    pub fn of(config: &Config) -> Self {
        Self::new(config.watch_dir.clone(), config.follow_symlinks)
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn follows_symlinks(&self) -> bool {
        self.follow_symlinks
    }

    /// The components of `path` below the root, when it is below it and plain (no `..`).
    fn relative<'a>(&self, path: &'a Path) -> Result<Vec<&'a std::ffi::OsStr>, Refusal> {
        let rel = path.strip_prefix(&self.root).map_err(|_| self.outside())?;
        rel.components()
            .map(|c| match c {
                Component::Normal(n) => Ok(n),
                _ => Err(self.outside()),
            })
            .collect::<Result<Vec<_>, _>>()
            .and_then(|v| if v.is_empty() { Err(self.outside()) } else { Ok(v) })
    }

    fn outside(&self) -> Refusal {
        Refusal::Outside { root: self.root.clone() }
    }

    /// The first symbolic link on the way from the root to `path` (`path` included), by
    /// `lstat`; `None` when there is none (or the path is gone). Always `None` when links
    /// are followed.
    pub fn symlink_on_path(&self, path: &Path) -> Option<PathBuf> {
        if self.follow_symlinks {
            return None;
        }
        let parts = self.relative(path).ok()?;
        let mut at = self.root.clone();
        for p in parts {
            at.push(p);
            match std::fs::symlink_metadata(&at) {
                Ok(m) if m.file_type().is_symlink() => return Some(at),
                Ok(_) => {}
                Err(_) => return None,
            }
        }
        None
    }

    /// Opens `path` (below the root) for reading: a regular file, reached without
    /// following any symbolic link unless the configuration allows it. Never blocks on a
    /// FIFO or a device.
    pub fn open(&self, path: &Path) -> Result<File, Refusal> {
        let parts = self.relative(path)?;
        let file = if self.follow_symlinks { open_following(path)? } else { self.open_beneath(&parts)? };
        let meta = file.metadata().map_err(Refusal::Io)?;
        if !meta.is_file() {
            return Err(Refusal::NotAFile);
        }
        Ok(file)
    }

    #[cfg(unix)]
    fn open_beneath(&self, parts: &[&std::ffi::OsStr]) -> Result<File, Refusal> {
        use std::os::fd::{AsRawFd, FromRawFd};
        use std::os::unix::ffi::OsStrExt;
        use std::os::unix::fs::OpenOptionsExt;

        let mut dir = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_DIRECTORY | libc::O_CLOEXEC)
            .open(&self.root)
            .map_err(Refusal::Io)?;
        let mut at = self.root.clone();
        for (i, part) in parts.iter().enumerate() {
            at.push(part);
            let last = i + 1 == parts.len();
            let name = std::ffi::CString::new(part.as_bytes()).map_err(|_| Refusal::NotAFile)?;
            let flags = libc::O_RDONLY
                | libc::O_NOFOLLOW
                | libc::O_CLOEXEC
                | libc::O_NOCTTY
                | if last { libc::O_NONBLOCK } else { libc::O_DIRECTORY };
            // SAFETY: `dir` is an open descriptor for the whole call and `name` a valid C
            // string; the returned descriptor, if any, is owned by the `File` made from it.
            let fd = unsafe { libc::openat(dir.as_raw_fd(), name.as_ptr(), flags) };
            if fd < 0 {
                let e = std::io::Error::last_os_error();
                // ELOOP: the component is a link (O_NOFOLLOW); ENOTDIR on the way may be one
                // too (O_DIRECTORY on a link to a file).
                let is_link = std::fs::symlink_metadata(&at).is_ok_and(|m| m.file_type().is_symlink());
                return Err(if e.raw_os_error() == Some(libc::ELOOP) || is_link {
                    Refusal::Symlink { link: at }
                } else {
                    Refusal::Io(e)
                });
            }
            // SAFETY: `fd` was just opened and is owned by nothing else.
            let opened = unsafe { File::from_raw_fd(fd) };
            if last {
                return Ok(opened);
            }
            dir = opened;
        }
        unreachable!("relative() returns at least one component")
    }

    #[cfg(not(unix))]
    fn open_beneath(&self, parts: &[&std::ffi::OsStr]) -> Result<File, Refusal> {
        let mut at = self.root.clone();
        for p in parts {
            at.push(p);
            if std::fs::symlink_metadata(&at).is_ok_and(|m| m.file_type().is_symlink()) {
                return Err(Refusal::Symlink { link: at });
            }
        }
        File::open(&at).map_err(Refusal::Io)
    }
}

/// Two of the service's folders that overlap: the same folder, or one inside the other.
#[derive(Debug, Error, PartialEq, Eq)]
#[error("{} and {} {}: the watched, output and state folders must be apart (none equal to or inside another), or the service would read what it writes and write where it reads", .a_key, .b_key, .how)]
pub struct Overlap {
    pub a_key: String,
    pub b_key: String,
    pub how: String,
}

/// Checks that the folders named in `folders` (`(what, path)`: `watch.dir`, `output.dir`,
/// `state.dir`) are apart: none is the same folder as another or inside another, however
/// they are spelled (`inbox`, `./inbox`, `/x/../inbox`, an absolute path, a symbolic link
/// on the way, a bind mount of the same folder). Paths are resolved against the current
/// folder; the part of a path that exists is resolved through the file system (links,
/// `..`), the rest by its components. Folders that do not exist yet are compared by path.
pub fn check_apart(folders: &[(&str, &Path)]) -> Result<(), Overlap> {
    let resolved: Vec<(&str, &Path, PathBuf)> = folders.iter().map(|&(k, p)| (k, p, resolve(p))).collect();
    for (i, (ka, pa, ra)) in resolved.iter().enumerate() {
        for (kb, pb, rb) in &resolved[i + 1..] {
            let shown = |k: &str, p: &Path| format!("{k} ({})", p.display());
            let (a, b) = (shown(ka, pa), shown(kb, pb));
            let overlap = if ra == rb || same_folder(ra, rb) {
                Some((a, b, format!("are the same folder ({})", ra.display())))
            } else if inside(ra, rb) {
                Some((a, b, format!("are nested: the first is inside the second ({})", rb.display())))
            } else if inside(rb, ra) {
                Some((b, a, format!("are nested: the first is inside the second ({})", ra.display())))
            } else {
                None
            };
            if let Some((a_key, b_key, how)) = overlap {
                return Err(Overlap { a_key, b_key, how });
            }
        }
    }
    Ok(())
}

/// `path` made absolute: its longest existing ancestor canonicalised (links and `..`
/// resolved by the file system), the rest appended with `.` dropped and `..` taken back.
pub fn resolve(path: &Path) -> PathBuf {
    let abs = if path.is_absolute() {
        path.to_owned()
    } else {
        std::env::current_dir().unwrap_or_else(|_| PathBuf::from("/")).join(path)
    };
    let comps: Vec<Component> = abs.components().collect();
    for cut in (1..=comps.len()).rev() {
        let head: PathBuf = comps[..cut].iter().collect();
        if let Ok(mut base) = std::fs::canonicalize(&head) {
            for c in &comps[cut..] {
                match c {
                    Component::ParentDir => {
                        base.pop();
                    }
                    Component::Normal(n) => base.push(n),
                    _ => {}
                }
            }
            return base;
        }
    }
    abs
}

/// Whether `a` is strictly inside `b`: by path, or because one of `a`'s existing
/// ancestors is `b`'s folder itself (device and inode: a bind mount of `b` elsewhere).
fn inside(a: &Path, b: &Path) -> bool {
    a != b && (a.starts_with(b) || a.ancestors().skip(1).any(|up| same_folder(up, b)))
}

/// Whether two existing paths are the same folder (device and inode).
fn same_folder(a: &Path, b: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (std::fs::metadata(a), std::fs::metadata(b)) {
            (Ok(x), Ok(y)) => x.is_dir() && x.dev() == y.dev() && x.ino() == y.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        let _ = (a, b);
        false
    }
}

fn open_following(path: &Path) -> Result<File, Refusal> {
    let mut o = std::fs::OpenOptions::new();
    o.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY);
    }
    o.open(path).map_err(Refusal::Io)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folders_spelled_differently_are_still_the_same_or_nested() {
        let tmp = tempfile::tempdir().unwrap();
        let t = tmp.path().canonicalize().unwrap();
        std::fs::create_dir_all(t.join("in/sub")).unwrap();
        std::fs::create_dir_all(t.join("other")).unwrap();
        #[cfg(unix)]
        std::os::unix::fs::symlink(t.join("in"), t.join("alias")).unwrap();
        let check = |w: PathBuf, o: PathBuf, s: PathBuf| {
            check_apart(&[("watch.dir", &w), ("output.dir", &o), ("state.dir", &s)])
        };
        let ok = check(t.join("in"), t.join("out"), t.join("state"));
        assert_eq!(ok, Ok(()));
        for (w, o, s, keys) in [
            (t.join("in"), t.join("in/."), t.join("st"), ("watch.dir", "output.dir")),
            (t.join("in"), t.join("other/../in"), t.join("st"), ("watch.dir", "output.dir")),
            (t.join("in"), t.join("alias"), t.join("st"), ("watch.dir", "output.dir")),
            (t.join("in"), t.join("out"), t.join("in/sub/state"), ("state.dir", "watch.dir")),
            (t.join("in"), t.join("out"), t.join("alias/new/state"), ("state.dir", "watch.dir")),
            (t.join("in"), t.join("out"), t.join("out"), ("output.dir", "state.dir")),
            (t.join("in/sub"), t.join("in"), t.join("st"), ("watch.dir", "output.dir")),
            (t.join("x"), t.join("y"), t.join("y/z/.."), ("output.dir", "state.dir")),
        ] {
            let e = check(w.clone(), o.clone(), s.clone()).expect_err(&format!("{w:?} {o:?} {s:?}"));
            assert!(e.a_key.starts_with(keys.0) && e.b_key.starts_with(keys.1), "{e}");
            assert!(e.to_string().contains(keys.0) && e.to_string().contains(keys.1), "{e}");
        }
    }

    #[test]
    fn ordinary_names_are_kept() {
        for n in ["s1", "_root", "facade 2026-11-22", "façade-été", "a.b", "IMG_0001", "x~", "a:b"] {
            assert_eq!(session_dir_name(n), n);
        }
    }

    #[test]
    fn every_name_becomes_one_plain_component() {
        let long = "é".repeat(300);
        let names = [
            "",
            ".",
            "..",
            "../..",
            "/etc",
            "/",
            "a/../../b",
            "..\\..\\windows",
            "a\nb",
            "a\rb",
            "\0",
            "tab\there",
            "\u{7f}",
            "\u{85}next-line",
            ".hidden",
            "%",
            "%2E%2E",
            "a%~0",
            &long,
        ];
        let mut seen = std::collections::HashSet::new();
        for n in names {
            let d = session_dir_name(n);
            let mut comps = Path::new(&d).components();
            assert!(matches!(comps.next(), Some(Component::Normal(_))), "{n:?} -> {d:?}");
            assert!(comps.next().is_none(), "{n:?} -> {d:?}");
            assert!(!d.starts_with('.'), "{n:?} -> {d:?}");
            assert!(!d.contains(['/', '\\']) && !d.chars().any(char::is_control), "{n:?} -> {d:?}");
            assert!(d.len() <= MAX_DIR_NAME, "{n:?}: {} bytes", d.len());
            assert!(seen.insert(d.clone()), "two names share {d:?}");
        }
        assert_eq!(session_dir_name(".."), "%2E.");
        assert_eq!(session_dir_name("a/b"), "a%2Fb");
        assert_eq!(session_dir_name("a\nb"), "a%0Ab");
        assert_eq!(session_dir_name("50%"), "50%25");
    }

    #[test]
    fn long_names_keep_a_readable_start_and_stay_apart() {
        let a = format!("{}a", "x".repeat(200));
        let b = format!("{}b", "x".repeat(200));
        let (da, db) = (session_dir_name(&a), session_dir_name(&b));
        assert_ne!(da, db);
        assert!(da.starts_with("xxxxxxxx") && da.contains("%~"), "{da}");
        assert!(da.len() <= MAX_DIR_NAME && db.len() <= MAX_DIR_NAME);
        // A cut never splits an escape or a character.
        for pad in 0..6 {
            let n = format!("{}{}", "y".repeat(90 + pad), "\n".repeat(40));
            let d = session_dir_name(&n);
            let head = d.split("%~").next().unwrap();
            assert!(head.split('%').skip(1).all(|e| e.len() == 2), "{d}");
        }
    }

    #[cfg(unix)]
    #[test]
    fn links_are_refused_unless_followed() {
        use std::os::unix::fs::symlink;
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("in");
        let outside = tmp.path().join("outside");
        std::fs::create_dir_all(root.join("s1")).unwrap();
        std::fs::create_dir_all(&outside).unwrap();
        std::fs::write(outside.join("secret.png"), b"secret").unwrap();
        std::fs::write(root.join("s1/a.png"), b"inside").unwrap();
        symlink(outside.join("secret.png"), root.join("s1/out.png")).unwrap();
        symlink(root.join("s1/a.png"), root.join("s1/in.png")).unwrap();
        symlink(&outside, root.join("s2")).unwrap();
        symlink("loop.png", root.join("s1/loop.png")).unwrap();
        let strict = Inbox::new(&root, false);
        let read = |i: &Inbox, p: &str| {
            i.open(&root.join(p)).map(|mut f| {
                let mut s = String::new();
                std::io::Read::read_to_string(&mut f, &mut s).unwrap();
                s
            })
        };
        assert_eq!(read(&strict, "s1/a.png").unwrap(), "inside");
        for p in ["s1/out.png", "s1/in.png", "s2/secret.png", "s1/loop.png"] {
            assert!(matches!(read(&strict, p), Err(Refusal::Symlink { .. })), "{p}");
            assert!(strict.symlink_on_path(&root.join(p)).is_some(), "{p}");
        }
        assert_eq!(strict.symlink_on_path(&root.join("s2/secret.png")), Some(root.join("s2")));
        assert_eq!(strict.symlink_on_path(&root.join("s1/a.png")), None);
        assert!(matches!(read(&strict, "../outside/secret.png"), Err(Refusal::Outside { .. })));
        assert!(matches!(strict.open(&outside.join("secret.png")), Err(Refusal::Outside { .. })));
        assert!(matches!(read(&strict, "s1"), Err(Refusal::NotAFile)));
        let lenient = Inbox::new(&root, true);
        assert_eq!(read(&lenient, "s1/out.png").unwrap(), "secret");
        assert_eq!(read(&lenient, "s2/secret.png").unwrap(), "secret");
        assert!(read(&lenient, "s1/loop.png").is_err(), "a loop is an error, not a hang");
    }

    #[cfg(unix)]
    #[test]
    fn a_fifo_is_refused_without_blocking() {
        let tmp = tempfile::tempdir().unwrap();
        let fifo = tmp.path().join("a.png");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a valid C string; mkfifo touches nothing else.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        for follow in [false, true] {
            assert!(matches!(Inbox::new(tmp.path(), follow).open(&fifo), Err(Refusal::NotAFile)));
        }
    }
}
