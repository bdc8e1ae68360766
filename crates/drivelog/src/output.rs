//! Output files that never destroy the last good one: every program's logs, plots, tables
//! and calibrations are written through [`Staged`].
//!
//! A file `NAME` is written as `NAME.part` beside it ([`part_path`]) and renamed to `NAME`
//! only when the caller says it is complete ([`Staged::commit`]): until then the previous
//! `NAME` stays as it was, and a run that fails leaves it so. The `.part` is created with
//! `O_CREAT | O_EXCL | O_NOFOLLOW`: a link planted at either name by another user of a shared
//! output folder is never written through (a leftover `.part` is unlinked first, which never
//! follows a link; if another appears between the two calls, creation fails), and the rename
//! replaces a link at `NAME` instead of following it. [`Staged::commit`] does not `fsync`:
//! that protects against the process dying, not against the machine losing power
//! (`docs/logs.md`, "Crash safety"); [`Staged::commit_durable`] does, for a file that must
//! survive a power cut once committed (the runner's saved parameters).
//!
//! [`file_stem`] is the one place a name that came from input (a scenario's `name`) becomes a
//! file name.

use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use crate::LogError;

/// Characters of a file stem made by [`file_stem`], at most.
pub const MAX_STEM: usize = 64;

/// A file name (without extension) from `name`: ASCII letters and digits and `-` kept, every
/// other character `_`, at most [`MAX_STEM`] characters, `_` for an empty name. It never holds
/// a path separator or starts with a dot, so it stays in the folder it is joined to.
#[must_use]
pub fn file_stem(name: &str) -> String {
    let stem: String = name
        .chars()
        .take(MAX_STEM)
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if stem.is_empty() {
        "_".to_string()
    } else {
        stem
    }
}

/// Where `NAME` is written until it is complete: `NAME.part`.
#[must_use]
pub fn part_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".part");
    PathBuf::from(name)
}

/// An output file being written as [`part_path`]`(path)`. Dropped without
/// [`commit`](Self::commit), its `.part` is removed, unless [`keep_part`](Self::keep_part)
/// said to keep it (a log: what a failed run logged is worth reading).
#[derive(Debug)]
pub struct Staged {
    file: File,
    path: PathBuf,
    part: PathBuf,
    keep_part: bool,
    committed: bool,
}

impl Staged {
    /// Creates `path`'s `.part`, write-only, without following links.
    ///
    /// # Errors
    /// [`LogError::Io`] naming the `.part`: the folder is missing or not writable, or
    /// something that is not a file (a folder) holds the name, or a link appeared there
    /// while the leftover was removed.
    pub fn create(path: &Path) -> Result<Self, LogError> {
        let part = part_path(path);
        let err = |source| LogError::Io {
            path: part.clone(),
            source,
        };
        // A leftover of an earlier run (or anything else of that name but a folder): unlink
        // never follows a link, so this removes the link, not its target.
        match std::fs::symlink_metadata(&part) {
            Ok(meta) if meta.is_dir() => {
                return Err(err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    "a folder holds the name of the output's temporary file",
                )));
            }
            Ok(_) => std::fs::remove_file(&part).map_err(err)?,
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(err(e)),
        }
        let file = open_new(&part).map_err(err)?;
        Ok(Self {
            file,
            path: path.to_path_buf(),
            part,
            keep_part: false,
            committed: false,
        })
    }

    /// Keeps the `.part` if this is dropped without [`commit`](Self::commit).
    #[must_use]
    pub fn keep_part(mut self) -> Self {
        self.keep_part = true;
        self
    }

    /// The file's final name.
    #[must_use]
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Where it is written until it is committed.
    #[must_use]
    pub fn part(&self) -> &Path {
        &self.part
    }

    /// The open `.part` (for a second handle: [`File::try_clone`]).
    #[must_use]
    pub fn file(&self) -> &File {
        &self.file
    }

    /// Flushes the file and renames it to its final name, replacing what was there.
    ///
    /// # Errors
    /// [`LogError::Io`] naming the file that could not be flushed or renamed (the `.part`
    /// is then kept).
    pub fn commit(mut self) -> Result<PathBuf, LogError> {
        self.keep_part = true; // an error below leaves the complete `.part` to the user
        self.file.flush().map_err(|source| LogError::Io {
            path: self.part.clone(),
            source,
        })?;
        std::fs::rename(&self.part, &self.path).map_err(|source| LogError::Io {
            path: self.path.clone(),
            source,
        })?;
        self.committed = true;
        Ok(self.path.clone())
    }
}

