//! Puts `memory.x` where the linker finds it (`-Tlink.x` includes it), and the drive
//! configuration into the image.
//!
//! The configuration is `MECANUM_CONFIG` (a TOML file, relative to this directory; the
//! 4 x M3508/C620 example `../../config/dji_m3508.toml` when unset). It is read and validated
//! here, on the host, by the same code as `mecanum-runner --config` (so with the same errors),
//! and written encoded (`firmware::Config::encode`) to `$OUT_DIR/config.bin`, which the image
//! decodes at boot. Its file name goes into the image as `MECANUM_CONFIG_NAME` for the boot
//! log line; the id the image logs and sends is `firmware::Config::id`
//! (`mecanum-codec config-id FILE` prints it on the host).

use std::env;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// The configuration without `MECANUM_CONFIG`.
const DEFAULT_CONFIG: &str = "../../config/dji_m3508.toml";

fn main() -> ExitCode {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    fs::copy("memory.x", out.join("memory.x")).expect("copy memory.x to OUT_DIR");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=build.rs");

    println!("cargo:rerun-if-env-changed=MECANUM_CONFIG");
    let path = env::var("MECANUM_CONFIG").unwrap_or_else(|_| DEFAULT_CONFIG.to_owned());
    println!("cargo:rerun-if-changed={path}");
    let config = match firmware::Config::from_toml_file(Path::new(&path)) {
        Ok(config) => config,
        Err(e) => {
            // Cargo prints a failed build script's stderr under the package's name.
            eprintln!("error: MECANUM_CONFIG: {e}");
            return ExitCode::FAILURE;
        }
    };
    fs::write(out.join("config.bin"), config.encode()).expect("write config.bin to OUT_DIR");
    let name = Path::new(&path)
        .file_name()
        .map_or_else(|| path.clone(), |n| n.to_string_lossy().into_owned());
    println!("cargo:rustc-env=MECANUM_CONFIG_NAME={name}");
    ExitCode::SUCCESS
}
