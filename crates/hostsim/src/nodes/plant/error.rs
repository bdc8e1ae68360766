//! The one error of the plant: a parameter out of range, named.

use core::fmt;

/// A plant parameter (or a `step` argument) that is not acceptable: which field, which value,
/// and what is expected of it.
///
/// Constructors and setters of the plant validate everything they take and return this
/// instead of panicking or producing NaN later.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParamError {
    /// Dotted path of the field, e.g. `"chassis.mass"` or `"chassis.wheels.radius"`.
    pub field: &'static str,
    /// The wheel (0..4, order FL, FR, RL, RR) for per-wheel fields.
    pub wheel: Option<usize>,
    /// The rejected value.
    pub value: f64,
    /// What is expected of it.
    pub expected: &'static str,
}

impl ParamError {
    pub(crate) const fn new(field: &'static str, value: f64, expected: &'static str) -> Self {
        Self {
            field,
            wheel: None,
            value,
            expected,
        }
    }

    pub(crate) const fn at(mut self, wheel: usize) -> Self {
        self.wheel = Some(wheel);
        self
    }
}

impl fmt::Display for ParamError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.wheel {
            Some(w) => write!(
                f,
                "{}[{}] = {}: expected {}",
                self.field, w, self.value, self.expected
            ),
            None => write!(
                f,
                "{} = {}: expected {}",
                self.field, self.value, self.expected
            ),
        }
    }
}

impl std::error::Error for ParamError {}

/// `value` finite and `> 0`.
pub(crate) fn positive(field: &'static str, value: f64) -> Result<f64, ParamError> {
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(ParamError::new(field, value, "a finite number > 0"))
    }
}

/// `value` finite and `>= 0`.
pub(crate) fn non_negative(field: &'static str, value: f64) -> Result<f64, ParamError> {
    if value.is_finite() && value >= 0.0 {
        Ok(value)
    } else {
        Err(ParamError::new(field, value, "a finite number >= 0"))
    }
}

/// `value` finite.
pub(crate) fn finite(field: &'static str, value: f64) -> Result<f64, ParamError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(ParamError::new(field, value, "a finite number"))
    }
}
