//! Crash-safe file writes (shell layer), shared by the service and the one-shot commands:
//! a reader sees the old file or the new one, never a part.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

/// Marks our temporary files: `.<name>.clearview-tmp-<pid>-<n>`.
pub(crate) const TMP_MARK: &str = ".clearview-tmp-";

static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes `bytes` to `path` so that a reader sees the old file or the new one, never a
/// part: a temporary name in the same folder, fsync, rename, fsync of the folder.
pub fn atomic_write(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    atomic_write_linked(path, bytes, None)
}

/// [`atomic_write`] that also gives the new file a second name `also` (atomically too: a
/// hard link to the fsynced temporary, falling back to a copy where links are refused).
pub fn atomic_write_linked(path: &Path, bytes: &[u8], also: Option<&Path>) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}{TMP_MARK}{}-{n}", std::process::id()));
    let result: std::io::Result<()> = (|| {
        // A new file, never an existing name: a link planted under the temporary's
        // (guessable) name in the inbox is not followed to write elsewhere (O_EXCL).
        let mut f = OpenOptions::new().write(true).create_new(true).open(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        if let Some(also) = also {
            let _ = std::fs::remove_file(also);
            if std::fs::hard_link(&tmp, also).is_err() {
                atomic_write(also, bytes)?;
            }
        }
        std::fs::rename(&tmp, path)?;
        for d in [Some(dir), also.and_then(Path::parent)].into_iter().flatten() {
            if let Ok(d) = File::open(d) {
                let _ = d.sync_all();
            }
        }
        Ok(())
    })();
    if let Err(e) = &result
        && e.kind() != std::io::ErrorKind::AlreadyExists
    {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.txt");
        atomic_write(&p, b"one").unwrap();
        atomic_write(&p, b"two").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[cfg(unix)]
    #[test]
    fn a_link_planted_under_the_temporary_name_is_not_written_through() {
        let dir = tempfile::tempdir().unwrap();
        let victim = dir.path().join("victim");
        std::fs::write(&victim, b"keep").unwrap();
        let n = TMP_COUNTER.load(Ordering::Relaxed);
        for k in n..n + 64 {
            let tmp = dir.path().join(format!(".a.png{TMP_MARK}{}-{k}", std::process::id()));
            std::os::unix::fs::symlink(&victim, tmp).unwrap();
        }
        let _ = atomic_write(&dir.path().join("a.png"), b"new");
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep");
    }

    #[test]
    fn a_linked_write_gives_two_names_to_the_new_file_and_keeps_the_old_history() {
        let dir = tempfile::tempdir().unwrap();
        let (p, h1, h2) = (dir.path().join("r.png"), dir.path().join("h1.png"), dir.path().join("h2.png"));
        atomic_write_linked(&p, b"one", Some(&h1)).unwrap();
        atomic_write_linked(&p, b"two", Some(&h2)).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(std::fs::read(&h1).unwrap(), b"one");
        assert_eq!(std::fs::read(&h2).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 3);
    }
}
