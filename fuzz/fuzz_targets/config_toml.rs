//! The configuration loader: `Config::from_toml_str` on any text never panics (errors are
//! fine); whatever it accepts, `Controller::new` accepts too, survives a few steps, and
//! `to_toml_string` writes back a text that loads to the same configuration.
#![no_main]

use firmware::config::Config;
use firmware::control::{Controller, Instant};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let config = match Config::from_toml_str(text) {
        Ok(c) => c,
        Err(e) => {
            let _ = std::format!("{e}");
            return;
        }
    };
    let mut ctl = match Controller::new(&config) {
        Ok(c) => c,
        Err(e) => panic!("the loader accepted a configuration the controller refuses: {e}"),
    };
    let again = Config::from_toml_str(&config.to_toml_string());
    assert_eq!(
        again.ok(),
        Some(config),
        "to_toml_string does not round-trip"
    );
    let period = ctl.period_micros();
    assert!(period > 0);
    for i in 0..3 {
        let _ = ctl.step(Instant::from_micros(i * period));
    }
    let _ = ctl.snapshot();
});
