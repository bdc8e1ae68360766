//! The file and the thread that writes it: [`Out`] under the `mcap` writer, the start of a
//! file, and the [`BatchWriter`] thread that takes batches from the caller's thread and
//! gives them back once they are in the file.

use std::collections::BTreeMap;
use std::io::{self, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TryRecvError, TrySendError, sync_channel};
use std::thread::JoinHandle;

use mcap::records::Metadata;

use super::ZSTD_LEVEL;
use super::encode::{Batch, Encoder};
use super::file::McapFile;
use crate::{Channel, METADATA_NAME, PROFILE};

/// The file under the [`McapFile`]: passes writes on until the first error, then refuses
/// every later one (so that nothing follows a failed write, not even the summary written when
/// a log is dropped), and refuses to write while its thread panics.
pub(super) struct Out {
    inner: Box<dyn Write + Send>,
    failed: bool,
    /// Bytes passed on so far: [`McapLog::bytes_written`].
    written: Arc<AtomicU64>,
}

impl Out {
    fn check(&self) -> io::Result<()> {
        if self.failed || std::thread::panicking() {
            return Err(io::Error::other("an earlier write to this log failed"));
        }
        Ok(())
    }
}

impl Write for Out {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.check()?;
        let n = self.inner.write(buf).inspect_err(|_| self.failed = true)?;
        self.written.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.check()?;
        self.inner.flush().inspect_err(|_| self.failed = true)
    }
}

pub(super) type Writer = McapFile<Out>;

/// Starts an MCAP file on `out`: the header, the metadata, the schemas and channels, all on
/// disk when this returns.
pub(super) fn start_file(
    out: Box<dyn Write + Send>,
    metadata: &BTreeMap<String, String>,
    chunk_size: u64,
    written: Arc<AtomicU64>,
) -> io::Result<Writer> {
    let out = Out {
        inner: out,
        failed: false,
        written,
    };
    let library = concat!("drivelog ", env!("CARGO_PKG_VERSION"));
    let mut writer = McapFile::new(out, PROFILE, library, ZSTD_LEVEL, chunk_size)?;
    // The metadata first: a log cut anywhere after it still has its configuration.
    writer.write_metadata(&Metadata {
        name: METADATA_NAME.to_string(),
        metadata: metadata.clone(),
    })?;
    // One schema per message type, from id 1, shared by the channels of that type.
    let mut schemas: Vec<&str> = Vec::new();
    for channel in Channel::ALL {
        let def = channel.def();
        let schema = match schemas.iter().position(|name| *name == def.name) {
            Some(i) => i,
            None => {
                schemas.push(def.name);
                let id = schemas.len() as u16;
                writer.add_schema(id, def.name, "ros2msg", def.schema_text().as_bytes())?;
                schemas.len() - 1
            }
        };
        writer.add_channel(channel.id(), schema as u16 + 1, channel.topic(), "cdr")?;
    }
    writer.flush()?;
    Ok(writer)
}

/// Lowers the calling thread's priority as far as an unprivileged thread can (Linux:
/// `SCHED_BATCH`, niceness 19; also out of a real-time class inherited from a runner started
/// with `chrt`). Best effort: a refusal leaves the thread as it was. The log's writing thread
/// does it in the non-blocking mode, and a live server's thread (the `live` crate) always:
/// neither may hold up a control loop that shares their process.
pub fn step_aside() {
    #[cfg(target_os = "linux")]
    {
        use thread_priority::unix::{
            NormalThreadSchedulePolicy, ThreadSchedulePolicy, set_thread_priority_and_policy,
            thread_native_id,
        };
        let _ = set_thread_priority_and_policy(
            thread_native_id(),
            thread_priority::ThreadPriority::Min,
            ThreadSchedulePolicy::Normal(NormalThreadSchedulePolicy::Batch),
        );
    }
}

/// The thread that writes batches, and the two channels to it: batches go there, and each
/// comes back (emptied, for reuse) once it is in the file, or the error that stopped the
/// thread.
pub(super) struct BatchWriter {
    to_thread: Option<SyncSender<Batch>>,
    from_thread: Receiver<io::Result<Batch>>,
    thread: Option<JoinHandle<Writer>>,
    /// A batch was sent and has not come back yet.
    in_flight: bool,
    /// The thread lowers its own priority before its next batch (see `docs/logs.md`, section
    /// "A control loop that must not wait: dropping instead of blocking").
    pub(super) background: Arc<AtomicBool>,
}

