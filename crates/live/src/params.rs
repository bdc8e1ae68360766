//! The robot's parameters for live clients: the Foxglove `parameters` capability
//! (`getParameters`, `setParameters`, answered with `parameterValues`), over the robot's
//! parameter service on its bus (expedited SDO, `firmware::params`; docs/protocol.md,
//! "Parameters").
//!
//! The server is a client of the service like any other host (`mecanum-drive param`, the ROS 2
//! bridge): through a [`ParamLink`] it sends each request on the bus, so the robot applies a
//! change at its next step, logs the request as a received frame and says the change on
//! `/rosout`. Names are the configuration file's keys (`gains.kp`), as in the EDS.
//!
//! - `getParameters` with no names gets every parameter the robot's configuration has (those
//!   of another geometry or drive are left out), each as its type: a `REAL32` as a float
//!   (its shortest decimal: 1.2, not 1.2000000476837158), an enum or count as an integer, a
//!   flag as a boolean.
//! - `setParameters` writes each value in order, then reads it back: the answer carries the
//!   values in force. A value the robot refuses is answered with the value it kept, and a
//!   `status` error names the parameter, the value and the rule (from the abort code and the
//!   parameter's description). A name it does not have, or a value that is no number, is
//!   refused before anything is sent.
//! - No answer within [`PARAM_TIMEOUT`] is a `status` error; a `getParameters` of everything
//!   stops at the first one (a robot that does not answer would take 73 time-outs).
//!
//! Changes made by other clients of the service are not pushed (`parametersSubscribe` is not
//! declared): a client sees them at its next `getParameters`.

use std::io;
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

use firmware::params::{self, PARAMS, Param, ParamType};
use firmware::protocol::canopen::{SdoRequest, SdoResponse, abort_code, abort_text};
use foxglove::websocket::ws_protocol::parameter::{Parameter, ParameterValue};
use mecanum_linux::{FramePort, SdoClient};

/// How long the server waits for the robot's answer to one request: the robot answers at its
/// next step (a few milliseconds), a save-free write included.
pub const PARAM_TIMEOUT: Duration = Duration::from_millis(500);

/// The way to the robot's parameter service: sends one expedited SDO request to it and
/// returns its answer, or `None` when none came within the time-out: an [`SdoClient`] on a
/// SocketCAN interface, or on the simulated bus of `hostsim run`.
pub trait ParamLink: Send + 'static {
    /// One request and its answer.
    ///
    /// # Errors
    /// The bus failed.
    fn exchange(
        &mut self,
        request: SdoRequest,
        timeout: Duration,
    ) -> io::Result<Option<SdoResponse>>;
}

impl<P: FramePort + Send + 'static> ParamLink for SdoClient<P> {
    fn exchange(
        &mut self,
        request: SdoRequest,
        timeout: Duration,
    ) -> io::Result<Option<SdoResponse>> {
        SdoClient::exchange(self, request, timeout)
    }
}

/// What a request got: the values to answer with, and the errors to tell in `status`es.
#[derive(Debug, Default)]
pub(crate) struct Answer {
    pub(crate) values: Vec<Parameter>,
    pub(crate) errors: Vec<String>,
}

/// The service, shared by the clients: one request on the bus at a time.
pub(crate) struct ParamService {
    link: Mutex<Box<dyn ParamLink>>,
}

/// Why a read or a write got no value.
enum Failure {
    /// The robot refused, with this abort code.
    Abort(u32),
    /// No answer, or the bus failed: the robot is not there.
    Silent(String),
}

impl ParamService {
    pub(crate) fn new(link: Box<dyn ParamLink>) -> Self {
        Self {
            link: Mutex::new(link),
        }
    }

