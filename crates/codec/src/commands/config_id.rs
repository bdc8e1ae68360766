//! `config-id`: the id of each drive configuration, as a robot running it reports it.

use std::path::PathBuf;
use std::process::ExitCode;

/// `config-id`: the id of each configuration file.
pub(crate) fn run(files: &[PathBuf]) -> ExitCode {
    for file in files {
        match firmware::Config::from_toml_file(file) {
            Ok(config) => println!("0x{:04x}  {}", config.id(), file.display()),
            Err(e) => {
                eprintln!("mecanum-codec: {e}");
                return ExitCode::FAILURE;
            }
        }
    }
    ExitCode::SUCCESS
}