impl Staged {
    /// [`commit`](Self::commit) that survives a power cut once it returns: the file's data is
    /// synced before the rename, and the folder after it (the rename itself).
    ///
    /// # Errors
    /// [`LogError::Io`] naming the file or folder that could not be synced or renamed (the
    /// previous file stays, or the new one is in place but its folder's entry may not be
    /// durable yet).
    pub fn commit_durable(self) -> Result<PathBuf, LogError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| LogError::Io { path, source }
        };
        self.file.sync_all().map_err(io(&self.part))?;
        let path = self.commit()?;
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        File::open(dir)
            .and_then(|d| d.sync_all())
            .map_err(io(dir))?;
        Ok(path)
    }
}

/// `O_CREAT | O_EXCL | O_NOFOLLOW`, mode 0666 less the umask, as `File::create`. (`O_EXCL`
/// alone already fails on a link; `O_NOFOLLOW` says so to every reader of the call.)
fn open_new(path: &Path) -> io::Result<File> {
    let mut options = OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::custom_flags(&mut options, libc::O_NOFOLLOW);
    options.open(path)
}

impl Write for Staged {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.file.write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> io::Result<()> {
        self.file.write_all(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.file.flush()
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.committed && !self.keep_part {
            let _ = std::fs::remove_file(&self.part);
        }
    }
}

/// Writes `bytes` to `path` through a [`Staged`] file: all of them, or the previous file
/// stays.
///
/// # Errors
/// [`LogError::Io`] naming the file.
pub fn write_whole(path: &Path, bytes: &[u8]) -> Result<PathBuf, LogError> {
    let mut staged = Staged::create(path)?;
    staged.write_all(bytes).map_err(|source| LogError::Io {
        path: staged.part().to_path_buf(),
        source,
    })?;
    staged.commit()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A folder of its own for a test, removed when dropped.
    struct TempDir(PathBuf);

    impl TempDir {
        fn new(test: &str) -> Self {
            let dir =
                std::env::temp_dir().join(format!("drivelog-out-{}-{test}", std::process::id()));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            Self(dir)
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    #[test]
    fn stems_stay_in_their_folder() {
        assert_eq!(file_stem("square_60s"), "square_60s");
        assert_eq!(file_stem("../../x"), "______x");
        assert_eq!(file_stem("/etc/passwd"), "_etc_passwd");
        assert_eq!(file_stem(".hidden"), "_hidden");
        assert_eq!(file_stem(""), "_");
        assert_eq!(file_stem("ä\u{1b}[31m"), "___31m");
        assert_eq!(file_stem(&"a".repeat(1000)).len(), MAX_STEM);
    }

    #[test]
    fn a_dropped_output_leaves_the_previous_file() {
        let dir = TempDir::new("dropped");
        let path = dir.0.join("out.csv");
        write_whole(&path, b"good\n").unwrap();
        let mut staged = Staged::create(&path).unwrap();
        staged.write_all(b"half").unwrap();
        assert!(staged.part().exists());
        drop(staged);
        assert_eq!(std::fs::read(&path).unwrap(), b"good\n");
        assert!(
            !part_path(&path).exists(),
            "an abandoned output's .part is removed"
        );

        let mut kept = Staged::create(&path).unwrap().keep_part();
        kept.write_all(b"half").unwrap();
        drop(kept);
        assert_eq!(std::fs::read(part_path(&path)).unwrap(), b"half");
        assert_eq!(std::fs::read(&path).unwrap(), b"good\n");
        // The next run replaces the leftover.
        write_whole(&path, b"new\n").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new\n");
        assert!(!part_path(&path).exists());
    }

    #[cfg(unix)]
    #[test]
    fn planted_links_are_not_followed() {
        let dir = TempDir::new("links");
        let victim = dir.0.join("victim");
        std::fs::write(&victim, b"theirs").unwrap();
        let path = dir.0.join("square.png");
        std::os::unix::fs::symlink(&victim, &path).unwrap();
        std::os::unix::fs::symlink(&victim, part_path(&path)).unwrap();
        write_whole(&path, b"ours").unwrap();
        assert_eq!(std::fs::read(&victim).unwrap(), b"theirs");
        assert_eq!(std::fs::read(&path).unwrap(), b"ours");
        assert!(
            !std::fs::symlink_metadata(&path)
                .unwrap()
                .file_type()
                .is_symlink()
        );
    }

    #[test]
    fn a_folder_at_the_part_name_is_refused_by_name() {
        let dir = TempDir::new("folder");
        let path = dir.0.join("s.mcap");
        std::fs::create_dir(part_path(&path)).unwrap();
        let err = Staged::create(&path).unwrap_err().to_string();
        assert!(
            err.contains("s.mcap.part") && err.contains("folder"),
            "{err}"
        );
    }
}
