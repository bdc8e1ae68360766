//! What the binaries' command lines share: how an error is printed, how a duration is read,
//! how the statistics are written.

/// An error and its causes on one line, each cause once (`a: b: c`): many errors already
/// include their source in their own message, so a cause whose text is already there is
/// skipped. For the binaries' error messages.
pub fn error_line(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(c) = cause {
        let next = c.to_string();
        if !text.contains(&next) {
            text.push_str(": ");
            text.push_str(&next);
        }
        cause = c.source();
    }
    text
}

/// A `--duration`-like argument: seconds, a finite number in [0, 1e9). For clap's
/// `value_parser`; the message names the value.
///
/// # Errors
/// What is wrong with `s`, naming it.
pub fn parse_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..1e9).contains(&v) => Ok(v),
        Ok(v) => Err(format!(
            "expected a number of seconds in [0, 1e9) (about 31 years), got {v}"
        )),
        Err(e) => Err(format!("expected a number of seconds, got {s:?}: {e}")),
    }
}

/// Writes a run's statistics as `--stats-json` does: one pretty-printed JSON object and a
/// newline. The object goes through a [`serde_json::Value`], whose keys are sorted by name
/// (serde_json without `preserve_order`), as `hostsim`'s `--json`.
///
/// # Errors
/// The writer's, or a report that does not serialise (a map whose keys are not strings).
pub fn write_stats_json(
    out: &mut impl std::io::Write,
    stats: &impl serde::Serialize,
) -> std::io::Result<()> {
    let value = serde_json::to_value(stats)?;
    serde_json::to_writer_pretty(&mut *out, &value)?;
    out.write_all(b"\n")
}