    fn exchange(&self, request: SdoRequest) -> Result<SdoResponse, Failure> {
        let mut link = self.link.lock().unwrap_or_else(PoisonError::into_inner);
        match link.exchange(request, PARAM_TIMEOUT) {
            Ok(Some(SdoResponse::Abort { code, .. })) => Err(Failure::Abort(code)),
            Ok(Some(answer)) => Ok(answer),
            Ok(None) => Err(Failure::Silent(format!(
                "no answer from the robot's parameter service within {} ms",
                PARAM_TIMEOUT.as_millis()
            ))),
            Err(e) => Err(Failure::Silent(format!("the CAN bus failed: {e}"))),
        }
    }

    fn read(&self, p: &Param) -> Result<Parameter, Failure> {
        let request = SdoRequest::Upload {
            index: p.index,
            sub: p.sub,
        };
        match self.exchange(request)? {
            SdoResponse::Uploaded { value, .. } => Ok(parameter(p, value)),
            other => Err(Failure::Silent(format!(
                "{}: answered a read with {other:?}",
                p.name
            ))),
        }
    }

    /// `getParameters`: the named parameters (every one the robot has when `names` is
    /// empty), in the order asked.
    pub(crate) fn get(&self, names: &[String]) -> Answer {
        let mut answer = Answer::default();
        let all = names.is_empty();
        let asked: Vec<Result<&Param, &String>> = if all {
            PARAMS.iter().map(Ok).collect()
        } else {
            names.iter().map(|n| params::find(n).ok_or(n)).collect()
        };
        for p in asked {
            let p = match p {
                Ok(p) => p,
                Err(name) => {
                    answer.errors.push(format!("{name}: no such parameter"));
                    continue;
                }
            };
            match self.read(p) {
                Ok(value) => answer.values.push(value),
                // Another layout's or drive's parameter: not this robot's.
                Err(Failure::Abort(abort_code::NO_SUBINDEX)) if all => {}
                Err(Failure::Abort(code)) => answer.errors.push(refusal(p, None, code)),
                Err(Failure::Silent(why)) => {
                    answer
                        .errors
                        .push(format!("getParameters {}: {why}", p.name));
                    break;
                }
            }
        }
        answer
    }

    /// `setParameters`: each value written, then read back; the answer has the values in
    /// force.
    pub(crate) fn set(&self, asked: &[Parameter]) -> Answer {
        let mut answer = Answer::default();
        for want in asked {
            let Some(p) = params::find(&want.name) else {
                answer
                    .errors
                    .push(format!("{}: no such parameter", want.name));
                continue;
            };
            let raw = match number(want.value.as_ref()).and_then(|v| raw_value(p, v)) {
                Ok(raw) => raw,
                Err(why) => {
                    answer.errors.push(format!("{}: {why}", p.name));
                    continue;
                }
            };
            let request = SdoRequest::Download {
                index: p.index,
                sub: p.sub,
                value: raw,
                size: p.ty.size(),
            };
            match self.exchange(request) {
                Ok(_) => {}
                Err(Failure::Abort(code)) => answer.errors.push(refusal(p, Some(raw), code)),
                Err(Failure::Silent(why)) => {
                    answer
                        .errors
                        .push(format!("setParameters {}: {why}", p.name));
                    continue;
                }
            }
            match self.read(p) {
                Ok(value) => answer.values.push(value),
                Err(Failure::Abort(code)) => answer.errors.push(refusal(p, None, code)),
                Err(Failure::Silent(why)) => answer.errors.push(format!("{}: {why}", p.name)),
            }
        }
        answer
    }
}

/// `raw` as a live client sees parameter `p`.
fn parameter(p: &Param, raw: u32) -> Parameter {
    match p.ty {
        ParamType::Boolean => Parameter::bool(p.name, raw != 0),
        ParamType::Unsigned8 | ParamType::Unsigned32 => Parameter::integer(p.name, raw.into()),
        ParamType::Real32 => Parameter::float64(p.name, shortest(f32::from_bits(raw))),
    }
}

/// The `f64` whose shortest decimal is the `f32`'s: 1.2f32 as 1.2, which rounds back to it.
fn shortest(x: f32) -> f64 {
    x.to_string().parse().unwrap_or_else(|_| f64::from(x))
}

