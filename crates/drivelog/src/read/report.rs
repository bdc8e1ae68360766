//! What a read delivered: the messages ([`Message`]), the [`ReadReport`] of the walk, and the
//! messages a reader could not decode ([`Undecodable`]).

use std::collections::BTreeMap;
use std::fmt;

use super::Damage;

/// What [`for_each_message`](super::for_each_message) read, and where it stopped if the file is damaged.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReadReport {
    /// File length, bytes.
    pub file_len: u64,
    /// The MCAP profile in the file's Header (`ros2` for this project's logs).
    pub profile: String,
    /// Chunks read and used (complete, CRC correct).
    pub chunks: u64,
    /// Messages delivered.
    pub messages: u64,
    /// Largest log time of the messages delivered, ns.
    pub last_time_ns: Option<u64>,
    /// The Data End record was read and its CRC matched: every message of the file was
    /// delivered, whatever [`damage`](Self::damage) says about the summary section after it.
    pub data_complete: bool,
    /// Where and why reading stopped early; `None` for a complete, intact file.
    pub damage: Option<Damage>,
}

impl ReadReport {
    /// `true` if the file is complete and intact.
    #[must_use]
    pub const fn is_complete(&self) -> bool {
        self.damage.is_none()
    }

    /// The messages read, as a phrase: "12345 messages up to t=12.340 s".
    #[must_use]
    pub fn messages_read(&self) -> String {
        let mut text = format!("{} message{}", self.messages, plural(self.messages));
        if let Some(t) = self.last_time_ns {
            text.push_str(&format!(" up to t={:.3} s", t as f64 * 1e-9));
        }
        text
    }
}

fn plural(n: u64) -> &'static str {
    if n == 1 { "" } else { "s" }
}

impl fmt::Display for ReadReport {
    /// `complete: 68 chunks, 686425 messages up to t=60.000 s`, or
    /// `damaged: <where and what>; read the 41 complete chunks before it: 12345 messages up
    /// to t=12.340 s`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (n, s) = (self.chunks, plural(self.chunks));
        let messages = self.messages_read();
        match &self.damage {
            None => write!(f, "complete: {n} chunk{s}, {messages}"),
            Some(d) if self.data_complete => write!(
                f,
                "damaged: {d}; every message was read before it: {n} chunk{s}, {messages}"
            ),
            Some(d) => write!(
                f,
                "damaged: {d}; read the {n} complete chunk{s} before it: {messages}"
            ),
        }
    }
}

/// A message as [`for_each_message`](super::for_each_message) hands it over.
#[derive(Debug, Clone, Copy)]
pub struct Message<'a> {
    /// Its channel's topic.
    pub topic: &'a str,
    /// Its channel's schema name (`can_msgs/msg/Frame`...); empty for a channel without one.
    pub schema: &'a str,
    /// Log time, ns.
    pub log_time: u64,
    /// Publish time, ns.
    pub publish_time: u64,
    /// The message's data (CDR in this project's logs).
    pub data: &'a [u8],
}

/// Messages a reader could not decode, by topic, and the first of them. Every command that
/// reads a log decodes through one and reports it: nothing is skipped in silence
/// (`docs/logs.md`, "Reading damaged logs").
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Undecodable {
    /// Messages not decoded, by topic.
    pub by_topic: BTreeMap<String, u64>,
    /// The first: topic, log time (ns) and why, the reason [`quote`](firmware::input::quote)d.
    pub first: Option<(String, u64, String)>,
}

impl Undecodable {
    /// `m`'s data decoded as `M`; `None`, counted, if it is not one.
    pub fn decode<M: crate::msg::RosMsg>(&mut self, m: &Message<'_>) -> Option<M> {
        match crate::msg::decode::<M>(m.data) {
            Ok(value) => Some(value),
            Err(e) => {
                self.count(m, &e);
                None
            }
        }
    }

    /// A `/can/rx` or `/can/tx` message's frame; `None`, counted, if the message does not
    /// decode or holds no valid CAN frame (identifier or length out of range).
    pub fn frame(&mut self, m: &Message<'_>) -> Option<firmware::CanFrame> {
        let frame = self.decode::<crate::msg::Frame>(m)?;
        let can = frame.to_can();
        if can.is_none() {
            self.count(
                m,
                &"not a valid CAN frame (identifier or length out of range)",
            );
        }
        can
    }

    /// Counts `m` as not decoded, for `why`.
    pub fn count(&mut self, m: &Message<'_>, why: &dyn fmt::Display) {
        *self.by_topic.entry(m.topic.to_string()).or_default() += 1;
        if self.first.is_none() {
            let why = firmware::input::quote(&why.to_string());
            self.first = Some((m.topic.to_string(), m.log_time, why));
        }
    }

    /// Messages not decoded in all.
    #[must_use]
    pub fn total(&self) -> u64 {
        self.by_topic.values().sum()
    }

    /// Messages of `topic` not decoded.
    #[must_use]
    pub fn on(&self, topic: &str) -> u64 {
        self.by_topic.get(topic).copied().unwrap_or(0)
    }
}

impl fmt::Display for Undecodable {
    /// `2 messages could not be decoded (/can/rx 1, /odom 1); the first: /can/rx at 1.234000 s:
    /// ...`, or `every message decoded`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Some((topic, t_ns, why)) = &self.first else {
            return f.write_str("every message decoded");
        };
        let topics: Vec<String> = self
            .by_topic
            .iter()
            .map(|(t, n)| format!("{t} {n}"))
            .collect();
        write!(
            f,
            "{} messages could not be decoded ({}); the first: {topic} at {:.6} s: {why}",
            self.total(),
            topics.join(", "),
            *t_ns as f64 * 1e-9
        )
    }
}
