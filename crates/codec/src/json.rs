//! The JSON lines `decode` and `golden` print: a decoded message ([`Decoded`]), in the order
//! its fields are written, and the error lines (serde_json, one line each).

use embedded_can::Id;
use firmware::protocol::wire::Field;
use firmware::protocol::{DecodeError, non_finite_name};
use serde::Serialize;
use serde_json::Value;

/// A JSON number: the codecs' integers and floats (a non-finite float is `null`, as
/// serde_json writes it; the codecs never produce one).
#[derive(Clone, Copy, Serialize)]
#[serde(untagged)]
pub(crate) enum Num {
    Int(i64),
    Float(f32),
}

/// Named values as a JSON object, in their order.
struct Fields<'a, V>(&'a [(&'a str, V)]);

impl<V: Serialize> Serialize for Fields<'_, V> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_map(self.0.iter().map(|(k, v)| (k, v)))
    }
}

/// One decoded message, protocol-independent.
pub(crate) struct Decoded {
    protocol: &'static str,
    /// The DBC message name (`TWIST_CMD`, `Axis2_Heartbeat`, `FEEDBACK_3`).
    pub(crate) message: String,
    /// The sender's address: an ODrive's `node`, a DJI ESC's `esc`.
    extra: Vec<(&'static str, Num)>,
    /// The fields: DBC signal names and values.
    pub(crate) fields: Vec<(&'static str, Num)>,
}

impl Decoded {
    pub(crate) fn new(protocol: &'static str, message: impl Into<String>) -> Self {
        Self {
            protocol,
            message: message.into(),
            extra: Vec::new(),
            fields: Vec::new(),
        }
    }

    pub(crate) fn extra(mut self, key: &'static str, value: i64) -> Self {
        self.extra.push((key, Num::Int(value)));
        self
    }

    pub(crate) fn f(mut self, field: &Field, value: f32) -> Self {
        self.fields.push((field.name, Num::Float(value)));
        self
    }

    pub(crate) fn i(mut self, field: &Field, value: impl Into<i64>) -> Self {
        self.fields.push((field.name, Num::Int(value.into())));
        self
    }

    /// The line of `decode`: `{"id", "protocol", "message", <extra>, "fields"}`; with
    /// `golden`, the frame's candump text and the encoder's input before the fields.
    pub(crate) fn json(&self, id: Id, golden: Option<(&str, &Decoded)>) -> String {
        #[derive(Serialize)]
        struct Line<'a> {
            id: u32,
            protocol: &'a str,
            message: &'a str,
            #[serde(flatten)]
            extra: Fields<'a, Num>,
            #[serde(skip_serializing_if = "Option::is_none")]
            candump: Option<&'a str>,
            #[serde(skip_serializing_if = "Option::is_none")]
            input: Option<Fields<'a, Num>>,
            fields: Fields<'a, Num>,
        }
        to_line(&Line {
            id: raw_id(id),
            protocol: self.protocol,
            message: &self.message,
            extra: Fields(&self.extra),
            candump: golden.map(|(text, _)| text),
            input: golden.map(|(_, input)| Fields(&input.fields)),
            fields: Fields(&self.fields),
        })
    }
}

/// One JSON line. The values here always serialise; were one not to, the line is an error
/// line like the others (serde_json escapes its message), not a hand-written one.
fn to_line(value: &impl Serialize) -> String {
    serde_json::to_string(value).unwrap_or_else(|e| {
        serde_json::json!({"error": {"kind": "internal", "message": e.to_string()}}).to_string()
    })
}

fn raw_id(id: Id) -> u32 {
    match id {
        Id::Standard(id) => u32::from(id.as_raw()),
        Id::Extended(id) => id.as_raw(),
    }
}

/// `{"id", "error": {"kind", "message", <extra>}}` (no `id` for a line that does not parse).
pub(crate) fn error_json(
    id: Option<Id>,
    kind: &str,
    message: &str,
    extra: &[(&str, Value)],
) -> String {
    #[derive(Serialize)]
    struct Error<'a> {
        kind: &'a str,
        message: &'a str,
        #[serde(flatten)]
        extra: Fields<'a, Value>,
    }
    #[derive(Serialize)]
    struct Line<'a> {
        #[serde(skip_serializing_if = "Option::is_none")]
        id: Option<u32>,
        error: Error<'a>,
    }
    to_line(&Line {
        id: id.map(raw_id),
        error: Error {
            kind,
            message,
            extra: Fields(extra),
        },
    })
}

pub(crate) fn decode_error_json(id: Id, e: &DecodeError) -> String {
    let extra: Vec<(&str, Value)> = match *e {
        DecodeError::WrongDlc { expected, got, .. } => {
            vec![("expected", expected.into()), ("got", got.into())]
        }
        DecodeError::NonFinite { field, bits } => vec![
            ("field", field.into()),
            ("value", non_finite_name(bits).into()),
            ("bits", format!("{bits:#010x}").into()),
        ],
        DecodeError::OutOfRange { field, value } => {
            vec![("field", field.into()), ("value", value.into())]
        }
        _ => Vec::new(),
    };
    error_json(Some(id), e.kind().as_str(), &e.to_string(), &extra)
}