/// A set's value as a number: JSON numbers and booleans.
fn number(value: Option<&ParameterValue>) -> Result<f64, String> {
    match value {
        Some(ParameterValue::Float64(v)) => Ok(*v),
        #[allow(clippy::cast_precision_loss)]
        Some(ParameterValue::Integer(v)) => Ok(*v as f64),
        Some(ParameterValue::Bool(b)) => Ok(f64::from(u8::from(*b))),
        Some(other) => Err(format!("{other:?} is not a number")),
        None => Err("no value (a parameter cannot be unset)".to_string()),
    }
}

/// `value` in `p`'s type, or why it cannot be.
fn raw_value(p: &Param, value: f64) -> Result<u32, String> {
    p.ty.from_f64(value).ok_or_else(|| {
        let ty = match p.ty {
            ParamType::Boolean => "a flag (false or true, 0 or 1)",
            ParamType::Unsigned8 => "a whole number 0..255",
            ParamType::Unsigned32 => "a whole number 0..4294967295",
            ParamType::Real32 => "a number",
        };
        format!("{value} is not {ty}")
    })
}

/// The robot's refusal of `p` (set to `raw`, or read) as a sentence: the parameter, the value
/// and the rule, from the abort code and the parameter's description.
fn refusal(p: &Param, raw: Option<u32>, code: u32) -> String {
    let name = p.name;
    let value = raw.map_or(String::new(), |r| {
        format!(
            " = {}",
            match parameter(p, r).value {
                Some(ParameterValue::Float64(v)) => v.to_string(),
                Some(ParameterValue::Integer(v)) => v.to_string(),
                Some(ParameterValue::Bool(b)) => b.to_string(),
                _ => r.to_string(),
            }
        )
    });
    let rule = match code {
        abort_code::TOO_HIGH => format!("above {}", p.high),
        abort_code::TOO_LOW => format!("below {}", p.low),
        abort_code::READ_ONLY => {
            "read-only over CAN (a new configuration file or image changes it)".to_string()
        }
        abort_code::DEVICE_STATE => "changes only while the robot is disabled".to_string(),
        abort_code::NO_SUBINDEX => "not in this robot's configuration".to_string(),
        abort_code::INVALID_VALUE => {
            "invalid: a rule of the configuration refuses it (docs/protocol.md, \"Parameters\")"
                .to_string()
        }
        _ => abort_text(code).unwrap_or("refused").to_string(),
    };
    format!("{name}{value}: {rule} (SDO abort {code:#010x}); the value in force is kept")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_take_their_types_and_the_shortest_decimal_of_an_f32() {
        let kp = params::find("gains.kp").unwrap();
        let p = parameter(kp, 1.2f32.to_bits());
        assert_eq!(p.value, Some(ParameterValue::Float64(1.2)));
        assert_eq!(raw_value(kp, 1.2), Ok(1.2f32.to_bits()));
        let flag = PARAMS.iter().find(|p| p.ty == ParamType::Boolean).unwrap();
        assert_eq!(parameter(flag, 1).value, Some(ParameterValue::Bool(true)));
        assert_eq!(number(Some(&ParameterValue::Bool(true))), Ok(1.0));
        assert!(raw_value(flag, 2.0).unwrap_err().contains("a flag"));
        assert!(
            number(Some(&ParameterValue::String("1.5".into())))
                .unwrap_err()
                .contains("not a number")
        );
    }

    #[test]
    fn a_refusal_names_the_parameter_the_value_and_the_rule() {
        let kp = params::find("gains.kp").unwrap();
        let text = refusal(kp, Some(1e6f32.to_bits()), abort_code::TOO_HIGH);
        assert_eq!(
            text,
            format!(
                "gains.kp = 1000000: above {} (SDO abort 0x06090031); the value in force is kept",
                kp.high
            )
        );
    }
}
