//! SIGINT and SIGTERM as a flag the loop polls.

use core::sync::atomic::{AtomicUsize, Ordering};
use std::io;

/// The value [`stop_on_signals`] stored in `stop` (the signal's number), `None` while it is 0.
#[must_use]
pub fn stop_requested(stop: &AtomicUsize) -> Option<usize> {
    match stop.load(Ordering::Relaxed) {
        0 => None,
        n => Some(n),
    }
}

/// Installs the stop signals a runner honours and returns the flag [`run`](crate::run) polls:
///
/// - the first SIGINT or SIGTERM stores its number in the flag, so the loop ends cleanly at
///   the next step (and sends its shutdown frames);
/// - a second one while the flag is set exits the process at once with status 1 (for a
///   loop that does not stop).
///
/// (signal-hook runs the actions in registration order: the exit checks the `stopping` flag
/// before the same signal sets it.) Call it once per process, before the bus is opened.
///
/// # Errors
/// The OS refused a handler; the message names the signal.
pub fn stop_on_signals() -> io::Result<std::sync::Arc<AtomicUsize>> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    use std::sync::Arc;
    use std::sync::atomic::AtomicBool;
    let stop = Arc::new(AtomicUsize::new(0));
    let stopping = Arc::new(AtomicBool::new(false));
    for signal in [SIGINT, SIGTERM] {
        let number = usize::try_from(signal).unwrap_or(1);
        signal_hook::flag::register_conditional_shutdown(signal, 1, Arc::clone(&stopping))
            .and_then(|_| signal_hook::flag::register(signal, Arc::clone(&stopping)))
            .and_then(|_| signal_hook::flag::register_usize(signal, Arc::clone(&stop), number))
            .map_err(|e| {
                io::Error::new(
                    e.kind(),
                    format!("cannot install the handler of signal {signal}: {e}"),
                )
            })?;
    }
    Ok(stop)
}
