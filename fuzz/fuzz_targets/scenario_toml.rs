//! The scenario loader: `Scenario::from_toml_with_config` on any text never panics (errors
//! are fine, and print); whatever it accepts builds its plant, and a scenario of at most
//! 20 ms runs to its end without a panic.
#![no_main]

use std::path::Path;

use firmware::config::Config;
use hostsim::scenario::Scenario;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    // The configuration given, as `--config` does: a `config = "..."` key reads nothing.
    let scenario = match Scenario::from_toml_with_config(
        text,
        Path::new("fuzz.toml"),
        Some(Config::dji_m3508_example()),
    ) {
        Ok(s) => s,
        Err(e) => {
            let _ = std::format!("{e}");
            return;
        }
    };
    let Ok(mut plant) = hostsim::engine::plant_for(&scenario) else {
        return;
    };
    if scenario.duration_us() <= 20_000 {
        let _ = hostsim::engine::run(
            &scenario,
            &mut plant,
            None,
            hostsim::engine::LogOptions::default(),
            |_| {},
        );
    }
});
