//! The runner's saved parameters (`--params FILE`): one record of `firmware::storage`, the
//! format the board keeps in flash, in a file. A save writes the record to `FILE.part`,
//! syncs it, renames it over `FILE` and syncs the folder, on a thread of its own (the loop
//! never waits for the disk), and is answered once that returned: a power cut at any moment
//! leaves the old set or the new one. At start the set in the file is run if it was saved
//! for this configuration file's built-in configuration (`storage::usable`), as the board
//! does. See `docs/protocol.md`, "Saving parameters".

use std::path::{Path, PathBuf};
use std::thread::JoinHandle;

use firmware::Config;
use firmware::control::SaveOutcome;
use firmware::protocol::canopen::abort_code;
use firmware::storage::{self, Content, MAGIC, RECORD_BYTES};
use mecanum_linux::ParamStore;

/// The abort code of a save the file system refused ("access failed due to a hardware
/// error", as a flash error on the board).
const WRITE_FAILED: u32 = abort_code::HARDWARE;

/// What a start found in the parameter file.
#[derive(Debug, Clone, PartialEq)]
pub enum Found {
    /// No file yet: the built-in set runs; the first save creates it.
    Missing,
    /// A set saved for this configuration: it runs.
    Saved {
        /// The set.
        config: Box<Config>,
        /// Its record's number.
        seq: u32,
    },
    /// A set saved for another built-in configuration (`base_id`), or not one this firmware
    /// runs: the built-in set runs, and the next save replaces it.
    Other {
        /// The built-in id it was saved under.
        base_id: u16,
    },
    /// A record whose CRC fails (written by something else, or damaged): the built-in set
    /// runs, and the next save replaces it.
    Damaged,
}

/// Why the parameter file cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ParamFileError {
    /// It could not be read.
    #[error("--params {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// It is missing and its folder is not there to hold it: every save would fail.
    #[error("--params {path}: the folder {folder} does not exist")]
    NoFolder {
        /// The file.
        path: PathBuf,
        /// Its folder.
        folder: PathBuf,
    },
    /// It is not a saved parameter set: never overwritten (it may be the user's file).
    #[error(
        "--params {path}: not a saved parameter set ({len} bytes; a set is {RECORD_BYTES} \
         bytes starting with \"MCF1\"): give a new file name, or remove it"
    )]
    NotASet {
        /// The file.
        path: PathBuf,
        /// Its length, bytes.
        len: usize,
    },
}

/// The parameter file and the save being written. See the module doc.
#[derive(Debug)]
pub struct ParamFile {
    path: PathBuf,
    /// The next record's number.
    next_seq: u32,
    /// The save being written: its number and the thread writing it.
    writing: Option<(u32, JoinHandle<Result<PathBuf, drivelog::LogError>>)>,
    /// The last save's error, for the report.
    last_error: Option<String>,
}

impl ParamFile {
    /// Opens `path` for a runner whose configuration file gives `builtin`: what it holds.
    ///
    /// # Errors
    /// [`ParamFileError`] if it cannot be read or is not a saved parameter set.
    pub fn open(path: &Path, builtin: &Config) -> Result<(Self, Found), ParamFileError> {
        let read = |source| ParamFileError::Read {
            path: path.to_path_buf(),
            source,
        };
        let bytes = match firmware::input::read_bounded(path, RECORD_BYTES as u64) {
            Ok(b) => Some(b),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) if e.kind() == std::io::ErrorKind::FileTooLarge => {
                return Err(ParamFileError::NotASet {
                    path: path.to_path_buf(),
                    len: std::fs::metadata(path).map_or(0, |m| m.len() as usize),
                });
            }
            Err(e) => return Err(read(e)),
        };
        let (found, seq) = match bytes {
            None => {
                let folder = match path.parent() {
                    Some(p) if !p.as_os_str().is_empty() => p,
                    _ => Path::new("."),
                };
                if !folder.is_dir() {
                    return Err(ParamFileError::NoFolder {
                        path: path.to_path_buf(),
                        folder: folder.to_path_buf(),
                    });
                }
                (Found::Missing, 0)
            }
            Some(b) => {
                let record: Option<[u8; RECORD_BYTES]> = b.as_slice().try_into().ok();
                let Some(record) = record.filter(|r| r[..4] == MAGIC.to_le_bytes()) else {
                    return Err(ParamFileError::NotASet {
                        path: path.to_path_buf(),
                        len: b.len(),
                    });
                };
                match storage::parse(&record) {
                    Content::Record {
                        seq,
                        base_id,
                        config: Some(config),
                    } if storage::usable(&config, base_id, builtin) => (
                        Found::Saved {
                            config: Box::new(config),
                            seq,
                        },
                        seq,
                    ),
                    Content::Record { seq, base_id, .. } => (Found::Other { base_id }, seq),
                    Content::Blank | Content::Garbage => (Found::Damaged, 0),
                }
            }
        };
        let file = Self {
            path: path.to_path_buf(),
            next_seq: seq.wrapping_add(1).max(1),
            writing: None,
            last_error: None,
        };
        Ok((file, found))
    }

    /// The file.
    #[must_use]
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether a save is being written.
    #[must_use]
    pub const fn busy(&self) -> bool {
        self.writing.is_some()
    }

    /// Why the last save failed, if it did.
    #[must_use]
    pub fn last_error(&self) -> Option<&str> {
        self.last_error.as_deref()
    }
}

impl ParamStore for ParamFile {
    fn begin(&mut self, config: &Config, builtin_id: u16) -> Result<(), SaveOutcome> {
        if self.writing.is_some() {
            // The core asks for one save at a time; a second is its state's refusal.
            return Err(SaveOutcome::Failed {
                code: abort_code::DEVICE_STATE,
            });
        }
        let seq = self.next_seq;
        let bytes = storage::record_bytes(config, seq, builtin_id);
        let path = self.path.clone();
        let spawned = std::thread::Builder::new()
            .name("params-save".into())
            .spawn(move || {
                let mut staged = drivelog::Staged::create(&path)?;
                std::io::Write::write_all(&mut staged, &bytes).map_err(|source| {
                    drivelog::LogError::Io {
                        path: staged.part().to_path_buf(),
                        source,
                    }
                })?;
                staged.commit_durable()
            });
        match spawned {
            Ok(handle) => {
                self.writing = Some((seq, handle));
                Ok(())
            }
            Err(e) => {
                self.last_error = Some(format!("cannot start the saving thread: {e}"));
                Err(SaveOutcome::Failed { code: WRITE_FAILED })
            }
        }
    }

    fn poll(&mut self) -> Option<SaveOutcome> {
        let (seq, handle) = self.writing.take_if(|(_, h)| h.is_finished())?;
        let result = handle.join().unwrap_or_else(|_| {
            Err(drivelog::LogError::Io {
                path: self.path.clone(),
                source: std::io::Error::other("the saving thread panicked"),
            })
        });
        Some(match result {
            Ok(_) => {
                self.next_seq = seq.wrapping_add(1).max(1);
                self.last_error = None;
                SaveOutcome::Stored { seq }
            }
            Err(e) => {
                self.last_error = Some(e.to_string());
                SaveOutcome::Failed { code: WRITE_FAILED }
            }
        })
    }
}