impl BatchWriter {
    /// Starts the thread, which writes with `writer`.
    pub(super) fn start(writer: Writer) -> io::Result<Self> {
        let mut encoder = Encoder::new(writer);
        // One batch waits while the thread writes the one before it; two answers at most are
        // pending (the previous batch's, and the waiting one's if the thread is quick).
        let (to_thread, batches) = sync_channel::<Batch>(1);
        let (done, from_thread) = sync_channel(2);
        let background = Arc::new(AtomicBool::new(false));
        let thread_background = Arc::clone(&background);
        let thread = std::thread::Builder::new()
            .name("mcap-writer".to_string())
            .spawn(move || {
                let mut in_background = false;
                for mut batch in batches {
                    if !in_background && thread_background.load(Ordering::Relaxed) {
                        in_background = true;
                        step_aside();
                    }
                    match encoder.batch(&mut batch) {
                        Ok(()) => {
                            batch.clear();
                            if done.send(Ok(batch)).is_err() {
                                break;
                            }
                        }
                        Err(e) => {
                            let _ = done.send(Err(e));
                            break;
                        }
                    }
                }
                encoder.writer
            })?;
        Ok(Self {
            to_thread: Some(to_thread),
            from_thread,
            thread: Some(thread),
            in_flight: false,
            background,
        })
    }

    /// Waits until the batch in flight, if any, is in the file; returns it emptied.
    pub(super) fn wait(&mut self) -> io::Result<Option<Batch>> {
        if !self.in_flight {
            return Ok(None);
        }
        self.in_flight = false;
        match self.from_thread.recv() {
            Ok(result) => result.map(Some),
            Err(_) => Err(stopped()),
        }
    }

    /// Hands `batch` to the thread, then waits until the one handed over before it is in the
    /// file, and returns that one, emptied, for reuse. The thread finds `batch` waiting when
    /// it is done with the previous one: it does not idle between batches while this thread
    /// wakes up.
    pub(super) fn send(&mut self, batch: Batch) -> io::Result<Option<Batch>> {
        let sent = self
            .to_thread
            .as_ref()
            .is_some_and(|to_thread| to_thread.send(batch).is_ok());
        // The previous batch's error, if that is what stopped the thread.
        let previous = self.wait()?;
        if !sent {
            return Err(stopped());
        }
        self.in_flight = true;
        Ok(previous)
    }

    /// As [`send`](Self::send), without waiting: if the batch in flight is not in the file
    /// yet, gives `batch` back (`Ok(Err(batch))`) instead.
    pub(super) fn try_send(&mut self, batch: Batch) -> io::Result<Result<Option<Batch>, Batch>> {
        let mut spare = None;
        if self.in_flight {
            match self.from_thread.try_recv() {
                Ok(result) => {
                    self.in_flight = false;
                    spare = Some(result?);
                }
                Err(TryRecvError::Empty) => return Ok(Err(batch)),
                Err(TryRecvError::Disconnected) => {
                    self.in_flight = false;
                    return Err(stopped());
                }
            }
        }
        let Some(to_thread) = self.to_thread.as_ref() else {
            return Err(stopped());
        };
        match to_thread.try_send(batch) {
            Ok(()) => {
                self.in_flight = true;
                Ok(Ok(spare))
            }
            Err(TrySendError::Full(batch)) => Ok(Err(batch)),
            Err(TrySendError::Disconnected(_)) => Err(stopped()),
        }
    }

    /// Waits for the batch in flight, stops the thread and returns the `mcap` writer.
    pub(super) fn finish(&mut self) -> io::Result<Writer> {
        self.wait()?;
        self.to_thread = None;
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(writer)) => Ok(writer),
            _ => Err(stopped()),
        }
    }
}

/// The error for a thread that is gone without saying why (it panicked, or an earlier error
/// was already reported).
fn stopped() -> io::Error {
    io::Error::other("the MCAP writer thread has stopped")
}

impl Drop for BatchWriter {
    fn drop(&mut self) {
        // Let the thread finish the batch in flight and end.
        self.to_thread = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
