//! Reading a configuration from TOML: the file, the parser's errors quoting the line, and
//! the checks of [`Config::validate`].

use std::boxed::Box;
use std::path::{Path, PathBuf};
use std::string::String;

use super::{Config, ConfigError};
use crate::input::TomlError;

/// Why a configuration file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The TOML is malformed, has an unknown or missing field, or a value of the wrong type.
    /// (The message quotes the line and names the key: [`TomlError`]; not the error's
    /// `source`, whose text would show the line raw.)
    #[error("{path}: {parse}")]
    Toml {
        /// The file (or `<string>`).
        path: PathBuf,
        /// The parser's error, with line and column, and the key it points at.
        parse: Box<TomlError>,
    },
    /// A value is out of range.
    #[error("{path}: {source}")]
    Invalid {
        /// The file (or `<string>`).
        path: PathBuf,
        /// Which field and value.
        source: ConfigError,
    },
}

impl Config {
    /// Parses and validates a TOML configuration.
    ///
    /// # Errors
    /// [`LoadError::Toml`] for syntax, unknown fields and wrong types (with line, column
    /// and key), [`LoadError::Invalid`] naming the field and value out of range.
    pub fn from_toml_str(text: &str) -> Result<Self, LoadError> {
        Self::parse(text, Path::new("<string>"))
    }

    /// Reads, parses and validates a TOML configuration file.
    ///
    /// # Errors
    /// As [`from_toml_str`](Self::from_toml_str), plus [`LoadError::Io`].
    pub fn from_toml_file(path: &Path) -> Result<Self, LoadError> {
        let text = crate::input::read_toml_text(path).map_err(|source| LoadError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// The configuration as TOML.
    #[must_use]
    pub fn to_toml_string(&self) -> String {
        // Every field is a number, bool, string, array or table: serialisation cannot fail.
        toml::to_string_pretty(self).unwrap_or_default()
    }

    fn parse(text: &str, path: &Path) -> Result<Self, LoadError> {
        let config: Self = toml::from_str(text).map_err(|parse| LoadError::Toml {
            path: path.to_path_buf(),
            parse: Box::new(TomlError::new(text, parse)),
        })?;
        config.validate().map_err(|source| LoadError::Invalid {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(config)
    }
}
